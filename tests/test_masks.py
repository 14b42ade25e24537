"""Mask proceduralisation: PPTBF query-and-optimise fitting, instance sampling, "pptbf"/"instances" graph nodes.

A tiny PPTBF index (60 entries, 64 px) is built in memory with the database's own render/describe/PCA functions,
so the tests do not depend on the bundled database and need no Ray.
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy import ndimage

from pptbf_db import pptbf as pp
from pptbf_db.build import render_and_describe
from pptbf_db.descriptor import DescriptorConfig, fit_pca
from pptbf_db.index import PPTBFIndex
from workers import graph
from workers.assemble import add_instances_node, add_mask_node
from workers.errors import GraphError, InputError
from workers.lattice import analyse_lattice
from workers.mask_opt import DISCRETE_VALUES, Budget, ContinuousSpace, OptSettings, explore, optimise, structure_sweep
from workers.masks import (
    MaskFit,
    MaskFitConfig,
    MaskLoss,
    best_shift_iou,
    downsample_mask,
    fit_inpainted_mask,
    fit_pptbf_mask,
    realisation_distance,
)
from workers.nodes.instances import instance_shares, sample_instances

from .conftest import real_material_files

RES = 64
I = pp.PARAM_INDEX


@pytest.fixture(scope="module")
def tiny_index() -> PPTBFIndex:
    """60 database-like entries at 64 px, described and PCA-reduced exactly like a real database, with the
    weight-free random Gram features: these tests exercise the query-and-optimise mechanics, many hundreds of
    descriptor evaluations, where the VGG-19 descriptor costs ~10x more (the bundled database's descriptor is
    checked on real masks in tests/test_layout_fit.py and bench/masks.py)."""
    cfg = DescriptorConfig(dim=32, extractor="random")
    params = pp.sample_params(np.random.default_rng(0), 60, ref_width=RES)
    raw, white, _ = render_and_describe(params, RES, cfg, analyse_lattice)
    pca = fit_pca(raw, cfg)
    return PPTBFIndex(params, pca.transform(raw), pca, cfg, RES, white)


def _grid_mask(n: int, cell: int) -> np.ndarray:
    """n x n squares of `cell` px separated by 1 px gaps (n*n 4-connected components)."""
    m = np.zeros((n * cell, n * cell), dtype=bool)
    for k in range(cell - 1):
        m[k::cell, :] |= True
    keep = np.zeros(cell, dtype=bool)
    keep[:cell - 1] = True
    return m & np.tile(keep, n)[None, :]


# ----------------------------------------------------------------------------- instance sampling


def test_sample_instances_reproduces_shares_on_large_canvas():
    parent = _grid_mask(100, 6)          # 10,000 components
    shares = [0.5, 0.3, 0.2]
    labels = sample_instances(parent, shares, np.random.default_rng(3))
    assert labels.shape == parent.shape and labels.dtype.kind == "i"
    assert np.all(labels[~parent] == -1) and np.all(labels[parent] >= 0)
    lab, n = ndimage.label(parent)
    assert n == 10_000
    # each component carries exactly one cluster
    mins = ndimage.minimum(labels, lab, np.arange(1, n + 1))
    maxs = ndimage.maximum(labels, lab, np.arange(1, n + 1))
    assert np.array_equal(mins, maxs)
    got = instance_shares(labels, 3)
    assert np.all(np.abs(got - shares) <= 0.1 * np.asarray(shares)), got
    # seeded: same seed same labels, another seed other labels
    assert np.array_equal(labels, sample_instances(parent, shares, np.random.default_rng(3)))
    assert not np.array_equal(labels, sample_instances(parent, shares, np.random.default_rng(4)))


def test_sample_instances_cut_cells_joined_through_gaps():
    """Cells whose outlines have gaps: components give one piece and one cluster everywhere; cut at the necks,
    each cell draws its own cluster (both clusters appear, each cell essentially one cluster)."""
    y, x = np.mgrid[:256, :256] % 32
    parent = _grid_mask(8, 32) | ((x == 31) & (y >= 12) & (y < 20)) | ((y == 31) & (x >= 12) & (x < 20))
    rng = np.random.default_rng(0)
    assert np.unique(sample_instances(parent, [0.5, 0.5], rng)[parent]).size == 1
    labels = sample_instances(parent, [0.5, 0.5], np.random.default_rng(0), separate=10.0)
    assert np.all(labels[~parent] == -1) and np.all(labels[parent] >= 0)
    cell = (np.arange(256)[:, None] // 32) * 8 + np.arange(256)[None, :] // 32
    purity = [np.bincount(labels[(cell == k) & parent]).max() / ((cell == k) & parent).sum() for k in range(64)]
    ones = np.mean([labels[(cell == k) & parent].mean() > 0.5 for k in range(64)])
    assert min(purity) >= 0.9 and 0.3 < ones < 0.7, (min(purity), ones)


def test_sample_instances_bad_shares():
    parent = _grid_mask(4, 6)
    with pytest.raises(InputError, match="shares"):
        sample_instances(parent, [0.5, -0.1], np.random.default_rng(0))
    with pytest.raises(InputError, match="shares"):
        sample_instances(parent, [], np.random.default_rng(0))


# ----------------------------------------------------------------------------- graph nodes


def _fit_from_params(params: np.ndarray, complement: bool = False, width: int = RES) -> MaskFit:
    """A MaskFit holding known parameters (no optimisation)."""
    return MaskFit(params=np.asarray(params, dtype=np.float64), complement=complement, loss_query=1.0,
                   loss_final=0.5, evaluations=0, seconds=0.0, history=[], fit_size=(width, width))


def _brickish_params() -> np.ndarray:
    """A running-bond brick pattern (tiling 4), cells about 16 px at 64 px."""
    p = pp.sample_params(np.random.default_rng(1), 1, ref_width=RES)[0]
    p[[I["tiling"], I["jitter"], I["resolution"], I["rotation"], I["aspect_ratio"]]] = [4, 0.2, 16, 0, 0.5]
    p[[I["distortion_base"], I["window_shape"], I["window_larp"], I["window_blend"], I["window_sigma"]]] = [
        0.0, 3, 1.0, 1.0, 2.0]
    p[[I["feature_mixture"], I["window_smoothness"]]] = [0, 0.0]
    p[0] = 0.5
    return p


def test_pptbf_node_matches_fit_and_scales(tmp_path):
    p = _brickish_params()
    fit = _fit_from_params(p, complement=True)
    fit.shift = (0.3, 0.7)
    mat = graph.new_material(seed=5, working_size=(4 * RES, 4 * RES))
    add_mask_node(mat, "m", fit, pin_shift=True)
    mat.maps.append({"name": "mask", "node": "m"})
    path = graph.save(mat, tmp_path / "material.json")
    doc = json.loads(path.read_text())
    node = next(n for n in doc["nodes"] if n["id"] == "m")
    assert node["params"]["ref_width"] == 4 * RES and node["params"]["complement"] is True
    assert node["params"]["params"][I["resolution"]] == pytest.approx(16 * 4)   # period in working pixels
    loaded = graph.load(path)
    base = graph.evaluate(loaded, 4 * RES, 4 * RES)["mask"][..., 0]
    assert set(np.unique(base)) <= {0.0, 1.0}
    # at the working size the node renders the fitted pattern magnified 4x: compare at the fit resolution
    ref = fit.render()
    assert (base[::4, ::4] > 0.5).__eq__(ref).mean() > 0.97            # same sample points: same pattern
    # super-resolution: scale 2 at twice the size = same pattern, more pixels
    sr = graph.evaluate(loaded, 8 * RES, 8 * RES, scale=2.0)["mask"][..., 0]
    assert (sr[::2, ::2] == base).mean() > 0.97
    # extension: a larger extent at scale 1 continues the same pattern
    ext = graph.evaluate(loaded, 6 * RES, 5 * RES)["mask"][..., 0]
    assert ext.shape == (5 * RES, 6 * RES)
    assert (ext[:4 * RES, :4 * RES] == base).mean() > 0.97


def test_pptbf_node_seed_gives_new_realisation_and_parent_input():
    p = _brickish_params()
    mat = graph.new_material(seed=1, working_size=(RES, RES))
    add_mask_node(mat, "parent", _fit_from_params(p))
    add_mask_node(mat, "child", _fit_from_params(pp.sample_params(np.random.default_rng(2), 1, ref_width=RES)[0]),
                  parent="parent")
    mat.maps += [{"name": "a", "node": "parent"}, {"name": "b", "node": "child"}]
    r1 = graph.evaluate(mat, RES, RES, seed=1)
    r2 = graph.evaluate(mat, RES, RES, seed=2)
    assert not np.array_equal(r1["a"], r2["a"])                         # shift from the seed
    assert np.array_equal(r1["a"], graph.evaluate(mat, RES, RES, seed=1)["a"])
    assert abs(r1["a"].mean() - 0.5) < 0.05                             # white fraction ~ T
    assert np.all(r1["b"] <= r1["a"])                                   # child stays inside its parent


def test_instances_node_one_hot_within_parent():
    mat = graph.new_material(seed=3, working_size=(128, 128))
    add_mask_node(mat, "bricks", _fit_from_params(_brickish_params(), width=128))
    add_instances_node(mat, "inst", "bricks", [2, 1])
    mat.add("c1", "channel", {"channels": [1]}, input="inst")
    mat.maps += [{"name": "bricks", "node": "bricks"}, {"name": "inst", "node": "inst"}, {"name": "c1", "node": "c1"}]
    out = graph.evaluate(mat, 256, 256)
    inst, parent = out["inst"], out["bricks"][..., 0]
    assert inst.shape == (256, 256, 2)
    assert np.array_equal(inst.sum(-1), parent)                         # one-hot exactly inside the parent
    assert np.array_equal(out["c1"][..., 0], inst[..., 1])
    lab, n = ndimage.label(parent > 0.5)
    first = ndimage.labeled_comprehension(inst[..., 1], lab, np.arange(1, n + 1), np.max, float, 0)
    assert n > 40 and 0.15 < first.mean() < 0.55                       # ~1/3 of the bricks in cluster 1


def test_node_validation_errors():
    mat = graph.new_material()
    mat.add("m", "pptbf", {"params": [0.5] * 28, "ref_width": 64})
    mat.maps.append({"name": "mask", "node": "m"})
    with pytest.raises(GraphError, match="29"):
        graph.from_json(mat.to_json())
    mat.nodes["m"]["params"] = {"params": [0.5] * 29, "ref_width": -1}
    with pytest.raises(GraphError, match="ref_width"):
        graph.from_json(mat.to_json())
    mat.nodes["m"]["params"] = {"params": [0.5] * 29, "ref_width": 64, "shift": [1]}
    with pytest.raises(GraphError, match="shift"):
        graph.from_json(mat.to_json())
    mat.add("i", "instances", {"shares": [1, -2]}, parent="m")
    mat.nodes["m"]["params"] = {"params": [0.5] * 29, "ref_width": 64}
    with pytest.raises(GraphError, match="shares"):
        graph.from_json(mat.to_json())
    mat.nodes["i"]["params"] = {"shares": [1, 2], "separate": -3}
    with pytest.raises(GraphError, match="separate"):
        graph.from_json(mat.to_json())


# ----------------------------------------------------------------------------- optimiser scaffolding


def test_optimiser_recovers_synthetic_optimum():
    """On a cheap synthetic loss (distance to a known vector in the optimiser's own coordinates), the
    alternating continuous/discrete search finds the discrete optimum and gets close on the continuous part."""
    rng = np.random.default_rng(0)
    space = ContinuousSpace.for_width(RES)
    truth = pp.sample_params(rng, 1, ref_width=RES)[0]
    truth[[I["feature_mixture"], I["tiling"]]] = [2, 7]
    zt = space.encode(truth)
    disc = [I[n] for n in DISCRETE_VALUES]

    def loss(p):
        return float(np.sum((space.encode(p) - zt) ** 2) + 0.5 * np.sum(p[disc] != truth[disc]))

    start = pp.sample_params(np.random.default_rng(1), 1, ref_width=RES)[0]
    budget = optimise(loss, start, RES, OptSettings(rounds=3, max_evals=1500, time_budget_s=60, seed=0))
    best = budget.best_params
    assert budget.evaluations <= 1500
    assert np.array_equal(best[disc], truth[disc])
    assert np.abs(space.encode(best) - zt).max() < 0.1
    assert budget.history == sorted(budget.history, reverse=True)      # best-ever is monotone
    assert budget.best_loss < loss(start) / 20


def test_budget_limits_and_best_ever():
    calls = []

    def loss(p):
        calls.append(1)
        return float(abs(p[2] - 0.3))

    b = Budget(loss, max_evals=5, deadline=math.inf)
    x = pp.sample_params(np.random.default_rng(0), 1)[0]
    for j in (0.9, 0.3, 0.5, 0.3):                                     # the repeat is cached, not counted
        y = x.copy()
        y[2] = j
        b(y)
    assert b.evaluations == 3 and len(calls) == 3 and b.best_params[2] == pytest.approx(0.3)
    res = optimise(loss, x, RES, OptSettings(rounds=2, max_evals=5, time_budget_s=60), budget=b)
    assert res.evaluations == 5 and res.best_loss == pytest.approx(0.0)


def test_structure_sweep_jumps_period_and_orientation():
    """Large layout moves a small-step local search would not make: period x2 and a 90-degree turn are found in
    one sweep of 9 evaluations; `explore` stays within its own budget."""
    truth = _brickish_params()
    start = truth.copy()
    start[I["resolution"]] = 8
    start[I["rotation"]] = (truth[I["rotation"]] + 1.5) % 2.0

    def loss(p):
        return float(abs(math.log(p[I["resolution"]] / truth[I["resolution"]]))
                     + min(abs(p[I["rotation"]] - truth[I["rotation"]]) % 2.0,
                           2.0 - abs(p[I["rotation"]] - truth[I["rotation"]]) % 2.0))

    b = Budget(loss, max_evals=20, deadline=math.inf)
    best = structure_sweep(b, start, RES)
    assert b.evaluations == 10                                          # start + 4 period + 2 aspect + 3 turns
    assert best[I["resolution"]] == 16 and best[I["rotation"]] == pytest.approx(truth[I["rotation"]])
    assert b.best_loss == pytest.approx(0.0)
    small = explore(Budget(loss, max_evals=12, deadline=math.inf), start, RES, OptSettings(structure_moves=True))
    assert small.evaluations <= 12 and small.best_loss < loss(start)


# ----------------------------------------------------------------------------- fitting


def _random_targets(rng: np.random.Generator, n: int, width: int = RES):
    """n (true params, unrelated params, shift, target mask) from sample_params at a random realisation, skipping
    degenerate draws (white fraction outside 5-95%, e.g. a flat PPTBF)."""
    out = []
    while len(out) < n:
        p, o = pp.sample_params(rng, 2, ref_width=width)
        shift = tuple(rng.uniform(0, 4, 2))
        target = pp.render_mask(p, width, shift=shift)
        if 0.05 < target.mean() < 0.95:
            out.append((p, o, shift, target))
    return out


def test_realisation_ceiling_iou_vs_descriptor(tiny_index):
    """Why the acceptance on random parameters uses the descriptor distance: the same parameters re-rendered at
    the same realisation give IoU 1 and distance 0, but another realisation (another shift of the point
    process) of the SAME parameters has a best-shift IoU near chance (f/(2-f) for white fraction f), far below
    0.8, while its descriptor distance (the "truth floor") stays well below that of unrelated parameters."""
    ious, floors, wrong = [], [], []
    for p, o, shift, target in _random_targets(np.random.default_rng(3), 6):
        loss = MaskLoss(target, tiny_index, shift=shift)
        assert best_shift_iou(pp.render_mask(p, RES, shift=shift), target)[0] == pytest.approx(1.0)
        assert loss(p, threshold_from_target=False) == pytest.approx(0.0, abs=1e-9)
        ious.append(best_shift_iou(pp.render_mask(p, RES, shift=(11.3, 9.7)), target)[0])
        floors.append(realisation_distance(loss, p))
        wrong.append(realisation_distance(loss, o))
    print("other-realisation IoU", np.round(ious, 2), "floor", np.round(floors, 2), "unrelated", np.round(wrong, 2))
    assert sum(i >= 0.8 for i in ious) <= 1, ious                     # IoU >= 0.8 is out of reach across realisations
    assert all(f > 0.05 for f in floors)
    assert sum(f < w for f, w in zip(floors, wrong)) >= 5, (floors, wrong)


def assert_fit_loss_is_real(fit, target, index, valid=None) -> None:
    """Checks that can fail, instead of ``loss_final <= loss_query`` (the fitter keeps the better of the two, so
    that held by construction): the reported loss is the descriptor distance of the mask the fit renders
    (recomputed here, independently), and it beats a baseline the fitter never sees, a white-noise mask of the
    target's density (a fit that returned a wrong or unstructured mask fails)."""
    small = downsample_mask(np.asarray(target, bool), *fit.fit_size) if np.shape(target) != fit.fit_size[::-1] \
        else np.asarray(target, bool)
    v = None if valid is None else (downsample_mask(np.asarray(valid, bool), *fit.fit_size)
                                    if np.shape(valid) != fit.fit_size[::-1] else np.asarray(valid, bool))
    loss = MaskLoss(small, index, v)
    assert loss.of_mask(fit.render()) == pytest.approx(fit.loss_final, rel=1e-3, abs=1e-6)
    noise = np.random.default_rng(0).random(small.shape) < small[v if v is not None else slice(None)].mean()
    assert fit.loss_final < loss.of_mask(noise), (fit.loss_final, loss.of_mask(noise))


def test_refit_random_parameters_reaches_truth_floor(tiny_index):
    """Issue 6 acceptance on truly random known parameters (sample_params, not database entries, random
    realisation), alignment-free by descriptor distance: a fresh realisation of the fit (as a graph node renders
    it) is at most 1.5x as far from the target as fresh realisations of the true parameters, on most targets;
    unrelated random parameters (same threshold) fail the same criterion, so it discriminates.
    Bundled-database numbers at 128 px: see bench/masks.py and the slow variant below."""
    ratios, wrong = [], []
    for p, o, _, target in _random_targets(np.random.default_rng(5), 5):
        loss = MaskLoss(target, tiny_index)
        floor = realisation_distance(loss, p)
        fit = fit_pptbf_mask(target, tiny_index, config=MaskFitConfig(max_evals=80, time_budget_s=120,
                                                                       lattice=False))   # the query path
        assert fit.evaluations <= 80
        assert_fit_loss_is_real(fit, target, tiny_index)
        assert np.isfinite(fit.meta["validation_loss"]) and len(fit.history) == fit.evaluations
        ratios.append(realisation_distance(loss, fit.params, fit.complement) / floor)
        wrong.append(realisation_distance(loss, o) / floor)
    print("fit / truth floor", np.round(ratios, 2), "unrelated / truth floor", np.round(wrong, 2))
    assert sum(r <= 1.5 for r in ratios) >= 3, (ratios, wrong)
    assert sum(r <= 1.5 for r in wrong) <= 1, (ratios, wrong)
    assert np.mean(ratios) < np.mean(wrong)


def test_query_path_with_the_vgg19_loss(tiny_index):
    """loss = "vgg19": the re-rank, search and validation use the VGG-19 Gram + layout distance; the reported
    loss is that distance of the mask the fit renders (recomputed here), it beats a white-noise mask of the
    target's density, and a fresh realisation of the fit is nearer the target than unrelated parameters'."""
    from workers.layout_fit import GramMaskLoss

    p, o, _, target = _random_targets(np.random.default_rng(5), 1)[0]
    fit = fit_pptbf_mask(target, tiny_index, config=MaskFitConfig(max_evals=40, time_budget_s=120, lattice=False,
                                                                  loss="vgg19", rerank_pool=8))
    assert fit.evaluations <= 40
    judge = GramMaskLoss(target)
    assert judge.of_mask(fit.render()) == pytest.approx(fit.loss_final, rel=1e-3, abs=1e-6)
    noise = np.random.default_rng(0).random(target.shape) < target.mean()
    assert fit.loss_final < judge.of_mask(noise)
    assert realisation_distance(judge, fit.params, fit.complement) < realisation_distance(judge, o)
    with pytest.raises(InputError, match="masks.loss"):
        MaskFitConfig(loss="lbp")


def test_multi_start_fit_respects_budget(tiny_index):
    """starts=3 with structure moves: the explored starts and the validation count against max_evals, the
    history has one (monotone) entry per evaluation, and the result is never worse than the query."""
    p, _, _, target = _random_targets(np.random.default_rng(8), 1)[0]
    cfg = MaskFitConfig(max_evals=120, time_budget_s=120, starts=3, structure_moves=True, lattice=False)
    fit = fit_pptbf_mask(target, tiny_index, config=cfg)
    assert fit.evaluations <= 120 and len(fit.history) == fit.evaluations
    assert fit.history == sorted(fit.history, reverse=True)
    assert np.isfinite(fit.meta["validation_loss"])
    assert_fit_loss_is_real(fit, target, tiny_index)
    plain = fit_pptbf_mask(target, tiny_index, config=MaskFitConfig(max_evals=120, time_budget_s=120, lattice=False))
    assert not np.array_equal(plain.params, fit.params) or plain.evaluations != fit.evaluations


@pytest.mark.slow
def test_refit_random_parameters_bundled_database():
    """The same acceptance with the bundled 5000-entry database at 128 px and a 150-evaluation budget, on 15
    targets: most (a majority, and the median) re-fitted within 1.5x of the truth floor.

    15 rather than 5 targets: the ratio of one target is noisy (it is measured on fresh realisations; the same
    fit with a 2 % different resolution measured 1.07 and 1.31), so 3 of 5 passed or failed on one ratio near
    1.5. Measured on these 15: 9 within 1.5x, median 1.37, mean 1.45 (generator pptbf/1: 11, 1.27, 1.44)."""
    from pptbf_db.index import default_database_path

    path = default_database_path()
    if not (path / "meta.json").is_file():
        pytest.skip("bundled PPTBF database not present")
    index = PPTBFIndex.load(path)
    ratios = []
    for p, _, _, target in _random_targets(np.random.default_rng(1), 15, 128):
        loss = MaskLoss(target, index)
        fit = fit_pptbf_mask(target, index, config=MaskFitConfig(max_evals=150, time_budget_s=60))
        assert fit.seconds < 70
        ratios.append(realisation_distance(loss, fit.params, fit.complement) / realisation_distance(loss, p))
    assert sum(r <= 1.5 for r in ratios) >= 8 and np.median(ratios) <= 1.5, np.round(ratios, 2)


def test_refit_known_parameters(tiny_index):
    """Masks from random known parameters near database entries (random threshold T in [0.3, 0.7], random
    changes of 3 window/feature parameters, sd 2% of their range) are re-fitted with best-shift IoU >= 0.8 in
    most cases (alignment-free: best IoU over shifts up to 16 px), better than the query result alone on
    average, and the loss never gets worse than the query's. Truly random targets: see the truth-floor tests below."""
    rng = np.random.default_rng(11)
    usable = np.flatnonzero(tiny_index.usable)
    ious, ious_q = [], []
    for j in rng.choice(usable, size=3, replace=False):
        p = tiny_index.params[j].copy()
        p[0] = rng.uniform(0.3, 0.7)
        for name in ("window_blend", "window_sigma", "feature_phase_shift"):
            s = pp.PARAM_SPECS[I[name]]
            p[I[name]] = np.clip(p[I[name]] + rng.normal(0, 0.02) * (s.hi - s.lo), s.lo, s.hi)
        target = pp.render_mask(p, RES)
        fit = fit_pptbf_mask(target, tiny_index, config=MaskFitConfig(max_evals=60, time_budget_s=120, top_k=5))
        assert_fit_loss_is_real(fit, target, tiny_index)
        assert fit.fit_size == (RES, RES) and fit.evaluations <= 60 and len(fit.history) == fit.evaluations
        back = MaskFit.from_dict(json.loads(json.dumps(fit.to_dict())))
        assert np.array_equal(back.params, fit.params) and back.fit_size == fit.fit_size
        ious.append(best_shift_iou(fit.render(), target)[0])
        q = tiny_index.query(~target if fit.meta["query_complement"] else target, k=1)[0]
        qm = pp.render_mask(q.params, RES)
        ious_q.append(best_shift_iou(~qm if fit.meta["query_complement"] else qm, target)[0])
    assert sum(i >= 0.8 for i in ious) >= 2, (ious, ious_q)
    assert np.mean(ious) > np.mean(ious_q)


def _brick_mask(materials_dir) -> np.ndarray:
    """Real brick mask: band-passed height of castle_brick_broken_06 at 256 px, top 70% = bricks, 128 px crop."""
    from workers.height import normal_to_height
    from workers.maps import load_material

    f = real_material_files("castle_brick_broken_06")
    mat = load_material(f["albedo"], f["normal"], f["roughness"], roughness_channel=f["roughness_channel"],
                        working_size=256)
    h, _ = normal_to_height(mat.normal)
    band = ndimage.gaussian_filter(h, 0.7) - ndimage.gaussian_filter(h, 3)
    return (band > np.quantile(band, 0.3))[:128, :128]


def test_real_brick_mask_fit_improves_on_query(materials_dir, tiny_index):
    mask = _brick_mask(materials_dir)
    assert 0.6 < mask.mean() < 0.8
    # the query-and-optimise path (the lattice-first path has its own tests in test_layout_fit.py)
    fit = fit_pptbf_mask(mask, tiny_index, config=MaskFitConfig(max_evals=50, time_budget_s=120, seed=1,
                                                                lattice=False))
    assert fit.fit_size == (RES, RES)
    assert fit.loss_final < fit.loss_query
    # the reported loss is the descriptor distance of the rendered fit to the downsampled target
    small = downsample_mask(mask, RES, RES)
    assert MaskLoss(small, tiny_index).of_mask(fit.render()) == pytest.approx(fit.loss_final, rel=1e-4, abs=1e-6)
    assert abs(fit.render().mean() - small.mean()) < 0.08            # T set from the target's white fraction


def test_valid_restricts_loss_to_parent_pixels(tiny_index):
    p = tiny_index.params[np.flatnonzero(tiny_index.usable)[0]].copy()
    p[0] = 0.5
    target = pp.render_mask(p, RES)
    valid = np.zeros_like(target)
    valid[:, : RES // 2 + 8] = True
    corrupted = target.copy()
    corrupted[~valid] = np.random.default_rng(0).random(int((~valid).sum())) < 0.5
    white = target[valid].mean()
    q = p.copy()
    q[0] = white
    with_valid = MaskLoss(corrupted, tiny_index, valid)
    without = MaskLoss(corrupted, tiny_index)
    clean = MaskLoss(target, tiny_index, valid)
    print(with_valid(q), without(q), clean(q))
    assert with_valid(q) == pytest.approx(clean(q), abs=0.02)          # outside pixels are ignored
    assert with_valid(q) < without(q) - 0.05
    fit = fit_pptbf_mask(corrupted, tiny_index, valid, MaskFitConfig(max_evals=20, time_budget_s=60))
    assert fit.meta["white_fraction"] == pytest.approx(white, abs=0.02)
    assert_fit_loss_is_real(fit, corrupted, tiny_index, valid)


def test_fit_inpainted_mask_uses_segmentation(tiny_index):
    p = tiny_index.params[np.flatnonzero(tiny_index.usable)[1]].copy()
    grey = pp.evaluate(p, RES)[..., None].astype(np.float32)
    seen = {}

    def segment(maps):
        seen["keys"] = sorted(maps)
        g = maps["albedo"][..., 0]
        return g > np.median(g)

    fit = fit_inpainted_mask({"albedo": np.repeat(grey, 3, -1), "height": grey}, segment, tiny_index,
                             MaskFitConfig(max_evals=15, time_budget_s=60))
    assert seen["keys"] == ["albedo", "height"]
    assert fit.meta["white_fraction"] == pytest.approx(0.5, abs=0.02) and fit.evaluations <= 15
    with pytest.raises(InputError, match="size"):
        fit_inpainted_mask({"a": grey, "b": grey[:32]}, segment, tiny_index)


def test_fit_bad_input(tiny_index):
    with pytest.raises(InputError, match="uniform"):
        fit_pptbf_mask(np.ones((64, 64), bool), tiny_index)
    with pytest.raises(InputError, match="shape"):
        fit_pptbf_mask(np.zeros((64, 64, 3)), tiny_index)
    with pytest.raises(InputError, match="valid"):
        fit_pptbf_mask(np.eye(64, dtype=bool), tiny_index, valid=np.ones((32, 32), bool))
