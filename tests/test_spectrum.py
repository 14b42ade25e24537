"""Local Welch spectra: exactness against a brute-force window FFT, frequency localisation, texture separation."""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from workers.spectrum import WELCH_OFFSETS, local_spectrum, pca_project, spectral_features


def _brute_spectrum(img: np.ndarray, y: int, x: int) -> np.ndarray:
    """Spec definition at one pixel: RMS over 4x4 offsets of |FFT8x8| / 64 (64 dims), wrapping windows."""
    acc = np.zeros((8, 8))
    for oy in WELCH_OFFSETS:
        for ox in WELCH_OFFSETS:
            win = np.roll(np.roll(img, -(y - oy), 0), -(x - ox), 1)[:8, :8]
            acc += np.abs(np.fft.fft2(win) / 64) ** 2
    return np.sqrt(acc / 16).reshape(-1)


def test_matches_brute_force_geometry():
    rng = np.random.default_rng(1)
    img = ndimage.gaussian_filter(rng.random((48, 40)), 1.0).astype(np.float32)
    s = local_spectrum(img)
    assert s.shape == (48, 40, 40)
    pts = [(0, 0), (5, 39), (47, 3), (20, 17)]
    full = [_brute_spectrum(img, y, x) for y, x in pts]
    half = [s[y, x] for y, x in pts]
    for a, b in zip(full, half):  # norms equal
        np.testing.assert_allclose(np.linalg.norm(a), np.linalg.norm(b), rtol=1e-4)
    for i in range(len(pts)):  # pairwise distances equal, so PCA sees the 64-dim geometry
        for j in range(i + 1, len(pts)):
            np.testing.assert_allclose(np.linalg.norm(full[i] - full[j]), np.linalg.norm(half[i] - half[j]),
                                       rtol=1e-4, atol=1e-7)


def test_sinusoid_peaks_at_its_frequency_and_is_shift_equivariant():
    x = np.arange(64)
    img = np.tile(0.5 + 0.4 * np.cos(2 * np.pi * x / 4), (64, 1)).astype(np.float32)  # 2 cycles per 8 px
    s = local_spectrum(img)
    spec = s.reshape(64, 64, 8, 5).copy()
    spec[..., 0, 0] = 0
    peak = np.unravel_index(np.argmax(spec[10, 10]), (8, 5))
    assert peak == (0, 2), peak
    rolled = local_spectrum(np.roll(img, (3, 5), axis=(0, 1)))
    np.testing.assert_allclose(rolled, np.roll(s, (3, 5), axis=(0, 1)), atol=1e-6)


def test_fine_and_coarse_noise_separate_on_a_spectral_component():
    rng = np.random.default_rng(0)
    n = 128
    fine = rng.standard_normal((n, n))
    coarse = ndimage.gaussian_filter(rng.standard_normal((n, n)), 4, mode="wrap")
    coarse /= coarse.std()
    truth = np.zeros((n, n), bool)
    truth[:, n // 2:] = True
    img = (0.5 + 0.1 * np.where(truth, coarse, fine)).astype(np.float32)
    f = spectral_features([img], n_components=3)
    assert f.shape == (n, n, 3) and f.min() >= 0 and f.max() <= 1
    inner = np.zeros((n, n), bool)
    inner[:, 8:n // 2 - 8] = True
    gaps = []
    for c in range(3):
        a, b = f[..., c][inner], f[..., c][np.roll(inner, n // 2, axis=1)]
        gaps.append(abs(a.mean() - b.mean()) / (a.std() + b.std()))
        print(f"spectral component {c}: fine {a.mean():.3f}+-{a.std():.3f}, coarse {b.mean():.3f}+-{b.std():.3f}")
    assert max(gaps) > 1.5, gaps


def test_pca_project_is_deterministic_and_thin_svd_matches_covariance():
    rng = np.random.default_rng(3)
    x = rng.standard_normal((20, 200)).astype(np.float32) * np.linspace(3, 0.1, 200).astype(np.float32)
    p1, p2 = pca_project(x, 5), pca_project(x, 5)
    np.testing.assert_array_equal(p1, p2)
    # projections on the top axes keep most of the variance, ordered by decreasing variance
    var = p1.var(axis=0)
    assert np.all(np.diff(var) <= 1e-5)
    xx = rng.standard_normal((500, 4)).astype(np.float32) @ np.diag([5, 3, 1, 0.1]).astype(np.float32)
    p = pca_project(xx, 4)
    np.testing.assert_allclose(np.linalg.norm(p, axis=1), np.linalg.norm(xx - xx.mean(0), axis=1), rtol=1e-4)
