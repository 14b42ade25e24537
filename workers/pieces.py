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
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .errors import InputError
from .instances import nearest_labels
from .nodes.pieces import psd_root

MIN_PIECES = 8      # fewer pieces than this: no covariance worth estimating (offsets of zero)


@dataclass
class PieceStats:
    """Spread of the pieces' means of one kind: ``cov`` (C x C, between-piece covariance), ``pieces`` counted."""

    cov: np.ndarray
    pieces: int

    def to_dict(self) -> dict:
        return {"cov": np.round(np.asarray(self.cov, np.float64), 8).tolist(), "pieces": int(self.pieces)}

    @classmethod
    def from_dict(cls, d: dict) -> "PieceStats":
        return cls(cov=np.asarray(d["cov"], np.float64), pieces=int(d.get("pieces", 0)))


def _psd(cov: np.ndarray) -> np.ndarray:
    """The nearest positive semi-definite matrix (negative eigenvalues set to zero)."""
    f = psd_root(cov)
    return f @ f.T


def piece_residual(image: np.ndarray, labels: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, PieceStats]:
    """(residual HxWxC, stats): ``image`` with every piece's mean (pixels of ``mask`` with the same label > 0)
    replaced by the mean over ``mask``, and the between-piece covariance of those means. The covariance of the
    means over-states the between-piece spread by the pooled within-piece covariance / piece size (a small
    piece's mean is itself noisy); that part is subtracted, and the result clipped to be semi-definite."""
    img = np.asarray(image, np.float32)
    img3 = img[..., None] if img.ndim == 2 else img
    m = np.asarray(mask, bool) & (np.asarray(labels) > 0)
    if img3.shape[:2] != m.shape:
        raise InputError(f"pieces: image {img3.shape[:2]} and labels {m.shape} differ in size")
    c = img3.shape[2]
    lab = np.where(m, labels, 0).astype(np.int64)
    ids, counts = np.unique(lab[m], return_counts=True)
    if ids.size < MIN_PIECES:
        return img.copy(), PieceStats(np.zeros((c, c)), int(ids.size))
    sums = np.stack([ndimage.sum(img3[..., k], lab, ids) for k in range(c)], axis=1)
    means = sums / counts[:, None]
    kind_mean = sums.sum(0) / counts.sum()
    table = np.zeros((int(lab.max()) + 1, c))
    table[ids] = means - kind_mean
    res = img3 - table[lab]                                       # label 0 (outside) subtracts nothing
    dev = (res - kind_mean)[m]                                    # within-piece deviations
    within = dev.T @ dev / max(1, dev.shape[0] - ids.size)
    cov = np.atleast_2d(np.cov(means.T)) - within * float(np.mean(1.0 / counts))
    out = res.astype(np.float32)
    return (out[..., 0] if img.ndim == 2 else out), PieceStats(_psd(cov), int(ids.size))


def kind_piece_labels(labels: np.ndarray, kinds, kind: int) -> np.ndarray:
    """The pieces of kind ``kind`` (HxW int, 0 elsewhere) from an instance split's labels (1..N, 0 = no kept
    piece) and kinds (kind of piece i+1): gaps join the nearest piece, as the kind masks do
    (``workers.instances.split_instances``)."""
    lab = np.asarray(labels, np.int64)
    k = np.concatenate([[-1], np.asarray(kinds, np.int64)])
    near = nearest_labels(lab) if (lab == 0).any() and lab.max() > 0 else lab
    return np.where(k[near] == int(kind), near, 0)
