"""Re-run the recomposition of a finished job's materials with other settings, and score each map.

The decomposition, noise models and mask fits of the job are kept (read from its folders); only the
recomposition runs again, so a change of its settings is measured on the same masks and leaves. Each material's
optimised graph goes to ``--out`` (the job is not touched). The score is the evaluation's VGG-19 Gram distance
(workers.evaluate: 4 layers, left half of the input as reference) in units of the input's own half-to-half
distance, averaged over ``--seeds`` evaluation realisations, per map, with the per-layer ratios (which VGG depth
carries the error: relu1_1..relu4_1). ``--options '{}'`` with ``--score-only`` scores the job's published graphs
as they are (the baseline)::

    python bench/rerecompose.py /tmp/w/six512 --score-only --materials plastered,coast
    python bench/rerecompose.py /tmp/w/six512 --options '{"iterations": 100}' --out /tmp/rc100
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from service.folder import MaterialFolder  # noqa: E402
from service.pipeline import load_recompose_inputs, read_npz  # noqa: E402
from workers import graph as G  # noqa: E402

MAPS = ("albedo", "normal", "roughness", "height")


def layer_distances(ref, cand) -> np.ndarray:
    """Per-layer VGG-19 Gram distance of two HxWxC images, as workers.evaluate scores them (mean = its value)."""
    from pptbf_db.features import gram_layer_distances
    from workers.evaluate import vgg_grams

    return gram_layer_distances(vgg_grams(cand[None]), vgg_grams(ref[None]))[:, 0].numpy()


def score(mat: G.ProceduralMaterial, inputs: dict, seeds: list[int]) -> dict[str, tuple[float, np.ndarray]]:
    """Per map: (Gram / floor, per-layer ratios) of the graph's maps at the reference's size and pattern scale."""
    from workers.evaluate import reference_size, split_halves, vgg_image

    w, h = reference_size(inputs)
    outs = [G.evaluate(mat, w, h, scale=mat.working_scale, seed=int(mat.seed) + s) for s in seeds]
    res = {}
    for k in MAPS:
        if k not in inputs or k not in outs[0]:
            continue
        ref, half = split_halves(inputs[k])
        hr = (float(ref.min()), float(ref.max())) if k == "height" else None
        r = vgg_image(k, ref, hr)
        floor = layer_distances(r, vgg_image(k, half, hr))
        d = np.mean([layer_distances(r, vgg_image(k, o[k][:h, :w], hr)) for o in outs], axis=0)
        res[k] = (float(d.mean() / floor.mean()), d / np.maximum(floor, 1e-12))
    return res


def recompose(folder: MaterialFolder, options: dict) -> tuple[G.ProceduralMaterial, dict]:
    """The folder's graph assembled and optimised again from its stage outputs with ``options``."""
    from workers.actors import Recomposer

    mat, tree, noises, fits, pieces = load_recompose_inputs(folder)
    return Recomposer().run(mat, tree, noises, fits, options=options, seed=int(G.load(folder.published).seed),
                            pieces=pieces)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("job", type=Path, help="a finished job's output folder")
    ap.add_argument("--materials", default="", help="comma-separated material names (default: every folder)")
    ap.add_argument("--options", default="{}", help="recompose settings as JSON, e.g. '{\"iterations\": 100}'")
    ap.add_argument("--score-only", action="store_true", help="score the published graphs, no recomposition")
    ap.add_argument("--seeds", default="1000,1001", help="evaluation seeds (offsets to the graph's seed)")
    ap.add_argument("--out", type=Path, default=Path("rerecompose_out"), help="folder for the optimised graphs")
    a = ap.parse_args(argv)
    names = [n for n in a.materials.split(",") if n] or sorted(
        p.name for p in a.job.iterdir() if (p / "material.json").is_file())
    seeds = [int(s) for s in a.seeds.split(",")]
    options = json.loads(a.options)
    ratios = []
    print(f"{'material':10s} {'map':9s} {'gram/floor':>10s}  per layer (relu1_1..4_1)   seconds")
    for name in names:
        folder = MaterialFolder.of(a.job / name)
        if not folder.published.is_file():
            print(f"{name}: no published graph in {folder.path}, skipped", file=sys.stderr)
            continue
        t0 = time.perf_counter()
        if a.score_only:
            mat = G.load(folder.published)
        else:
            mat, _ = recompose(folder, options)
            a.out.mkdir(parents=True, exist_ok=True)
            G.save(mat, a.out / f"{name}.json")
        secs = time.perf_counter() - t0
        for k, (r, per) in score(mat, read_npz(folder.working_maps), seeds).items():
            ratios.append(r)
            print(f"{name:10s} {k:9s} {r:10.2f}  {' '.join(f'{x:5.1f}' for x in per)}   {secs:7.1f}", flush=True)
    if ratios:
        print(f"median gram/floor over {len(ratios)} maps: {statistics.median(ratios):.3f}")
    return 0 if ratios else 1


if __name__ == "__main__":
    sys.exit(main())
