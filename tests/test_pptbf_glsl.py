"""The PPTBF's GLSL port (workers/mtlx/library/genglsl/lib/pptbf_core.glsl) against the numpy generator, run on the
CPU (Mesa llvmpipe through moderngl): binary masks at the database thresholds and the cell keys, per tiling,
window, mixture, cellular-window setting and over random parameter vectors."""
from __future__ import annotations

import numpy as np
import pytest

from pptbf_db import pptbf as pp
from workers.mtlx import glsl

W = 64
SHIFT = (0.37, 0.21)
#: share of equal mask pixels required (float32 against float64 flips pixels whose value sits at the cut)
AGREEMENT = 0.99


pytestmark = pytest.mark.skipif(not glsl.available(), reason="no headless OpenGL 4 context here (moderngl with EGL: "
                                                              "Debian libegl1 libegl-mesa0 libgl1-mesa-dri)")


def _base(seed: int) -> np.ndarray:
    return pp.sample_params(np.random.default_rng(seed), 1, ref_width=W, crisp_share=0.0)[0]


def _with(v: np.ndarray, **edit) -> np.ndarray:
    v = v.copy()
    for k, x in edit.items():
        v[pp.PARAM_INDEX[k]] = x
    return pp.clip_params(v)


def _cases() -> dict[str, np.ndarray]:
    cases = {f"tiling{t}": _with(_base(100 + t), tiling=t) for t in range(18)}
    cases.update({f"window_shape{s}": _with(_base(200 + s), window_shape=s, window_blend=0.0, feature_mixture=0)
                  for s in range(4)})
    cases.update({f"mixture{m}": _with(_base(300 + m), feature_mixture=m) for m in range(6)})
    for larp in (0.0, 0.5, 1.0):
        for sm in (0.0, 0.5, 1.5, 2.0):
            cases[f"cellular_larp{larp}_smooth{sm}"] = _with(
                _base(400 + int(10 * larp + sm * 2)), window_blend=1.0, window_larp=larp, window_smoothness=sm,
                feature_mixture=0, jitter=0.3, distortion_amplitude=0.0)
    cases["distorted"] = _with(_base(500), distortion_amplitude=0.1, distortion_base=0.5, distortion_frequency=2.0)
    cases["jittered"] = _with(_base(501), jitter=1.0)
    cases["relaxed"] = _with(_base(502), tiling=3, jitter=0.5)
    rng = np.random.default_rng(7)
    cases.update({f"sample{k}": v for k, v in enumerate(pp.sample_params(rng, 20, ref_width=W))})
    return cases


CASES = _cases()


@pytest.mark.parametrize("name", sorted(CASES))
def test_glsl_pptbf_masks_match_numpy(name):
    from workers.mtlx.check import render_pptbf

    params = CASES[name]
    got, _ = render_pptbf(params, W, shift=SHIFT)
    ref = pp.evaluate(params, W, W, shift=SHIFT, ref_width=W)
    for q in pp.DATABASE_THRESHOLDS:
        cut = float(np.quantile(ref, 1.0 - q))
        share = float(np.mean((got > cut) == (ref > cut)))
        assert share >= AGREEMENT, (name, q, share)


@pytest.mark.parametrize("name", ["tiling4", "tiling10", "tiling14", "tiling17", "relaxed", "sample3"])
def test_glsl_pptbf_cell_keys_match_numpy(name):
    from workers.mtlx.check import render_pptbf

    params = CASES[name]
    got, _ = render_pptbf(params, W, shift=SHIFT, function="pptbf_cell")
    _, keys = pp.evaluate(params, W, W, shift=SHIFT, ref_width=W, cells=True)
    gk = np.rint(got.astype(np.float64) * 2 ** 24).astype(np.int64)
    assert np.mean(gk == keys) >= AGREEMENT, name
    assert len(np.unique(keys)) > 3        # several cells in view: the keys are not all one value


def test_glsl_pptbf_follows_shift_and_scale():
    """A different realisation (shift) and a doubled unit change the image as numpy's do."""
    from workers.mtlx.check import render_pptbf

    params = CASES["tiling4"]
    a, _ = render_pptbf(params, W, shift=(1.5, 0.25))
    b, _ = render_pptbf(params, W, shift=SHIFT)
    assert np.mean(np.abs(a - b)) > 1e-3
    big, _ = render_pptbf(params, W, ref_width=2 * W, shift=(1.5, 0.25))
    ref = pp.evaluate(params, W, W, shift=(1.5, 0.25), ref_width=2 * W)
    cut = float(np.quantile(ref, 0.5))
    assert np.mean((big > cut) == (ref > cut)) >= AGREEMENT


def _crisp(tiling: int, aspect: float, rotation: float = 0.0, arity: float = 6.0) -> np.ndarray:
    from workers.lattice import STRAIGHT_CELLS, template_cells

    v = template_cells(np.zeros(pp.N_PARAMS), {**STRAIGHT_CELLS, "window_arity": arity})
    return _with(v, tiling=tiling, resolution=W / 3.0, aspect_ratio=aspect, rotation=rotation)


BORDER_CASES = {"running_bond": _crisp(4, 0.5), "square_tall": _crisp(0, 2.0), "herringbone": _crisp(10, 1.0),
                "pythagorean_rotated": _crisp(14, 0.8, rotation=0.1),
                "apavement_16_sectors": _crisp(16, 1.0, arity=4.0),
                "cellular_larp0.5": _with(CASES["cellular_larp0.5_smooth0.0"], jitter=0.0)}


@pytest.mark.parametrize("name", sorted(BORDER_CASES))
def test_glsl_pptbf_border_distance_matches_numpy(name):
    """The border field (pptbf_border, the pptbf node's ``border`` input) equals numpy's to float32 precision
    (1e-5 reference widths, 0.0006 px here) and cuts as numpy's at network shares, except for pixels at the cut
    itself: on these aligned grids a whole column of pixels has one distance, and float32 puts it on either side."""
    from workers.mtlx.check import render_pptbf

    params = BORDER_CASES[name]
    got, _ = render_pptbf(params, W, shift=SHIFT, function="pptbf_border")
    ref = pp.evaluate(params, W, W, shift=SHIFT, ref_width=W, field="border")
    assert np.mean(np.abs(got - ref) <= 1e-5) >= AGREEMENT, name
    for q in (0.08, 0.15, 0.3):
        cut = float(np.quantile(ref, q))
        away = np.abs(ref - cut) > 1e-5
        share = float(np.mean(((got > cut) == (ref > cut))[away]))
        assert share >= AGREEMENT and away.mean() > 0.9, (name, q, share, away.mean())
