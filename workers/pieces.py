"""Per-piece variation of an instance kind (bricks, tiles, slates): one random offset per piece.

The bricks of one kind differ from each other by a shade each (a brick is darker or redder as a whole), and
inside a brick the texture varies smoothly. Fitting the kind's stationary noise on all its pixels mixes the
two: the between-piece steps become low-frequency blotches that run across bricks and the pieces' edges add
grain (castle_brick_broken_06 at 512 px: whitish and dark blobs wider than a brick in the kind's albedo).
So a kind's noise is fitted on the *within-piece residual* (each piece's mean replaced by the kind's mean,
:func:`piece_residual`) and the spread of the pieces' means is kept as a covariance (:class:`PieceStats`, with
the sampling noise of small pieces' means taken out). At render time, ``piece_labels`` numbers the pieces of the
procedural cells (the same neck cut and components as the ``instances`` node, so the same partition) and
``piece_offsets`` draws one N(0, cov) offset per piece from its node seed; the leaf is noise + offsets.

Measured on castle_brick_broken_06 at 512 px (VGG-19 Gram distance in units of the input's half-to-half
distance, after recomposition): on the height it moves the normals from 3.62 to 3.02 (the bricks' steps at their
edges) with the height itself unchanged (2.85); on the albedo 3.69 -> 4.89 and the roughness 3.12 -> 3.43 (a
Gaussian draw of a kind's shades gives bricks darker and brighter than any in the input, and the residual's
noise loses the low-frequency part the recomposition matched), so ``NoiseConfig.per_piece`` defaults to the
height only.

A piece's offset is measured against the surface's smooth background, not against the kind's mean: a height
integrated from normals drifts across the whole map, and so do albedos under large stains. Against the kind's
mean, that drift counted as between-piece spread and came back as independent steps between neighbours
(roof_slates_02 at 512 px: the pieces' height means spread 0.16-0.18 about their kinds' means, where
neighbouring slates differ by 0.049 each, half the variance of adjacent pieces' differences, and 0.035 about the
background): a checkerboard of slates set high and low where the input's neighbours lie nearly level.
:func:`piece_trend` is that background (a twiced Gaussian low-pass, ``TREND_SPACINGS`` piece spacings wide, of every
piece of the split with each kind's mean taken out); a piece's offset is its mean less the background over it
(its own pixels' share of the low-pass taken out). The residual the kind's noise is fitted on loses the
background with the offsets, as before: a random-phase noise cannot hold a drift longer than its spectra's
windows and put its power into blobs of the windows' size (tried: the roof at 512 px, its slates' edges lost in
wavy normals, VGG-19 Gram / floor normal 6.11 -> 8.66).

Overlapping slates and shingles are not level inside: each rises towards its lower edge, where it steps down onto
the next course. Where a kind's pieces slope the same way, the slope is fitted once for the kind about each
piece's centroid (:func:`piece_ramp`), taken out of the residual with the means, and drawn back by a
``piece_ramps`` node. Without it the roof's slates came back level with a groove or a ridge on every side, their
normals facing up and down the roof alike (skewness of the y component 0.05, the input's -2.77); with it -1.54,
and at 512 px (VGG-19 Gram / floor) render 6.09 -> 5.05, normal 4.77 -> 4.01, height 1.14 -> 1.05. The castle's
bricks get none but one kind of 40 that slope the same way in its height (normal 2.98 -> 3.26, by
bench/rerecompose.py 3.22 -> 3.43: the castle's one step back).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .errors import InputError
from .instances import nearest_labels
from .nodes import as3
from .nodes.pieces import piece_coordinates, psd_root

MIN_PIECES = 8      # fewer pieces than this: no covariance worth estimating (offsets of zero)
TREND_SPACINGS = 1.5  # the background's Gaussian sigma in piece spacings (sqrt(image area / pieces)): wide enough
#                       that a piece's own pixels weigh ~10 % of it, narrow enough to follow the drift. The
#                       offsets' spread grows slowly with it (roof_slates_02 at 512 px, height: 0.035 / 0.039 /
#                       0.042 at 1.5 / 2 / 2.5): the roof's relief also varies over 2-5 slates


@dataclass
class PieceStats:
    """Spread of the pieces' means of one kind: ``cov`` (C x C, between-piece covariance), ``pieces`` counted, and
    the kind's ``ramp`` (C x 2: each channel's slope along x and y per working px inside every piece, about the
    piece's centroid; None when the pieces have none, see :func:`piece_ramp`)."""

    cov: np.ndarray
    pieces: int
    ramp: np.ndarray | None = None
    reach: np.ndarray | None = None       # (x, y) px: how far from their centroids the pieces reach (99th pct.)

    def to_dict(self) -> dict:
        d = {"cov": np.round(np.asarray(self.cov, np.float64), 8).tolist(), "pieces": int(self.pieces)}
        for k in ("ramp", "reach"):
            if getattr(self, k) is not None:
                d[k] = np.round(np.asarray(getattr(self, k), np.float64), 8).tolist()
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "PieceStats":
        ramp, reach = d.get("ramp"), d.get("reach")
        return cls(cov=np.asarray(d["cov"], np.float64), pieces=int(d.get("pieces", 0)),
                   ramp=None if ramp is None else np.asarray(ramp, np.float64),
                   reach=None if reach is None else np.asarray(reach, np.float64))


def _psd(cov: np.ndarray) -> np.ndarray:
    """The nearest positive semi-definite matrix (negative eigenvalues set to zero)."""
    f = psd_root(cov)
    return f @ f.T


@dataclass
class Trend:
    """The smooth background under a split's pieces: ``field`` (HxWxC, the low-pass of the pieces' pixels with each
    kind's mean taken out, so zero on average over a kind), ``density`` (HxW, the low-pass of the pieces'
    coverage) and the low-pass's ``sigma`` (px)."""

    field: np.ndarray
    density: np.ndarray
    sigma: float

    def own_weight(self, counts: np.ndarray, density: np.ndarray) -> np.ndarray:
        """The share of the background over a piece of ``counts`` px (where the coverage is ``density``) that
        comes from the piece itself: the low-pass kernel's peak mass times its area (1.5 / (2 pi sigma^2) for
        the twiced Gaussian 2G - G*G), below 0.5."""
        return np.clip(1.5 * counts / (2.0 * np.pi * self.sigma ** 2 * np.maximum(density, 1e-9)), 0.0, 0.5)


def piece_trend(image: np.ndarray, labels: np.ndarray, kinds=None) -> Trend:
    """The background of ``image`` under the pieces ``labels`` (1..N, 0 = gap) of a split whose piece i+1 has kind
    ``kinds[i]`` (None: one kind): a periodic Gaussian low-pass ``TREND_SPACINGS`` piece spacings wide of the
    pieces' pixels, each less its kind's mean, normalised by the pieces' coverage, then twiced (2F - G*F: a
    plain low-pass leaves part of a curved drift in the pieces' offsets, 16 % of a sinusoid 16 spacings long)."""
    img3 = as3(np.asarray(image, np.float32))
    lab = np.asarray(labels, np.int64)
    if img3.shape[:2] != lab.shape:
        raise InputError(f"pieces: image {img3.shape[:2]} and labels {lab.shape} differ in size")
    m = lab > 0
    kind = np.zeros(int(lab.max()) + 1, np.int64)
    if kinds is not None and kind.size > 1:
        kind[1:] = np.asarray(kinds, np.int64)[:kind.size - 1]
    k, vals = kind[lab[m]], img3[m]
    counts = np.bincount(k, minlength=1).astype(np.float64)
    means = np.stack([np.bincount(k, vals[:, c], minlength=counts.size) for c in range(img3.shape[2])], 1)
    means /= np.maximum(counts, 1.0)[:, None]
    centred = np.where(m[..., None], img3 - means[kind[lab]], 0.0)
    pieces = max(1, int(np.unique(lab[m]).size))
    sigma = TREND_SPACINGS * float(np.sqrt(lab.size / pieces))
    density = ndimage.gaussian_filter(m.astype(np.float64), sigma, mode="wrap")
    field = np.empty(img3.shape, np.float32)
    for c in range(img3.shape[2]):
        f = ndimage.gaussian_filter(centred[..., c], sigma, mode="wrap") / np.maximum(density, 1e-9)
        field[..., c] = 2.0 * f - ndimage.gaussian_filter(f, sigma, mode="wrap")   # twicing: no curvature bias
    return Trend(field, density.astype(np.float32), sigma)


def piece_residual(image: np.ndarray, labels: np.ndarray, mask: np.ndarray,
                   trend: Trend | None = None) -> tuple[np.ndarray, PieceStats]:
    """(residual HxWxC, stats): ``image`` with every piece's mean (pixels of ``mask`` with the same label > 0)
    replaced by the kind's mean, and the between-piece covariance of the pieces' offsets. A piece's offset is its
    mean less the kind's mean and the background ``trend`` over it (default: :func:`piece_trend` of these pieces
    alone), divided by 1 - its own pixels' weight in the background (:meth:`Trend.own_weight`). The covariance of
    the offsets over-states the between-piece spread by the pooled within-piece covariance / piece size (a small
    piece's mean is itself noisy); that part is subtracted, and the result clipped to be semi-definite. Where the
    pieces slope the same way inside (:func:`piece_ramp`), that ramp is taken out of the residual too and kept in
    the stats with how far the pieces reach from their centroids."""
    img = np.asarray(image, np.float32)
    img3 = as3(img)
    m = np.asarray(mask, bool) & (np.asarray(labels) > 0)
    if img3.shape[:2] != m.shape:
        raise InputError(f"pieces: image {img3.shape[:2]} and labels {m.shape} differ in size")
    c = img3.shape[2]
    lab = np.where(m, labels, 0).astype(np.int64)
    ids, counts = np.unique(lab[m], return_counts=True)
    if ids.size < MIN_PIECES:
        return img.copy(), PieceStats(np.zeros((c, c)), int(ids.size))
    if trend is None:
        trend = piece_trend(img3, lab)
    if trend.field.shape != img3.shape:
        raise InputError(f"pieces: trend {trend.field.shape} and image {img3.shape} differ in size")
    sums = np.stack([ndimage.sum(img3[..., k], lab, ids) for k in range(c)], axis=1)
    means = sums / counts[:, None]
    kind_mean = sums.sum(0) / counts.sum()
    back = np.stack([ndimage.mean(trend.field[..., k], lab, ids) for k in range(c)], axis=1)
    own = trend.own_weight(counts, ndimage.mean(trend.density, lab, ids))
    off = (means - kind_mean - back) / (1.0 - own)[:, None]
    table = np.zeros((int(lab.max()) + 1, c))
    table[ids] = means
    dev = (img3 - table[lab])[m]                                  # within-piece deviations
    table[ids] -= kind_mean
    res = img3 - table[lab]                                       # label 0 (outside) subtracts nothing
    xy = piece_coordinates(lab, m)
    ramp, _ = piece_ramp(dev, xy)
    if ramp is not None:
        along = xy @ ramp.T
        dev = dev - along
        res[m] -= along
    within = dev.T @ dev / max(1, dev.shape[0] - ids.size)
    cov = np.atleast_2d(np.cov(off.T)) - within * float(np.mean(1.0 / (counts * (1.0 - own) ** 2)))
    out = res.astype(np.float32)
    reach = None if ramp is None else np.maximum(np.quantile(np.abs(xy), 0.99, axis=0), 1.0)
    return (out[..., 0] if img.ndim == 2 else out), PieceStats(_psd(cov), int(ids.size), ramp, reach)


#: a kind's pieces get a ramp where it explains at least this share of their within-piece variance:
#: roof_slates_02's slates rise towards their lower edge (height +0.0037 per px down the slope at 512 px, 0.074
#: over a slate; 17 % of the variance inside the slates), where the castle's bricks lie flat (0.5 %)
RAMP_MIN_SHARE = 0.05


def piece_ramp(dev: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray | None, float]:
    """(ramp C x 2 or None, share explained): the slope of the within-piece deviations ``dev`` (N x C) along the
    pixels' coordinates about their piece's centroid ``xy`` (N x 2), pooled over the pieces by least squares;
    None where it explains less than RAMP_MIN_SHARE of their variance. Overlapping slates and shingles are
    ramps, thick at their lower edge: without one the pieces come back level, with steps or grooves between
    them on every side (roof_slates_02's normals: the input's slopes down the roof are one-sided, skewness -2.8,
    the procedural ones symmetric, 0.05)."""
    if dev.shape[0] < 3:
        return None, 0.0
    g, *_ = np.linalg.lstsq(xy, dev, rcond=None)                  # 2 x C
    total = float((dev ** 2).sum())
    explained = 1.0 - float(((dev - xy @ g) ** 2).sum()) / total if total > 0 else 0.0
    return (g.T.copy() if explained >= RAMP_MIN_SHARE else None), explained


def kind_piece_labels(labels: np.ndarray, kinds, kind: int) -> np.ndarray:
    """The pieces of kind ``kind`` (HxW int, 0 elsewhere) from an instance split's labels (1..N, 0 = no kept
    piece) and kinds (kind of piece i+1): gaps join the nearest piece, as the kind masks do
    (``workers.instances.split_instances``)."""
    lab = np.asarray(labels, np.int64)
    k = np.concatenate([[-1], np.asarray(kinds, np.int64)])
    near = nearest_labels(lab) if (lab == 0).any() and lab.max() > 0 else lab
    return np.where(k[near] == int(kind), near, 0)
