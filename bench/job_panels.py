"""Input beside output for every material of a finished job, at the same pattern scale (what a user judges).

Run: python bench/job_panels.py JOB_DIR [--out DIR] [--seed 0]

Per material folder of JOB_DIR (one with material.json), one PNG: top row the input albedo at the working size
(load/maps) | the procedural albedo regenerated at the same size and pattern size (a fresh seed); bottom row each
decomposition mask (decompose/masks) | its fitted PPTBF mask rendered as the graph renders it (a nested split's
inside its parent's fitted mask, as the graph uses it). Also prints, per
material and mask, the lattice of the decomposition mask and of the fitted mask (period, kind).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from workers import graph  # noqa: E402
from workers import lattice as L  # noqa: E402
from workers.assemble import graph_id  # noqa: E402
from workers.maps import linear_to_srgb, read_image, write_image  # noqa: E402


def _rgb(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=np.float32)
    if a.ndim == 2:
        a = a[..., None]
    return np.repeat(a[..., :1], 3, axis=2) if a.shape[2] == 1 else a[..., :3]


def material_panel(mdir: Path, seed: int) -> tuple[np.ndarray, list[str]]:
    """The panel of one material folder and its lattice lines."""
    mat = graph.load(mdir / "material.json")
    albedo_in = read_image(mdir / "load" / "maps" / "albedo.png")[..., :3]
    h, w = albedo_in.shape[:2]
    maps = graph.evaluate(mat, w, h, scale=mat.working_scale, seed=seed)  # the working input's pattern size
    rows = [np.concatenate([albedo_in, np.ones((h, 4, 3), np.float32), linear_to_srgb(maps["albedo"])[..., :3]], 1)]
    lines, fits = [], {}
    for fit_file in sorted((mdir / "masks").glob("*.json"), key=lambda f: (f.stem.count("."), f.stem)):
        doc = json.loads(fit_file.read_text())
        node = doc["node"]
        src = mdir / "decompose" / "masks" / f"{fit_file.stem}.png"
        if not src.is_file():
            continue
        target = read_image(src)[..., 0] > 0.5
        nid = graph_id("mask", node)    # the recomposition may have given it the crisp template's cells
        if nid not in mat.nodes or mat.nodes[nid]["type"] != "pptbf":
            continue
        ctx = graph.EvalContext(width=w, height=h, seed=seed, working_size=mat.working_size)
        fitted = graph.evaluate_node(mat, nid, ctx)[..., 0] > 0.5
        if doc.get("parent") in fits:   # a nested split's mask as the graph uses it: inside its parent's fit
            fitted &= fits[doc["parent"]]
        fits[node] = fitted
        lt, lf = L.analyse_lattice(target), L.analyse_lattice(fitted)
        per, ang = L.compare_lattices(lt, lf)
        lines.append(f"{mdir.name} {node}: target {lt.kind} period {lt.period or 0:.1f} px | fit {lf.kind} period "
                     f"{lf.period or 0:.1f} px | period error {100 * per:.1f} %, angle {ang:.1f} deg")
        rows.append(np.concatenate([_rgb(target), np.ones((h, 4, 3), np.float32), _rgb(fitted)], 1))
    sep = np.ones((4, rows[0].shape[1], 3), np.float32)
    parts = []
    for r in rows:
        parts += [r, sep]
    return np.concatenate(parts[:-1], 0), lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("job", type=Path)
    ap.add_argument("--out", type=Path, default=None, help="panel folder (default JOB/panels)")
    ap.add_argument("--seed", type=int, default=1, help="realisation of the procedural maps")
    args = ap.parse_args()
    out = args.out or args.job / "panels"
    for mdir in sorted(p.parent for p in args.job.glob("*/material.json")):
        panel, lines = material_panel(mdir, args.seed)
        path = write_image(out / f"{mdir.name}.png", np.clip(panel, 0, 1), bits=8)
        print("\n".join(lines) + f"\n-> {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
