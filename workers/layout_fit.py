"""Structure-faithful PPTBF fitting of masks that have a layout (bricks, tiles, slates, plates).

The database query and a free derivative-free search rarely land a PPTBF on a target's lattice: on a brick
wall they return streaks or speckle at another period, and the old descriptor (LBP + random-conv Gram + radial
spectrum) even scores that speckle better than a hand-built wall. Here the layout is measured first and kept:

1. ``workers.lattice`` measures the target's lattice and turns it into starting vectors: tiling families whose
   cells sit on that lattice, with period, aspect and rotation solved for, and a crisp cellular window (up to
   60 layouts, screened on a quarter of the pixels (``screen_loss``), the best 14 kept); the
   database's nearest entries (both polarities) join them as further starts, and so do transplants: the best
   lattice starts' placement of cells (tiling, period, rotation, aspect, jitter, distortion) with a database
   entry's look (cell window and features), for looks the crisp template cannot express.
2. Every start is scored with the pretrained VGG-19 Gram distance (``GramMaskLoss``: relu1_1..relu4_1 of the mask,
   the paper's texture loss) plus an autocorrelation (layout) distance, at the target's resolution (up to 256 px),
   rendered there and area-averaged by an integer factor to the loss resolution (128 px for a 256 px mask), so 2-3
   px mortar lines survive as grey lines instead of vanishing in a binary downsample.
3. From the best lattice start the layout (tiling, period, rotation, aspect) is frozen while the cell shape is
   fitted: a line search over larp, smoothness, sector count (2^arity), jitter and norm (``window_lines``; the
   sector count is a rounded step a local search cannot move, and the loss is sharp in larp) on a crop of the
   target at full resolution (a quarter of the cost), then the window entries by local search at full size
   (window shape and mixture by sweep); then the best candidate so far gets a line over larp and smoothness at
   full size and every entry is freed for a final polish with small steps. A mask of rows alone whose cells'
   length is given skips the cell shape: the crisp template's cells stay (``FIXED_CELLS``).
4. The candidates (polished, layout-fixed, best start, best database entry) are compared on fresh realisations;
   the best there is returned.

A target without a lattice keeps the query-and-optimise path of ``workers.masks``.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from pptbf_db import pptbf as pp
from pptbf_db.features import GramExtractor, gram_distance

from .inpaint import masked_autocorrelation
from .lattice import (
    CELL_TEMPLATE,
    ROW_FAMILIES,
    SPLIT_FAMILIES,
    Lattice,
    analyse_lattice,
    compare_lattices,
    compare_rows,
    half_turn,
    layout_lattices,
    pptbf_starts,
    radial_profile,
    split_sibling,
)
from .mask_opt import Budget, BudgetExhausted, OptSettings, optimise
from .masks import MaskFit, MaskFitConfig, MaskLoss, _validate, downsample_mask, time_limited, warn_time_limited

logger = logging.getLogger(__name__)

#: entries that place the cells on the lattice: kept while the window is fitted
LAYOUT = ("tiling", "resolution", "rotation", "aspect_ratio")
#: entries left out of the window stage (features and distortion stay at the crisp template's values)
#: (and jitter, which the line search sets within WINDOW_LINES' range: free, the local search drove a noisy real
#: wall's jitter to 0.49, which scored well by Gram statistics and lost the wall's lattice)
WINDOW_STAGE_FROZEN = LAYOUT + ("jitter",) + tuple(n for n in pp.PARAM_NAMES if n.startswith("feature_")
                                                   and n != "feature_mixture" or n.startswith("distortion_"))
#: pixels of the loss image: masks are area-averaged by an integer factor down to about this width
LOSS_WIDTH = 128


def loss_factor(width: int, loss_width: int = LOSS_WIDTH) -> int:
    """Integer area-averaging factor from the fit width to the loss width (1 below it)."""
    return max(1, int(round(width / float(loss_width))))


#: weight of the layout term (autocorrelation distance) next to the VGG-19 Gram distance in the mask loss
STRUCTURE_WEIGHT = 1.0
#: the layout term's weight on rows of random heights (``random_heights``): there the target's autocorrelation
#: repeats only every few rows, at a lag its own draw of heights sets, and the term prefers a render that
#: happens to share it (bench target 3, an ashlar of 35 px rows repeating at 114 px: the true parameters scored
#: 0.74 on the fit's realisation against 0.60 for a fit at 1.7x their Gram distance)
RANDOM_HEIGHTS_WEIGHT = 0.25
#: rows whose mean height is under this share of their repeat are rows of random heights
RANDOM_HEIGHTS_SHARE = 0.5


def random_heights(lat: Lattice) -> bool:
    """The lattice is rows that repeat only every few rows: their mean height (network lines crossed across the
    rows) is under RANDOM_HEIGHTS_SHARE of the repeat the autocorrelation shows."""
    return lat.kind == "rows" and bool(lat.row_height) and bool(lat.row_spacing) and \
        lat.row_height < RANDOM_HEIGHTS_SHARE * lat.row_spacing


def layout_weight(lat: Lattice) -> float:
    """The layout term's weight for a target of lattice `lat` (STRUCTURE_WEIGHT, less on random heights)."""
    return STRUCTURE_WEIGHT * (RANDOM_HEIGHTS_WEIGHT if random_heights(lat) else 1.0)


def layout_part(ac: np.ndarray) -> np.ndarray:
    """The (shifted) autocorrelation less its ring means (``lattice.radial_profile``), inside the largest centred
    disc: what a layout adds to the isotropic decay (lattice peaks, row ridges), zero elsewhere."""
    h, w = ac.shape
    yy, xx = np.mgrid[:h, :w]
    r = np.rint(np.hypot(yy - h // 2, xx - w // 2)).astype(np.int64)
    out = ac - radial_profile(ac)[0][r]
    out[r > min(h, w) // 2 - 1] = 0.0
    return out


def _layout_distance(la: np.ndarray, lb: np.ndarray) -> float:
    """1 - correlation of two layout parts."""
    den = float(np.sqrt((la * la).sum() * (lb * lb).sum()))
    return 1.0 - float((la * lb).sum()) / den if den > 1e-12 else 1.0


def autocorrelation_distance(a: np.ndarray, b: np.ndarray) -> float:
    """1 - correlation of the layout parts of two autocorrelations (``layout_part``): 0 for the same layout
    whatever the realisation, 1 for no shared structure (a scatter, or a flat render), up to 2 for opposite.
    A correlation, not a difference: a grid with the right periods but a wrong row offset shares half its
    peaks with the target and must score better than no layout at all."""
    return _layout_distance(layout_part(a), layout_part(b))


class GramMaskLoss(MaskLoss):
    """Texture and layout distance between renders of a parameter vector and a target mask, both area-averaged
    by ``factor``: the pretrained VGG-19 Gram distance (``features.gram_distance``) plus ``structure_weight`` x
    the autocorrelation distance. Gram statistics are local (a render of scattered junctions and short seams
    scores close to a plate grid: looked at on metal_plate_02, the picture said otherwise), the autocorrelation
    holds the layout (periods, offsets, orientation) and, being shift-invariant, compares realisations. Same
    interface as ``MaskLoss`` (threshold from the target's white fraction, fixed realisation, fresh
    realisations for validation). ``valid`` weights the Gram statistics and masks the autocorrelation."""

    def __init__(self, target: np.ndarray, valid: np.ndarray | None = None, *, shift=(0.0, 0.0),
                 factor: int = 1, realisations: int = 1, extractor: GramExtractor | None = None,
                 structure_weight: float = STRUCTURE_WEIGHT, pixel_scale: float = 1.0,
                 ref_width: int | None = None) -> None:
        self._set_target(target, valid, shift, realisations, pixel_scale, ref_width)
        self.index = None
        self.factor = int(factor)
        self.extractor = extractor or GramExtractor.vgg19(1)
        self.structure_weight = float(structure_weight)
        self._valid_t = None if valid is None else self._image(valid)[0, 0]
        self._known = np.ones(self._image(target).shape[-2:], bool) if valid is None else \
            self._valid_t.numpy() > 0.5
        self._target_desc = self.describe(target)
        self._target_layout = None if self._target_desc[1] is None else layout_part(self._target_desc[1])

    def _image(self, mask: np.ndarray) -> torch.Tensor:
        """1x1xhxw float tensor of a bool mask, area-averaged by the factor."""
        x = torch.from_numpy(np.ascontiguousarray(mask, dtype=np.float32))[None, None]
        if self.factor > 1:
            h, w = (x.shape[-2] // self.factor) * self.factor, (x.shape[-1] // self.factor) * self.factor
            x = F.avg_pool2d(x[..., :h, :w], self.factor)
        return x

    def describe(self, mask: np.ndarray) -> tuple[list[torch.Tensor], np.ndarray | None]:
        """Gram matrices of a mask (relu1_1..relu4_1) and its autocorrelation (None when unweighted)."""
        img = self._image(mask)
        with torch.no_grad():
            grams = self.extractor.grams(img, self._valid_t)
        if self.structure_weight <= 0:
            return grams, None
        x = img[0, 0].numpy().astype(np.float64)
        if float(x[self._known].std()) < 1e-6:          # a flat render has no layout: as far as can be
            return grams, np.zeros(x.shape)
        ac, _ = masked_autocorrelation(x[..., None], self._known)
        return grams, np.fft.fftshift(ac)

    def gram_distance(self, mask: np.ndarray) -> float:
        """The VGG-19 Gram part alone (the field's yardstick)."""
        return float(gram_distance(self.describe(mask)[0], self._target_desc[0])[0])

    def of_mask(self, mask: np.ndarray) -> float:
        """Gram + structure_weight x autocorrelation distance of a bool mask (the target's size) to the target."""
        grams, ac = self.describe(mask)
        d = float(gram_distance(grams, self._target_desc[0])[0])
        if ac is not None:
            d += self.structure_weight * _layout_distance(layout_part(ac), self._target_layout)
        return d


#: values tried for each cell-shape entry by the window stage's line search (larp: straight to round borders;
#: smoothness: polygon to curved cells; arity: 2^arity sectors of the cell border, a rounded step a local search
#: cannot move; jitter: irregular cells; norm: the Minkowski norm of the cell distance). The loss is sharp in
#: larp: a pavement whose true larp is 0.125 scores 0.014 there and 0.10-0.17 at 0 and 0.25, so each line is
#: refined around its best value
WINDOW_LINES: dict[str, tuple[float, ...]] = {
    "window_larp": tuple(np.linspace(0.0, 1.0, 9)),
    "window_smoothness": (0.0, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0),
    "window_arity": (3.0, 4.0, 5.0, 6.0),
    "jitter": (0.0, 0.05, 0.1, 0.15, 0.2),
    "window_norm": (1.0, 1.5, 2.0, 2.5, 3.0),
}
#: entries refined by halving steps around the best grid value (the others are steps of their own)
WINDOW_REFINED = ("window_larp", "window_smoothness", "jitter", "window_norm")


def _line(budget: Budget, x: np.ndarray, name: str, values) -> np.ndarray:
    """x with entry `name` set to the value of `values` the budget scores best (x's own value included)."""
    i = pp.PARAM_INDEX[name]
    best, best_loss = x, budget(x)
    for v in values:
        p = np.array(x, np.float64)
        p[i] = v
        p = pp.clip_params(p)
        loss = budget(p)
        if loss < best_loss:
            best, best_loss = p, loss
    return best


def _same_lattice(x: np.ndarray) -> list[np.ndarray]:
    """Other layouts on x's lattice: its half turn (chiral families), its split or unsplit sibling, and both."""
    turned, sibling = half_turn(x), split_sibling(x)
    both = None if turned is None or sibling is None else split_sibling(turned)
    return [q for q in (turned, sibling, both) if q is not None]


#: the lines each layout on the start's lattice gets before the cycles (``window_lines``' scan)
SCAN_LINES = ("window_arity", "window_larp", "window_smoothness")


def _scan_layouts(budget: Budget, x: np.ndarray, judge: Budget | None = None) -> np.ndarray:
    """The best of x and the other layouts on its lattice (``_same_lattice``), each after one line over each of
    SCAN_LINES: a split pavement loses to its unsplit sibling at the crisp template and at the sibling's fitted
    cell shape (bench target 14: 0.32-0.40 against 0.28) and wins at its own (0.07). `judge` (the full-size
    loss) picks among them when given: a crop ranks a chiral pavement's half turns wrongly (target 14 at its true
    cell shape: 0.17 against 0.14 for the half turn on the crop, 0.068 against 0.10 at full size)."""
    pick = judge or budget
    best, best_loss = x, pick(x)
    for q in [x] + _same_lattice(x):
        for name in SCAN_LINES:
            q = _line(budget, q, name, WINDOW_LINES[name])
        if pick(q) < best_loss:
            best, best_loss = q, pick(q)
    return best


def _arity_sweep(budget: Budget, x: np.ndarray) -> np.ndarray:
    """The best of x at each sector count (WINDOW_LINES' arity values), each after one line over larp and one
    over smoothness: the cell shape's loss has a valley per sector count, and a coordinate line over the sector
    count at the crisp template's larp and smoothness picks the wrong one (bench target 24, a herringbone of
    8-sector cells: the lines from 16 sectors stop at 0.25 on the crop, the sweep reaches 0.07 and the true
    parameters score 0.13)."""
    best, best_loss = x, budget(x)
    i = pp.PARAM_INDEX["window_arity"]
    for a in WINDOW_LINES["window_arity"]:
        q = np.array(x, np.float64)
        q[i] = a
        for name in ("window_larp", "window_smoothness"):
            q = _line(budget, q, name, WINDOW_LINES[name])
        if budget(q) < best_loss:
            best, best_loss = q, budget(q)
    return best


#: factors of a layout entry tried by ``_factor_line``, then refined by halving steps: on a target of rows the
#: cells' aspect ratio (rows fix the row height, not the cells' length along them, and the lattice analysis's
#: mean cell length is an estimate: bench target 3: 40.4 px measured, 45 px true; Gram distance of fresh
#: realisations 0.24 at the measured length, 0.175 at the true one), and on rows of random heights the
#: resolution too (their mean height crossed on one draw is an estimate: bench target 18, 40 px measured, 48 px
#: true; Gram distance 0.18 at 40 px, 0.092 at 48 px)
FACTORS = (0.8, 0.9, 1.1, 1.25)


def _halving(budget: Budget, x: np.ndarray, name: str, step: float, relative: bool = False) -> np.ndarray:
    """Two line steps of entry `name` either side of its value, the second half the first (`relative`: steps
    are fractions of the value)."""
    i = pp.PARAM_INDEX[name]
    for _ in range(2):
        d = step * x[i] if relative else step
        x = _line(budget, x, name, (x[i] - d, x[i] + d))
        step /= 2.0
    return x


def _factor_line(budget: Budget, x: np.ndarray, name: str) -> np.ndarray:
    """x with entry `name` scaled by the best of FACTORS (or kept), then two halving steps."""
    i = pp.PARAM_INDEX[name]
    x = _line(budget, x, name, tuple(x[i] * f for f in FACTORS))
    return _halving(budget, x, name, 0.05, relative=True)


def window_lines(budget: Budget, x0: np.ndarray, cycles: int = 3, scan: bool = True, sweep: bool = False,
                 scaled: tuple[str, ...] = (), judge: Budget | None = None) -> np.ndarray:
    """Coordinate line search over the cell shape (WINDOW_LINES), layout untouched: each entry over its values,
    then halving steps around the best (two per entry), cycle after cycle until one improves nothing; returns
    the best vector (also the budget's). A coarse grid over larp x smoothness x arity misses the narrow valleys
    of the loss, a local search from the crisp template does not cross the arity steps; lines do both for a
    few dozen evaluations a cycle. A chiral family's half turn (``lattice.half_turn``) and the family's split or
    unsplit sibling (``lattice.split_sibling``) each get a short line search first (`scan`,
    ``_scan_layouts``) and are tried again at each cycle. `judge` (a second budget, e.g. the full-size loss when
    `budget` is a crop's) chooses among those layouts, and the search's own end point is returned instead of
    the budget's best (which may lie on a layout the judge turned down). Stops quietly when a budget is spent."""
    x = pp.clip_params(np.asarray(x0, np.float64))
    pick = judge or budget
    try:
        for name in scaled:     # the cells' size first: the layouts on the lattice compare at it
            x = _factor_line(budget, x, name)
        if scan:
            x = _scan_layouts(budget, x, judge)
        if sweep:           # on the layout the scan chose (a split pavement's half turn: bench target 14)
            x = _arity_sweep(budget, x)
        for _ in range(max(1, cycles)):
            before = budget(x)
            for q in _same_lattice(x):
                if pick(q) < pick(x):
                    x = q
            for name, values in WINDOW_LINES.items():
                x = _line(budget, x, name, values)
            for name in WINDOW_REFINED:
                values = WINDOW_LINES[name]
                x = _halving(budget, x, name, (max(values) - min(values)) / (len(values) - 1) / 2.0)
            for name in scaled:
                x = _factor_line(budget, x, name)
            if budget(x) >= before:
                break
    except BudgetExhausted:
        pass
    if judge is not None:
        return x
    return budget.best_params if budget.best_params is not None else x


#: a candidate keeps the target's layout when a fresh realisation's lattice is within these of the target's
GATE_PERIOD, GATE_ANGLE = 0.10, 5.0
#: starts checked (best first) for one that keeps the lattice before the window stage
GATE_CHECKS = 8


#: fresh realisations (shifts from the fit's own) on which a candidate must show the target's lattice
GATE_SHIFTS = ((53.3, 29.9), (17.7, 71.1))


def _shows_lattice(loss: GramMaskLoss, lat: Lattice, params: np.ndarray, complement: bool, shift) -> bool:
    """Whether one render of `params` has the target's lattice (GATE_PERIOD, GATE_ANGLE): for a target of rows
    the render's rows next to the target's (``lattice.compare_rows``), else the render's own analysis."""
    return mask_shows_lattice(loss.render(params, complement, True, shift=shift), lat, params)


def mask_shows_lattice(mask: np.ndarray, lat: Lattice, params: np.ndarray) -> bool:
    """Whether a render ``mask`` of ``params`` has the lattice ``lat`` (GATE_PERIOD, GATE_ANGLE): for rows the
    render's rows next to them (``lattice.compare_rows``), else the render's own analysis."""
    if mask.all() or not mask.any():          # a uniform render
        return False
    if lat.kind == "rows":
        return _close(compare_rows(lat, mask))
    seen = analyse_lattice(mask)
    return _close(compare_lattices(lat, seen)) or _near_lattices_agree(lat, seen, params)


def _close(errors: tuple[float, float]) -> bool:
    """(period error, angle error) within GATE_PERIOD and GATE_ANGLE."""
    return errors[0] <= GATE_PERIOD and errors[1] <= GATE_ANGLE


def _near_lattices_agree(lat: Lattice, seen: Lattice, params: np.ndarray) -> bool:
    """The target and a render read two different (near-)lattices of the parameters' own layout (a family with
    several, ``lattice.layout_lattices``): which one an analysis reads depends on the draw (bench target 8, a
    split 2:1 herringbone: the target reads the near-lattice that adds half a cell, every render of the true
    parameters the exact one, period 2x), so the layout is the target's although the two readings differ."""
    own = layout_lattices(params)
    if len(own) < 2 or seen.kind != "2d":
        return False
    return any(_close(compare_lattices(o, lat)) for o in own) and any(_close(compare_lattices(o, seen)) for o in own)


def _keeps_lattice(loss: GramMaskLoss, lat: Lattice, cand: tuple) -> bool:
    """Whether fresh realisations of candidate (loss, complement, params, ...) have the target's lattice
    (period within 10 %, angle within 5 degrees) on every shift of GATE_SHIFTS: a noisy candidate's lattice
    analysis can pass on one realisation by chance. For a target of rows, the realisation's rows next to the
    target's (``lattice.compare_rows``), not its own analysis: rows with random cuts often read as no lattice
    (the true parameters' own realisations of bench target 20 did, and the gate turned away the true layout),
    and clean bricks as a repeat along the rows (a hand-built slate roof). A family that splits its cells at
    random (``lattice.SPLIT_FAMILIES``) also passes a shift where its unsplit sibling (the same placement and
    cell shape) shows the lattice: the random cuts blur what a render's analysis reads, most on a mask of few
    periods (bench target 23, a split herringbone 2.3 periods across: the crisp split start read as no lattice
    and as one 33 % off on the two shifts, its sibling within 1 % on both; the gate turned the best start and the
    window stage's split herringbones away and kept a crisp unsplit start, Gram ratio 1.9, 0.95 with the
    sibling's check). Not the sibling alone: an unsplit 3:1 herringbone often reads as one of its near-lattices
    where the split one reads the exact lattice (target 10)."""
    params = np.asarray(cand[2], np.float64)
    sibling = split_sibling(params) if int(params[pp.PARAM_INDEX["tiling"]]) in SPLIT_FAMILIES else None
    for dx, dy in GATE_SHIFTS:
        shift = (loss.shift[0] + dx, loss.shift[1] + dy)
        if not _shows_lattice(loss, lat, params, cand[1], shift) and \
                (sibling is None or not _shows_lattice(loss, lat, sibling, cand[1], shift)):
            return False
    return True


def _lattice_gate(loss: GramMaskLoss, lat: Lattice, cands: list, at_most: int | None = None,
                  first: bool = False) -> list:
    """The candidates (in order) that keep the target's lattice, checking at most `at_most` of them (`first`:
    stop at the first that does; each check renders two realisations). The loss is a texture statistic: on a
    noisy real wall it can prefer a finer grid or loose rows to the wall's own courses
    (castle_brick_broken_06: the picture says otherwise), so the layout is checked on its own."""
    out = []
    for c in cands[:at_most]:
        if _keeps_lattice(loss, lat, c):
            out.append(c)
            if first:
                break
    return out


@dataclass
class _Starts:
    """Scored starting vectors (loss, complement, params, kind) best first, and the verbatim query result."""

    scored: list[tuple[float, bool, np.ndarray, str]]
    history: list[float]
    query: tuple | None = None          # (best database match, its complement)
    loss_query: float = float("nan")
    matches: list = field(default_factory=list)   # database matches (params, complement) for transplants
    screened: int = 0                   # lattice layouts scored on the reduced copy (not in the evaluations)
    screen_seconds: float = 0.0


#: the screening loss sees the target at this scale (a quarter of the pixels; about 0.15 s an evaluation at 256
#: px against 0.37 s at full size)
SCREEN_SCALE = 0.5
#: layouts screened in both polarities first; the later ones in the likely polarity, then in the other
SCREEN_BOTH = 16


def likely_complement(lat: Lattice) -> bool:
    """The polarity a crisp cellular template most likely needs: the complement (white network) when the
    lattice analysis found a white network that is also the smaller phase, or, without such a network, when
    the mask is mostly black. A connected majority phase is not taken for the network: rounded cells of a
    pavement at 74 % white touch through their corners, and the white cells were read as the network."""
    if network_side_known(lat):
        return bool(lat.network_is_white)
    return lat.white_fraction < 0.5


def network_side_known(lat: Lattice) -> bool:
    """The lattice analysis found a connected network that is the smaller phase."""
    if lat.network_is_white is None:
        return False
    return (lat.white_fraction < 0.5) == bool(lat.network_is_white)


#: the screening uses the full-resolution crop (``crop_loss``) when it holds this many lattice periods across
SCREEN_CROP_PERIODS = 4.0


def screen_loss(loss: GramMaskLoss, lat: Lattice) -> GramMaskLoss | None:
    """The loss layouts are screened with, at a quarter of the full loss's pixels: the full-resolution crop
    when it holds SCREEN_CROP_PERIODS periods of the lattice (a castle wall's 7 px courses at 256 px are a blur
    at half size, where a square grid screened better than the running bond), else a half-size copy of the
    target (large plates); None when that copy would be under 32 px."""
    h, w = loss.target.shape
    crop = crop_loss(loss)
    vectors = [float(np.hypot(*v)) for v in lat.vectors] or [0.0]
    if crop is not None and SCREEN_CROP_PERIODS * max(vectors) <= min(crop.target.shape):
        return crop
    if min(h, w) * SCREEN_SCALE < 32:
        return None
    sw, sh = int(round(w * SCREEN_SCALE)), int(round(h * SCREEN_SCALE))
    small_valid = None if loss.valid is None else downsample_mask(loss.valid, sw, sh)
    return GramMaskLoss(downsample_mask(loss.target, sw, sh), small_valid, shift=loss.shift,
                        factor=loss_factor(sw, int(LOSS_WIDTH * SCREEN_SCALE)), pixel_scale=SCREEN_SCALE,
                        extractor=loss.extractor, structure_weight=loss.structure_weight)


def _screened_layouts(loss: GramMaskLoss, lat: Lattice, cfg: MaskFitConfig,
                      deadline: float) -> tuple[list[tuple[np.ndarray, bool]], int]:
    """(params, complement) of the lattice's layouts to score at full size. Up to cfg.lattice_screen layouts that
    put cells on the lattice (the first SCREEN_BOTH in both polarities: a cellular window is high inside cells, a
    white network needs the complement, and real masks are often broken networks on both sides; the later ones
    in the likely polarity (``likely_complement``) before the other) are scored with ``screen_loss`` (a crop or
    a half-size copy) and the best cfg.lattice_starts (layout, polarity) pairs kept: the right kind of layout (a
    herringbone or a pavement is often far down the list of matches, after square grids and bonds at several
    supercells) shows there already, for a quarter of the cost. At most max(cfg.lattice_starts,
    cfg.max_evals / 2) are screened. Returns the kept starts and the number of screening evaluations."""
    w = loss.target.shape[1]
    likely = likely_complement(lat)
    layouts = pptbf_starts(lat, w, max_matches=max(cfg.lattice_screen, cfg.lattice_starts))
    both = layouts[:SCREEN_BOTH]
    cands = [(p, c) for p in both for c in (likely, not likely)] + \
        [(p, likely) for p in layouts[SCREEN_BOTH:]] + [(p, not likely) for p in layouts[SCREEN_BOTH:]]
    keep = cfg.lattice_starts
    cands = cands[:max(keep, cfg.max_evals // 2)]
    screen = None if len(cands) <= keep else screen_loss(loss, lat)
    if screen is None:
        return cands[:keep], 0
    scored, n = [], 0
    for i, (p, c) in enumerate(cands):
        if time.perf_counter() > deadline:
            scored.append((np.inf, i, p, c))
            continue
        scored.append((screen(screen.with_threshold(p, c), c), i, p, c))
        n += 1
    scored.sort(key=lambda s: (s[0], s[1]))
    kept = []
    for v, _, p, c in scored[:keep]:        # the other half turn of a chiral layout, where it screens better
        q = half_turn(p)
        if q is not None and time.perf_counter() < deadline:
            n += 1
            vq = screen(screen.with_threshold(q, c), c)
            p = q if vq < v else p
        kept.append((p, c))
    return kept, n


#: database entries per polarity scored as starts on a mask with a lattice (a noisy entry renders slowly and
#: rarely wins there; the top_k all serve as transplant looks)
DATABASE_STARTS = 3


def _score_starts(target, valid, index, lat: Lattice, loss: GramMaskLoss, cfg: MaskFitConfig,
                  deadline: float, max_evals: int) -> _Starts:
    """Score the lattice starts (both polarities: a cellular window is high inside cells, so a white network
    needs the complement, but real masks are often broken networks on both sides) and the database's nearest
    entries (both polarities, threshold from the target)."""
    out = _Starts([], [])
    t0 = time.perf_counter()
    layouts, out.screened = _screened_layouts(loss, lat, cfg, deadline)
    out.screen_seconds = time.perf_counter() - t0
    starts = [(p, c, "lattice") for p, c in layouts]
    matches = []
    if index is not None:
        for compl in (False, True):
            for i, mt in enumerate(index.query(~target if compl else target, k=cfg.top_k, valid=valid)):
                out.query = out.query or (mt, compl)
                matches.append((np.asarray(mt.params, np.float64), compl))
                if i < DATABASE_STARTS:     # all of them lend their look to transplants
                    starts.append((matches[-1][0], compl, "database"))

    def score(batch) -> None:
        for p, compl, kind in batch:
            if len(out.scored) >= max(1, max_evals - 1) or (out.scored and time.perf_counter() > deadline):
                return
            p = loss.with_threshold(p, compl)
            out.scored.append((loss(p, compl), compl, p, kind))
            out.history.append(min(s[0] for s in out.scored))

    score(starts)
    out.matches = matches
    if out.query is not None:
        out.loss_query = loss(out.query[0].params, out.query[1], threshold_from_target=False)
        out.history.append(min(out.history[-1], out.loss_query))
    out.scored.sort(key=lambda s: s[0])
    return out


#: entries a transplant takes from the lattice start (where the cells are); the rest (cell shape, features)
#: comes from a database entry
PLACEMENT = LAYOUT + ("jitter", "distortion_base", "distortion_amplitude", "distortion_frequency")


def transplant(placement: np.ndarray, appearance: np.ndarray) -> np.ndarray:
    """A vector with the cells of `placement` (PLACEMENT entries) and the look of `appearance` (the rest)."""
    out = np.array(appearance, np.float64)
    for name in PLACEMENT:
        out[pp.PARAM_INDEX[name]] = placement[pp.PARAM_INDEX[name]]
    return pp.clip_params(out)


def _transplants(loss: "GramMaskLoss", lat: Lattice, placement: tuple, matches: list, max_evals: int,
                 deadline: float) -> tuple[list[tuple], list[float]]:
    """The database entries' appearance (window and feature settings, their polarity) on the cells of a start
    that keeps the lattice, scored; those that keep the lattice themselves, best first. The database knows
    looks the crisp template cannot express (noisy, rounded or split cells), the lattice where the cells are.
    Returns (the kept transplants, the loss of every evaluation in order)."""
    out = []
    for m_params, compl in matches[:max(0, max_evals)]:
        if time.perf_counter() > deadline:
            break
        p = loss.with_threshold(transplant(placement[2], m_params), compl)
        out.append((loss(p, compl), compl, p, "transplant"))
    losses = [c[0] for c in out]
    out.sort(key=lambda c: c[0])
    return _lattice_gate(loss, lat, out, at_most=3, first=True), losses


#: the crop the window stage's line search scores on: this share of the mask's width and height (a quarter of
#: the pixels at full resolution: 0.1 s an evaluation against 0.38 s at 256 px, and on a pavement the same
#: ranking of 25 cell shapes), used from this width of the crop up
CROP_SHARE, CROP_MIN_WIDTH = 0.5, 64
#: crop evaluations the window stage's line search may spend per full-size evaluation it is given (a crop costs
#: about a quarter of one)
CROP_EVALS = 2


def crop_loss(loss: GramMaskLoss) -> GramMaskLoss | None:
    """The loss on the top-left CROP_SHARE x CROP_SHARE of its target, at full resolution, parameters referring
    to the whole mask's width: cell shapes are local, so a crop ranks them as the whole does, for a quarter of
    the render and VGG cost. None when the crop would be narrower than CROP_MIN_WIDTH or mostly unknown."""
    h, w = loss.target.shape
    ch, cw = int(h * CROP_SHARE), int(w * CROP_SHARE)
    if cw < CROP_MIN_WIDTH or ch < CROP_MIN_WIDTH:
        return None
    valid = None if loss.valid is None else loss.valid[:ch, :cw]
    if valid is not None and valid.mean() < 0.5:
        return None
    return GramMaskLoss(loss.target[:ch, :cw], valid, shift=loss.shift, factor=loss.factor,
                        extractor=loss.extractor, structure_weight=loss.structure_weight, ref_width=loss.ref_width)


@dataclass
class _Window:
    """What the window stage found: the full-size budget of the chosen polarity, that polarity, the full-size
    evaluations (both polarities) and their history, and the crop line search's evaluations (not counted)."""

    budget: Budget
    complement: bool
    evaluations: int
    history: list[float]
    search_evals: int


def scaled_entries(lat: Lattice) -> tuple[str, ...]:
    """The layout entries the window stage scales by ``_factor_line`` (the rest of the layout stays as the
    lattice put it): on rows, the aspect ratio (cells' length along them), and on rows of random heights
    (``random_heights``) the resolution (their mean height) too; the aspect ratio not when the cells' length is
    given (``Lattice.cell_length_fixed``)."""
    if lat.kind != "rows":
        return ()
    out = ("aspect_ratio", "resolution") if random_heights(lat) else ("aspect_ratio",)
    return tuple(e for e in out if e not in fixed_cells(lat))


def _window_stage(loss: GramMaskLoss, crop: GramMaskLoss | None, start: tuple, width: int, max_evals: int,
                  deadline: float, cfg: MaskFitConfig, seed: int, network_known: bool = False,
                  scaled: tuple[str, ...] = ()) -> _Window:
    """Layout frozen: the cell shape by line search (``window_lines``) on the crop, one cycle in each polarity
    unless the lattice analysis knows which side is the network (the crisp template may prefer the complement
    that the target's own cell shape does not: a pavement with round 16-sector cells), more cycles in the
    better one, after the short line search of each layout on the lattice (``_scan_layouts``; run in both
    polarities it took the whole budget and a pavement's cell shape was lost) and the sweep over sector counts
    (``_arity_sweep``), with a line of its own for each layout entry in `scaled` (``scaled_entries``); then the
    window entries by local
    search (window shape and mixture by sweep) at full size from the line search's best or its half turn or
    split sibling, whichever scores best at full size (the crop ranks them less surely). Without a crop the line
    search runs on the full-size loss, counted."""
    own, compl, x0, _ = start
    compl = bool(compl)
    pols = (compl,) if network_known else (compl, not compl)
    small = crop or loss
    cap = CROP_EVALS * max_evals if crop is not None else max(0, max_evals // 2)
    searches = {c: Budget(lambda q, c=c: small(q, c), cap // len(pols) if len(pols) > 1 else cap, deadline)
                for c in pols}
    for c in pols:
        window_lines(searches[c], x0, cycles=1, scan=False)
    c = min(searches, key=lambda k: searches[k].best_loss)
    s = searches[c]
    s.max_evals = max(s.evaluations, cap - sum(x.evaluations for k, x in searches.items() if k != c))
    # full size: the judge of the layouts on the lattice during a crop search, then the window entries
    b = Budget(lambda q, c=c: loss(q, c), max_evals, deadline)
    if c == compl:
        b.seed(x0, own)
    end = window_lines(s, x0 if s.best_params is None else s.best_params, cycles=3, sweep=True, scaled=scaled,
                       judge=b if crop is not None else None)
    search_evals = sum(x.evaluations for x in searches.values())
    counted = 0 if crop is not None else search_evals
    b.max_evals = max(b.evaluations, max_evals - counted)
    history = [] if crop is not None else [v for k in pols for v in searches[k].history]
    try:                # the crop can rank a half turn or a split sibling wrongly (target 14)
        for q in ([end] + _same_lattice(end) if crop is not None else []) + \
                ([s.best_params] + _same_lattice(s.best_params) if s.best_params is not None else []):
            b(q)
    except BudgetExhausted:
        pass
    x = b.best_params if b.best_params is not None else x0
    optimise(b.loss, x, width, OptSettings(rounds=2, max_evals=b.max_evals, algorithm=cfg.algorithm,
                                           step=0.08, seed=seed, frozen=WINDOW_STAGE_FROZEN), budget=b)
    return _Window(b, c, b.evaluations + counted, history + b.history, search_evals if crop is not None else 0)


#: entries no stage of a fit moves when the cells' length along rows is given (cell_length_fixed): the aspect ratio
#: (a network of rows alone scores longer cells better: fewer ends to miss, which is no information on the cells)
#: and the cell window and features, kept at the crisp template's rectangles (``lattice.CELL_TEMPLATE``): such a
#: network says nothing of the cells' ends either, and the fit shaped them to hide them: the README roof's slates
#: came back as rounded bars whose joints were notches at the rows (VGG-19 Gram 0.37 to the rows-only network,
#: the crisp rectangles 0.70; with the joints read off the albedo's dark lines drawn into it, 0.45 and 0.37). The
#: distortion too: on such thin lines a polish's slight, slow distortion (amplitude 0.0004, frequency 0.03) left
#: the fitted 256 px window clean and erased the rows from half of a render four times its area
FIXED_CELLS = ("aspect_ratio",) + tuple(CELL_TEMPLATE)


def fixed_cells(lat: Lattice) -> tuple[str, ...]:
    """The entries no stage of a fit moves on ``lat``: FIXED_CELLS when the cells' length is given, else none."""
    return FIXED_CELLS if lat.cell_length_fixed else ()


def shape_fixed(lat: Lattice) -> bool:
    """The cells' window is not fitted (FIXED_CELLS): no window stage, no transplanted looks, no polish lines."""
    return "window_larp" in fixed_cells(lat)


#: cell-shape lines the polish runs first at full size: the candidate it starts from may come from a database
#: entry's look or the crop's line search, whose larp a local search with small steps cannot move far
POLISH_LINES = ("window_larp", "window_smoothness")


def _polish(loss: GramMaskLoss, best: tuple, width: int, max_evals: int, deadline: float, cfg: MaskFitConfig,
            seed: int, frozen: tuple[str, ...] = ()) -> Budget:
    """From the best candidate so far: the POLISH_LINES at full size, then everything but ``frozen`` free with small
    steps."""
    own, compl, x0 = best[0], best[1], best[2]
    b = Budget(lambda q, c=compl: loss(q, c), max(0, max_evals), deadline)
    b.seed(x0, own)
    try:
        for name in (n for n in POLISH_LINES if n not in frozen):
            x0 = _line(b, x0, name, WINDOW_LINES[name])
    except BudgetExhausted:
        return b
    optimise(b.loss, x0, width, OptSettings(rounds=2, max_evals=b.max_evals, algorithm=cfg.algorithm, step=0.03,
                                            seed=seed + 1, frozen=frozen), budget=b)
    return b


def _layouts_first(scored: list, lat: Lattice) -> list:
    """The scored starts (best first) with, on a 2-D lattice, the random-cut row families after the layouts
    that repeat in two directions, for the choice of the window stage's start: rows with random cuts share only
    the rows of a 2-D lattice (the lattice gate accepts them on the row spacing), and on a noisy real wall an
    ashlar start won by Gram statistics and its window stage lost the courses (castle_brick_broken_06's
    mortar). They stay candidates of their own (on that wall a random-bond start still wins, keeping the
    courses: period error 1.3 %)."""
    if lat.kind != "2d":
        return scored
    rows = [s for s in scored if int(s[2][pp.PARAM_INDEX["tiling"]]) in ROW_FAMILIES]
    return [s for s in scored if int(s[2][pp.PARAM_INDEX["tiling"]]) not in ROW_FAMILIES] + rows


def fit_layout(target: np.ndarray, valid: np.ndarray | None, index, lat: Lattice, cfg: MaskFitConfig,
               seed: int) -> MaskFit:
    """Lattice-first fit of a bool target (HxW at the fit resolution); see the module doc."""
    t0 = time.perf_counter()
    h, w = target.shape
    loss = GramMaskLoss(target, valid, shift=cfg.shift, factor=loss_factor(w), realisations=cfg.realisations,
                        structure_weight=layout_weight(lat))
    deadline = t0 + cfg.time_budget_s
    reserve = max(0, int(cfg.validate)) * 4            # validation: up to 4 candidates on fresh realisations
    reserve = reserve if cfg.max_evals - reserve >= 20 else 0
    st = _score_starts(target, valid, index, lat, loss, cfg, deadline, cfg.max_evals - reserve)
    scored, history = st.scored, list(st.history)
    n0 = len(history)
    logger.info("layout fit: %d starts, best lattice start %.4f, best overall %.4f (%s)", len(scored),
                min((s[0] for s in scored if s[3] == "lattice"), default=float("nan")), scored[0][0], scored[0][3])
    left = max(0, cfg.max_evals - n0 - reserve)
    per_eval = (time.perf_counter() - t0 - st.screen_seconds) / max(1, n0)
    stage_deadline = deadline - reserve * per_eval * 2
    cands = [(s[0], s[1], s[2], s[3], True) for s in scored[:2]]
    # window stage from the best start that keeps the lattice (else the best lattice start, else the best)
    ordered = _layouts_first(scored, lat)
    kept = _lattice_gate(loss, lat, ordered, at_most=GATE_CHECKS, first=True)
    lat_best = kept[0] if kept else next((s for s in ordered if s[3] == "lattice"), scored[0])
    fixed_shape = shape_fixed(lat)
    if kept:
        cands.append((kept[0][0], kept[0][1], kept[0][2], kept[0][3], True))
    if kept and not fixed_shape:
        trans, t_losses = _transplants(loss, lat, kept[0], st.matches, left // 5, stage_deadline)
        history += list(np.minimum.accumulate([history[-1]] + t_losses)[1:])
        n0, left = n0 + len(t_losses), left - len(t_losses)
        if trans:       # a candidate of its own: the window stage starts from the crisp cells (features off)
            cands.append((*trans[0], True))
    w_evals, window_loss, window_search = 0, None, 0
    if not fixed_shape:
        win = _window_stage(loss, crop_loss(loss), lat_best, w, int(0.6 * left), stage_deadline, cfg, seed,
                            network_known=network_side_known(lat), scaled=scaled_entries(lat))
        b1, w_compl, w_evals = win.budget, win.complement, win.evaluations
        history += win.history
        logger.info("layout fit: window stage from %s (%.4f): %d evals (+%d on the crop) -> %.4f%s, %.1f s into "
                    "the fit", lat_best[3], lat_best[0], w_evals, win.search_evals, b1.best_loss,
                    " (other polarity)" if w_compl != lat_best[1] else "", time.perf_counter() - t0)
        cands.append((b1.best_loss, w_compl, b1.best_params, "window", True))
        window_loss, window_search = float(b1.best_loss), win.search_evals
    if lat.cell_length_fixed:   # the mask cannot tell the cells: only layouts placed with the given length
        cands = [c for c in cands if c[3] != "database"]
        cands = cands or [(lat_best[0], lat_best[1], lat_best[2], lat_best[3], True)]
    best = min(cands, key=lambda c: c[0])
    b2 = _polish(loss, best, w, left - w_evals, stage_deadline, cfg, seed, fixed_cells(lat))
    limited = time_limited(stage_deadline)
    history += b2.history
    cands.append((b2.best_loss, best[1], b2.best_params, "polish", True))
    cands.sort(key=lambda c: c[0])
    gated = _lattice_gate(loss, lat, cands, at_most=GATE_CHECKS)
    # none keeps the lattice on a fresh realisation (a noisy target's own analysis is noisy too): the layouts
    # built on the lattice (window stage, lattice starts) rather than a database entry or a drifted polish
    on_lattice = [c for c in cands if c[3] in ("window", "lattice", "transplant")]
    cands = (gated or on_lattice or cands)[:4]
    n_val, val = 0, None
    if reserve:               # the candidate best on fresh realisations
        params, own, complement, chosen, val, n_val = _validate(loss, cands, cfg.validate)
        history += [history[-1]] * n_val
    else:
        own, complement, params, chosen = cands[0][0], cands[0][1], np.asarray(cands[0][2], np.float64), cands[0][3]
    secs = time.perf_counter() - t0
    evals = n0 + w_evals + b2.evaluations + n_val
    logger.info("PPTBF layout fit %dx%d (%s lattice, period %.1f px): loss %.4f (best start) -> %.4f, "
                "%d evals, %.1f s%s", w, h, lat.kind, lat.period or 0.0, scored[0][0], own, evals, secs,
                " (complement)" if complement else "")
    if limited:
        warn_time_limited(f"PPTBF layout fit {w}x{h}", evals, cfg)
    q = st.query
    # every evaluation set the threshold from the target's white fraction for its polarity; a vector that came
    # from the other polarity's start (window stage, polish) still carries that polarity's threshold
    params = loss.with_threshold(params, complement)
    return MaskFit(params=pp.clip_params(params), complement=bool(complement),
                   loss_query=float(st.loss_query if np.isfinite(st.loss_query) else scored[0][0]),
                   loss_final=float(own), evaluations=int(evals), seconds=secs,
                   history=[float(x) for x in np.minimum.accumulate(history)], fit_size=(w, h),
                   shift=tuple(cfg.shift), entry_id=getattr(q[0], "entry_id", None) if q else None,
                   meta={"method": "lattice", "loss": "vgg19+layout", "white_fraction": loss.white,
                         "lattice": lat.to_dict(), "validation_loss": val, "start_loss": float(scored[0][0]),
                         "start_kind": scored[0][3], "window_stage_loss": window_loss,
                         "lattice_kept": len(gated) > 0, "chosen": chosen, "time_limited": limited,
                         "screened": st.screened, "window_search_evals": window_search})
