"""The ``warp`` node: identity at amount 0, an exact periodic shift for a constant driver, torch parity, a
recovered amount, editing, validation."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from pptbf_db import pptbf as pp
from workers import graph as G
from workers.errors import GraphError
from workers.nodes import NODE_TYPES, EvalContext
from workers.recompose import RecomposeConfig, torch_maps
from workers.torch_graph import TorchGraph

SIZE = 64


def _material(amount: float, angle: float = 30.0) -> G.ProceduralMaterial:
    """albedo = warp(blur(PPTBF cells), by = blur(another PPTBF)): smooth, so bilinear sampling is well posed."""
    mat = G.new_material(seed=2, working_size=(SIZE, SIZE))
    for i, seed in enumerate((3, 8)):
        params = [float(x) for x in pp.sample_params(np.random.default_rng(seed), 1, ref_width=SIZE)[0]]
        mat.add(f"m{i}", "pptbf", {"params": params, "ref_width": SIZE})
        mat.add(f"s{i}", "blur", {"sigma": 1.0}, input=f"m{i}")
    mat.add("w", "warp", {"amount": amount, "angle": angle}, input="s0", by="s1")
    mat.maps.append({"name": "albedo", "node": "w"})
    return mat


def _warp(x: np.ndarray, by: np.ndarray, **params) -> np.ndarray:
    return NODE_TYPES["warp"].evaluate(params, {"input": x, "by": by}, EvalContext(x.shape[1], x.shape[0]), "w")


def test_zero_amount_is_the_identity_and_a_constant_driver_is_a_periodic_shift():
    x = np.random.default_rng(0).random((40, 56, 3)).astype(np.float32)
    assert np.array_equal(_warp(x, np.full((40, 56, 1), 0.9, np.float32), amount=0.0), x)
    # by - 0.5 = 0.5 everywhere, amount 6 along x: every pixel reads 3 px to its left, wrapping around
    shifted = _warp(x, np.ones((40, 56, 1), np.float32), amount=6.0, angle=0.0)
    assert np.abs(shifted - np.roll(x, 3, axis=1)).max() < 1e-5
    down = _warp(x, np.ones((40, 56, 1), np.float32), amount=-4.0, angle=90.0)
    assert np.abs(down - np.roll(x, -2, axis=0)).max() < 1e-5
    # half a pixel: the mean of two neighbours
    half = _warp(x, np.ones((40, 56, 1), np.float32), amount=1.0, angle=0.0)
    assert np.abs(half - 0.5 * (x + np.roll(x, 1, axis=1))).max() < 1e-5


def test_warp_follows_the_pattern_scale():
    x = np.random.default_rng(1).random((32, 48, 1)).astype(np.float32)
    ones = np.ones((32, 48, 1), np.float32)
    warp = NODE_TYPES["warp"]
    for scale, px in ((1.0, 3), (2.0, 6), (0.5, 1.5)):
        out = warp.evaluate({"amount": 6.0}, {"input": x, "by": ones}, EvalContext(48, 32, scale=scale), "w")
        lo = int(np.floor(px))
        want = np.roll(x, lo, axis=1) * (1 - (px - lo)) + np.roll(x, lo + 1, axis=1) * (px - lo)
        assert np.abs(out - want).max() < 1e-5, scale
    mat = _material(6.0)
    moved = np.abs(G.evaluate(mat, SIZE, SIZE)["albedo"] - G.evaluate(_material(0.0), SIZE, SIZE)["albedo"])
    assert moved.max() > 0.2  # the warp moved the cells' edges


def test_torch_form_matches_numpy_and_recovers_the_amount():
    truth = _material(5.0)
    ref = G.evaluate(truth, SIZE, SIZE)["albedo"]
    assert np.abs(torch_maps(truth, SIZE, SIZE)["albedo"] - ref).max() < 1e-4
    start = _material(2.0)
    cfg = RecomposeConfig(optimise=("warp",))
    tg = TorchGraph(start, SIZE, SIZE, 1.0, torch.device("cpu"), cfg)
    assert list(tg.params) == ["w.amount"] and tg.kinds["w.amount"] == "value"
    target = torch.from_numpy(ref)
    opt = torch.optim.Adam(tg.params.values(), lr=0.2)
    for _ in range(80):
        opt.zero_grad()
        loss = (tg.forward()["albedo"] - target).pow(2).mean()
        loss.backward()
        opt.step()
    assert abs(float(tg.params["w.amount"].detach()) - 5.0) < 0.3, float(tg.params["w.amount"].detach())


def test_warp_is_edited_and_validated_by_its_declarations():
    mat = _material(3.0)
    mat.node("w")["params"].pop("angle")
    G.set_param(mat, "w.angle", 45.0)  # declared, so settable although absent from the file
    assert mat.node("w")["params"]["angle"] == 45.0
    with pytest.raises(GraphError, match="warp.amount"):
        G.set_param(mat, "w.amount", 5e3)
    with pytest.raises(GraphError, match="no parameter 'strength'"):
        G.set_param(mat, "w.strength", 1.0)
    doc = mat.to_json()
    doc["nodes"][-1]["params"]["angle"] = "north"
    with pytest.raises(GraphError, match="warp.angle"):
        G.from_json(doc)
    assert "warp" in RecomposeConfig.from_dict({"optimise": ["warp"]}).optimise
