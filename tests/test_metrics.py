"""Quality metrics: identical statistics score near zero, different textures score higher."""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from workers import metrics


def _noise(seed: int, sigma: float, size: int = 128) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = ndimage.gaussian_filter(rng.standard_normal((size, size)), sigma, mode="wrap")
    return (0.5 + 0.15 * x / x.std()).astype(np.float32)


def test_same_process_scores_lower_than_different_process():
    a, a2, b = _noise(0, 2.0), _noise(1, 2.0), _noise(2, 6.0)
    same = metrics.texture_metrics(a, a2)
    diff = metrics.texture_metrics(a, b)
    assert same["spectrum"] < 0.25 * diff["spectrum"]
    assert same["swd"] < 0.5 * diff["swd"]
    assert same["histogram"] < 0.02


def test_random_phase_noise_keeps_spectrum_and_mean():
    a = _noise(3, 3.0)
    r = metrics.random_phase_noise(a, seed=1)
    assert abs(float(r.mean()) - float(a.mean())) < 1e-4
    other = _noise(6, 6.0)
    assert metrics.spectrum_distance(a, r) < 0.3 * metrics.spectrum_distance(a, other)
    assert not np.allclose(r[..., 0], a)


def test_flat_baseline_is_worst():
    a, a2 = _noise(4, 2.0), _noise(5, 2.0)
    flat = metrics.flat_mean(a)
    assert metrics.sliced_wasserstein(a, flat) > 3 * metrics.sliced_wasserstein(a, a2)


def test_halves_shapes():
    left, right = metrics.split_halves(np.zeros((10, 21, 3)))
    assert left.shape == right.shape == (10, 10, 3)
