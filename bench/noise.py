"""Noise model speed and size: fit time (RGB, masked by half) and synthesis time per output size, bytes per model.

Run: ``python bench/noise.py [--material plastered_stone_wall] [--repeat 3]`` (single thread; prints a table).
"""
from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from workers.maps import read_image, resize_image, srgb_to_linear  # noqa: E402
from workers.noise import fit_noise, synthesize, synthesize_layers  # noqa: E402


def best_of(fn, repeat: int) -> tuple[float, object]:
    """Minimum wall time of ``repeat`` calls and the last result."""
    best, out = float("inf"), None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--material", default="plastered_stone_wall")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    path = REPO.parent / "shared" / "materials" / args.material / f"{args.material}_diff_1k.jpg"
    if path.exists():
        src = srgb_to_linear(read_image(path)[..., :3])
    else:
        print(f"({path} not found: using random data)")
        src = np.random.default_rng(0).random((1024, 1024, 3)).astype(np.float32)
    rows = []
    model = None
    for n in (256, 512):
        img = resize_image(src, n, n).astype(np.float32)
        mask = np.zeros((n, n), bool)
        mask[:, : n // 2] = True
        t, model = best_of(lambda: fit_noise(img, mask), args.repeat)
        size = len(json.dumps(model.to_params()))
        rows.append((f"fit {n}x{n} RGB, half mask", t, f"{size} B JSON, T={model.info['window']}"))
    for n in (512, 1024, 2048):
        t, _ = best_of(lambda: synthesize(model, n, n, seed=1), args.repeat)
        rows.append((f"synthesize {n}x{n} RGB", t, f"{n * n / t / 1e6:.1f} Mpx/s"))
    t, _ = best_of(lambda: synthesize_layers(model, 2048, 2048, seed=1), args.repeat)
    rows.append(("synthesize_layers 2048x2048 RGB", t, f"{len(model.layers)} layers kept"))
    t, _ = best_of(lambda: synthesize(model, 1024, 1024, scale=4.0, seed=1), args.repeat)
    rows.append(("synthesize 1024x1024 scale 4", t, ""))
    print(f"{'case':34s} {'seconds':>8s}  note")
    for name, sec, note in rows:
        print(f"{name:34s} {sec:8.3f}  {note}")


if __name__ == "__main__":
    main()
