"""Mask proceduralisation (paper 5.2): PPTBF query-and-optimise fitting.

* `fit_pptbf_mask`: downsample the binary mask to the fit resolution (default: the database's, e.g. 512 -> 128 px),
  query the index with the mask and its complement, re-rank both top-k lists at our realisation with the threshold T
  set to the target's white fraction (binarize is a percentile cut, so T is never searched); optionally explore the
  best `starts` re-ranked entries (either polarity) with short local searches; refine the most promising
  (workers.mask_opt: nlopt local search on the continuous entries alternating with exhaustive discrete sweeps and,
  optionally, large period/aspect/orientation moves; best ever kept); finally compare the candidates (query result,
  explored starts, final) on fresh realisations and return the best there (`validate`): a lower loss at the fit's
  own realisation is often over-fitting that realisation, not a better pattern. The loss is the descriptor distance
  (LBP + Gram + spectrum, the index's own descriptor and weights, before PCA) computed in memory: no image files.
  With `valid` (incomplete masks of sub-layers) the descriptor statistics use only the parent's pixels.
* `fit_inpainted_mask`: the inpainting variant for sub-layers: segment the inpainted sub-material maps with a
  caller-given segmentation and fit that complete mask.

The fitted masks become "pptbf" nodes (:mod:`workers.nodes.pptbf`); instance masks are sampled, not fitted
(:mod:`workers.nodes.instances`).

Acceptance on random known parameters, alignment-free by descriptor distance: a PPTBF is stochastic,
and another realisation (shift) of the TRUE parameters has a best-shift IoU near chance, f/(2-f) for white
fraction f (measured 0.1-0.7 at 128 px), so "IoU >= 0.8" is only reachable for the same realisation. The
criterion is `realisation_distance(fit) <= 1.5 x realisation_distance(truth)` (fresh realisations, as a graph
node renders them) on most targets; unrelated parameters fail it (tests/test_masks.py, bench/masks.py).

No torch gradient step: the differentiable torch PPTBF costs 2-7 s per forward+backward at 64 px here against
~0.1 s for one numpy render + descriptor, so a gradient step is worth 30-70 derivative-free evaluations.
"""
from __future__ import annotations

import logging
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable

import numpy as np
from scipy import ndimage

from pptbf_db import pptbf as pp

from .errors import InputError
from .instances import check_mask
from .mask_opt import Budget, OptSettings, explore, optimise

if TYPE_CHECKING:
    from .lattice import Lattice

logger = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- configuration and result


@dataclass
class MaskFitConfig:
    """Budget and resolution of one PPTBF mask fit.

    max_evals / time_budget_s: every stage of a fit divides evaluations, not seconds, so a job returns the
    same fit on every run and machine (with the 50 s clock as the binding limit, two runs of the README job
    fitted the castle's mortar differently: another machine load, another stopping point); the time is a safety
    limit for a machine far slower or busier than expected.
    fit_size: width (px) the mask is fitted at (None: the index's resolution, else 128); the loss is cheap
    there (one render + descriptor ~0.05-0.3 s at 128 px) and the pattern is resolution-free afterwards.
    starts / explore_share: re-ranked entries explored with short local searches, and the share of the
    evaluations they get (skipped when fewer than 10 evaluations per start would be left).
    structure_moves: large period/aspect/orientation moves after each discrete sweep.
    (starts=3 with structure moves lowered the final loss on 4/6 random targets at 200 evaluations / 20 s,
    but on 1/9 (1 tie) at the default 300 / 50 s, and did not improve fresh realisations: off by default.)
    incomplete: how the service fits a sub-layer's (incomplete) mask; fit_pptbf_mask itself takes `valid`.
    validate: fresh realisations on which the candidates (query, explored starts, final) are compared at the
    end; the best there is returned (0: the best at the fit's own realisation). Guards against over-fitting
    the fit's realisation; its evaluations are reserved from max_evals.
    realisations: realisations averaged per loss evaluation (2 generalises slightly better to fresh
    realisations at equal time in one measurement, but halves the evaluations; default 1).
    lattice / layout_size: a mask whose lattice analysis (workers.lattice) finds a repeat is fitted by
    workers.layout_fit at up to layout_size px (starts on the lattice, pretrained VGG-19 Gram loss, layout
    kept, then a free polish); other masks (stains, rust) take the query-and-optimise path at fit_size.
    """

    rounds: int = 5
    max_evals: int = 300          # how far a fit searches: the same evaluations, so the same fit, on any machine
    time_budget_s: float = 300.0  # a safety limit only: a fit that reaches it stops early, logs a warning and
    #                               records meta["time_limited"], since where it stopped depends on the load (300
    #                               evaluations at 256 px: 50-56 s alone on this 2-core machine, the castle's
    #                               8.5 px bricks 81 s alone and 113-118 s beside other fits in a job)
    fit_size: int | None = None
    seed: int = 0
    top_k: int = 5
    algorithm: str = "LN_SBPLX"
    step: float = 0.08
    shift: tuple[float, float] = (0.0, 0.0)
    torch_threads: int | None = 1
    starts: int = 1
    explore_share: float = 0.35
    structure_moves: bool = False
    realisations: int = 1
    validate: int = 2
    loss: str = "descriptor"      # query path: the loss of the re-rank, the search and the validation:
    #                               "descriptor" (the database's descriptor distance) or "vgg19" (pretrained
    #                               VGG-19 Gram + layout distance, workers.layout_fit.GramMaskLoss, the paper's
    #                               loss); both cost about 0.5 s an evaluation at 128 px on one thread, and on
    #                               rusty_metal_05's rust both return the same entry (Gram distance 0.54 at 256 px)
    #                               (on the six-material job's rust layer "vgg19" fitted a mask nearer in Gram,
    #                               0.22 vs 0.28 at 256 px, yet the material's maps came out farther: albedo
    #                               2.29 vs 2.11, roughness 1.71 vs 1.58 x floor; the default stays)
    rerank_pool: int = 12         # "vgg19": database entries per polarity re-ranked by that loss (>= top_k)
    lattice: bool = True          # masks with a lattice (bricks, tiles): lattice-first fit with the VGG-19 loss
    layout_size: int = 256        # fit width (px) of that path (the mask's own when smaller)
    lattice_starts: int = 14      # (layout, polarity) pairs on the lattice scored as starts at full size
    lattice_screen: int = 60      # layouts (each in both polarities) screened on a half-size copy to pick them
    thin_share: float = 0.1       # a 2-D layout whose network (the smaller phase) covers less than this share
    #                               is fitted widened to WIDE_SHARE, then thresholded back (widen_network; 0 =
    #                               never). At 0.2, three synthetic targets of bench/layout.py (networks of 16-18 %,
    #                               1-px widening) came back far from their truth (Gram ratio 0.95 -> 16.8,
    #                               0.90 -> 3.5, 1.17 -> 6.6): thresholded back, a fit's cells need not keep
    #                               their borders' shape; metal_plate_02's seams are 7-8 %
    thin_refine_evals: int = 90   # a widened fit's cell shape re-chosen on the thin network itself
    #                               (refine_thin_shape; 0 = keep the widened fit's shape)
    incomplete: str = "known"   # sub-layer masks in the service: "known" (loss on the parent's pixels) or
    #                             "inpaint" (complete the maps by workers.inpaint, re-segment, fit the full mask)

    def __post_init__(self) -> None:
        if self.incomplete not in ("known", "inpaint"):
            raise InputError(f"masks.incomplete must be 'known' or 'inpaint', got {self.incomplete!r}")
        if self.loss not in LOSSES:
            raise InputError(f"masks.loss must be one of {', '.join(LOSSES)}, got {self.loss!r}")


#: the query path's losses (MaskFitConfig.loss)
LOSSES = ("vgg19", "descriptor")


@dataclass
class MaskFit:
    """Result of a fit: the 29-vector at `fit_size` (threshold = target white fraction) and its bookkeeping."""

    params: np.ndarray
    complement: bool
    loss_query: float
    loss_final: float
    evaluations: int
    seconds: float
    history: list[float]
    fit_size: tuple[int, int]
    shift: tuple[float, float] = (0.0, 0.0)
    entry_id: int | None = None
    meta: dict = field(default_factory=dict)
    field: str = "value"          # what the mask cuts (``pp.FIELDS``): the recomposition may choose "border"

    def render(self, width: int | None = None, height: int | None = None, *, pixel_scale: float = 1.0,
               shift=None) -> np.ndarray:
        """The fitted mask (bool HxW) as it looks at the fit resolution (or larger extent / pixel_scale)."""
        w = self.fit_size[0] if width is None else width
        h = self.fit_size[1] if height is None else height
        m = pp.render_mask(self.params, w, h, shift=self.shift if shift is None else shift,
                           pixel_scale=pixel_scale, ref_width=self.fit_size[0], field=self.field)
        return ~m if self.complement else m

    def to_dict(self) -> dict:
        """JSON-able form (lists instead of arrays); MaskFit(**d) with params as an array rebuilds it."""
        return {"params": [float(v) for v in self.params], "complement": bool(self.complement),
                "loss_query": float(self.loss_query), "loss_final": float(self.loss_final),
                "evaluations": int(self.evaluations), "seconds": float(self.seconds),
                "history": [float(v) for v in self.history], "fit_size": [int(v) for v in self.fit_size],
                "shift": [float(v) for v in self.shift],
                "entry_id": None if self.entry_id is None else int(self.entry_id),
                "meta": {k: (v.item() if isinstance(v, np.generic) else v) for k, v in self.meta.items()},
                "field": self.field}

    @classmethod
    def from_dict(cls, d: dict) -> "MaskFit":
        """Inverse of `to_dict`."""
        d = dict(d)
        d["params"] = np.asarray(d["params"], dtype=np.float64)
        d["fit_size"] = tuple(int(v) for v in d["fit_size"])
        d["shift"] = tuple(float(v) for v in d.get("shift", (0.0, 0.0)))
        return cls(**{k: v for k, v in d.items() if k in cls.__dataclass_fields__})

    def node_params(self, working_width: int, pin_shift: bool = False) -> dict:
        """Params of a "pptbf" graph node, with the period converted to `working_width` pixels."""
        p = np.array(self.params, dtype=np.float64)
        k = working_width / float(self.fit_size[0])
        p[pp.PARAM_INDEX["resolution"]] = float(np.clip(int(p[pp.PARAM_INDEX["resolution"]]) * k, 1.0, 1e6))
        out = {"params": [float(v) for v in p], "complement": bool(self.complement), "ref_width": int(working_width)}
        if self.field != "value":
            out["field"] = self.field
        if pin_shift:
            out["shift"] = [float(self.shift[0]), float(self.shift[1])]
        return out


# ----------------------------------------------------------------------------- helpers


def downsample_mask(mask: np.ndarray, width: int, height: int) -> np.ndarray:
    """Area-average a bool mask to width x height and cut at 0.5 (no aliasing of thin lines into noise)."""
    from skimage.transform import resize

    if mask.shape == (height, width):
        return mask.copy()
    a = resize(mask.astype(np.float32), (height, width), order=1, anti_aliasing=mask.shape[1] > width,
               preserve_range=True)
    return a > 0.5


def fit_shape(mask_shape: tuple[int, int], fit_width: int) -> tuple[int, int]:
    """(width, height) at the fit resolution, keeping the aspect ratio; never upsamples."""
    h, w = mask_shape
    fw = int(min(fit_width, w))
    return fw, max(8, int(round(h * fw / w)))


def _index_resolution(index) -> int | None:
    """The resolution the index's entries were rendered at, whatever the attribute is called."""
    for attr in ("resolution", "res", "size"):
        v = getattr(index, attr, None)
        if isinstance(v, (int, np.integer)) and v > 0:
            return int(v)
    meta = getattr(index, "meta", None)
    if isinstance(meta, dict) and isinstance(meta.get("resolution"), (int, np.integer)):
        return int(meta["resolution"])
    return None


class MaskLoss:
    """Descriptor distance between the PPTBF render of a parameter vector and a fixed target, in memory.

    The target's descriptor is computed once. `complement=True` scores the inverted render, so both polarities
    are compared with the same target descriptor. The render's threshold is forced so that the (possibly
    inverted) mask has the target's white fraction. With a PPTBFIndex the distance is taken in the full
    weighted, standardised descriptor space (before PCA), for the same cost: 6 targets near entries of a
    60-entry database were re-found at IoU >= 0.9 in 4/6 cases, against 3/6 (IoU >= 0.88) with the
    PCA-reduced distance even on a 400-entry database.
    """

    def __init__(self, target: np.ndarray, index, valid: np.ndarray | None = None, *,
                 shift=(0.0, 0.0), realisations: int = 1, pixel_scale: float = 1.0,
                 ref_width: int | None = None) -> None:
        self._set_target(target, valid, shift, realisations, pixel_scale, ref_width)
        self.index = index
        self._raw = _raw_describer(index)
        self._target_desc = self.describe(target)

    def _set_target(self, target: np.ndarray, valid: np.ndarray | None, shift, realisations: int,
                    pixel_scale: float, ref_width: int | None) -> None:
        """The fields every mask loss has: the target, its valid pixels, white fraction and realisation, and the
        frame its renders are drawn in. pixel_scale < 1: the target is a reduced copy; ref_width: the width
        the parameters refer to (the full mask's when the target is a crop of it); both keep the parameters'
        meaning."""
        self.target = target
        self.pixel_scale = float(pixel_scale)
        self.realisations = max(1, int(realisations))
        self.valid = valid
        self.shift = tuple(shift)
        self.height, self.width = target.shape
        self.ref_width = int(ref_width) if ref_width else int(round(self.width / self.pixel_scale))
        sel = target if valid is None else target[valid]
        self.white = float(np.clip(sel.mean() if sel.size else 0.5, 0.0, 1.0))

    def with_threshold(self, params: np.ndarray, complement: bool = False) -> np.ndarray:
        """A copy of params whose threshold gives the target's white fraction (after inversion if complement)."""
        p = np.array(params, dtype=np.float64)
        p[0] = 1.0 - self.white if complement else self.white
        return p

    def render(self, params: np.ndarray, complement: bool = False, threshold_from_target: bool = True,
               shift=None) -> np.ndarray:
        """Binary render (inverted if complement) at the target's size and the loss's realisation (or ``shift``)."""
        p = self.with_threshold(params, complement) if threshold_from_target else np.asarray(params, np.float64)
        m = pp.render_mask(p, self.width, self.height, shift=self.shift if shift is None else shift,
                           ref_width=self.ref_width, pixel_scale=self.pixel_scale)
        return ~m if complement else m

    def describe(self, mask: np.ndarray) -> np.ndarray:
        """Descriptor vector of a mask of the target's size (full standardised when possible, else reduced)."""
        if self._raw is not None:
            return self._raw(mask, self.valid)
        return np.asarray(self.index.describe(mask, valid=self.valid), dtype=np.float64).ravel()

    def of_mask(self, mask: np.ndarray) -> float:
        """Descriptor distance of a bool mask (same size as the target) to the target."""
        return float(np.linalg.norm(self.describe(mask) - self._target_desc))

    def fresh(self, params: np.ndarray, complement: bool = False, n: int = 2,
              threshold_from_target: bool = True) -> float:
        """Mean descriptor distance of `n` realisations far from any the fit or the tests use (validation)."""
        shifts = [(self.shift[0] + 41.3 + 7.9 * k, self.shift[1] + 37.1 + 6.1 * k) for k in range(max(1, int(n)))]
        return self.mean_at(params, complement, threshold_from_target, shifts)

    def mean_at(self, params: np.ndarray, complement: bool, threshold_from_target: bool, shifts: list) -> float:
        """Mean descriptor distance of the renders at the given realisation shifts."""
        total = 0.0
        for s in shifts:
            total += self.of_mask(self.render(params, complement, threshold_from_target, shift=s))
        return total / len(shifts)

    def __call__(self, params: np.ndarray, complement: bool = False, threshold_from_target: bool = True) -> float:
        """Loss of a parameter vector: the mean over `realisations` shifts (the first is the loss's own shift;
        the others far away: independent realisations)."""
        shifts = [(self.shift[0] + 3.7 * k, self.shift[1] + 5.3 * k) for k in range(self.realisations)]
        return self.mean_at(params, complement, threshold_from_target, shifts)


def _raw_describer(index) -> Callable | None:
    """describe(mask, valid) -> standardised raw descriptor, as the index sees masks (resized to its resolution),
    or None when the index does not expose its descriptor config and standardisation."""
    pca, config, res = getattr(index, "pca", None), getattr(index, "config", None), _index_resolution(index)
    if pca is None or config is None or res is None or not hasattr(pca, "standardise"):
        return None
    from pptbf_db.descriptor import describe_masks
    from pptbf_db.index import resize_mask

    def describe(mask: np.ndarray, valid: np.ndarray | None) -> np.ndarray:
        h, w = mask.shape
        th, tw = max(8, int(round(h * res / w))), res
        m = resize_mask(mask.astype(np.float32), th, tw)
        if (th, tw) != (h, w):
            m = (m > 0.5).astype(np.float32)
        v = None if valid is None else resize_mask(valid.astype(np.float32), th, tw) > 0.5
        raw = describe_masks(m[None], None if v is None or v.all() else v, config)
        return np.asarray(pca.standardise(raw), dtype=np.float64).ravel()

    return describe


def realisation_distance(loss: MaskLoss, params: np.ndarray, complement: bool = False, n: int = 3,
                         seed: int = 0) -> float:
    """Mean descriptor distance to `loss`'s target of `n` fresh realisations of params (shifts 8-16 reference
    widths away, drawn from `seed`, threshold from the target): the alignment-free score of a stochastic mask as
    a graph node renders it (a new realisation, not the one fitted). For the true parameters of a synthetic
    target this is the "truth floor": what a perfect fit scores."""
    draws = np.random.default_rng(seed).uniform(8.0, 16.0, size=(max(1, int(n)), 2))
    return loss.mean_at(params, complement, True, [(float(a), float(b)) for a, b in draws])


@contextmanager
def torch_threads(n: int | None):
    """Temporarily limit torch's intra-op threads (the descriptor's convs are 4x faster single-threaded on a
    busy machine, and a fit is meant to use one core); None leaves it unchanged."""
    if n is None:
        yield
        return
    import torch

    old = torch.get_num_threads()
    torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(old)


def best_shift_iou(a: np.ndarray, b: np.ndarray, max_shift: int | None = None) -> tuple[float, tuple[int, int]]:
    """Largest IoU of two same-size bool masks over translations |dy|,|dx| <= max_shift (default 1/4 of the
    size), counted on the overlap only (no wrap-around); returns (iou, (dy, dx)). Alignment-free comparison."""
    a = np.asarray(a, dtype=bool)
    b = np.asarray(b, dtype=bool)
    if a.shape != b.shape:
        raise InputError(f"best_shift_iou: shapes differ {a.shape} vs {b.shape}")
    h, w = a.shape
    s = int(max_shift if max_shift is not None else min(h, w) // 4)
    ph, pw = h + s, w + s
    fa, fb = (np.fft.rfft2(x.astype(np.float64), (ph, pw)) for x in (a, b))
    ones = np.fft.rfft2(np.ones((h, w)), (ph, pw))

    def corr(x, y):  # c[dy, dx] = sum_p x[p] y[p - d] (circular in the padded frame: exact for |d| <= s)
        return np.fft.irfft2(x * np.conj(y), (ph, pw))

    inter, a_in, b_in = corr(fa, fb), corr(fa, ones), corr(ones, fb)
    dy = np.r_[0:s + 1, -s:0] % ph
    dx = np.r_[0:s + 1, -s:0] % pw
    sel = np.ix_(dy, dx)
    i, u = inter[sel], a_in[sel] + b_in[sel] - inter[sel]
    iou = np.where(u > 0.5, i / np.maximum(u, 1e-9), 0.0)
    k = np.unravel_index(int(np.argmax(iou)), iou.shape)
    sy = int(np.r_[0:s + 1, -s:0][k[0]])
    sx = int(np.r_[0:s + 1, -s:0][k[1]])
    return float(iou[k]), (sy, sx)


# ----------------------------------------------------------------------------- fitting


def fit_pptbf_mask(mask, index, valid=None, config: MaskFitConfig | None = None, seed: int | None = None,
                   cell_length: float | None = None) -> MaskFit:
    """Fit a PPTBF to a binary mask (HxW): query mask and complement, re-rank both top-k lists with the target's
    white fraction at our realisation (the better one fixes the polarity), then optimise; best ever kept.

    `valid` (HxW bool) restricts the loss to the parent's pixels for incomplete sub-layer masks.
    `seed` overrides config.seed (the optimiser's random sweep order).
    `cell_length` (px at the mask's size): the cells' length along the rows when the mask is a network of rows
    alone, measured elsewhere (workers.structure.cells_along_rows); a lattice fit of rows keeps it.
    """
    cfg = config or MaskFitConfig()
    seed = cfg.seed if seed is None else int(seed)
    with torch_threads(cfg.torch_threads):
        return _fit(mask, index, valid, cfg, seed, cell_length)


def _prepare_target(mask, valid, fit_width: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Validate and downsample mask (and valid) to the fit width; InputError for unusable input."""
    m = check_mask(mask, "mask")
    v = None if valid is None else check_mask(valid, "valid")
    if v is not None and v.shape != m.shape:
        raise InputError(f"valid: shape {v.shape} differs from the mask's {m.shape}")
    if v is not None and v.sum() < 64:
        raise InputError("valid: fewer than 64 valid pixels, nothing to fit")
    w, h = fit_shape(m.shape, fit_width)
    target = downsample_mask(m, w, h)
    valid_s = None if v is None else downsample_mask(v, w, h)
    if valid_s is not None and valid_s.all():
        valid_s = None
    sel = target if valid_s is None else target[valid_s]
    if sel.all() or not sel.any():
        raise InputError(f"mask: uniform ({'all' if sel.all() else 'no'} pixels set) inside the valid region; "
                         "a constant mask needs no PPTBF")
    return target, valid_s


#: a mask larger than the fit size is analysed again at up to this width when the fit size shows no lattice
LATTICE_ANALYSIS_WIDTH = 1024


def _lattice_above_fit_size(mask: np.ndarray, fit_shape_hw: tuple[int, int]) -> Lattice | None:
    """The lattice of a mask larger than the fit size, measured at up to LATTICE_ANALYSIS_WIDTH px and scaled to
    the fit size, when it has one there whose period stays representable (>= the analysis' minimum period);
    else None. A noisy real layout can lose its repeat in the downsample to the fit size (roof_slate_02's
    decomposition mask at working size 512: significance 2.72 at 512 px, 2.25 at 256 px), while its cells are
    still several pixels wide there."""
    from .lattice import LatticeConfig, analyse_lattice

    h, w = mask.shape
    if w <= fit_shape_hw[1]:
        return None
    aw, ah = fit_shape((h, w), LATTICE_ANALYSIS_WIDTH)
    lat = analyse_lattice(downsample_mask(mask, aw, ah))
    if lat.kind == "none":
        return None
    lat = lat.scaled(fit_shape_hw[1] / aw)
    if (lat.period or 0.0) < LatticeConfig().min_period:
        return None
    logger.info("mask: lattice found at %d px (not at the fit size), scaled to %d px: period %.1f px", aw,
                fit_shape_hw[1], lat.period)
    return lat


#: the share of the pixels a thin network is widened to for its fit (metal_plate_02's seams at 25 %, 12-20 px
#: wide, were fitted as plates in courses at the right size)
WIDE_SHARE = 0.2


def widen_network(mask: np.ndarray, share: float) -> tuple[np.ndarray, int] | None:
    """The mask with its smaller phase (the network: seams, grout, mortar) dilated by the smallest disc radius
    that makes it cover at least ``share`` of the pixels, and that radius; None when it already does.

    A layout's network of 2-3 px lines on 86 px plates (metal_plate_02's seams at 512 px, 7 % of the pixels) is
    under a pixel wide in the fit's loss image: fitted as it is, the plates came back as columns half their width
    with the horizontal seams as ticks. The same plates with 12-20 px seams (25 %) were fitted in courses at the
    right size. The PPTBF's threshold is a percentile, so a fit of the widened network thresholded back to the
    network's own share draws thin lines along the same cell borders. Only 2-D lattices are widened: rows of
    thin lines (roof_slates_02's slate edges, 10 % at 512 px) came back as lens-shaped cells with diamond gaps
    (normal 5.8 -> 9.0 x floor), where the rows fitted as they are show slates in courses."""
    m = np.asarray(mask, bool)
    white = m.mean() < 0.5
    net = m if white else ~m
    if net.mean() >= share:
        return None
    for r in range(1, max(2, min(m.shape) // 8)):
        y, x = np.mgrid[-r:r + 1, -r:r + 1]
        wide = ndimage.maximum_filter(net, footprint=x * x + y * y <= r * r + r, mode="wrap")
        if wide.mean() >= share:
            return (wide if white else ~wide), r
    return None


def _layout_first(mask, index, valid, cfg: MaskFitConfig, seed: int,
                  cell_length: float | None = None) -> MaskFit | None:
    """The lattice-first fit when the mask (fully known or nearly) has a lattice, else None. A thin network is
    fitted widened and thresholded back to its own share (widen_network). A given ``cell_length`` replaces the
    one a rows lattice reads off the mask (Lattice.cell_length_fixed)."""
    from .lattice import analyse_lattice
    from .layout_fit import fit_layout

    target, valid_s = _prepare_target(mask, valid, cfg.layout_size)
    if valid_s is not None and valid_s.mean() < 0.9:
        return None
    lat = analyse_lattice(target)
    full = check_mask(mask, "mask")
    if lat.kind == "none":
        lat = _lattice_above_fit_size(full, target.shape) or lat
    if lat.kind == "none":
        logger.info("mask has no lattice (regularity %.2f): query-and-optimise fit", lat.regularity)
        return None
    if lat.kind == "rows" and cell_length:
        lat.cell_length, lat.cell_length_fixed = float(cell_length) * target.shape[1] / full.shape[1], True
        logger.info("mask: rows with cells %.1f px long (given)", lat.cell_length)
    thin = cfg.thin_share > 0 and valid is None and lat.kind == "2d" and \
        min(full.mean(), 1.0 - full.mean()) < cfg.thin_share
    widened = widen_network(full, WIDE_SHARE) if thin else None
    if widened is None:
        return fit_layout(target, valid_s, index, lat, cfg, seed)
    wide, radius = widened
    wtarget, _ = _prepare_target(wide, None, cfg.layout_size)
    wlat = analyse_lattice(wtarget)
    if wlat.kind == "none":
        logger.info("mask: the widened network lost the lattice; fitted as it is")
        return fit_layout(target, valid_s, index, lat, cfg, seed)
    white = float(full.mean())
    logger.info("mask: thin network (%.1f %% of the pixels) fitted widened by %d px to %.1f %%, then thresholded "
                "back", 100 * min(white, 1 - white), radius, 100 * min(wide.mean(), 1 - wide.mean()))
    fit = fit_layout(wtarget, None, index, wlat, cfg, seed)
    fit.params = fit.params.copy()
    fit.params[0] = 1.0 - white if fit.complement else white
    fit.meta.update(widened={"radius_px": radius, "white_fraction": fit.meta.get("white_fraction"),
                             "lattice": fit.meta.get("lattice")}, white_fraction=white, lattice=lat.to_dict())
    if cfg.thin_refine_evals > 0:
        refine_thin_shape(fit, target, lat, cfg)
    return fit


def refine_thin_shape(fit: MaskFit, target: np.ndarray, lat: Lattice, cfg: MaskFitConfig) -> None:
    """Re-choose a widened fit's cell shape (the window lines of workers.layout_fit: larp, smoothness, arity,
    jitter, norm; layout untouched) by the loss of the thin network itself, in place.

    The widened network's best cells need not be the thin one's: on metal_plate_02 at 512 px the widened seams
    chose rounded cells (larp 0.69: loss 0.36 there against 0.45 for straight borders), which thresholded back
    to the seams' 7 % bow the course lines and pinch the vertical seams into wedges; on the thin seams the
    straight borders score better (0.55 against 0.61) and look like the input's plates. The shape found here is
    kept only when it also wins on fresh realisations (``_validate``)."""
    from .layout_fit import GramMaskLoss, layout_weight, loss_factor, window_lines

    t0 = time.perf_counter()
    loss = GramMaskLoss(target, None, shift=cfg.shift, factor=loss_factor(target.shape[1]),
                        realisations=cfg.realisations, structure_weight=layout_weight(lat))
    c = fit.complement
    x0 = loss.with_threshold(fit.params, c)
    budget = Budget(lambda q: loss(q, c), cfg.thin_refine_evals, t0 + 0.25 * cfg.time_budget_s)
    start = budget(x0)
    x = window_lines(budget, x0, cycles=2, scan=False)
    cands = [(budget.best_loss, c, x, "thin", True), (start, c, x0, "widened", True)]
    params, own, _, chosen, val, n_val = _validate(loss, cands, max(1, cfg.validate))
    threshold = fit.params[0]        # the network's share at full size (the fit size's lines lose pixels)
    fit.params = pp.clip_params(params)
    fit.params[0] = threshold
    fit.evaluations += budget.evaluations + n_val
    fit.seconds += time.perf_counter() - t0
    fit.meta["thin_shape"] = {"start_loss": float(start), "loss": float(own), "validation_loss": float(val),
                              "chosen": chosen, "evaluations": budget.evaluations + n_val}
    logger.info("mask: thin network's cell shape %s (loss %.4f -> %.4f, %d evals)", chosen, start, own,
                budget.evaluations + n_val)


def _fit(mask, index, valid, cfg: MaskFitConfig, seed: int, cell_length: float | None = None) -> MaskFit:
    """fit_pptbf_mask without the thread setting."""
    if cfg.lattice:
        fit = _layout_first(mask, index, valid, cfg, seed, cell_length)
        if fit is not None:
            return fit
    t0 = time.perf_counter()
    target, valid_s = _prepare_target(mask, valid, cfg.fit_size or _index_resolution(index) or 128)
    h, w = target.shape
    k = max(cfg.top_k, cfg.rerank_pool) if cfg.loss == "vgg19" else cfg.top_k
    q_pos, q_neg = index.query(target, k=k, valid=valid_s), index.query(~target, k=k, valid=valid_s)
    if not q_pos and not q_neg:
        raise InputError("index: the PPTBF database returned no match (is it empty?)")
    loss = _vgg_loss(target, valid_s, cfg) if cfg.loss == "vgg19" else \
        MaskLoss(target, index, valid_s, shift=cfg.shift, realisations=cfg.realisations)
    # "the query result alone": the index's nearest entry over both polarities, rendered verbatim
    q_compl = nearer_is_complement(q_pos, q_neg)
    q_best = (q_neg if q_compl else q_pos)[0]
    loss_query = loss(q_best.params, q_compl, threshold_from_target=False)
    # re-rank both top-k lists with the target's threshold at our realisation; the best fixes the polarity
    history, n0 = [loss_query], 1
    scored = []
    for compl, matches in ((False, q_pos), (True, q_neg)):
        for mt in matches:
            if n0 >= cfg.max_evals or time.perf_counter() - t0 > cfg.time_budget_s:
                break
            p = loss.with_threshold(mt.params, compl)
            scored.append((loss(p, compl), compl, p, mt))
            n0 += 1
            history.append(min(history[-1], scored[-1][0]))
    settings = OptSettings(rounds=cfg.rounds, max_evals=cfg.max_evals, time_budget_s=cfg.time_budget_s,
                           algorithm=cfg.algorithm, step=cfg.step, seed=seed, structure_moves=cfg.structure_moves)
    scored.sort(key=lambda s: s[0])
    best_loss, complement, x0, start = scored[0] if scored else (
        loss_query, q_compl, np.asarray(q_best.params, np.float64), q_best)
    n_explore, explored = 0, []
    n_starts = min(cfg.starts, len(scored))
    reserve = max(0, int(cfg.validate)) * (n_starts + 2)
    reserve = reserve if cfg.max_evals - n0 - reserve >= 20 else 0          # too small a budget: no validation
    per_eval = (time.perf_counter() - t0) / max(1, n0)
    deadline = t0 + cfg.time_budget_s - reserve * per_eval
    each = int(cfg.explore_share * (cfg.max_evals - n0 - reserve) / max(1, n_starts))
    if n_starts > 1 and each >= 10:   # multi-start: short searches from the best re-ranked entries
        for l0, compl, p, mt in scored[:cfg.starts]:
            b = Budget(lambda q, c=compl: loss(q, c), each, deadline)
            b.seed(p, l0)
            explore(b, p, w, settings)
            n_explore += b.evaluations
            history += b.history
            explored.append((b.best_loss, compl, b.best_params, mt))
        best_loss, complement, x0, start = min(explored, key=lambda s: s[0])
    budget = Budget(lambda p: loss(p, complement), cfg.max_evals - n0 - n_explore - reserve, deadline)
    budget.seed(x0, best_loss)
    settings.max_evals = budget.max_evals
    optimise(budget.loss, x0, w, settings, budget=budget)
    limited = time_limited(deadline)
    history += budget.history
    cands = [(budget.best_loss, complement, budget.best_params, start, True)]
    cands += [(l, c, p, mt, True) for l, c, p, mt in explored]
    cands = [c for c in cands if c[0] < loss_query] + [(loss_query, q_compl, q_best.params, q_best, False)]
    n_val, val = 0, None
    if reserve:   # the candidate best on fresh realisations (never one worse than the query at our realisation)
        best, loss_final, complement, start, val, n_val = _validate(loss, cands, cfg.validate)
        history += [history[-1]] * n_val
    else:         # best ever at our realisation (the verbatim query result when nothing beat it)
        loss_final, complement, best, start, _ = cands[0]
        best = np.array(best, dtype=np.float64)
    secs = time.perf_counter() - t0
    evals = n0 + n_explore + budget.evaluations + n_val
    logger.info("PPTBF mask fit %dx%d: loss %.4f (query) -> %.4f in %d evals, %.1f s%s", w, h, loss_query,
                loss_final, evals, secs, " (complement)" if complement else "")
    if limited:
        warn_time_limited(f"PPTBF mask fit {w}x{h}", evals, cfg)
    return MaskFit(params=pp.clip_params(best), complement=bool(complement), loss_query=float(loss_query),
                   loss_final=float(loss_final), evaluations=evals, seconds=secs,
                   history=[float(x) for x in np.minimum.accumulate(history)], fit_size=(w, h), shift=tuple(cfg.shift),
                   entry_id=getattr(start, "entry_id", None),
                   meta={"white_fraction": loss.white, "query_distance": float(q_best.distance),
                         "query_complement": q_compl, "validation_loss": val, "time_limited": limited,
                         "rerank_loss": float(min((s[0] for s in scored), default=loss_query))})


def _vgg_loss(target: np.ndarray, valid: np.ndarray | None, cfg: MaskFitConfig) -> MaskLoss:
    """The query path's VGG-19 Gram + layout loss (the paper's texture loss, also the layout fit's): the
    database descriptor finds the starts; this loss judges them on the field's yardstick rather than on the
    descriptor's sketch of the Grams plus LBP and spectrum."""
    from .layout_fit import GramMaskLoss

    return GramMaskLoss(target, valid, shift=cfg.shift, realisations=cfg.realisations)


def nearer_is_complement(q_pos: list, q_neg: list) -> bool:
    """Whether the database's nearest entry over both polarities is a match of the complement (``q_neg``: the
    query of ~mask) rather than of the mask (``q_pos``): the polarity of "the query result alone"."""
    return bool(q_neg and (not q_pos or q_neg[0].distance < q_pos[0].distance))


def time_limited(deadline: float) -> bool:
    """Whether a fit's search reached its time limit (the deadline before validation) rather than its evaluations
    (checked once the search is over: a search that ran out of evaluations ends before its deadline)."""
    return time.perf_counter() >= deadline


def warn_time_limited(what: str, evals: int, cfg: MaskFitConfig) -> None:
    """Say that a fit stopped on the clock: its result then depends on the machine's speed and load."""
    logger.warning("%s stopped at its time limit (masks.time_budget_s = %.0f s) after %d of %d evaluations: "
                   "another run may return another fit; raise time_budget_s or lower max_evals for a "
                   "repeatable one", what, cfg.time_budget_s, evals, cfg.max_evals)


def _validate(loss: MaskLoss, cands: list, n: int):
    """Pick the candidate (own loss, complement, params, start, threshold_from_target) with the lowest mean
    distance over `n` fresh realisations; returns (params, own loss, complement, start, that distance, evals)."""
    seen, best, evals = set(), None, 0
    for own, compl, p, start, from_target in cands:
        key = (bool(compl), np.round(np.asarray(p, np.float64), 9).tobytes())
        if key in seen:
            continue
        seen.add(key)
        v = loss.fresh(p, compl, n, threshold_from_target=from_target)
        evals += n
        if best is None or v < best[4]:
            best = (np.array(p, dtype=np.float64), float(own), bool(compl), start, float(v))
    return (*best, evals)


def fit_inpainted_mask(inpainted_maps: dict[str, np.ndarray], segment: Callable[[dict[str, np.ndarray]], np.ndarray],
                       index, config: MaskFitConfig | None = None, seed: int | None = None) -> MaskFit:
    """Inpainting variant for sub-layers: segment the inpainted (complete) sub-material maps and fit that mask.

    `inpainted_maps` are the sub-material's maps with the holes outside the parent filled in (any inpainting);
    `segment(maps) -> HxW bool` is the same segmentation that made the incomplete mask (e.g. a matting call).
    The fit then uses the whole image, so no `valid` restriction is needed.
    """
    if not inpainted_maps:
        raise InputError("inpainted_maps: no maps given")
    shapes = {k: np.shape(a)[:2] for k, a in inpainted_maps.items()}
    if len(set(shapes.values())) != 1:
        raise InputError(f"inpainted_maps: maps differ in size {shapes}")
    mask = check_mask(segment(inpainted_maps), "segment(inpainted_maps)")
    if mask.shape != next(iter(shapes.values())):
        raise InputError(f"segment(inpainted_maps): returned shape {mask.shape}, "
                         f"maps are {next(iter(shapes.values()))}")
    return fit_pptbf_mask(mask, index, None, config, seed)
