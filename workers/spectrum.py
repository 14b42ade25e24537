"""Local (Welch) amplitude spectra per pixel: the texture features that make matting spectrum-aware.

Per map (grey albedo, height, roughness) every pixel gets the 8x8 FFT amplitude (divided by 64) of the
windows that cover it, Welch-averaged over a 4x4 grid of window offsets (step 2) and RMS-combined. All
windows are transformed at once (strided view + batched rFFT) and the Welch sum is a separable sum of
shifted arrays, so there is no per-pixel Python loop. Windows wrap around the borders (material maps tile).

The amplitude of a real window is Hermitian-symmetric, so only the 8x5 half-spectrum is computed; the
columns that stand for two bins of the full 8x8 spectrum are weighted by sqrt(2), which keeps Euclidean
distances (hence PCA) identical to the 64-dimensional spectrum of the spec at 5/8 of the memory.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import scipy.fft

logger = logging.getLogger(__name__)

WINDOW = 8
WELCH_OFFSETS = (0, 2, 4, 6)  # window top-left = pixel - offset, per axis: a 4x4 grid with step 2


@dataclass
class SpectrumConfig:
    """Window size and Welch offsets of the local spectrum (spec defaults)."""

    window: int = WINDOW
    offsets: tuple[int, ...] = WELCH_OFFSETS
    rows_per_chunk: int = 64  # bounds the memory of the batched FFT


def _half_weights(window: int) -> np.ndarray:
    """sqrt(2) for rFFT columns that represent two full-spectrum bins, 1 for self-conjugate ones."""
    ncol = window // 2 + 1
    w = np.full(ncol, np.sqrt(2.0), np.float32)
    w[0] = 1.0
    if window % 2 == 0:
        w[-1] = 1.0
    return np.broadcast_to(w, (window, ncol)).reshape(-1)


def window_power(image: np.ndarray, config: SpectrumConfig = SpectrumConfig()) -> np.ndarray:
    """Squared (weighted) half-spectrum amplitude / window^2 of every window, indexed by its top-left pixel.

    image: HxW float. Returns HxWxD float32 with D = window * (window // 2 + 1).
    """
    w = config.window
    h, wd = image.shape
    pad = np.pad(np.asarray(image, np.float32), ((0, w - 1), (0, w - 1)), mode="wrap")
    wts = _half_weights(w) ** 2
    out = np.empty((h, wd, w * (w // 2 + 1)), np.float32)
    for r0 in range(0, h, config.rows_per_chunk):
        r1 = min(h, r0 + config.rows_per_chunk)
        win = np.lib.stride_tricks.sliding_window_view(pad[r0:r1 + w - 1], (w, w))  # (rows, W, w, w)
        spec = scipy.fft.rfft2(win, axes=(-2, -1))
        p = (spec.real ** 2 + spec.imag ** 2).reshape(r1 - r0, wd, -1) / float(w * w) ** 2
        out[r0:r1] = p * wts
    return out


def local_spectrum(image: np.ndarray, config: SpectrumConfig = SpectrumConfig()) -> np.ndarray:
    """Welch/RMS local amplitude spectrum of a grey HxW image: HxWxD float32 (D = 40 for 8x8 windows).

    The Euclidean geometry equals that of the 64 full-spectrum amplitudes (see module docstring).
    """
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    if image.ndim != 2:
        raise ValueError(f"local_spectrum needs a grey HxW image, got shape {image.shape}")
    p = window_power(image, config)
    # pixel (y, x) averages the windows with top-left (y - oy, x - ox): roll by +offset, separably.
    acc_y = np.zeros_like(p)
    for o in config.offsets:
        acc_y += np.roll(p, o, axis=0)
    del p
    acc = np.zeros_like(acc_y)
    for o in config.offsets:
        acc += np.roll(acc_y, o, axis=1)
    acc /= float(len(config.offsets) ** 2)
    return np.sqrt(acc, out=acc)


def spectrum_stack(channels: list[np.ndarray], config: SpectrumConfig = SpectrumConfig()) -> np.ndarray:
    """Concatenated local spectra of several grey maps: HxWx(D*len(channels)) float32."""
    return np.concatenate([local_spectrum(c, config) for c in channels], axis=2)


def pca_project(x: np.ndarray, n_components: int, weights_mask: np.ndarray | None = None,
                max_fit: int = 50_000, seed: int = 0) -> np.ndarray:
    """Project rows of x (N x D) on their top principal axes, fitted on <= max_fit rows (deterministic)."""
    n = x.shape[0]
    fit_rows = np.arange(n) if weights_mask is None else np.flatnonzero(weights_mask)
    if fit_rows.size > max_fit:
        fit_rows = np.sort(np.random.default_rng(seed).choice(fit_rows, max_fit, replace=False))
    sample = x[fit_rows].astype(np.float64)
    mean = sample.mean(axis=0)
    if sample.shape[0] < sample.shape[1]:  # few rows (e.g. instances): thin SVD, not a DxD covariance
        _, _, vt = np.linalg.svd(sample - mean, full_matrices=False)
        axes = vt[:n_components].T
    else:
        cov = np.cov(sample - mean, rowvar=False) if sample.shape[0] > 1 else np.zeros((x.shape[1],) * 2)
        _, evecs = np.linalg.eigh(np.atleast_2d(cov))
        axes = evecs[:, ::-1][:, :n_components]
    # fix the sign of each axis (largest |loading| positive) so results do not flip between runs/platforms
    signs = np.sign(axes[np.abs(axes).argmax(axis=0), np.arange(axes.shape[1])])
    axes = axes * np.where(signs == 0, 1.0, signs)
    out = (x - mean.astype(np.float32)) @ axes.astype(np.float32)
    if out.shape[1] < n_components:
        out = np.pad(out, ((0, 0), (0, n_components - out.shape[1])))
    return out.astype(np.float32)


def minmax(x: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Min-max normalise each column of x (N x D) to [0, 1], using the rows in mask for the range."""
    ref = x if mask is None else x[mask]
    if ref.size == 0:
        return np.zeros_like(x, dtype=np.float32)
    lo, hi = ref.min(axis=0), ref.max(axis=0)
    span = np.where(hi - lo > 1e-12, hi - lo, 1.0)
    return np.clip((x - lo) / span, 0.0, 1.0).astype(np.float32)


def spectral_features(channels: list[np.ndarray], n_components: int = 3, mask: np.ndarray | None = None,
                      config: SpectrumConfig = SpectrumConfig(), seed: int = 0) -> np.ndarray:
    """Spec's spectral feature: local spectra of the maps, PCA to n_components, min-max normalised: HxWxn.

    mask (HxW bool, optional) restricts the PCA fit and the min-max range to a parent region.
    """
    h, w = channels[0].shape[:2]
    stack = spectrum_stack(channels, config).reshape(h * w, -1)
    flat_mask = None if mask is None else np.asarray(mask, bool).reshape(-1)
    proj = pca_project(stack, n_components, flat_mask, seed=seed)
    return minmax(proj, flat_mask).reshape(h, w, n_components)
