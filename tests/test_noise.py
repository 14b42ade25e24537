"""Multi-layer noise model: spectra, masks, histograms, multi- vs single-layer, seeds, serialisation, node."""
from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import ndimage

from tests.conftest import real_material_files
from workers import graph
from workers.errors import GraphError, InputError
from workers.maps import read_image, resize_image, srgb_to_linear
from workers.noise import (
    NoiseConfig,
    NoiseModel,
    erode_mask,
    expected_psd,
    fit_noise,
    noise_params,
    synthesize,
    synthesize_layers,
)

BIN = 1.0 / 128  # radial bin width in cycles per pixel


def known_psd(r: np.ndarray) -> np.ndarray:
    """A smooth low-pass plus band-pass PSD (density units, arbitrary scale)."""
    return np.exp(-0.5 * (r / 0.03) ** 2) + 0.15 * np.exp(-0.5 * ((r - 0.12) / 0.04) ** 2)


def gaussian_field(psd_fn, size: int, seed: int, std: float = 0.08, mean: float = 0.5) -> np.ndarray:
    """A Gaussian random field with the given PSD shape, rescaled to ``mean`` / ``std`` (HxWx1)."""
    rng = np.random.default_rng(seed)
    fy = np.fft.fftfreq(size)[:, None]
    fx = np.fft.fftfreq(size)[None, :]
    amp = np.sqrt(psd_fn(np.sqrt(fx ** 2 + fy ** 2)))
    amp[0, 0] = 0.0
    x = np.real(np.fft.ifft2(np.fft.fft2(rng.standard_normal((size, size))) * amp))
    return (mean + std * x / x.std())[..., None].astype(np.float32)


def radial_power(x: np.ndarray) -> np.ndarray:
    """Radially averaged PSD (|FFT|^2 / N) of a 2-D field in bins of BIN cycles/pixel."""
    h, w = x.shape
    f = np.fft.fft2(x - x.mean())
    p = (np.abs(f) ** 2 / (h * w)).ravel()
    r = np.sqrt(np.fft.fftfreq(h)[:, None] ** 2 + np.fft.fftfreq(w)[None, :] ** 2).ravel()
    b = np.round(r / BIN).astype(int)
    return np.bincount(b, p, minlength=92)[:92] / np.maximum(np.bincount(b, minlength=92)[:92], 1)


def radial_of_half(psd_half: np.ndarray) -> np.ndarray:
    """Radial average of an rfft-half PSD grid (H, W//2+1) for a W = H field."""
    h = psd_half.shape[0]
    r = np.sqrt(np.fft.fftfreq(h)[:, None] ** 2 + np.fft.rfftfreq(h)[None, :] ** 2).ravel()
    b = np.round(r / BIN).astype(int)
    return np.bincount(b, psd_half.ravel(), minlength=92)[:92] / np.maximum(np.bincount(b, minlength=92)[:92], 1)


def log_mean_error(p: np.ndarray, truth: np.ndarray, rel_floor: float = 1e-2) -> float:
    """Mean |log(p / truth)| over radial bins 1.. where the truth holds >= rel_floor of its peak."""
    sel = np.arange(truth.size) >= 1
    sel &= truth >= rel_floor * truth[1:].max()
    return float(np.mean(np.abs(np.log(p[sel] / truth[sel]))))


def truth_radial(scale: float = 1.0) -> np.ndarray:
    """Radial truth PSD (unnormalised) at output frequency bins for pattern scale ``scale``."""
    return scale ** 2 * known_psd(scale * np.arange(92) * BIN)


def normalised(p: np.ndarray) -> np.ndarray:
    """Scale a radial PSD to unit sum over bins 1..63 (compare shapes at the variance fixed by histograms)."""
    return p / p[1:64].sum()


@pytest.fixture(scope="module")
def synthetic():
    """A 256^2 Gaussian field with a known PSD and its full-image model."""
    img = gaussian_field(known_psd, 256, seed=3)
    return img, fit_noise(img, None)


@pytest.fixture(scope="module")
def stone():
    """plastered_stone_wall albedo, linear, 256^2."""
    f = real_material_files("plastered_stone_wall")
    if not f["albedo"].exists():
        pytest.skip("shared materials not available")
    a = srgb_to_linear(read_image(f["albedo"])[..., :3])
    return resize_image(a, 256, 256).astype(np.float32)


# ----------------------------------------------------------------------------- spectrum and stationarity


@pytest.mark.parametrize("size", [256, 1024])
def test_spectrum_matches_known_psd(synthetic, size):
    """Synthesised noise keeps the true PSD (log-mean error < 10%) at 1x and 4x the input size."""
    _, model = synthetic
    n_seeds = 6 if size == 256 else 1
    p = np.mean([radial_power(synthesize(model, size, size, seed=s)[..., 0]) for s in range(n_seeds)], axis=0)
    err = log_mean_error(normalised(p), normalised(truth_radial()))
    print(f"size {size}: radial PSD log-mean error {err:.3f}")
    assert err < 0.10


def test_expected_psd_and_scale(synthetic):
    """The model's expected PSD follows the truth; scale 2 maps f -> 2f with 4x density (features twice as big)."""
    _, model = synthetic
    e1 = radial_of_half(expected_psd(model, 512, 512)[0])
    e2 = radial_of_half(expected_psd(model, 512, 512, scale=2.0)[0])
    assert log_mean_error(normalised(e1), normalised(truth_radial())) < 0.10
    assert log_mean_error(normalised(e2), normalised(truth_radial(2.0))) < 0.10
    # realised scale-2 synthesis: energy moves to lower frequencies
    x2 = synthesize(model, 512, 512, scale=2.0, seed=1)[..., 0]
    x1 = synthesize(model, 512, 512, scale=1.0, seed=1)[..., 0]
    c1 = np.corrcoef(x1[:, :-1].ravel(), x1[:, 1:].ravel())[0, 1]
    c2 = np.corrcoef(x2[:, :-1].ravel(), x2[:, 1:].ravel())[0, 1]
    assert c2 > c1 + 0.01


def test_white_noise_variance_exact():
    """The complex white-noise draw gives unit variance after irfft2 for even and odd sizes."""
    import scipy.fft as sfft

    from workers.noise import _white

    for h, w in ((128, 128), (97, 131), (64, 200)):
        z = _white(np.random.default_rng(0), 4, h, w)
        y = sfft.irfft2(z, s=(h, w), axes=(1, 2))
        assert abs(y.var() - 1.0) < 0.03, (h, w, y.var())


def test_stationarity(synthetic):
    """Variance is the same in every quadrant and at the borders (no tile seams, no vignetting)."""
    _, model = synthetic
    x = np.stack([synthesize(model, 512, 512, seed=s)[..., 0] for s in range(4)])
    quads = [x[:, :256, :256], x[:, :256, 256:], x[:, 256:, :256], x[:, 256:, 256:], x[:, :16], x[:, :, -16:]]
    v = np.array([q.var() for q in quads])
    assert v.max() / v.min() < 1.25, v
    # periodic: the wrap-around step (last column -> first) is like any interior step, so maps tile
    wrap = np.abs(x[:, :, 0] - x[:, :, -1]).mean()
    inner = np.abs(np.diff(x, axis=2)).mean()
    assert abs(wrap / inner - 1.0) < 0.1


def test_tiled_synthesis_keeps_variance_spectrum_and_periodicity(synthetic):
    """Blended tiles (weights normalised by root-sum-square): no variance dip in the overlaps, the true PSD,
    still periodic; deterministic per seed. Large outputs take this path automatically."""
    from workers.noise import TILE, tile_plan, tile_size

    _, model = synthetic
    size, tile = 640, 256   # 3 x 3 wrapping tiles, sin^2 ramps over 32 px
    fields = np.stack([np.add.reduce(synthesize_layers(model, size, size, seed=s, tile=tile).layers)[..., 0]
                       for s in range(6)])
    plain = np.stack([np.add.reduce(synthesize_layers(model, size, size, seed=s).layers)[..., 0] for s in range(6)])
    col = fields.var(axis=(0, 1)).reshape(-1, 16).mean(axis=1)   # variance profile across tiles and overlaps
    print(f"tiled column variance min/max {col.min() / col.max():.3f}, tiled/plain {fields.var() / plain.var():.3f}")
    assert col.min() / col.max() > 0.8
    assert abs(fields.var() / plain.var() - 1.0) < 0.1
    p = np.mean([radial_power(f) for f in fields], axis=0)
    assert log_mean_error(normalised(p), normalised(truth_radial())) < 0.10
    wrap = np.abs(fields[:, :, 0] - fields[:, :, -1]).mean()
    assert abs(wrap / np.abs(np.diff(fields, axis=2)).mean() - 1.0) < 0.1
    a = synthesize(model, 300, 200, seed=4, tile=128)
    assert np.array_equal(a, synthesize(model, 300, 200, seed=4, tile=128))
    assert not np.array_equal(a, synthesize(model, 300, 200, seed=4))
    # automatic choice: one FFT up to 4096^2; above, TILE px tiles grown to the pattern's longest wavelength
    assert tile_size(model, 4096, 4096, 1.0) is None and tile_size(model, 6000, 5000, 1.0) == TILE
    assert tile_size(model, 6000, 5000, 16.0) == 16 * 256 and tile_size(model, 6000, 5000, 32.0) is None
    starts, prof = tile_plan(1000, 256)
    cover = np.zeros(1000)
    for x0 in starts:
        np.add.at(cover, (x0 + np.arange(256)) % 1000, prof ** 2)
    assert cover.min() > 0.4 and len(starts) == 5


# ----------------------------------------------------------------------------- masks


def test_half_mask_spectrum_close_to_full(synthetic):
    """Fitting on a 50%-masked image gives a spectrum within 15% of the full-image fit."""
    img, full_model = synthetic
    mask = np.zeros(img.shape[:2], bool)
    mask[:, :128] = True
    blobs = gaussian_field(lambda r: np.exp(-0.5 * (r / 0.01) ** 2), 256, seed=9)[..., 0]
    mask_blob = blobs > np.median(blobs)
    ref = radial_of_half(expected_psd(full_model, 256, 256)[0])
    for m in (mask, mask_blob):
        half = fit_noise(np.where(m[..., None], img, 0.0), m)
        e = radial_of_half(expected_psd(half, 256, 256)[0])
        err = log_mean_error(normalised(e), normalised(ref))
        print(f"mask fraction {m.mean():.2f}: T={half.info['window']} spectrum log-mean diff {err:.3f}")
        assert err < 0.15


def test_mask_values_outside_are_ignored(synthetic):
    """Garbage outside the mask does not change the model."""
    img, _ = synthetic
    m = np.zeros(img.shape[:2], bool)
    m[:, :128] = True
    a = fit_noise(np.where(m[..., None], img, 0.0), m)
    b = fit_noise(np.where(m[..., None], img, 5.0), m)
    np.testing.assert_allclose(a.base, b.base, atol=1e-5)
    np.testing.assert_allclose(a.layers[0].spectrum, b.layers[0].spectrum, rtol=1e-3, atol=1e-7)


def _mortar_grid(n: int = 256, period: int = 32, width: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """A mortar network (lines ``width`` px wide every ``period`` px) and its distance to the bricks."""
    d1 = np.minimum(np.arange(n) % period, (-np.arange(n)) % period)  # 0 on the line's axis
    inside = d1 <= width // 2
    mask = inside[:, None] | inside[None, :]
    return mask, ndimage.distance_transform_edt(np.pad(mask, 4, mode="wrap"))[4:-4, 4:-4]


def test_erosion_follows_the_mask_thickness():
    """A thin network keeps its core (the full radius would erase it); a wide region is eroded by the full
    radius."""
    mask, _ = _mortar_grid()
    em = erode_mask(mask, 0.02)          # 5 px at 256: more than the 5 px lines' half-width
    kept = em.sum() / mask.sum()
    print(f"mortar pixels kept {kept:.2f}")
    assert 0.5 <= kept < 1.0 and not em[~mask].any()
    wide = np.zeros((256, 256), bool)
    wide[:, 40:200] = True
    ew = erode_mask(wide, 0.02)
    assert ew[:, 46:194].all() and not ew[:, :45].any() and not ew[:, 195:].any()


def test_thin_mask_histogram_ignores_its_mixed_edge():
    """Mortar lines whose one-pixel edge holds the bricks' colour (as a soft matte's threshold leaves it): the
    fitted histogram is the mortar's, not the mortar's mixed with the bricks'."""
    mask, dist = _mortar_grid()
    rng = np.random.default_rng(0)
    img = np.where(mask, 0.55, 0.85) + 0.01 * rng.standard_normal(mask.shape)
    img = np.where(mask & (dist <= 1), 0.85, img).astype(np.float32)   # the edge: brick-coloured
    out = synthesize(fit_noise(img, mask), 256, 256, seed=1)
    print(f"synthesised mortar mean {out.mean():.3f} (mortar 0.55, edge 0.85)")
    assert abs(float(np.median(out)) - 0.55) < 0.03 and abs(float(out.mean()) - 0.55) < 0.04


# ----------------------------------------------------------------------------- histogram


def _lag_correlation(x: np.ndarray, dy: int, dx: int) -> float:
    """Normalised autocorrelation of a periodic HxWx1 field at lag (dy, dx)."""
    x = x[..., 0] - x[..., 0].mean()
    return float((x * np.roll(x, (dy, dx), (0, 1))).mean() / x.var())


@pytest.mark.parametrize("height,gap", [(10, 3), (8, 2)])
def test_thin_pieces_keep_their_grain_direction(height, gap):
    """Rows of pieces narrower than a spectrum window (slates, planks) with a vertical grain inside: the
    synthesis keeps the grain (the correlation 4 px along it stays high, across it near 0). The truth's is
    0.77 / -0.03; windows wholly inside the pieces gave 8 px windows or none (white noise): 0.27 and 0.09."""
    rng = np.random.default_rng(0)
    grain = ndimage.gaussian_filter(rng.standard_normal((256, 256)), (4.0, 0.8), mode="wrap")
    grain = (0.5 + 0.08 * grain / grain.std()).astype(np.float32)[..., None]
    mask = np.repeat(((np.arange(256) % (height + gap)) < height)[:, None], 256, axis=1)
    model = fit_noise(np.where(mask[..., None], grain, 0.1), mask)
    out = synthesize(model, 256, 256, seed=1)
    along, across = _lag_correlation(out, 4, 0), _lag_correlation(out, 0, 4)
    print(f"pieces {height} px: correlation 4 px along the grain {along:.2f}, across {across:.2f}")
    assert along >= 0.45 and abs(across) <= 0.1


def test_histogram_matches_masked_quantiles(stone):
    """Synthesised values match the masked input's quantiles per channel (max error < 0.02)."""
    mask = np.zeros(stone.shape[:2], bool)
    mask[:, :128] = True
    model = fit_noise(stone, mask)
    probs = np.linspace(0.01, 0.99, 99)
    target = np.quantile(stone[mask], probs, axis=0)
    for size in (256, 512):
        out = synthesize(model, size, size, seed=2)
        err = np.abs(np.quantile(out.reshape(-1, 3), probs, axis=0) - target).max()
        print(f"size {size}: max quantile error {err:.4f}")
        assert err < 0.02
    # a skewed single-channel map too (roughness-like)
    g = gaussian_field(known_psd, 256, seed=5, std=1.0, mean=0.0)
    skew = (0.2 + 0.5 * (1 - np.exp(-np.exp(g)))).astype(np.float32)
    mk = fit_noise(skew, None)
    out = synthesize(mk, 256, 256, seed=0)
    err = np.abs(np.quantile(out, probs) - np.quantile(skew, probs)).max()
    assert err < 0.02


def _sliced_distance(a: np.ndarray, b: np.ndarray, n: int = 64) -> float:
    """Mean over n fixed random directions of the quantile distance of two colour sets (sliced Wasserstein-1)."""
    d = np.random.default_rng(0).standard_normal((3, n))
    d /= np.linalg.norm(d, axis=0)
    p = np.linspace(0.005, 0.995, 199)
    return float(np.mean(np.abs(np.quantile(a.reshape(-1, 3) @ d, p, axis=0) - np.quantile(b.reshape(-1, 3) @ d, p,
                                                                                           axis=0))))


def test_colour_transport_keeps_the_joint_colour_distribution():
    """Three colour phases (not on one line in RGB): the transported noise's colours are closer to the input's
    than channel-by-channel matching gives (sliced distance over 3 seeds), and its marginals stay matched."""
    rng = np.random.default_rng(1)
    lab = np.argmax(np.stack([ndimage.gaussian_filter(rng.standard_normal((256, 256)), 4) for _ in range(3)]), 0)
    cols = np.array([[0.7, 0.15, 0.1], [0.1, 0.6, 0.15], [0.15, 0.2, 0.7]])
    img = (cols[lab] + 0.03 * rng.standard_normal((256, 256, 3))).astype(np.float32)
    dist = {}
    for steps in (0, 12):
        model = fit_noise(img, None, NoiseConfig(transport=steps))
        assert (model.transport is None) == (steps == 0)
        outs = [synthesize(model, 256, 256, seed=s) for s in range(3)]
        dist[steps] = float(np.mean([_sliced_distance(o, img) for o in outs]))
        probs = np.linspace(0.01, 0.99, 99)
        err = np.abs(np.quantile(outs[0].reshape(-1, 3), probs, axis=0) - np.quantile(img.reshape(-1, 3), probs,
                                                                                      axis=0)).mean()
        assert err < 0.02  # mean: 64 stored quantiles interpolate across the gaps between the phases
    print(f"sliced colour distance: channels matched {dist[0]:.4f}, transported {dist[12]:.4f}")
    assert dist[12] < 0.5 * dist[0]
    gray = fit_noise(img[..., :1], None)
    assert gray.transport is None


def test_colour_transport_round_trips_and_old_params_still_read(stone):
    """The transport travels in the params; a params dict of kind noise/1 (no transport) still synthesises."""
    model = fit_noise(stone, None)
    params = json.loads(json.dumps(model.to_params()))
    assert params["kind"] == "proceduralize.noise/1.1" and "transport" in params
    back = NoiseModel.from_params(params)
    assert np.abs(synthesize(back, 128, 128, seed=1) - synthesize(model, 128, 128, seed=1)).max() < 2e-3
    old = {k: v for k, v in params.items() if k != "transport"} | {"kind": "proceduralize.noise/1"}
    assert NoiseModel.from_params(old).transport is None
    bad = dict(params, transport={"rotations": params["transport"]["rotations"], "quantiles": params["quantiles"]})
    with pytest.raises(GraphError, match="transport"):
        NoiseModel.from_params(bad)


# ----------------------------------------------------------------------------- multi vs single layer (Fig. 7)


def test_multilayer_beats_single_layer(stone):
    """On plastered_stone_wall albedo masked by half, the multi-layer model's spectrum is closer to the input's."""
    mask = np.zeros(stone.shape[:2], bool)
    mask[:, :128] = True
    grey = stone.mean(axis=2)
    truth = radial_power(grey)
    multi = fit_noise(stone, mask)
    single = fit_noise(stone, mask, NoiseConfig(n_levels=0, gabor_last=False))
    d = {}
    for name, model in (("multi", multi), ("single", single)):
        p = np.mean([radial_power(synthesize(model, 256, 256, seed=s).mean(axis=2)) for s in range(6)], axis=0)
        d[name] = log_mean_error(p, truth, rel_floor=1e-4)
    print(f"plastered_stone_wall spectrum distance (mean |log P/P_in|): multi {d['multi']:.3f} "
          f"single {d['single']:.3f}")
    assert d["multi"] < d["single"]
    assert len(multi.layers) == 3 and multi.layers[-1].kind == "gabor"


# ----------------------------------------------------------------------------- seeds


def test_seeds(synthetic):
    """Same seed -> identical; different seeds -> different fields with the same statistics."""
    _, model = synthetic
    a = synthesize(model, 256, 256, seed=7)
    b = synthesize(model, 256, 256, seed=7)
    c = synthesize(model, 256, 256, seed=8)
    assert np.array_equal(a, b)
    assert np.abs(a - c).mean() > 0.01
    assert abs(a.mean() - c.mean()) < 0.01 and abs(a.std() - c.std()) < 0.01
    pa, pc = radial_power(a[..., 0]), radial_power(c[..., 0])
    assert log_mean_error(pa[:64], pc[:64]) < 0.35  # single realisations: sampling noise only


# ----------------------------------------------------------------------------- serialisation and node


def test_params_round_trip_and_size(stone):
    """to_params is JSON, small (no pixels), and from_params synthesises the identical map."""
    model = fit_noise(stone, None)
    doc = json.dumps(model.to_params())
    print(f"RGB model JSON: {len(doc)} bytes")
    assert len(doc) < 64_000
    back = NoiseModel.from_params(json.loads(doc))
    a = synthesize(model, 200, 120, seed=1)
    b = synthesize(back, 200, 120, seed=1)
    assert a.shape == (120, 200, 3)
    assert np.abs(a - b).max() < 2e-3  # float16 spectra
    assert all(l.spectrum.shape[1] <= 64 for l in back.layers if l.kind == "window")


def test_noise_node_in_graph(stone, tmp_path):
    """The 'noise' node renders the matched map with identity filters; filters edit layers; scale works."""
    model = fit_noise(stone, None)
    mat = graph.new_material(seed=3, working_size=(256, 256))
    mat.add("n", "noise", noise_params(model, seed=11))
    mat.maps.append({"name": "albedo", "node": "n"})
    path = graph.save(mat, tmp_path / "m.json")
    out = graph.evaluate(graph.load(path), 128, 96)["albedo"]
    ref = np.clip(synthesize_layers(model, 128, 96, seed=11).matched, 0, 1)
    assert np.abs(out - ref).max() < 2e-3
    # amplify the finest layer: more high-frequency energy
    graph.set_param(mat, "n.filters.0.a", 3.0)
    edited = graph.evaluate(mat, 128, 96)["albedo"]
    hf = lambda x: np.abs(np.diff(x, axis=1)).mean()  # noqa: E731
    assert hf(edited) > 1.5 * hf(out)
    graph.set_param(mat, "n.filters.0.a", 1.0)
    graph.set_param(mat, "n.d", 0.1)
    shifted = graph.evaluate(mat, 128, 96)["albedo"]
    assert abs((shifted - out).mean() - 0.1) < 0.01
    # scale: same extent, bigger features
    big = graph.evaluate(mat, 128, 96, scale=3.0)["albedo"]
    assert hf(big) < 0.7 * hf(shifted)
    # the node seed follows the material seed when params has none
    mat.node("n")["params"].pop("seed")
    s1 = graph.evaluate(mat, 64, 64, seed=1)["albedo"]
    s2 = graph.evaluate(mat, 64, 64, seed=2)["albedo"]
    assert not np.array_equal(s1, s2)


def test_bad_inputs():
    """Errors name the problem."""
    img = np.zeros((32, 32, 3), np.float32)
    with pytest.raises(InputError, match="mask shape"):
        fit_noise(img, np.ones((16, 16), bool))
    with pytest.raises(InputError, match="empty"):
        fit_noise(img, np.zeros((32, 32), bool))
    with pytest.raises(InputError, match="NaN"):
        fit_noise(np.full((32, 32), np.nan), None)
    with pytest.raises(InputError, match="n_levels"):
        NoiseConfig(n_levels=9)
    model = fit_noise(np.random.default_rng(0).random((32, 32, 1)).astype(np.float32), None)
    p = noise_params(model)
    p["filters"] = [{"a": "x"}]
    with pytest.raises((GraphError, ValueError)):
        graph.NODE_TYPES["noise"].validate(p)
    p = model.to_params()
    p["layers"][0]["kind"] = "bogus"
    with pytest.raises(GraphError, match="kind"):
        NoiseModel.from_params(p)


def test_small_and_flat_regions():
    """Tiny masks (no 8x8 window fits) and constant images still give a usable model."""
    rng = np.random.default_rng(1)
    img = rng.random((64, 64, 3)).astype(np.float32)
    m = np.zeros((64, 64), bool)
    m[::3, ::3] = True  # scattered pixels: no window is 99% inside
    model = fit_noise(img, m)
    out = synthesize(model, 64, 64, seed=0)
    assert np.all(np.isfinite(out)) and out.std() > 0.05
    flat = fit_noise(np.full((64, 64, 1), 0.3, np.float32), None)
    out = synthesize(flat, 32, 32)
    np.testing.assert_allclose(out, 0.3, atol=1e-5)


def test_gabor_fit_recovers_oriented_spectrum():
    """A PSD made of two oriented Gabor bumps is refitted with small error and the peak in the right place."""
    from workers.gabor import fit_gabor, gabor_psd

    truth = np.array([[0.04, 0.015, 0.012, 1.0], [-0.015, 0.03, 0.01, 0.5]], np.float32)
    fy = np.fft.fftfreq(256)
    fx = np.fft.fftfreq(256)
    psd = gabor_psd(truth, fy, fx).astype(np.float64)
    params, err = fit_gabor(psd, n_kernels=16)
    fit = gabor_psd(params, fy, fx)
    assert err < 0.1  # against the smoothed periodogram it fits
    assert np.linalg.norm(fit - psd) / np.linalg.norm(psd) < 0.25  # against the exact PSD (smoothing bias)
    iy, ix = np.unravel_index(np.argmax(fit), fit.shape)
    assert abs(abs(fy[iy]) - 0.015) < 0.006 and abs(abs(fx[ix]) - 0.04) < 0.006


def test_node_formula_with_filters(stone):
    """O = matched + sum_k (blur(a_k L_k + b_k; sigma_k * scale) - L_k) + (c-1) base + d, per-channel values too."""
    from workers.nodes import EvalContext, gaussian_blur

    model = fit_noise(stone, None)
    filters = [{"a": 0.5, "b": 0.0, "sigma": 0.0}, {"a": [1.2, 1.0, 0.8], "b": 0.01, "sigma": [1.0, 2.0, 1.0]},
               {"a": 1.0, "b": 0.0, "sigma": 1.5}]
    params = noise_params(model, filters=filters, c=0.9, d=[0.0, 0.02, 0.0], seed=4)
    node = graph.NODE_TYPES["noise"]
    node.validate(params)
    ctx = EvalContext(width=96, height=64, scale=2.0, seed=0)
    out = node.evaluate(params, {}, ctx, "n")
    res = synthesize_layers(model, 96, 64, scale=2.0, seed=4)
    exp = res.matched.copy()
    a1, s1 = np.array([1.2, 1.0, 0.8]), [1.0, 2.0, 1.0]
    exp += 0.5 * res.layers[0] - res.layers[0]
    blur1 = np.stack([gaussian_blur(a1[k] * res.layers[1][..., k] + 0.01, 2 * s1[k]) for k in range(3)], -1)
    exp += blur1 - res.layers[1]
    exp += gaussian_blur(res.layers[2], 3.0) - res.layers[2]
    exp += -0.1 * model.base + np.array([0.0, 0.02, 0.0])
    assert np.abs(out - exp).max() < 1e-4
