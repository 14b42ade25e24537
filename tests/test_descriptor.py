"""PPTBF mask descriptor: layout, valid-pixel statistics, spectrum and LBP behaviour, PCA, realisation invariance."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from pptbf_db import pptbf
from pptbf_db.descriptor import DescriptorConfig, block_slices, describe_masks, fit_pca, lbp_histograms, spectrum_block

CFG = DescriptorConfig()


def noise_masks(n: int, size: int = 64, sigma: float = 2.0, seed: int = 0, frac: float = 0.5) -> np.ndarray:
    """Thresholded Gaussian-filtered white noise (synthetic blob masks), (n, size, size) float32."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        f = gaussian_filter(rng.standard_normal((size, size)), sigma, mode="wrap")
        out.append(f > np.quantile(f, 1 - frac))
    return np.stack(out).astype(np.float32)


def stripes(size: int, period: float, vertical: bool) -> np.ndarray:
    """Binary stripes of the given period (vertical = varying along x)."""
    t = np.arange(size, dtype=np.float64)
    s = (np.sin(2 * np.pi * t / period) > 0).astype(np.float32)
    return np.tile(s[None, :], (size, 1)) if vertical else np.tile(s[:, None], (1, size))


def test_layout_and_determinism():
    m = noise_masks(3)
    a = describe_masks(m)
    b = describe_masks(m)
    sl = block_slices(CFG, a.shape[1])
    assert a.dtype == np.float32 and np.isfinite(a).all()
    assert sl["lbp"].stop - sl["lbp"].start == len(CFG.lbp_radii) * (CFG.lbp_points + 2)
    assert sl["gram"].stop - sl["gram"].start == CFG.gram_size == 4 * 16 * 17 // 2     # VGG-19, 16 directions
    rnd = DescriptorConfig(extractor="random")
    assert describe_masks(m, None, rnd).shape[1] - a.shape[1] == sum(w * (w + 1) // 2 for w in rnd.gram_widths) - 544
    assert sl["spectrum"].stop - sl["spectrum"].start == CFG.spectrum_radial + CFG.spectrum_angular
    np.testing.assert_array_equal(a, b)
    # a single 2-D mask is a batch of one, and batching does not change a descriptor (beyond float32 summation
    # order in the VGG convolutions)
    np.testing.assert_allclose(describe_masks(m[1]), a[1:2], rtol=1e-3, atol=1e-4)
    with pytest.raises(ValueError, match="masks must be"):
        describe_masks(np.zeros((2, 3, 4, 5)))


def test_config_round_trip():
    cfg = DescriptorConfig(lbp_radii=(1, 3), dim=32)
    assert DescriptorConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueError, match="unknown descriptor"):
        DescriptorConfig.from_dict({**cfg.to_dict(), "bogus": 1})


def test_invalid_pixels_are_ignored():
    """Whatever the invalid pixels hold, the descriptor is the same (statistics over valid pixels only)."""
    m = noise_masks(1, seed=3)[0]
    valid = np.ones_like(m, dtype=bool)
    valid[:, 40:] = False
    rng = np.random.default_rng(0)
    a, b = m.copy(), m.copy()
    a[~valid] = 1.0
    b[~valid] = rng.random(int((~valid).sum())) > 0.5
    da, db = describe_masks(a, valid), describe_masks(b, valid)
    np.testing.assert_allclose(da, db, rtol=1e-5, atol=1e-6)
    assert not np.allclose(describe_masks(a), describe_masks(b), atol=1e-3)


def test_partial_mask_stays_close_to_full():
    """A stationary pattern seen on 60% of its pixels describes close to the full one, far from another pattern."""
    fine = noise_masks(6, sigma=1.5, seed=1)
    coarse = noise_masks(6, sigma=4.0, seed=2)
    valid = np.ones((64, 64), dtype=bool)
    valid[:, 38:] = False
    pca = fit_pca(describe_masks(np.concatenate([fine, coarse, noise_masks(8, sigma=2.5, seed=5)])), CFG, dim=16)
    full = pca.transform(describe_masks(fine))
    part = pca.transform(describe_masks(fine, valid))
    other = pca.transform(describe_masks(coarse))
    same = np.linalg.norm(full - part, axis=1)
    diff = np.linalg.norm(full[:, None] - other[None], axis=2)
    assert same.max() < 0.5 * diff.min(), (same, diff.min())


def test_spectrum_finds_period_and_orientation():
    cfg = CFG
    m = np.stack([stripes(128, 8, True), stripes(128, 16, True), stripes(128, 8, False)])
    s = spectrum_block(m, None, cfg)
    rad, ang = s[:, :cfg.spectrum_radial], s[:, cfg.spectrum_radial:]
    # radial peak: period 8 (f = 1/8) sits in a higher bin than period 16
    assert rad[0].argmax() > rad[1].argmax()
    edges = np.geomspace(1 / 128, 0.5 * np.sqrt(2), cfg.spectrum_radial + 1)
    assert edges[rad[0].argmax()] <= 1 / 8 < edges[rad[0].argmax() + 1]
    # orientation: x-stripes put their energy at angle 0, y-stripes at pi/2
    assert ang[0].argmax() == 0
    assert ang[2].argmax() == cfg.spectrum_angular // 2


def test_lbp_of_flat_and_checker():
    flat = np.zeros((1, 32, 32), np.float32)
    h = lbp_histograms(flat, None, CFG)[0] ** 2           # back from the square root
    n = CFG.lbp_points + 2
    for j in range(len(CFG.lbp_radii)):
        assert h[j * n:(j + 1) * n].sum() == pytest.approx(1.0)
        assert h[j * n + CFG.lbp_points] == pytest.approx(1.0)   # all neighbours >= centre: code P
    blobs = lbp_histograms(noise_masks(1), None, CFG)[0] ** 2
    assert blobs[CFG.lbp_points] < 0.95                  # edges give other codes


def test_pca_recovers_low_rank_and_weights():
    rng = np.random.default_rng(0)
    basis = rng.standard_normal((3, CFG.lbp_size + 50 + CFG.spectrum_size))
    raw = (rng.standard_normal((200, 3)) @ basis).astype(np.float32)
    pca = fit_pca(raw, CFG, dim=8)
    assert pca.dim == 8 and pca.explained[:3].sum() > 0.999
    z = pca.standardise(raw)
    red = pca.transform(raw)
    d_full = np.linalg.norm(z[:20, None] - z[None, :20], axis=2)
    d_red = np.linalg.norm(red[:20, None] - red[None, :20], axis=2)
    np.testing.assert_allclose(d_red, d_full, rtol=1e-3, atol=1e-4)
    # a zero weight removes a block from the distance
    only_gram = fit_pca(raw, DescriptorConfig(weights=(0.0, 1.0, 0.0)), dim=8)
    sl = block_slices(CFG, raw.shape[1])
    bumped = raw[:1].copy()
    bumped[0, sl["lbp"]] += 5.0
    np.testing.assert_allclose(only_gram.transform(bumped), only_gram.transform(raw[:1]), atol=1e-4)


def test_pptbf_realisations_describe_alike():
    """Two realisations (shifts) of the same PPTBF are nearer than masks of other parameters, most of the time."""
    rng = np.random.default_rng(7)
    params = pptbf.sample_params(rng, 24, ref_width=64)
    a = np.stack([pptbf.render_mask(p, 64) for p in params]).astype(np.float32)
    b = np.stack([pptbf.render_mask(p, 64, shift=(3.7, 1.3)) for p in params]).astype(np.float32)
    ok = (a.mean(axis=(1, 2)) > 0.01) & (a.mean(axis=(1, 2)) < 0.99)
    pca = fit_pca(describe_masks(a[ok]), CFG, dim=16)
    ra, rb = pca.transform(describe_masks(a[ok])), pca.transform(describe_masks(b[ok]))
    d = np.linalg.norm(rb[:, None] - ra[None], axis=2)
    nearest_is_self = (d.argmin(axis=1) == np.arange(len(d))).mean()
    assert nearest_is_self >= 0.6, nearest_is_self
