"""Benchmark PPTBF evaluation: numpy at 128/256/512 and torch (CPU) at 256, per tiling family.

Run: python bench/pptbf.py [--n 3] [--seed 0] [--sizes 128 256 512] [--torch-size 256] [--device cpu]
Prints one row per family with the median time (s) over n random database-like parameter vectors
(sample_params(ref_width=128), rendered with ref_width=128 so the pattern scale is the database's).
With --dist N it prints instead the distribution over N vectors of all families at the largest size, for 1 and
for the default number of threads (median, mean, p90, max, share under 1 s).
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from pptbf_db import pptbf as pp


def _time(fn) -> float:
    """Wall time of one call."""
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def _distribution(params: np.ndarray, size: int, threads: int | None) -> None:
    """Table of evaluation times over many parameter vectors, single-threaded and with the default threads."""
    counts = sorted({1, pp.default_threads() if threads is None else threads})
    print(f"{'threads':>7} {'n':>5} {'median':>8} {'mean':>8} {'p90':>8} {'max':>8} {'< 1 s':>7}   (numpy {size} px)")
    for th in counts:
        t = np.array([_time(lambda p=p: pp.evaluate(p, size, ref_width=128, threads=th)) for p in params])
        print(f"{th:>7} {t.size:>5} {np.median(t):>8.3f} {t.mean():>8.3f} {np.percentile(t, 90):>8.3f} "
              f"{t.max():>8.3f} {np.mean(t < 1.0):>7.2f}")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=3, help="parameter vectors per family")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512])
    ap.add_argument("--torch-size", type=int, default=256, help="0 to skip torch")
    ap.add_argument("--device", default="cpu", help="torch device (cpu, cuda)")
    ap.add_argument("--threads", type=int, default=None, help="numpy chunk threads (default: pp.default_threads())")
    ap.add_argument("--dist", type=int, default=0, metavar="N", help="distribution over N vectors instead")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    if args.dist:
        _distribution(pp.sample_params(rng, args.dist, ref_width=128), max(args.sizes), args.threads)
        return
    cols = [f"numpy {s}" for s in args.sizes] + ([f"torch {args.torch_size}"] if args.torch_size else [])
    if args.torch_size and args.device != "cpu":
        import torch

        pp.evaluate_torch(torch.tensor(pp.sample_params(rng, 1)[0]), 64, device=args.device)  # warm-up
    threads = pp.default_threads() if args.threads is None else args.threads
    print(f"{'family':<10} " + " ".join(f"{c:>11}" for c in cols)
          + f"   (median seconds, numpy on {threads} thread(s))")
    for fam, types in pp.TILING_FAMILIES.items():
        params = pp.sample_params(rng, args.n, ref_width=128)
        params[:, 1] = rng.choice(types, size=args.n)
        row = []
        for s in args.sizes:
            row.append(np.median([_time(lambda p=p: pp.evaluate(p, s, ref_width=128, threads=args.threads))
                                  for p in params]))
        if args.torch_size:
            import torch

            def run(p, dev=args.device):
                v = pp.evaluate_torch(torch.tensor(p), args.torch_size, ref_width=128, device=dev)
                if v.is_cuda:
                    torch.cuda.synchronize()

            row.append(np.median([_time(lambda p=p: run(p)) for p in params]))
        print(f"{fam:<10} " + " ".join(f"{t:>11.3f}" for t in row))


if __name__ == "__main__":
    main()
