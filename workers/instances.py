"""Instance decomposition (paper 4.2): connected components of a mask, grouped into kinds by appearance.

Steps: optional open+close (2x2) of the parent mask; optionally (``separate`` > 0) a cut of the mask at its necks,
so that cells whose outline network has gaps (worn mortar, slate edges that fade) still come out one piece per
cell: the watershed of the inside distance from markers at its local maxima at least ``separate`` px apart,
computed on the periodically padded mask; 4-connected components, joined across opposite image
borders (material maps tile; ``wrap``), so a brick cut by the border is one instance; drop components whose
bounding box's shorter side is under ``min_side`` px; with more than ``outlier_min_count`` instances, drop size
outliers (robust z-score of log area, |z| > ``outlier_z``; median/MAD, the Iglewicz-Hoaglin rule, instead of
the reference's elliptic envelope that always drops 25%). Features per instance come from the instance's own
pixels only (pixels of the bounding-box crop outside the instance are set to the instance's mean before the
crop is resized to ``crop_size``^2): |FFT2| of grey albedo, height, roughness (DC removed) and 10-bin
histograms of r, g, b, height, roughness. Each block is L2-normalised per instance, reduced by PCA to
<= ``pca_dims`` (a rotation: distances kept) and weighted 1/sqrt(2), so instance distances lie in [0, 2].
Ward clustering cut at ``distance_threshold`` (default 1.5) gives the kinds; their number is free unless
``max_kinds`` caps it (the tree is then cut where it has that many clusters).

Pixels of the parent outside every kept instance (mortar gaps, dropped small pieces) join the kind of the
nearest kept instance (Euclidean distance transform), so the children masks partition the parent exactly.
Kinds are ordered by decreasing instance count; ``shares`` are each kind's fraction of the kept instances.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy import ndimage
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.sparse.csgraph import connected_components
from skimage.feature import peak_local_max
from skimage.segmentation import watershed

from .errors import InputError
from .spectrum import pca_project

logger = logging.getLogger(__name__)


@dataclass
class InstanceConfig:
    """Reference defaults of the instance split."""

    open_close: bool = False
    min_side: int = 10
    outlier_min_count: int = 10
    outlier_z: float = 3.5
    crop_size: int = 32
    hist_bins: int = 10
    pca_dims: int = 32
    distance_threshold: float = 1.5
    wrap: bool = True             # material maps tile: components touching opposite borders are one instance
    separate: float = 0.0         # > 0: cut the mask at its necks, markers this many px apart (0 = components only)
    max_kinds: int = 0            # > 0: at most this many kinds


@dataclass
class InstanceSplit:
    """Result: kept-instance labels (HxW, 0 = none, 1..N), each instance's kind, one mask per kind."""

    labels: np.ndarray
    kinds: np.ndarray             # (N,) kind index of instance i+1
    masks: list[np.ndarray]       # per kind, partition of the parent
    shares: list[float]
    features: np.ndarray          # (N, D)
    meta: dict = field(default_factory=dict)


def check_mask(mask, name: str) -> np.ndarray:
    """A 2-D boolean array (HxW or HxWx1), else InputError naming the argument."""
    m = np.asarray(mask)
    if m.ndim == 3 and m.shape[2] == 1:
        m = m[..., 0]
    if m.ndim != 2 or min(m.shape) < 8:
        raise InputError(f"{name}: expected an HxW mask of at least 8x8 pixels, got shape {np.shape(mask)}")
    if m.dtype != bool:
        if not np.all(np.isfinite(m)):
            raise InputError(f"{name}: mask contains non-finite values")
        m = m > 0.5
    return m


def _merge_across_borders(lab: np.ndarray, n: int) -> tuple[np.ndarray, int]:
    """Relabel so that components meeting across opposite image borders (a tiling material) are one."""
    pairs = [(lab[:, 0], lab[:, -1]), (lab[0, :], lab[-1, :])]
    i = np.concatenate([a[(a > 0) & (b > 0)] for a, b in pairs])
    j = np.concatenate([b[(a > 0) & (b > 0)] for a, b in pairs])
    if i.size == 0:
        return lab, n
    graph = sp.coo_matrix((np.ones(i.size), (i, j)), shape=(n + 1, n + 1))
    _, comp = connected_components(graph, directed=False)
    # new ids 1..m in order of the merged components' first old label (0 stays 0)
    _, first, inv = np.unique(comp[1:], return_index=True, return_inverse=True)
    rank = np.argsort(np.argsort(first))
    mapping = np.concatenate([[0], rank[inv] + 1]).astype(np.int32)
    return mapping[lab], int(first.size)


def instance_pixels(labels: np.ndarray, wrap: bool = True) -> list[tuple[np.ndarray, np.ndarray]]:
    """Pixel coordinates (ys, xs) of instances 1..N; with wrap, an instance cut by a border is unwrapped
    (coordinates on the low side shifted by +H / +W) so that it is contiguous."""
    h, w = labels.shape
    flat = labels.ravel()
    order = np.argsort(flat, kind="stable")
    bounds = np.searchsorted(flat[order], np.arange(1, int(flat.max()) + 2))
    out = []
    for k in range(bounds.size - 1):
        idx = order[bounds[k]:bounds[k + 1]]
        ys, xs = np.divmod(idx, w)
        if wrap:
            if ys.min() == 0 and ys.max() == h - 1:
                ys = np.where(ys < h // 2, ys + h, ys)
            if xs.min() == 0 and xs.max() == w - 1:
                xs = np.where(xs < w // 2, xs + w, xs)
        out.append((ys, xs))
    return out


def separate_cells(mask: np.ndarray, min_distance: float, wrap: bool = True) -> np.ndarray:
    """mask less the watershed lines that cut it at its necks: markers at the local maxima of the (lightly
    smoothed) distance to the outside, at least ``min_distance`` px apart. Two bricks joined through a gap in the
    mortar become two pieces; a piece with one maximum stays whole. With wrap the mask is treated as periodic."""
    m = np.asarray(mask, bool)
    r = int(np.ceil(min_distance))
    pad = min(max(2 * r, 8), *m.shape) if wrap else 0
    big = np.pad(m, pad, mode="wrap") if pad else m
    dist = ndimage.distance_transform_edt(big)
    peaks = peak_local_max(ndimage.gaussian_filter(dist, 1.0), min_distance=max(1, r), labels=big.astype(np.int32),
                           exclude_border=False)
    markers = np.zeros(big.shape, np.int32)
    markers[tuple(peaks.T)] = np.arange(1, len(peaks) + 1, dtype=np.int32)
    cut = watershed(-dist, markers, mask=big, watershed_line=True) > 0
    if pad:
        cut = cut[pad:-pad, pad:-pad]
    return m & cut


def nearest_labels(labels: np.ndarray) -> np.ndarray:
    """labels with every 0 pixel given the label of its nearest labelled pixel (Euclidean distance transform):
    gaps and cut lines join the nearest piece, so pieces extended this way partition their parent."""
    _, (iy, ix) = ndimage.distance_transform_edt(labels == 0, return_indices=True)
    return labels[iy, ix]


def piece_labels(mask: np.ndarray, separate: float = 0.0) -> np.ndarray:
    """Pieces of a cell mask (HxW int, 0 outside, 1..n): its 4-connected components after the cut at its
    necks (``workers.instances.separate_cells``, markers ``separate`` px apart), cut lines given to the nearest
    piece: the partition the ``instances`` node draws its kinds on."""
    m = np.asarray(mask, bool)
    lab, n = ndimage.label(separate_cells(m, separate) if separate > 0 else m)
    if separate > 0 and n:
        lab = np.where(m, nearest_labels(lab), 0)
    return lab


def find_instances(mask: np.ndarray, config: InstanceConfig = InstanceConfig()) -> tuple[np.ndarray, dict]:
    """Kept instances of mask as labels 1..N (0 elsewhere) and counts of what was dropped and why."""
    m = np.asarray(mask, bool)
    if config.open_close:
        k = np.ones((2, 2), bool)
        m = ndimage.binary_closing(ndimage.binary_opening(m, k), k) & np.asarray(mask, bool)
    if config.separate > 0:
        m = separate_cells(m, config.separate, config.wrap)
    lab, n = ndimage.label(m)
    if config.wrap and n:
        lab, n = _merge_across_borders(lab, n)
    info = {"components": int(n), "small": 0, "outliers": 0}
    if n == 0:
        return lab.astype(np.int32), info
    sides = np.array([min(np.ptp(ys), np.ptp(xs)) + 1 for ys, xs in instance_pixels(lab, config.wrap)])
    keep = sides >= config.min_side
    info["small"] = int((~keep).sum())
    area = np.bincount(lab.ravel(), minlength=n + 1)[1:].astype(np.float64)
    if keep.sum() > config.outlier_min_count:
        la = np.log(area[keep])
        med = np.median(la)
        mad = np.median(np.abs(la - med))
        if mad > 0:
            z = 0.6745 * (la - med) / mad
        else:  # more than half the areas are equal: fall back to the mean absolute deviation
            mean_ad = np.mean(np.abs(la - med))
            z = (la - med) / (1.2533 * mean_ad) if mean_ad > 0 else np.zeros_like(la)
        out = np.abs(z) > config.outlier_z
        info["outliers"] = int(out.sum())
        idx = np.flatnonzero(keep)
        keep[idx[out]] = False
    new_id = np.zeros(n + 1, np.int32)
    new_id[1:][keep] = np.arange(1, keep.sum() + 1, dtype=np.int32)
    info["kept"] = int(keep.sum())
    return new_id[lab], info


def _unit_rows(x: np.ndarray) -> np.ndarray:
    """L2-normalise each row (zero rows stay zero)."""
    norm = np.linalg.norm(x, axis=1, keepdims=True)
    return x / np.where(norm > 0, norm, 1.0)


def instance_features(labels: np.ndarray, channels: np.ndarray, grey_channels: list[int] | None = None,
                      config: InstanceConfig = InstanceConfig(), seed: int = 0) -> np.ndarray:
    """Feature rows (N x D) of instances 1..N: FFT-amplitude and histogram blocks (see module docstring).

    channels: HxWxC in [0,1] (e.g. sRGB r, g, b, height, roughness); grey_channels: indices whose spectra are
    used (None: luminance of the first three plus every channel after them).
    """
    n = int(labels.max())
    if n == 0:
        return np.zeros((0, 0), np.float32)
    h, w, c = channels.shape
    greys = [channels[..., :3] @ np.array([0.299, 0.587, 0.114], np.float32)] if c >= 3 else []
    greys += [channels[..., i] for i in (range(3, c) if grey_channels is None else grey_channels)]
    s = config.crop_size
    bins = np.linspace(0.0, 1.0, config.hist_bins + 1)
    ffts, hists = [], []
    for ys, xs in instance_pixels(labels, config.wrap):
        y0, x0 = ys.min(), xs.min()
        ch, cw = ys.max() - y0 + 1, xs.max() - x0 + 1
        py, px = ys % h, xs % w                      # where the pixels are in the maps
        yy = (np.arange(s) + 0.5) * ch / s - 0.5
        xx = (np.arange(s) + 0.5) * cw / s - 0.5
        coords = np.stack(np.meshgrid(yy, xx, indexing="ij"))
        amp = []
        for g in greys:
            vals = g[py, px].astype(np.float32)
            crop = np.full((ch, cw), vals.mean(), np.float32)  # outside the instance: its own mean
            crop[ys - y0, xs - x0] = vals
            small = ndimage.map_coordinates(crop, coords, order=1, mode="nearest")
            a = np.abs(np.fft.fft2(small - small.mean())) / (s * s)
            amp.append(np.fft.fftshift(a).reshape(-1))
        ffts.append(np.concatenate(amp))
        pix = channels[py, px]
        hists.append(np.concatenate([np.histogram(pix[:, k], bins=bins)[0] / max(1, pix.shape[0])
                                     for k in range(c)]))
    blocks = []
    for block in (np.array(ffts, np.float32), np.array(hists, np.float32)):
        block = _unit_rows(block)
        dims = min(config.pca_dims, block.shape[0], block.shape[1])
        proj = pca_project(block, dims, seed=seed) if block.shape[0] > 1 else block[:, :dims]
        blocks.append(proj / np.sqrt(2.0))
    return np.concatenate(blocks, axis=1).astype(np.float32)


def cluster_instances(features: np.ndarray, distance_threshold: float = 1.5, max_kinds: int = 0) -> np.ndarray:
    """Kind index per instance from Ward clustering cut at distance_threshold (or where the tree has max_kinds
    clusters, when the threshold leaves more), kinds ordered by size."""
    n = features.shape[0]
    if n < 2:
        return np.zeros(n, np.int64)
    z = linkage(features.astype(np.float64), method="ward")
    raw = fcluster(z, t=distance_threshold, criterion="distance") - 1
    if max_kinds > 0 and raw.max() + 1 > max_kinds:
        raw = fcluster(z, t=max_kinds, criterion="maxclust") - 1
    counts = np.bincount(raw)
    first = np.array([np.flatnonzero(raw == k)[0] if counts[k] else n for k in range(counts.size)])
    order = np.lexsort((first, -counts))  # most instances first, ties by first instance
    rank = np.empty(counts.size, np.int64)
    rank[order] = np.arange(counts.size)
    return rank[raw]


def split_instances(mask: np.ndarray, channels: np.ndarray, config: InstanceConfig = InstanceConfig(),
                    seed: int = 0) -> InstanceSplit:
    """Instance split of the parent mask over feature channels (HxWxC in [0,1]); see module docstring."""
    mask = np.asarray(mask, bool)
    if channels.shape[:2] != mask.shape:
        raise InputError(f"instance split: maps are {channels.shape[1]}x{channels.shape[0]} but the parent mask "
                         f"is {mask.shape[1]}x{mask.shape[0]}")
    labels, info = find_instances(mask, config)
    n = int(labels.max())
    if n == 0:
        logger.warning("instance split found no instance of at least %d px (of %d components); one kind",
                       config.min_side, info["components"])
        return InstanceSplit(labels, np.zeros(0, np.int64), [mask.copy()], [1.0], np.zeros((0, 0), np.float32), info)
    feats = instance_features(labels, channels, config=config, seed=seed)
    kinds = cluster_instances(feats, config.distance_threshold, config.max_kinds)
    n_kinds = int(kinds.max()) + 1
    # every parent pixel takes the kind of the nearest kept instance
    nearest = nearest_labels(labels)
    kind_map = np.where(mask, kinds[np.maximum(nearest, 1) - 1], -1)
    masks = [kind_map == k for k in range(n_kinds)]
    counts = np.bincount(kinds, minlength=n_kinds)
    info.update(kinds=n_kinds, instances_per_kind=counts.tolist(),
                gap_fraction=float((mask & (labels == 0)).sum() / max(1, mask.sum())))
    logger.info("instance split: %d components, %d kept (%d small, %d outliers), %d kinds %s",
                info["components"], n, info["small"], info["outliers"], n_kinds, counts.tolist())
    return InstanceSplit(labels, kinds, masks, (counts / counts.sum()).tolist(), feats, info)
