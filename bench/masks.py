"""Benchmark PPTBF mask fitting: time per mask and loss of the fit vs the query result alone.

Run: python bench/masks.py [--db DIR] [--n 6] [--budget 300] [--evals 300] [--working 512] [--seed 0]
     [--tiny 400] [--tiny-res 64] [--no-brick] [--realisations 1] [--starts 1] [--structure] [--validate 2]
(--validate 0 is the search before the fresh-realisation validation; --starts 3 --structure the multi-start)

Targets: n masks rendered at the working size (default 512) from random parameter vectors (sample_params, not
database entries, random shift), plus the real castle_brick_broken_06 brick mask (band-passed height, 512 px).
Each is fitted with fit_pptbf_mask (torch single-threaded, i.e. one core) at the database resolution.
Database: --db DIR, else the bundled default if present, else a tiny in-memory one (--tiny entries at --tiny-res px).
Columns: fit size, evaluations, seconds, loss of the query result alone (verbatim top-1), final loss (both at the
fit's own realisation), then the alignment-free scores of a *fresh* realisation (what a graph node renders):
  floor   descriptor distance of 3 other realisations of the TRUE parameters to the target (a perfect fit's score)
  r fit   realisation_distance(fit) / floor     (acceptance: <= 1.5 on most targets)
  r q     the same for the query result alone (top-1 entry, target threshold)
  IoU fl  best-shift IoU of another realisation of the true parameters (the IoU ceiling; chance is f/(2-f))
  IoU fit best-shift IoU of the fit (its own realisation) against the target
Timings are wall-clock on a shared machine: noisy.
"""
from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

from pptbf_db import pptbf as pp
from workers.masks import (
    MaskFitConfig,
    MaskLoss,
    best_shift_iou,
    downsample_mask,
    fit_pptbf_mask,
    nearer_is_complement,
    realisation_distance,
)

REPO = Path(__file__).resolve().parents[1]


def load_index(db: str | None, tiny: int, tiny_res: int = 64):
    """The index to fit against (named folder, bundled default, or a tiny in-memory one)."""
    from pptbf_db.index import PPTBFIndex, default_database_path

    path = Path(db) if db else default_database_path()
    if db or (path / "meta.json").is_file():
        return PPTBFIndex.load(path), str(path)
    from pptbf_db.build import render_and_describe
    from pptbf_db.descriptor import DescriptorConfig, fit_pca
    from workers.lattice import analyse_lattice

    cfg = DescriptorConfig(dim=64)
    params = pp.sample_params(np.random.default_rng(0), tiny, ref_width=tiny_res)
    t0 = time.perf_counter()
    raw, white, _ = render_and_describe(params, tiny_res, cfg, analyse_lattice)
    pca = fit_pca(raw, cfg)
    print(f"# tiny in-memory database: {tiny} entries at {tiny_res} px built in {time.perf_counter() - t0:.1f} s")
    return PPTBFIndex(params, pca.transform(raw), pca, cfg, tiny_res, white), f"in-memory {tiny}@{tiny_res}"


def brick_mask(size: int) -> np.ndarray | None:
    """The real brick mask at `size` px (None when the shared materials are missing)."""
    sys.path.insert(0, str(REPO))
    from scipy import ndimage

    from tests.conftest import real_material_files
    from workers.height import normal_to_height
    from workers.maps import load_material

    f = real_material_files("castle_brick_broken_06")
    if not Path(f["albedo"]).is_file():
        return None
    mat = load_material(f["albedo"], f["normal"], f["roughness"], roughness_channel=f["roughness_channel"],
                        working_size=size)
    h, _ = normal_to_height(mat.normal)
    k = size / 256.0
    band = ndimage.gaussian_filter(h, 0.7 * k) - ndimage.gaussian_filter(h, 3 * k)
    return band > np.quantile(band, 0.3)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--db", default=None, help="database folder (default: bundled, else tiny in-memory)")
    ap.add_argument("--tiny", type=int, default=400, help="entries of the in-memory fallback database")
    ap.add_argument("--tiny-res", type=int, default=64, help="resolution (px) of the in-memory fallback database")
    ap.add_argument("--n", type=int, default=6, help="random-parameter targets")
    ap.add_argument("--budget", type=float, default=MaskFitConfig.time_budget_s,
                    help="time limit per mask (s), a safety net: --evals decides how far a fit searches")
    ap.add_argument("--evals", type=int, default=300, help="evaluation budget per mask")
    ap.add_argument("--working", type=int, default=512, help="working size of the targets (px)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-brick", action="store_true")
    ap.add_argument("--realisations", type=int, default=1, help="realisations averaged in the fit loss")
    ap.add_argument("--starts", type=int, default=MaskFitConfig.starts, help="multi-start count (1: single start)")
    ap.add_argument("--structure", action="store_true", help="large period/aspect/rotation moves in the search")
    ap.add_argument("--validate", type=int, default=MaskFitConfig.validate,
                    help="fresh realisations for the final choice (0: best at the fit's own realisation)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    index, name = load_index(args.db, args.tiny, args.tiny_res)
    print(f"# database: {name}, {len(index)} entries, resolution {index.resolution} px")
    rng = np.random.default_rng(args.seed)
    W = args.working
    targets = []
    for i, p in enumerate(pp.sample_params(rng, args.n, ref_width=W)):
        shift = tuple(rng.uniform(0, 4, size=2))
        targets.append((f"random{i} t{int(p[1])}", pp.render_mask(p, W, shift=shift), p))
    if not args.no_brick:
        b = brick_mask(W)
        if b is not None:
            targets.append(("castle_brick", b, None))
    cfg = MaskFitConfig(max_evals=args.evals, time_budget_s=args.budget, seed=args.seed,
                        realisations=args.realisations, starts=args.starts,
                        structure_moves=args.structure, validate=args.validate)
    hdr = f"{'target':<16} {'fit px':>7} {'evals':>6} {'secs':>6} {'s/eval':>7} {'L query':>8} {'L final':>8} " \
          f"{'floor':>6} {'r fit':>6} {'r q':>6} {'IoU fl':>6} {'IoU chance':>10} {'IoU q':>6} {'IoU fit':>7}"
    print(hdr)
    print("-" * len(hdr))
    rows = []
    for label, target, truth in targets:
        fit = fit_pptbf_mask(target, index, config=cfg)
        w, h = fit.fit_size
        small = downsample_mask(target, w, h)
        loss = MaskLoss(small, index)
        qc = fit.meta.get("query_complement")
        if qc is None:      # the lattice-first path records no query polarity: the nearer one, as the query path
            qc = nearer_is_complement(index.query(small, k=1), index.query(~small, k=1))
        q = index.query(~small if qc else small, k=1)[0]
        qm = loss.render(q.params, qc, threshold_from_target=False)
        iou_q = best_shift_iou(qm, small)[0]
        iou_f = best_shift_iou(fit.render(), small)[0]
        f = float(small.mean())
        floor = r_fit = r_q = iou_fl = float("nan")
        if truth is not None:
            t = np.array(truth, dtype=np.float64)
            t[pp.PARAM_INDEX["resolution"]] = max(1.0, np.floor(t[pp.PARAM_INDEX["resolution"]] * w / W))
            floor = realisation_distance(loss, t)
            r_fit = realisation_distance(loss, fit.params, fit.complement) / floor
            r_q = realisation_distance(loss, q.params, qc) / floor
            other = pp.render_mask(loss.with_threshold(t), w, h, shift=(9.1, 13.7), ref_width=w)
            iou_fl = best_shift_iou(other, small)[0]
        rows.append((fit.loss_final < fit.loss_query, fit.seconds, iou_q, iou_f, r_fit, r_q))
        per_eval = fit.seconds / max(fit.evaluations, 1)
        print(f"{label:<16} {w:>7d} {fit.evaluations:>6d} {fit.seconds:>6.1f} {per_eval:>7.3f} "
              f"{fit.loss_query:>8.3f} {fit.loss_final:>8.3f} {floor:>6.3f} {r_fit:>6.2f} {r_q:>6.2f} "
              f"{iou_fl:>6.2f} {f / (2 - f):>10.2f} {iou_q:>6.2f} {iou_f:>7.2f}", flush=True)
    imp = np.array([r[0] for r in rows])
    secs = np.array([r[1] for r in rows])
    print("-" * len(hdr))
    print(f"improved over the query alone: {imp.sum()}/{len(rows)} ({100 * imp.mean():.0f}%); "
          f"median {np.median(secs):.1f} s per mask, max {secs.max():.1f} s (paper: ~13 min per mask); "
          f"mean best-shift IoU query {np.mean([r[2] for r in rows]):.2f} -> fit {np.mean([r[3] for r in rows]):.2f}")
    rf = np.array([r[4] for r in rows if np.isfinite(r[4])])
    rq = np.array([r[5] for r in rows if np.isfinite(r[5])])
    if rf.size:
        print(f"random targets, fresh-realisation distance / truth floor: fit median {np.median(rf):.2f}, "
              f"<= 1.5 in {int((rf <= 1.5).sum())}/{rf.size}; query alone median {np.median(rq):.2f}, "
              f"<= 1.5 in {int((rq <= 1.5).sum())}/{rq.size}")


if __name__ == "__main__":
    main()
