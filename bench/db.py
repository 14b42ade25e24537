"""PPTBF database benchmarks (run on demand, print tables; timings on a shared machine are noisy).

  python bench/db.py describe [--n 48] [--resolution 128]      render + describe cost, masks per core-minute
  python bench/db.py speedup  [--n 240] [--resolution 128]     Ray rebuild wall time, 1 vs 2 workers, same N
  python bench/db.py query    [--sizes 20000 100000]           query latency (synthetic reduced vectors)
  python bench/db.py quality  --db FOLDER [--probes 100]       retrieval vs PCA dimension (needs raw chunks)
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pptbf_db import pptbf  # noqa: E402
from pptbf_db.descriptor import DescriptorConfig, PCAModel, describe_masks, fit_pca  # noqa: E402


def table(rows: list[tuple], header: tuple) -> None:
    """Print a left-aligned table."""
    cells = [tuple(map(str, header))] + [tuple(map(str, r)) for r in rows]
    w = [max(len(r[i]) for r in cells) for i in range(len(header))]
    for j, r in enumerate(cells):
        print("  ".join(c.ljust(x) for c, x in zip(r, w)))
        if j == 0:
            print("  ".join("-" * x for x in w))


def bench_describe(n: int, res: int) -> None:
    """Single-thread render and describe cost per mask."""
    import torch

    torch.set_num_threads(1)
    params = pptbf.sample_params(np.random.default_rng(0), n, ref_width=res)
    t0 = time.perf_counter()
    masks = np.stack([pptbf.render_mask(p, res) for p in params]).astype(np.float32)
    t_render = (time.perf_counter() - t0) / n
    describe_masks(masks[:2])                         # warm-up (extractor construction)
    t0 = time.perf_counter()
    describe_masks(masks)
    t_desc = (time.perf_counter() - t0) / n
    table([(res, n, f"{1e3 * t_render:.1f}", f"{1e3 * t_desc:.1f}", f"{60 / t_desc:.0f}",
            f"{60 / (t_render + t_desc):.0f}")],
          ("px", "masks", "render ms", "describe ms", "descriptors/core-min", "entries/core-min"))


def bench_speedup(n: int, res: int, chunk: int) -> None:
    """Same build with 1 and 2 tasks in flight on one local Ray (2 CPUs)."""
    import ray

    from pptbf_db.build import BuildConfig
    from service.db_build import build_database

    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    ray.init(address="local", num_cpus=2, include_dashboard=False, logging_level="WARNING")
    rows = []
    try:
        cfg = BuildConfig(size=n, resolution=res, chunk=chunk, seed=5)
        base = Path(tempfile.mkdtemp(prefix="pptbf_bench_"))
        build_database(base / "warm", BuildConfig(size=8, resolution=res, chunk=4), workers=2, progress=False)
        t1 = None
        for k in (1, 2):
            t0 = time.perf_counter()
            rep = build_database(base / f"w{k}", cfg, workers=k, progress=False)
            wall = time.perf_counter() - t0
            t1 = t1 or wall
            rows.append((k, n, res, f"{wall:.1f}", f"{t1 / wall:.2f}", f"{rep.entries_per_core_minute:.0f}"))
        shutil.rmtree(base, ignore_errors=True)
    finally:
        ray.shutdown()
    table(rows, ("workers", "N", "px", "wall s", "speed-up", "entries/core-min"))


def bench_query(sizes: list[int], dims: list[int]) -> None:
    """Exact query latency over synthetic reduced vectors (matrix product + partial sort)."""
    from pptbf_db.index import PPTBFIndex

    rows = []
    rng = np.random.default_rng(0)
    for n in sizes:
        for d in dims:
            raw_dim = 64
            pca = PCAModel(np.zeros(raw_dim, np.float32), np.ones(raw_dim, np.float32),
                           np.eye(d, raw_dim, dtype=np.float32), np.ones(d, np.float32) / d)
            idx = PPTBFIndex(np.zeros((n, 29)), rng.standard_normal((n, d)).astype(np.float32), pca,
                             DescriptorConfig(dim=d), 128)
            qs = rng.standard_normal((50, d)).astype(np.float32)
            idx.query_vector(qs[0], k=5)
            t0 = time.perf_counter()
            for q in qs:
                idx.query_vector(q, k=5)
            rows.append((n, d, f"{1e3 * (time.perf_counter() - t0) / len(qs):.2f}"))
    table(rows, ("entries", "dim", "query ms (k=5)"))


def bench_quality(folder: Path, probes: int, dims: list[int]) -> None:
    """Retrieval of an entry's own parameters from a new realisation (shifted render), per PCA dimension."""
    import json

    from pptbf_db.build import raw_path

    meta = json.loads((folder / "meta.json").read_text())
    res, n_chunks = meta["resolution"], meta["chunks"]
    cfg = DescriptorConfig.from_dict(meta["descriptor"])
    raw = np.concatenate([np.load(raw_path(folder, c)) for c in range(n_chunks)])
    params = np.load(folder / "params.npy")
    white = np.load(folder / "white.npy")
    ok = (white > 0.01) & (white < 0.99)
    ids = np.flatnonzero(ok)[:probes]
    t0 = time.perf_counter()
    q_raw = describe_masks(np.stack([pptbf.render_mask(params[i], res, shift=(3.7, 1.3)) for i in ids])
                           .astype(np.float32), None, cfg)
    t_q = (time.perf_counter() - t0) / len(ids)
    rows = []
    for d in dims + [None]:
        pca = fit_pca(raw[ok], cfg, d if d else raw.shape[1])
        if d is None:        # no reduction: weighted standardised raw space
            a, b = pca.standardise(raw), pca.standardise(q_raw)
        else:
            a, b = pca.transform(raw), pca.transform(q_raw)
        d2 = (b ** 2).sum(1)[:, None] - 2 * b @ a.T + (a ** 2).sum(1)[None]
        d2[:, ~ok] = np.inf
        ranks = np.array([(d2[j] < d2[j, i]).sum() for j, i in enumerate(ids)])
        rows.append((d or f"raw {raw.shape[1]}", f"{100 * (ranks == 0).mean():.0f}",
                     f"{100 * (ranks < 5).mean():.0f}", f"{100 * (ranks < 0.01 * ok.sum()).mean():.0f}",
                     f"{100 * np.median(ranks) / ok.sum():.2f}",
                     f"{100 * float(pca.explained.sum()):.1f}" if d else "-"))
    print(f"{folder}: {len(raw)} entries ({ok.sum()} usable), {res} px, {len(ids)} probes "
          f"({1e3 * t_q:.0f} ms render+describe each)")
    table(rows, ("dim", "own entry 1st %", "in top-5 %", "in top-1% %", "median rank %", "variance %"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("section", choices=("describe", "speedup", "query", "quality", "all"))
    ap.add_argument("--n", type=int, default=None)
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--chunk", type=int, default=20)
    ap.add_argument("--sizes", type=int, nargs="+", default=[20000, 100000])
    ap.add_argument("--dims", type=int, nargs="+", default=[16, 32, 64, 128])
    ap.add_argument("--db", type=Path, default=None)
    ap.add_argument("--probes", type=int, default=100)
    a = ap.parse_args()
    if a.section in ("describe", "all"):
        bench_describe(a.n or 48, a.resolution)
    if a.section in ("query", "all"):
        bench_query(a.sizes, a.dims)
    if a.section in ("speedup", "all"):
        bench_speedup(a.n or 240, a.resolution, a.chunk)
    if a.section in ("quality", "all") and a.db is not None:
        bench_quality(a.db, a.probes, a.dims)


if __name__ == "__main__":
    main()
