"""Benchmark decomposition: local-spectrum features and KNN matting at 256/512 px with 2 and 3 layers.

Run: python bench/decompose.py [--sizes 256 512] [--layers 2 3] [--material DIR] [--threads 1]
Uses castle_brick_broken_06 from ../shared/materials when present (else a synthetic two-texture image).
Columns: spectrum = feature_maps() (3 local spectra + PCA), then matte() split into seeding (k-means),
Laplacian (two KD-tree passes) and CG solve, the total matting time (wall seconds) and its CPU seconds
(all threads; a load-independent figure on a shared machine).
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

REPO = Path(__file__).resolve().parents[1]


def _load(size: int, material: Path | None) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, str]:
    """(albedo, height, roughness, label) at size x size."""
    from workers.maps import load_material

    if material is not None and material.is_dir():
        name = material.name
        mat = load_material(material / f"{name}_diff_1k.jpg", material / f"{name}_nor_gl_1k.jpg",
                            material / f"{name}_arm_1k.jpg", roughness_channel="G", working_size=size)
        return mat.albedo, mat.height, mat.roughness, name
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[:size, :size]
    disc = (xx - size / 2) ** 2 + (yy - size / 2) ** 2 < (0.3 * size) ** 2
    coarse = ndimage.gaussian_filter(rng.standard_normal((size, size)), 4, mode="wrap")
    g = 0.4 + 0.12 * np.where(disc, coarse / coarse.std(), rng.standard_normal((size, size)))
    return np.repeat(np.clip(g, 0, 1)[..., None], 3, 2).astype(np.float32), None, None, "synthetic"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    ap.add_argument("--layers", type=int, nargs="+", default=[2, 3])
    ap.add_argument("--material", type=Path, default=REPO.parent / "shared" / "materials" / "castle_brick_broken_06")
    ap.add_argument("--threads", type=int, default=0, help="limit BLAS/FFT threads (0 = leave as is)")
    args = ap.parse_args(argv)
    if args.threads:
        for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ[var] = str(args.threads)
    from workers.matting import feature_maps, matte

    print(f"cores: {os.cpu_count()}, load average: {os.getloadavg()[0]:.1f} (timings are wall seconds)")
    print(f"{'input':<24}{'size':>6}{'layers':>7}{'spectrum':>10}{'cpu':>6}{'seeding':>9}{'laplacian':>10}{'solve':>8}"
          f"{'matting':>9}{'cpu':>7}{'CG its':>10}")
    for size in args.sizes:
        alb, hgt, rough, label = _load(size, args.material)
        t0, c0 = time.perf_counter(), time.process_time()
        fm = feature_maps(alb, hgt, rough)
        t_spec, c_spec = time.perf_counter() - t0, time.process_time() - c0
        for n in args.layers:
            t1, c1 = time.perf_counter(), time.process_time()
            res = matte(fm, n_layers=n)
            t_mat, c_mat = time.perf_counter() - t1, time.process_time() - c1
            s = res.meta["seconds"]
            print(f"{label:<24}{size:>6}{n:>7}{t_spec:>10.2f}{c_spec:>6.2f}{s['features_seeds']:>9.2f}"
                  f"{s['laplacian']:>10.2f}{s['solve']:>8.2f}{t_mat:>9.2f}{c_mat:>7.2f}{str(res.meta['cg_iterations']):>10}")


if __name__ == "__main__":
    main()
