"""Recomposition benchmark (issue 7): a 3-leaf material fitted from a real one, optimised, table printed.

Target: 256x256 working size, 3 leaves, under 60 s on 2 CPU cores. Leaves are two PPTBF masks (random
parameters, not fitted: this measures the optimiser, not the mask fit) and the rest; every map of a leaf is a
``noise`` node fitted on the leaf's pixels. Run::

    python bench/recompose.py --size 256 --iterations 100 --optimizer adam lbfgs --threads 2
    python bench/recompose.py --npz maps.npz ...   # arrays albedo/normal/roughness/height (+ height_scale)
    python bench/recompose.py --size 512 --iterations 60 --optimizer adam --features vgg19 random \
        --loss-size 128 256 --vgg-layers 3 4        # what the loss resolution and layers cost and keep

"check" is independent of the loss settings: the mean over albedo, normal, roughness, height of the full-size,
4-layer VGG-19 Gram distance (workers.evaluate) of the optimised maps (another seed) to the target.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from workers import graph as G  # noqa: E402
from workers.assemble import assemble_material  # noqa: E402
from workers.recompose import RecomposeConfig, optimise  # noqa: E402
from workers.tree import MaskNode, root_node  # noqa: E402


def load_target(args) -> dict:
    """Target maps (dict) at ``args.size`` from an npz or one of the shared real materials."""
    if args.npz:
        d = np.load(args.npz)
        return {k: d[k] for k in d.files}
    from tests.conftest import real_material_files
    from workers.maps import load_material

    f = real_material_files(args.material)
    m = load_material(f["albedo"], f["normal"], f["roughness"], roughness_channel=f["roughness_channel"],
                      working_size=args.size)
    return {**{k: v for k, v in m.maps().items() if v is not None}, "height_scale": np.float32(m.height_scale)}


def build(target: dict, size: int, leaves: int, seed: int = 0) -> G.ProceduralMaterial:
    """Material with ``leaves`` leaves: PPTBF masks carve the root, the last leaf is what is left."""
    from pptbf_db import pptbf as pp
    from workers.noise import fit_noise, noise_params

    proc = G.new_material(seed=seed, working_size=(size, size))
    ctx = G.EvalContext(size, size, 1.0, seed, (size, size))
    tree = root_node(size, size)
    tree.method = "matting"
    left = np.ones((size, size), bool)
    masks = {}
    for i in range(leaves - 1):
        p = [float(x) for x in pp.sample_params(np.random.default_rng(seed + 11 * i + 1), 1, ref_width=size)[0]]
        nid = proc.add(f"mask{i}", "pptbf", {"params": p, "ref_width": size, "complement": False})
        m = (G.evaluate_node(proc, nid, ctx)[..., 0] > 0.5) & left
        left &= ~m
        tree.children.append(MaskNode(f"L{i}", m))
        masks[f"L{i}"] = nid
    proc.add("sum_masks", "add", {}, **{f"m{i}": f"mask{i}" for i in range(leaves - 1)})
    masks[f"L{leaves - 1}"] = proc.add("rest", "level", {"a": -1.0, "d": 1.0, "clamp": True}, input="sum_masks")
    tree.children.append(MaskNode(f"L{leaves - 1}", left))
    leaf_nodes = {}
    for leaf in tree.children:
        leaf_nodes[leaf.id] = {m: proc.add(f"{leaf.id}_{m}", "noise", noise_params(fit_noise(target[m], leaf.mask)))
                               for m in ("albedo", "roughness", "height")}
    assemble_material(tree, leaf_nodes, masks, proc, height_strength=float(target.get("height_scale", 1.0)))
    return proc


def check(proc: G.ProceduralMaterial, maps: dict) -> float:
    """Mean full-size 4-layer VGG-19 Gram distance of the material's maps (seed 5) to the target maps."""
    from workers.evaluate import gram_distance_images, vgg_image

    h, w = maps["albedo"].shape[:2]
    out = G.evaluate(proc, w, h, scale=proc.working_scale, seed=5)
    names = [m for m in ("albedo", "normal", "roughness", "height") if m in out and m in maps]
    hr = (float(maps["height"].min()), float(maps["height"].max())) if "height" in maps else None
    return float(np.mean([gram_distance_images(vgg_image(m, maps[m], hr)[None], vgg_image(m, out[m], hr)[None])
                          for m in names]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--material", default="castle_brick_broken_06")
    ap.add_argument("--npz", help="target maps as an npz (albedo, normal, roughness, height, height_scale)")
    ap.add_argument("--save-npz", help="write the loaded target maps to this npz and exit")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--leaves", type=int, default=3)
    ap.add_argument("--iterations", type=int, nargs="+", default=[100])
    ap.add_argument("--optimizer", nargs="+", default=["adam", "lbfgs"])
    ap.add_argument("--device", nargs="+", default=["cpu"])
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads (the 2-core target)")
    ap.add_argument("--lr", type=float, default=0.02)
    ap.add_argument("--features", nargs="+", default=["vgg19"])
    ap.add_argument("--loss-size", type=int, nargs="+", default=[128])
    ap.add_argument("--vgg-layers", type=int, nargs="+", default=[3])
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    target = load_target(args)
    if args.save_npz:
        np.savez_compressed(args.save_npz, **target)
        print("wrote", args.save_npz)
        return 0
    t0 = time.perf_counter()
    proc = build(target, args.size, args.leaves)
    t_build = time.perf_counter() - t0
    maps = {k: v for k, v in target.items() if k != "height_scale"}
    rows = [("size", "leaves", "iterations", "optimizer", "features", "loss size", "layers", "device", "threads",
             "seconds", "s/iter", "loss before", "loss after", "ratio", "check before", "check after")]
    check_before = check(proc, maps)
    combos = [(f, ls, nl) for f in args.features for ls in args.loss_size
              for nl in (args.vgg_layers if f == "vgg19" else [0])]
    for dev in args.device:
        for opt in args.optimizer:
            for it in args.iterations:
                for feats, lsize, nl in combos:
                    cfg = RecomposeConfig(iterations=it, optimizer=opt, device=dev, lr=args.lr, features=feats,
                                          loss_size=lsize, vgg_layers=max(nl, 1))
                    res = optimise(proc, maps, cfg)
                    rows.append((f"{args.size}", f"{args.leaves}", f"{it}", opt, feats, f"{lsize}", f"{nl or '-'}",
                                 res.device, f"{args.threads}", f"{res.seconds:.1f}",
                                 f"{res.seconds / max(it, 1):.3f}", f"{res.loss_before:.4f}", f"{res.loss_after:.4f}",
                                 f"{res.loss_before / max(res.loss_after, 1e-12):.2f}", f"{check_before:.4f}",
                                 f"{check(res.material, maps):.4f}"))
                    print("  ".join(rows[-1]), flush=True)
    print(f"\n{args.material if not args.npz else args.npz}: noise fits + masks built in {t_build:.1f} s")
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    for j, r in enumerate(rows):
        print("  ".join(c.ljust(w) for c, w in zip(r, widths)))
        if j == 0:
            print("  ".join("-" * w for w in widths))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
