"""PPTBF generator: parameter space, hash/noise, tilings, point process, evaluation, thresholding, torch port."""
from __future__ import annotations

import numpy as np
import pytest

from pptbf_db import pptbf as pp


def make_params(**kw) -> np.ndarray:
    """A readable parameter vector: a plain cellular/classical setting overridden by name."""
    base = dict(threshold=0.5, tiling=0, jitter=0.0, resolution=16, rotation=0.0, aspect_ratio=1.0,
                distortion_base=0.0, distortion_amplitude=0.0, distortion_frequency=0.0, window_shape=2,
                window_arity=2.0, window_larp=0.0, window_norm=2.0, window_smoothness=0.0, window_blend=0.0,
                window_sigma=1.0, feature_mixture=0, feature_norm=2.0, feature_correlation=0.0, feature_aniso=0.0,
                feature_kernel_min=1, feature_kernel_max=3, feature_sigcos=2.0, feature_sigcosvar=0.3,
                feature_frequency=2, feature_phase_shift=0.0, feature_thickness=0.5, feature_curvature=0.0,
                feature_orientation=0.1)
    base.update(kw)
    p = np.zeros(pp.N_PARAMS)
    for k, v in base.items():
        p[pp.PARAM_INDEX[k]] = v
    return p


# ------------------------------------------------------------------------------------------------ parameters

def test_param_specs_match_spec():
    assert len(pp.PARAM_SPECS) == 29 and pp.N_PARAMS == 29
    assert pp.PARAM_NAMES[0] == "threshold" and pp.PARAM_NAMES[1] == "tiling"
    assert pp.PARAM_NAMES[28] == "feature_orientation"
    assert len(pp.CONTINUOUS_IDX) == 23 and len(pp.DISCRETE_IDX) == 6
    assert set(pp.DISCRETE_IDX.tolist()) == {1, 9, 16, 20, 21, 24}
    assert {s.kind for s in pp.PARAM_SPECS} == {"cont", "disc"}
    spec = {s.name: s for s in pp.PARAM_SPECS}
    assert (spec["tiling"].lo, spec["tiling"].hi) == (0, 17)
    assert (spec["resolution"].lo, spec["resolution"].hi) == (1.0, 1000.0)
    assert (spec["aspect_ratio"].lo, spec["aspect_ratio"].hi) == (0.01, 10.0)
    assert (spec["feature_mixture"].lo, spec["feature_mixture"].hi) == (0, 4)
    assert all(s.lo < s.hi for s in pp.PARAM_SPECS)


def test_clip_params_clamps_casts_and_orders_kernels():
    p = make_params(tiling=20.7, jitter=-0.5, window_shape=2.9, feature_kernel_min=9, feature_kernel_max=3,
                    aspect_ratio=50.0)
    c = pp.clip_params(p)
    assert c[1] == 17 and c[2] == 0.0 and c[9] == 2 and c[5] == 10.0
    assert (c[20], c[21]) == (3, 9)
    batch = pp.clip_params(np.stack([p, p]))
    assert batch.shape == (2, 29) and np.array_equal(batch[0], c)


def test_sample_params_cover_space_and_skip_flat_combination():
    rng = np.random.default_rng(0)
    s = pp.sample_params(rng, 2000, ref_width=128)
    assert s.shape == (2000, 29) and s.dtype == np.float64
    assert np.array_equal(pp.clip_params(s), s)
    assert set(np.unique(s[:, 0])) == {0.2, 0.5, 0.8}
    assert set(np.unique(s[:, 1]).astype(int)) == set(range(18))
    assert set(np.unique(s[:, 16]).astype(int)) == set(range(5))
    assert not np.any((s[:, 16] == 0) & (s[:, 9] == 0))
    assert s[:, 3].min() >= 128 / 16 - 1 and s[:, 3].max() <= 128 / 2
    assert np.all(s[:, 20] <= s[:, 21])
    # continuous parameters spread over their (sampling) range
    j = s[:, 2]
    assert j.min() < 0.05 and j.max() > 0.95 and abs(j.mean() - 0.5) < 0.05
    again = pp.sample_params(np.random.default_rng(0), 2000, ref_width=128)
    assert np.array_equal(s, again)


def test_sample_params_regular_share():
    """A share of nearly regular layouts, spread evenly; share 0 draws exactly the old vectors."""
    PI = pp.PARAM_INDEX
    old = pp.sample_params(np.random.default_rng(0), 2000, ref_width=128)
    assert np.array_equal(pp.sample_params(np.random.default_rng(0), 2000, ref_width=128, regular_share=0.0), old)
    s = pp.sample_params(np.random.default_rng(0), 2000, ref_width=128, regular_share=0.25)
    regular = (s[:, PI["jitter"]] <= 0.1) & (s[:, PI["distortion_amplitude"]] <= 0.05) \
        & (s[:, PI["distortion_base"]] <= 0.005)
    old_regular = (old[:, PI["jitter"]] <= 0.1) & (old[:, PI["distortion_amplitude"]] <= 0.05)
    assert old_regular.mean() < 0.02 and 0.25 <= regular.mean() < 0.27
    assert 0.2 < regular[:1000].mean() < 0.3                     # every part of a build gets its share
    assert set(np.unique(s[regular, 1]).astype(int)) == set(range(18))
    others = [i for i in range(29) if i not in (PI["jitter"], PI["distortion_amplitude"], PI["distortion_base"])]
    assert np.array_equal(s[:, others], old[:, others])           # only those three parameters change
    with pytest.raises(ValueError, match="regular_share"):
        pp.sample_params(np.random.default_rng(0), 10, regular_share=1.5)


def test_sample_params_crisp_cells_and_balanced_tiling():
    """Crisp cells: a disjoint, evenly spread share of cellular-window layouts without feature noise, at periods
    of 1/12..1/3 of the width; balanced tiling: every family the same number of times."""
    PI = pp.PARAM_INDEX
    s = pp.sample_params(np.random.default_rng(0), 1800, ref_width=128, regular_share=0.15, crisp_share=0.35,
                         balanced_tiling=True)
    reg, crisp = pp.stratum_indices(1800, 0.15, 0.35)
    assert len(reg) == 270 and len(crisp) == 630 and not set(reg) & set(crisp)
    c = s[crisp]
    assert (c[:, PI["window_shape"]] == 1).all() and (c[:, PI["feature_mixture"]] == 0).all()
    assert (c[:, PI["window_blend"]] >= 0.9).all() and (c[:, PI["jitter"]] <= 0.15).all()
    assert c[:, PI["resolution"]].min() >= 128 / 12 - 1 and c[:, PI["resolution"]].max() <= 128 / 3
    assert 0.3 < np.isin(np.arange(900), crisp).mean() < 0.4       # the first half of a build gets its share
    others = np.setdiff1d(np.arange(1800), np.concatenate([reg, crisp]))
    assert (s[others, PI["feature_mixture"]] > 0).mean() > 0.7       # the rest stays uniform
    assert np.array_equal(np.bincount(s[:, PI["tiling"]].astype(int)), np.full(18, 100))
    with pytest.raises(ValueError, match="crisp_share"):
        pp.sample_params(np.random.default_rng(0), 10, regular_share=0.7, crisp_share=0.5)


def test_bad_params_raise_clear_errors():
    with pytest.raises(ValueError, match="29"):
        pp.evaluate(np.zeros(5), 16)
    with pytest.raises(ValueError, match="tiling"):
        pp.evaluate(make_params(tiling=18), 16)
    with pytest.raises(ValueError, match="not finite"):
        pp.evaluate(make_params(jitter=np.nan), 16)


# ------------------------------------------------------------------------------------------------ PRNG / noise

def test_tables_and_prng():
    assert sorted(pp.PERM.tolist()) == list(range(1024))
    assert pp.NOISE.shape == (1024,) and np.abs(pp.NOISE).max() <= 1.0
    seed = pp.hash_seed(np.arange(50), np.arange(50) * 3)
    assert seed.min() >= 0 and seed.max() < 2 ** 25
    # random access equals the sequential multiplicative congruential sequence
    s, seq = int(seed[7]), []
    for _ in range(10):
        s = (s * 3039177861) % 2 ** 32
        seq.append(s / 2 ** 32 * 2 - 1)
    assert np.allclose(pp.draw(seed[7], np.arange(1, 11)), seq, atol=0, rtol=0)
    u = pp.draw(pp.hash_seed(np.arange(20000) % 997, np.arange(20000) // 997), 1)
    assert -1 <= u.min() and u.max() < 1 and abs(u.mean()) < 0.03


def test_value_noise_interpolates_lattice():
    i, j = np.arange(-3, 20), np.arange(5, 28)
    assert np.allclose(pp.value_noise(i.astype(float), j.astype(float)), pp._lattice(i, j))
    x = np.linspace(0, 10, 5001)
    v = pp.value_noise(x, np.full_like(x, 0.3))
    assert np.abs(v).max() <= 1.0 and np.abs(np.diff(v)).max() < 0.01  # continuous


# ------------------------------------------------------------------------------------------------ tilings

@pytest.mark.parametrize("tiling", range(18))
def test_every_point_lies_in_one_of_its_tiles(tiling):
    rng = np.random.default_rng(tiling)
    x, y = rng.uniform(100, 108, 5000), rng.uniform(100, 108, 5000)
    cx, cy, hx, hy = pp.tiles_at(x, y, pp.TILING_TYPES[tiling])
    inside = (np.abs(x[:, None] - cx) <= hx + 1e-9) & (np.abs(y[:, None] - cy) <= hy + 1e-9)
    assert inside.any(axis=1).all()
    if tiling >= 16:  # APAVEMENT: entry 0 is the containing tile
        assert inside[:, 0].all()


def test_true_tile_areas():
    """Herringbone bricks are N:1, the Pythagorean tiling has 2x2 and 1x1 squares, APAVEMENT 7 tiles/period."""
    rng = np.random.default_rng(3)
    x, y = rng.uniform(100, 101, 3000), rng.uniform(100, 101, 3000)
    for t, n in ((10, 2), (12, 3)):
        cx, cy, hx, hy = pp.tiles_at(x, y, pp.TILING_TYPES[t])
        ratio = np.maximum(hx, hy) / np.minimum(hx, hy)
        assert np.allclose(ratio, n)
    cx, cy, hx, hy = pp.tiles_at(x, y, pp.TILING_TYPES[14])
    assert set(np.round(hx.ravel() * 10, 6)) == {1.0, 2.0}
    cx, cy, hx, hy = pp.tiles_at(x, y, pp.TILING_TYPES[16])
    own = (np.abs(x[:, None] - cx) <= hx) & (np.abs(y[:, None] - cy) <= hy)
    k = np.argmax(own, axis=1)
    rows = np.arange(len(x))
    areas = np.round(16 * 4 * hx[rows, k] * hy[rows, k]).astype(int)  # in quarter cells
    centres = {(round(a % 1, 4), round(b % 1, 4)) for a, b in zip(cx[rows, k], cy[rows, k])}
    assert len(centres) == 7 and set(areas) == {1, 2, 4, 3}


def test_pave_random_cuts_are_consistent_between_neighbours():
    """Irregular PAVE: a tile's right side equals its right neighbour's left side, rows are straight."""
    tt = pp.TILING_TYPES[6]
    a = np.arange(100, 140)
    cx, cy, hx, hy = pp.tiles_from_codes(a, np.full_like(a, 120), np.zeros_like(a), tt)
    right, left = cx[:, 4] + hx[:, 4], cx[:, 5] - hx[:, 5]
    assert np.allclose(right, left)
    assert np.allclose(cy[:, 4] - hy[:, 4], cy[0, 4] - hy[0, 4])
    assert np.std(2 * hx[:, 4]) > 0.1


def test_subdivision_and_relaxation():
    rng = np.random.default_rng(5)
    n = 400
    cx, cy = rng.integers(100, 200, n) + 0.5, rng.integers(100, 200, n) + 0.5
    h = np.full(n, 0.5)
    never = pp.point_sets(cx, cy, h, h, 0.0)
    always = pp.point_sets(cx, cy, h, h, 1.0)
    half = pp.point_sets(cx, cy, h, h, 0.5)
    assert never["valid"].sum(1).max() == 1 and np.all(always["valid"].sum(1) == 4)
    frac = (half["valid"].sum(1) == 4).mean()
    assert 0.35 < frac < 0.65
    # points stay in their own sub-cell, sub-cells tile the tile
    v = always["valid"]
    assert np.all(np.abs(always["px"] - always["ccx"])[v] <= 0.9 * always["chx"][v] + 1e-12)
    assert np.allclose((4 * always["chx"] * always["chy"]).sum(1), 1.0)
    # relaxation spreads the points: larger minimum nearest-neighbour distance than without
    tt = pp.TILING_TYPES[2]
    relaxed = pp.relaxed_sets(cx, cy, h, h, tt)
    raw = pp.point_sets(*pp.tiles_at(cx, cy, tt), 1.0)

    def nn_dist(px, py, valid):
        px, py = np.where(valid, px, np.nan), np.where(valid, py, np.nan)
        dd = np.hypot(px[:, :, None] - px[:, None, :], py[:, :, None] - py[:, None, :])
        k = dd.shape[1]
        dd[:, np.arange(k), np.arange(k)] = np.inf
        return np.nanmin(np.where(np.isnan(dd), np.inf, dd), axis=2)[valid]

    d_relaxed = nn_dist(relaxed["px"], relaxed["py"], relaxed["valid"])
    d_raw = nn_dist(raw["px"].reshape(n, -1), raw["py"].reshape(n, -1), raw["valid"].reshape(n, -1))
    assert np.percentile(d_relaxed, 10) > 1.2 * np.percentile(d_raw, 10)
    assert relaxed["valid"].sum(1).min() >= 1


def test_larp_one_ranks_by_own_cell():
    """With larp = 1 the closest point of every pixel is the one whose (sub)cell contains it."""
    for t in (1, 7, 9, 11):
        p = make_params(tiling=t, jitter=1.0, window_larp=1.0, rotation=0.1, resolution=24)
        d, zoom, x, y, st = pp.prepare(p, 96)
        ps = pp.rank_pixels(x, y, st.code, st, d)
        P, p0 = st.points, ps.nbr[..., 0]
        inside = (np.abs(x - P.ccx[p0]) <= P.chx[p0] + 1e-9) & (np.abs(y - P.ccy[p0]) <= P.chy[p0] + 1e-9)
        assert inside.mean() > 0.995, (t, inside.mean())


# ------------------------------------------------------------------------------------------------ evaluation

PERIODS = {0: (1, 1), 4: (1, 2), 5: (1, 3), 10: (1, 1), 12: (1, 1), 14: (1, 1), 16: (1, 1)}


@pytest.mark.parametrize("tiling", sorted(PERIODS))
def test_deterministic_tilings_are_periodic(tiling):
    """Jitter 0, no distortion, rotation 0, constant feature, classical window: V repeats every period."""
    res = 16
    p = make_params(tiling=tiling, resolution=res, window_shape=2, window_blend=0.0, feature_mixture=0)
    px, py = PERIODS[tiling]
    v = pp.evaluate(p, 64, 64)
    assert v.std() > 1e-3
    assert np.allclose(v[:, : 64 - res * px], v[:, res * px:], atol=1e-5)
    assert np.allclose(v[: 64 - res * py], v[res * py:], atol=1e-5)
    # and not periodic at half the period
    assert not np.allclose(v[:, : 64 - res // 2], v[:, res // 2:], atol=1e-3)


@pytest.mark.parametrize("tiling", range(18))
def test_every_tiling_renders_a_structured_field(tiling):
    p = make_params(tiling=tiling, jitter=0.5, resolution=20, window_blend=0.6, window_shape=1,
                    window_larp=0.3, window_arity=3, window_smoothness=1.2, feature_mixture=1,
                    distortion_base=0.01, distortion_amplitude=0.5, distortion_frequency=0.5, rotation=0.2)
    v = pp.evaluate(p, 64)
    assert v.shape == (64, 64) and v.dtype == np.float32
    assert np.isfinite(v).all() and v.min() >= 0.0
    assert v.std() > 0.01 * max(v.mean(), 1e-6)
    # spatial structure at the period scale: neighbours correlate more than far pixels
    c1 = np.corrcoef(v[:, :-1].ravel(), v[:, 1:].ravel())[0, 1]
    assert c1 > 0.5


@pytest.mark.parametrize("mixture", range(5))
def test_mixtures(mixture):
    p = make_params(tiling=1, jitter=0.7, resolution=20, feature_mixture=mixture, window_shape=1 if mixture == 0 else 0,
                    window_blend=0.5, feature_kernel_min=2, feature_kernel_max=5, feature_sigcos=1.5)
    v = pp.evaluate(p, 64)
    assert np.isfinite(v).all() and v.min() >= 0 and v.std() > 1e-3
    if mixture == 3:
        assert (v == 0).mean() > 0.05          # bombing leaves background at 0
        assert v.max() <= 1.0
    if mixture == 4:
        assert v.max() <= 1.0 + 1e-9


def test_flat_combination_is_flat():
    """Mixture 0 with window shape 0 is the documented degenerate (flat) case."""
    p = make_params(tiling=0, jitter=0.5, window_shape=0, feature_mixture=0, window_blend=0.5)
    v = pp.evaluate(p, 48)
    assert np.allclose(v[v > 0], 1.0, atol=1e-6)


def test_window_shapes_and_cellular_window():
    # rectangular window: V takes integer values (count of windows covering the pixel)
    v = pp.evaluate(make_params(tiling=0, jitter=0.8, window_shape=3, window_blend=0.0), 48)
    assert np.allclose(v, np.round(v)) and v.max() >= 1
    # pure cellular window: 1 at the points, 0 on the cell borders
    p = make_params(tiling=0, jitter=0.6, window_shape=1, window_blend=1.0, window_sigma=0.01, resolution=32,
                    window_arity=4)
    v = pp.evaluate(p, 96)
    assert v.max() > 0.9 and v.min() < 0.05
    assert ((v > 0.3) & (v < 0.7)).mean() > 0.1


def test_determinism_and_shift_realisation():
    p = make_params(tiling=7, jitter=0.8, resolution=16, feature_mixture=2, window_blend=0.4,
                    distortion_base=0.01, distortion_amplitude=0.6, distortion_frequency=0.8)
    a, b = pp.evaluate(p, 64), pp.evaluate(p, 64)
    assert np.array_equal(a, b)
    c = pp.evaluate(p, 64, shift=(3.37, 5.81))
    assert not np.allclose(a, c, atol=1e-3)
    assert abs(a.mean() - c.mean()) < 0.3 * a.mean()           # same statistics, new realisation


def test_threaded_chunks_give_the_same_field(monkeypatch):
    """Row chunks evaluated on threads (and chunking itself) do not change a single value."""
    p = make_params(tiling=7, jitter=0.8, resolution=16, feature_mixture=2, window_blend=0.4,
                    distortion_base=0.01, distortion_amplitude=0.6, distortion_frequency=0.8)
    whole = pp.evaluate(p, 96, threads=1)
    monkeypatch.setattr(pp, "CHUNK_ELEMS", 2048)   # many small chunks
    assert pp._chunk_rows(96, 18) < 8
    assert np.array_equal(pp.evaluate(p, 96, threads=1), whole)
    assert np.array_equal(pp.evaluate(p, 96, threads=3), whole)
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    assert pp.default_threads() == 2


def test_border_memo_reuses_border_radii_with_identical_result(monkeypatch):
    """Cellular-window border radii looked up from the previous row chunk: same field, most keys reused when
    cells span many chunks (a zoomed render)."""
    p = make_params(tiling=0, jitter=0.5, resolution=8, window_shape=2, window_blend=0.6, window_larp=0.3)
    assert pp.uses_cellular(pp.decode(p))
    monkeypatch.setattr(pp, "CHUNK_ELEMS", 4096)
    orig = pp.BorderMemo.lookup
    stats = {"keys": 0, "hits": 0}

    def counting(self, ukey):
        found = orig(self, ukey)
        stats["keys"] += ukey.size
        stats["hits"] += 0 if found is None else int(found[0].sum())
        return found

    monkeypatch.setattr(pp.BorderMemo, "lookup", counting)
    with_memo = pp.evaluate(p, 96, pixel_scale=4.0, threads=1)
    assert stats["hits"] > 0.5 * stats["keys"], stats
    monkeypatch.setattr(pp.BorderMemo, "lookup", lambda self, ukey: None)
    assert np.array_equal(pp.evaluate(p, 96, pixel_scale=4.0, threads=1), with_memo)


def test_ref_width_extends_and_pixel_scale_zooms():
    p = make_params(tiling=8, jitter=0.7, resolution=16, feature_mixture=1, window_blend=0.5, window_shape=1,
                    distortion_base=0.02, distortion_amplitude=0.5, distortion_frequency=0.7)
    small = pp.evaluate(p, 64)
    wide = pp.evaluate(p, 128, 96, ref_width=64)
    assert wide.shape == (96, 128)
    assert np.allclose(wide[:64, :64], small, atol=1e-6)
    big = pp.evaluate(p, 128, ref_width=64, pixel_scale=2.0)
    assert np.allclose(big[::2, ::2], small, atol=1e-6)


def test_binarize_white_fraction_and_render_mask():
    rng = np.random.default_rng(0)
    v = rng.normal(size=(64, 64))
    for t in (0.2, 0.5, 0.8):
        assert abs(pp.binarize(v, t).mean() - t) < 0.01
    v[0, :5] = np.nan
    m = pp.binarize(v, 0.5)
    assert not m[0, :5].any()
    p = make_params(tiling=4, jitter=0.5, threshold=0.3, feature_mixture=2, window_blend=0.3, window_shape=1)
    mask = pp.render_mask(p, 64)
    assert mask.dtype == bool and abs(mask.mean() - 0.3) < 0.05


# ------------------------------------------------------------------------------------------------ torch

torch = pytest.importorskip("torch")


def _agreement_cases(n: int = 36) -> list[np.ndarray]:
    """Random parameter vectors covering every tiling type and every mixture (0..4)."""
    rng = np.random.default_rng(11)
    ps = pp.sample_params(rng, n, ref_width=48)
    for i, p in enumerate(ps):
        p[1] = i % 18
        p[16] = i % 5
        if p[16] == 0 and p[9] == 0:
            p[9] = 1 + i % 3
        p[3] = max(p[3], 10)
    return list(ps)


def test_torch_matches_numpy_exact_mode():
    worst = 0.0
    for p in _agreement_cases():
        a = pp.evaluate(p, 40)
        b = pp.evaluate_torch(torch.tensor(p), 40).numpy()
        assert b.shape == a.shape
        worst = max(worst, float(np.abs(a - b).max() / max(1.0, float(np.abs(a).max()))))
    assert worst < 1e-4, worst


def _grad_params(mixture: int) -> np.ndarray:
    return make_params(tiling=1, jitter=0.6, resolution=16, rotation=0.1, aspect_ratio=1.2, distortion_base=0.02,
                       distortion_amplitude=0.5, distortion_frequency=0.6, window_shape=1, window_arity=3,
                       window_larp=0.3, window_norm=2.3, window_smoothness=1.3, window_blend=0.5, window_sigma=1.5,
                       feature_mixture=mixture, feature_norm=1.7, feature_correlation=0.3, feature_aniso=0.5,
                       feature_kernel_min=2, feature_kernel_max=4, feature_sigcos=1.5, feature_sigcosvar=0.4,
                       feature_frequency=2, feature_phase_shift=0.2, feature_thickness=0.6, feature_curvature=0.4,
                       feature_orientation=0.2)


WINDOW_GRADS = ("window_larp", "window_norm", "window_smoothness", "window_blend", "window_sigma")
FEATURE_GRADS = ("feature_norm", "feature_correlation", "feature_aniso", "feature_sigcos", "feature_sigcosvar",
                 "feature_thickness", "feature_curvature", "feature_orientation")
GEOMETRY_GRADS = ("jitter", "rotation", "aspect_ratio", "distortion_base", "distortion_amplitude",
                  "distortion_frequency", "resolution")


@pytest.mark.parametrize("stable", [False, True])
def test_torch_gradients_finite_and_nonzero(stable):
    target = torch.rand(40, 40, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    for mixture, names in ((2, GEOMETRY_GRADS + WINDOW_GRADS + FEATURE_GRADS + ("feature_phase_shift",)),
                           (4, GEOMETRY_GRADS + FEATURE_GRADS)):
        pt = torch.tensor(_grad_params(mixture), requires_grad=True)
        v = pp.evaluate_torch(pt, 40, stable=stable)
        ((v - target) ** 2).mean().backward()
        g = pt.grad.numpy()
        assert np.isfinite(g).all()
        zero = [n for n in names if g[pp.PARAM_INDEX[n]] == 0.0]
        assert not zero, (mixture, zero)
        assert g[pp.PARAM_INDEX["threshold"]] == 0.0 and g[pp.PARAM_INDEX["tiling"]] == 0.0


def test_torch_gradients_match_finite_differences():
    """Shading-only parameters (no structure change): autograd equals central differences."""
    p = _grad_params(2)
    names = ("window_blend", "window_sigma", "window_smoothness", "feature_sigcos", "feature_phase_shift",
             "feature_thickness", "feature_curvature", "feature_aniso")
    pt = torch.tensor(p, requires_grad=True)
    pp.evaluate_torch(pt, 32).sum().backward()
    for n in names:
        i, h = pp.PARAM_INDEX[n], 1e-5
        hi, lo = p.copy(), p.copy()
        hi[i] += h
        lo[i] -= h
        fd = (pp.evaluate_torch(torch.tensor(hi), 32).sum() - pp.evaluate_torch(torch.tensor(lo), 32).sum()) / (2 * h)
        assert abs(float(fd) - float(pt.grad[i])) <= 1e-4 * max(1.0, abs(float(fd))), n


def test_stable_mode_keeps_random_values_when_jitter_moves():
    """Stable keys: per-point draws do not change with the jitter (exact mode reshuffles them)."""
    p1, p2 = _grad_params(2), _grad_params(2)
    p2[pp.PARAM_INDEX["jitter"]] = 0.95
    s1 = pp.prepare(p1, 32, stable=True)[-1].points
    s2 = pp.prepare(p2, 32, stable=True)[-1].points
    assert np.array_equal(s1.kdraw, s2.kdraw) and np.array_equal(s1.rot_u, s2.rot_u)
    e1 = pp.prepare(p1, 32)[-1].points
    e2 = pp.prepare(p2, 32)[-1].points
    assert not np.array_equal(e1.kdraw, e2.kdraw)


def test_torch_jitter_gradient_is_a_descent_direction():
    """A small step against the stable-mode gradient of a loss in jitter reduces the loss."""
    target = pp.evaluate_torch(torch.tensor(_grad_params(2)), 32, stable=True).detach()
    p = _grad_params(2)
    p[pp.PARAM_INDEX["jitter"]] = 0.5
    pt = torch.tensor(p, requires_grad=True)
    loss = ((pp.evaluate_torch(pt, 32, stable=True) - target) ** 2).mean()
    loss.backward()
    g = float(pt.grad[pp.PARAM_INDEX["jitter"]])
    assert g < 0.0                                 # target has the larger jitter (0.6)
    p[pp.PARAM_INDEX["jitter"]] = 0.5 - 0.02 * np.sign(g)
    loss2 = ((pp.evaluate_torch(torch.tensor(p), 32, stable=True) - target) ** 2).mean()
    assert float(loss2) < float(loss.detach())


# ------------------------------------------------------------------------------------------------ contact sheet

def test_contact_sheet(artifacts_dir):
    """18 tilings x 4 settings (cellular Voronoi, rounded cells, Gabor stripes, bombing) for a person to look at."""
    from skimage import io

    settings = [dict(feature_mixture=0, window_blend=1.0, window_shape=1, window_arity=4),
                dict(feature_mixture=0, window_blend=1.0, window_shape=1, window_larp=0.8, window_smoothness=2.0),
                dict(feature_mixture=2, window_blend=0.2, window_shape=1, feature_frequency=3),
                dict(feature_mixture=3, feature_kernel_min=1, feature_kernel_max=4)]
    rows = []
    for s in settings:
        tiles = []
        for t in range(18):
            v = pp.evaluate(make_params(tiling=t, jitter=0.4, resolution=32, **s), 96)
            v = v / max(float(v.max()), 1e-9)
            assert v.std() > 0.01
            tiles.append(np.pad(v, 2, constant_values=1.0))
        rows.append(np.concatenate(tiles, axis=1))
    sheet = np.concatenate(rows, axis=0)
    out = artifacts_dir / "pptbf"
    out.mkdir(parents=True, exist_ok=True)
    io.imsave(out / "contact_sheet.png", (sheet * 255).round().astype(np.uint8), check_contrast=False)
    assert (out / "contact_sheet.png").stat().st_size > 10_000


def _run_lengths(mask: np.ndarray, axis: int) -> np.ndarray:
    """Lengths of the white runs of a bool image along ``axis`` (0: down the columns)."""
    m = np.moveaxis(mask, axis, -1).astype(np.int8)
    edges = np.diff(np.pad(m, [(0, 0), (1, 1)]), axis=-1)
    return np.nonzero(edges == -1)[1] - np.nonzero(edges == 1)[1]


@pytest.mark.parametrize("aspect", [0.5, 2.0])
def test_border_field_cuts_a_network_of_one_width(aspect):
    """Crisp bricks twice as long as high (or tall): cut at 15 % of the pixels, the PPTBF value leaves joints as
    wide as each side's distance from the cell's point (one direction about twice the other), the border distance
    joints of one width in both directions (within a pixel), at the same share and on the same cells."""
    from workers.lattice import STRAIGHT_CELLS, template_cells

    p = template_cells(np.zeros(pp.N_PARAMS), STRAIGHT_CELLS)
    for k, v in {"tiling": 4.0, "resolution": 48.0, "aspect_ratio": aspect, "threshold": 0.85}.items():
        p[pp.PARAM_INDEX[k]] = v
    widths = {}
    for field in pp.FIELDS:
        net = ~pp.render_mask(p, 256, 256, shift=(1.3, 2.1), field=field)
        across_rows, across_cols = _run_lengths(net, 0), _run_lengths(net, 1)   # joints crossed down / across
        widths[field] = tuple(float(np.median(r[r < 15])) for r in (across_rows, across_cols))
        assert abs(net.mean() - 0.15) < 0.02     # the border field's cut sits between two sides' distances
    print(f"aspect {aspect}: (horizontal joints, vertical joints) px: {widths}")
    value, border = widths["value"], widths["border"]
    assert max(value) >= 1.7 * min(value)
    assert abs(border[0] - border[1]) <= 1.0


def test_border_field_needs_the_cellular_window():
    p = np.array(pp.sample_params(np.random.default_rng(0), 1, ref_width=64)[0])
    p[pp.PARAM_INDEX["window_blend"]] = 0.0
    with pytest.raises(ValueError, match="cellular window"):
        pp.evaluate(p, 32, 32, field="border")
    with pytest.raises(ValueError, match="field"):
        pp.evaluate(p, 32, 32, field="distance")
