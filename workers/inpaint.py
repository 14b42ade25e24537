"""Inpainting of sub-material maps outside their parent mask, and re-segmentation of the completed maps.

Used by the inpainting variant of incomplete-mask fitting (paper 5.2): a sub-layer's mask is only known inside
its parent; instead of a loss on the known pixels, complete the sub-material's maps over the whole image,
segment the completed maps with the same classes as inside the parent, and fit the complete mask.

Sub-materials that get split further are structured (bricks and mortar, tiles and grout), so a smooth fill
(biharmonic, Telea) would erase exactly what the segmentation must find. ``periodic_inpaint`` is exemplar-based
instead: it finds the texture's two dominant lattice vectors in the masked autocorrelation (normalised by the
known-pixel overlap, one FFT each) and fills every hole pixel from the nearest known pixel at a lattice offset
(k1 v1 + k2 v2), falling back to the nearest known pixel. Maps tile, so offsets wrap around.
``segment_like`` then labels each completed pixel by a k-nearest-neighbour vote among the known pixels'
classes in standardised map space.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from .errors import InputError

logger = logging.getLogger(__name__)


@dataclass
class InpaintConfig:
    """Lattice search and fill settings."""

    min_overlap: float = 0.25     # autocorrelation lags need this share of known-pixel overlap to count
    min_period: int = 3           # shortest lattice vector (px): shorter peaks are the texture's own blur
    max_order: int = 4            # lattice offsets k1 v1 + k2 v2 with |k1|, |k2| <= max_order
    knn: int = 7                  # neighbours voting in segment_like
    max_samples: int = 20000      # known pixels kept for the vote (seeded subsample)
    seed: int = 0


def _stack(maps: dict[str, np.ndarray]) -> np.ndarray:
    """HxWxC float64 stack of the maps (grey maps as one channel), InputError on mismatched sizes."""
    if not maps:
        raise InputError("inpaint: no maps given")
    arrs = [np.asarray(a, dtype=np.float64) for a in maps.values()]
    arrs = [a[..., None] if a.ndim == 2 else a for a in arrs]
    if len({a.shape[:2] for a in arrs}) != 1:
        raise InputError(f"inpaint: maps differ in size {({k: np.shape(a)[:2] for k, a in maps.items()})}")
    return np.concatenate(arrs, axis=-1)


def masked_autocorrelation(x: np.ndarray, known: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Periodic autocorrelation (H, W) of a multi-channel image over its known pixels, normalised by the
    known-pixel overlap at each lag, and that overlap as a share of the known pixels."""
    w = known.astype(np.float64)
    xm = (x - x[known].mean(axis=0)) / np.maximum(x[known].std(axis=0), 1e-8) * w[..., None]
    f = np.fft.rfft2(xm, axes=(0, 1))
    num = np.fft.irfft2((f * f.conj()).sum(axis=-1), s=known.shape)
    fw = np.fft.rfft2(w)
    overlap = np.fft.irfft2(fw * fw.conj(), s=known.shape)
    ac = num / np.maximum(overlap, 1.0) / x.shape[-1]
    return ac, overlap / max(float(w.sum()), 1.0)


def lattice_vectors(x: np.ndarray, known: np.ndarray, config: InpaintConfig | None = None) -> list[tuple[int, int]]:
    """The texture's two dominant, non-collinear periods (dy, dx) from the masked autocorrelation peaks
    (local maxima with positive correlation); fewer when the texture shows no repeat."""
    cfg = config or InpaintConfig()
    h, w = known.shape
    ac, share = masked_autocorrelation(x, known)
    ac = np.fft.fftshift(ac)
    share = np.fft.fftshift(share)
    cy, cx = h // 2, w // 2
    yy, xx = np.mgrid[:h, :w]
    dy, dx = yy - cy, xx - cx
    ok = (share >= cfg.min_overlap) & (np.hypot(dy, dx) >= cfg.min_period) & (ac > 0.0)
    ok &= (dy > 0) | ((dy == 0) & (dx > 0))          # half plane: v and -v are the same period
    peaks = ok & (ac == ndimage.maximum_filter(ac, size=3, mode="wrap"))
    order = np.argsort(-ac[peaks])
    cand = np.stack([dy[peaks], dx[peaks]], axis=1)[order]
    vecs: list[tuple[int, int]] = []
    for v in cand[:64]:
        if not vecs:
            vecs.append((int(v[0]), int(v[1])))
        elif abs(vecs[0][0] * int(v[1]) - vecs[0][1] * int(v[0])) > 0:   # not collinear with the first
            vecs.append((int(v[0]), int(v[1])))
            break
    return vecs


def periodic_inpaint(maps: dict[str, np.ndarray], known: np.ndarray,
                     config: InpaintConfig | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """Fill the maps' pixels outside ``known`` from known pixels at lattice offsets (see module doc).

    Returns the completed maps (same keys, shapes, dtypes) and info: the lattice vectors and the share of hole
    pixels filled by a lattice copy (the rest by the nearest known pixel)."""
    cfg = config or InpaintConfig()
    known = np.asarray(known, dtype=bool)
    x = _stack(maps)
    if known.shape != x.shape[:2]:
        raise InputError(f"inpaint: known mask is {known.shape}, maps are {x.shape[:2]}")
    if known.sum() < 16:
        raise InputError(f"inpaint: only {int(known.sum())} known pixels")
    vecs = lattice_vectors(x, known, cfg) if not known.all() else []
    out = x.copy()
    filled = known.copy()
    offsets = sorted({(k1 * a[0] + k2 * b[0], k1 * a[1] + k2 * b[1])
                      for a, b in [(vecs[0], vecs[1] if len(vecs) > 1 else (0, 0))] if vecs
                      for k1 in range(-cfg.max_order, cfg.max_order + 1)
                      for k2 in range(-cfg.max_order, cfg.max_order + 1) if (k1, k2) != (0, 0)},
                     key=lambda o: o[0] ** 2 + o[1] ** 2)
    for oy, ox in offsets:
        todo = ~filled
        if not todo.any():
            break
        src_known = np.roll(known, (-oy, -ox), axis=(0, 1))      # known at p + o, seen from p
        take = todo & src_known
        if take.any():
            out[take] = np.roll(x, (-oy, -ox), axis=(0, 1))[take]
            filled |= take
    holes = int((~known).sum())
    lattice_share = float((filled & ~known).sum() / holes) if holes else 1.0
    if not filled.all():  # no repeat found or far from any copy: nearest known pixel (wrapping)
        _, (iy, ix) = ndimage.distance_transform_edt(~filled, return_indices=True)
        rest = ~filled
        out[rest] = out[iy[rest], ix[rest]]
    res, c0 = {}, 0
    for k, a in maps.items():
        a = np.asarray(a)
        c = 1 if a.ndim == 2 else a.shape[2]
        v = out[..., c0:c0 + c]
        res[k] = (v[..., 0] if a.ndim == 2 else v).astype(a.dtype if a.dtype.kind == "f" else np.float32)
        c0 += c
    info = {"lattice": [list(v) for v in vecs], "lattice_fill_share": round(lattice_share, 4)}
    logger.debug("periodic inpaint: lattice %s, %.0f%% of holes from lattice copies", vecs, 100 * lattice_share)
    return res, info


def segment_like(maps: dict[str, np.ndarray], labels: np.ndarray, known: np.ndarray,
                 config: InpaintConfig | None = None) -> np.ndarray:
    """Label every pixel (H, W int) by a k-NN vote among the known pixels' labels in standardised map space."""
    cfg = config or InpaintConfig()
    x = _stack(maps)
    known = np.asarray(known, dtype=bool)
    if labels.shape != known.shape or known.shape != x.shape[:2]:
        raise InputError(f"segment_like: labels {labels.shape}, known {known.shape}, maps {x.shape[:2]} differ")
    if not known.any():
        raise InputError("segment_like: no known pixels")
    z = (x - x[known].mean(axis=0)) / np.maximum(x[known].std(axis=0), 1e-8)
    idx = np.flatnonzero(known.ravel())
    rng = np.random.default_rng(cfg.seed)
    if idx.size > cfg.max_samples:
        idx = np.sort(rng.choice(idx, cfg.max_samples, replace=False))
    flat = z.reshape(-1, z.shape[-1])
    tree = cKDTree(flat[idx])
    k = min(cfg.knn, idx.size)
    _, nn = tree.query(flat, k=k)
    nn = nn.reshape(flat.shape[0], k)
    lab = labels.ravel()[idx][nn]
    n_cls = int(labels.max()) + 1
    votes = np.stack([(lab == c).sum(axis=1) for c in range(n_cls)], axis=1)
    out = votes.argmax(axis=1).reshape(known.shape)
    return np.where(known, labels, out)


def complete_child_mask(maps: dict[str, np.ndarray], parent_mask: np.ndarray, child_masks: list[np.ndarray],
                        child: int, config: InpaintConfig | None = None) -> tuple[np.ndarray, dict]:
    """The inpainting variant's target: complete ``maps`` outside the parent, label the completed pixels like
    the parent's children (``child_masks``, known inside the parent) and return child ``child``'s whole-image
    mask with the fill info (lattice, lattice fill share, white fraction)."""
    known = np.asarray(parent_mask, dtype=bool)
    filled, info = periodic_inpaint(maps, known, config)
    labels = np.zeros(known.shape, dtype=np.int64)
    for i, m in enumerate(child_masks):
        labels[np.asarray(m, dtype=bool) & known] = i
    target = segment_like(filled, labels, known, config) == child
    info["white_fraction"] = round(float(target.mean()), 4)
    return target, info
