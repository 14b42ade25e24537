"""Sparse Gabor-kernel approximation of a power spectrum (Galerne et al. 2012, "Gabor noise by example").

A Gabor kernel (Gaussian envelope times a cosine) has a power spectrum made of two Gaussian bumps at
``+-(fx, fy)``. A power spectral density (PSD) is approximated by a few such bump pairs with non-negative
weights, fitted by NNLS over a fixed dictionary and pruned to the strongest kernels. Frequencies are in
cycles per pixel of the fitted image; the PSD is a density (its integral over [-1/2, 1/2]^2 is the variance).
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.optimize import nnls

GRID = 40  # samples per axis of the PSD fit grid (constant fit cost whatever the image size)


def _dictionary(fmax: float) -> np.ndarray:
    """Candidate bumps (K, 3) = (fx, fy, sigma) on two grids of the half plane fy >= 0 plus DC-centred bumps."""
    atoms = []
    for div, rel in ((6, 0.7), (3, 0.7)):
        d = fmax / div
        xs = np.arange(-div, div + 1) * d
        ys = np.arange(0, div + 1) * d
        for fy in ys:
            for fx in xs:
                if fy == 0 and fx < 0:
                    continue  # its mirror is already in the dictionary
                atoms.append((fx, fy, rel * d))
    for sig in (fmax / 16, fmax / 8, fmax / 4, fmax / 2):
        atoms.append((0.0, 0.0, sig))
    return np.asarray(atoms, dtype=np.float64)


def gabor_psd(params: np.ndarray, fy: np.ndarray, fx: np.ndarray) -> np.ndarray:
    """PSD of a Gabor-kernel set ``params`` (K, 4) = (fx, fy, sigma, weight) on the grid ``fy`` (H,) x ``fx`` (W,).

    Separable evaluation (each bump is an outer product), so an output-size grid costs O(K * H * W) mults.
    """
    out = np.zeros((fy.size, fx.size), dtype=np.float32)
    for cx, cy, sig, w in np.asarray(params, dtype=np.float64):
        if w <= 0 or sig <= 0:
            continue
        k = -0.5 / (sig * sig)
        for sgn in (1.0, -1.0):
            gy = w * np.exp(k * (fy - sgn * cy) ** 2)
            gx = np.exp(k * (fx - sgn * cx) ** 2)
            rows = np.flatnonzero(gy > 1e-9 * w)  # a bump covers few rows/columns of a fine grid
            cols = np.flatnonzero(gx > 1e-9)
            if rows.size and cols.size:
                out[np.ix_(rows, cols)] += np.outer(gy[rows], gx[cols]).astype(np.float32)
    return out


def _atom_matrix(atoms: np.ndarray, fy: np.ndarray, fx: np.ndarray) -> np.ndarray:
    """Design matrix (points, K): each column is one bump pair with unit peak weight."""
    cols = [gabor_psd(np.array([[a[0], a[1], a[2], 1.0]]), fy, fx).ravel() for a in atoms]
    return np.stack(cols, axis=1).astype(np.float64)


def band_limit(psd: np.ndarray, energy: float = 0.995) -> float:
    """Smallest radius (cycles/px) holding ``energy`` of the power of a PSD grid in numpy FFT order."""
    h, w = psd.shape
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.fftfreq(w)[None, :]
    r = np.sqrt(fy ** 2 + fx ** 2).ravel()
    p = psd.ravel()
    order = np.argsort(r)
    c = np.cumsum(p[order])
    if c[-1] <= 0:
        return 0.5
    i = int(np.searchsorted(c, energy * c[-1]))
    return float(r[order[min(i, r.size - 1)]])


def fit_gabor(psd: np.ndarray, n_kernels: int = 16, smooth: float = 1.5) -> tuple[np.ndarray, float]:
    """Fit ``n_kernels`` Gabor kernels to a PSD grid (H, W) in numpy FFT order -> (params (K, 4), relative error).

    The periodogram is smoothed by ``smooth`` bins first (a single realisation is chi-square noisy), resampled on
    a fixed GRID x GRID half-plane grid inside the band limit, fitted by NNLS and pruned to the strongest kernels.
    """
    h, w = psd.shape
    ps = ndimage.gaussian_filter(np.fft.fftshift(psd).astype(np.float64), smooth, mode="wrap")
    fmax = float(np.clip(1.25 * band_limit(psd), 4.0 / min(h, w), 0.5))
    gx = np.linspace(-fmax, fmax, GRID)
    gy = np.linspace(0.0, fmax, GRID // 2 + 1)
    # fftshift-ed index of frequency f is f * n + n // 2
    yy, xx = np.meshgrid(gy * h + h // 2, gx * w + w // 2, indexing="ij")
    target = ndimage.map_coordinates(ps, [yy.ravel(), xx.ravel()], order=1, mode="grid-wrap")
    if target.max() <= 0:
        return np.zeros((0, 4), dtype=np.float32), 0.0
    atoms = _dictionary(fmax)
    a = _atom_matrix(atoms, gy, gx)
    scale = target.max()
    y = target / scale
    keep = np.arange(atoms.shape[0])
    while True:  # NNLS, then halve the support by energy until n_kernels remain (refit each time)
        wk, _ = nnls(a[:, keep], y, maxiter=50 * keep.size)
        keep, wk = keep[wk > 0], wk[wk > 0]
        if keep.size <= n_kernels or keep.size == 0:
            break
        order = np.argsort(wk * atoms[keep, 2] ** 2)[::-1]
        keep = np.sort(keep[order[:max(n_kernels, keep.size // 2)]])
    if keep.size == 0:
        return np.zeros((0, 4), dtype=np.float32), 1.0
    fit = a[:, keep] @ wk
    err = float(np.linalg.norm(fit - y) / max(np.linalg.norm(y), 1e-12))
    params = np.concatenate([atoms[keep], (wk * scale)[:, None]], axis=1)
    params = params[params[:, 3] > 0]
    return params.astype(np.float32), err
