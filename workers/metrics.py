"""Texture similarity metrics for the quality scorecard and the baselines they are compared with.

All metrics compare *statistics*, not pixels: a procedural material is a new realisation, so a pixel
difference would be meaningless. Lower is better for every distance here.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy import ndimage


def _as3(a: np.ndarray) -> np.ndarray:
    """HxW -> HxWx1; float32."""
    a = np.asarray(a, dtype=np.float32)
    return a[..., None] if a.ndim == 2 else a


@dataclass
class SWDConfig:
    """Multi-scale patch sliced Wasserstein settings."""

    patch: int = 7
    levels: int = 3
    projections: int = 64
    patches: int = 4096


def _random_patches(img: np.ndarray, patch: int, n: int, rng: np.random.Generator) -> np.ndarray:
    """n random patch x patch x C patches (flattened) drawn uniformly from img."""
    win = sliding_window_view(img, (patch, patch), axis=(0, 1))  # (H-p+1, W-p+1, C, p, p)
    ys = rng.integers(0, win.shape[0], n)
    xs = rng.integers(0, win.shape[1], n)
    return win[ys, xs].reshape(n, -1).astype(np.float32)


def sliced_wasserstein(a: np.ndarray, b: np.ndarray, config: SWDConfig = SWDConfig(), seed: int = 0) -> float:
    """Multi-scale patch sliced Wasserstein distance (mean over levels of a Gaussian pyramid)."""
    a, b = _as3(a), _as3(b)
    if a.shape[2] != b.shape[2]:
        raise ValueError(f"channel counts differ: {a.shape} vs {b.shape}")
    rng = np.random.default_rng(seed)
    total = 0.0
    for _level in range(config.levels):
        if min(a.shape[:2] + b.shape[:2]) < config.patch + 1:
            break
        pa = _random_patches(a, config.patch, config.patches, rng)
        pb = _random_patches(b, config.patch, config.patches, rng)
        dirs = rng.standard_normal((pa.shape[1], config.projections)).astype(np.float32)
        dirs /= np.linalg.norm(dirs, axis=0, keepdims=True)
        qa = np.sort(pa @ dirs, axis=0)
        qb = np.sort(pb @ dirs, axis=0)
        total += float(np.mean(np.abs(qa - qb)))
        a = ndimage.zoom(ndimage.gaussian_filter(a, (1, 1, 0)), (0.5, 0.5, 1), order=1)
        b = ndimage.zoom(ndimage.gaussian_filter(b, (1, 1, 0)), (0.5, 0.5, 1), order=1)
    return total / max(config.levels, 1)


def radial_power_spectrum(img: np.ndarray, bins: int = 32) -> np.ndarray:
    """Radially averaged power spectrum per channel (bins x C), frequencies in cycles/pixel up to 0.5."""
    img = _as3(img)
    x = img - img.mean(axis=(0, 1), keepdims=True)
    h, w = x.shape[:2]
    win = np.outer(np.hanning(h), np.hanning(w))[..., None].astype(np.float32)
    p = np.abs(np.fft.fft2(x * win, axes=(0, 1))) ** 2 / (h * w)
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.fftfreq(w)[None, :]
    r = np.sqrt(fx**2 + fy**2)
    idx = np.clip((r / 0.5 * bins).astype(int), 0, bins)  # bin `bins` collects the corners (> 0.5)
    out = np.zeros((bins, x.shape[2]))
    counts = np.bincount(idx.ravel(), minlength=bins + 1)[:bins]
    for c in range(x.shape[2]):
        out[:, c] = np.bincount(idx.ravel(), weights=p[..., c].ravel(), minlength=bins + 1)[:bins]
    return out / np.maximum(counts, 1)[:, None]


SPECTRUM_FLOOR = 1e-7


def spectrum_distance(a: np.ndarray, b: np.ndarray, bins: int = 32) -> float:
    """Mean absolute log10 ratio of radially averaged power spectra (bin 0, the DC, excluded).

    Powers are floored at SPECTRUM_FLOOR, about 8-bit quantisation noise through the Hann window
    ((1/255)^2 / 12 * mean(w^2) ~ 2e-7): below it a map cannot be told from a flat one, and a smaller floor
    only inflates the distance of flat maps (1e-12 gave the flat baseline a 70x ratio to the floor)."""
    pa = radial_power_spectrum(a, bins)[1:]
    pb = radial_power_spectrum(b, bins)[1:]
    eps = SPECTRUM_FLOOR
    return float(np.mean(np.abs(np.log10(pa + eps) - np.log10(pb + eps))))


def histogram_distance(a: np.ndarray, b: np.ndarray, quantiles: int = 101) -> float:
    """1-D Wasserstein distance between value distributions, averaged over channels."""
    a, b = _as3(a), _as3(b)
    q = np.linspace(0, 1, quantiles)
    qa = np.quantile(a.reshape(-1, a.shape[2]), q, axis=0)
    qb = np.quantile(b.reshape(-1, b.shape[2]), q, axis=0)
    return float(np.mean(np.abs(qa - qb)))


def texture_metrics(a: np.ndarray, b: np.ndarray, seed: int = 0) -> dict[str, float]:
    """All three distances between two images of the same kind."""
    return {
        "swd": sliced_wasserstein(a, b, seed=seed),
        "spectrum": spectrum_distance(a, b),
        "histogram": histogram_distance(a, b),
    }


# ----------------------------------------------------------------------------- baselines


def random_phase_noise(img: np.ndarray, seed: int = 0) -> np.ndarray:
    """Random phase noise of a whole image (Galerne et al. 2011): same spectrum and mean, random phases."""
    img = _as3(img)
    h, w, c = img.shape
    mean = img.mean(axis=(0, 1), keepdims=True)
    amp = np.abs(np.fft.fft2(img - mean, axes=(0, 1)))
    rng = np.random.default_rng(seed)
    # phase of the FFT of white noise: Hermitian-symmetric, so the inverse is real; shared across channels
    phase = np.angle(np.fft.fft2(rng.standard_normal((h, w))))[..., None]
    out = np.real(np.fft.ifft2(amp * np.exp(1j * phase), axes=(0, 1))) + mean
    return out.astype(np.float32)


def split_halves(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Left and right halves of an image (the 'other half' floor baseline)."""
    img = _as3(img)
    w2 = img.shape[1] // 2
    return img[:, :w2], img[:, w2 : 2 * w2]


def flat_mean(img: np.ndarray) -> np.ndarray:
    """An image of the mean value (the 'flat material' baseline)."""
    img = _as3(img)
    return np.broadcast_to(img.mean(axis=(0, 1), keepdims=True), img.shape).astype(np.float32).copy()
