"""Lattice analysis of a binary structure mask, and PPTBF starting points that reproduce that lattice.

A brick wall, a tiled floor or a plate grid repeats along two lattice vectors; a PPTBF reproduces such a layout
only when its tiling family, period, orientation and aspect ratio put its cells on the same lattice, and a
derivative-free search from a database neighbour rarely lands there (bricks become streaks). So the layout is
measured first and the search starts on it:

* ``analyse_lattice``: the periodic autocorrelation of the mask (one FFT); its local maxima are candidate lattice
  vectors; the basis is the pair (cells of at most a tenth of the mask) whose lattice points stand highest above
  the autocorrelation's ring mean at their radius (its isotropic decay), the smallest cell among those within
  10 % of the best (a sub-lattice scores as high, with a larger cell); the basis is refined to sub-pixel
  accuracy by least squares over the sub-pixel peaks of all lattice points within half the image. A cell of two
  courses is halved when the courses between stand almost as high (offsets that drift from course to course
  repeat exactly only every second course; ``_finer``).
  ``regularity`` is that height (0..1); ``significance`` is the same in units of the ring's standard deviation
  and decides whether there is a repeat at all (rust and blob fields reach ~2, real slate rows 2.6, brick walls
  3.4, synthetic layouts 3-6; a repeat needs 2.5, or 2.0 when its points stand a quarter of the autocorrelation
  high: a large period leaves few points to stand out). Rows run along the short lattice vector along which the
  autocorrelation stays high between lattice points (a course's mortar lines keep matching along the course);
  when the lattice points barely rise above that ridge, the cuts along the rows are random and the mask is
  ``kind`` "rows" (one vector: the row spacing across the rows). Also reported: the row offset (0 stacked, 1/2
  running bond, 1/3 thirds), the rows' orientation and the width of the thin network phase (mortar, seams).
* ``pptbf_starts``: each PPTBF tiling family has a known lattice of cell centres in domain units
  (``DOMAIN_LATTICE``, checked against renders in tests); the pixel lattice of parameters (resolution r,
  aspect a, rotation alpha) is ``M D`` with ``M = r R(-alpha) diag(a, 1)``. For every family and every small
  change of basis of the target lattice (and its index-2 super-lattices: offsets that alternate row to row),
  M is solved for and projected onto that form; families that match within a tolerance give starting vectors
  with a crisp cellular window (the layout's cells, thresholded at the target's white fraction), ordered so
  that the first cover every kind of layout (square, half and third bonds, herringbone, pavement, Pythagorean,
  random-cut rows along the courses), bricks along the courses first.
* ``compare_lattices``: period and angle errors of one lattice against another (the acceptance yardstick);
  ``compare_layouts`` the same for the lattices two parameter vectors' layouts put their cells on.
"""
from __future__ import annotations

import itertools
import logging
import math
from dataclasses import asdict, dataclass, replace

import numpy as np
from scipy import ndimage

from pptbf_db import pptbf as pp

from .errors import InputError

logger = logging.getLogger(__name__)

_I = pp.PARAM_INDEX


@dataclass
class LatticeConfig:
    """Autocorrelation peak search and acceptance thresholds."""

    min_period: float = 4.0        # shortest lattice vector (px)
    max_peaks: int = 16            # candidate vectors (strongest local maxima)
    min_peak: float = 0.05         # autocorrelation a candidate needs
    max_cell_share: float = 1.0 / 10.0   # a layout shows at least 10 cells in the mask
    min_significance: float = 2.5  # lattice points' height above the ring mean, in ring standard deviations
    regular_significance: float = 2.0   # ... enough for a repeat whose regularity reaches regular_min
    regular_min: float = 0.25      # (layout-free masks: rust 0.075; relief cuts of plaster, sand, rust below 0.15)
    rows_ratio: float = 0.5        # a 2-D lattice wins over a one-directional repeat at this share of its contrast


@dataclass
class Lattice:
    """What was measured on a mask (vectors as (dx, dy) in pixels, y down the rows)."""

    kind: str                                  # "2d", "rows" or "none"
    vectors: list[tuple[float, float]]          # reduced basis: 2 vectors ("2d"), 1 ("rows"), none
    regularity: float                           # autocorrelation at lattice points above its ring mean (0..1)
    significance: float = 0.0                   # the same in ring standard deviations (>= 2.5: a repeat)
    row_vector: tuple[float, float] | None = None   # the lattice's row direction (the basis vector along rows)
    row_spacing: float | None = None            # distance between rows (px)
    row_offset: float | None = None             # shift of the next row along the row, in row periods (0..0.5)
    orientation_deg: float | None = None        # angle of the rows to the x axis, degrees in [0, 180)
    network_width: float | None = None          # width (px) of the thin connected phase (mortar), if any
    network_is_white: bool | None = None        # True when the mask's white pixels form that network
    white_fraction: float = 0.0
    row_height: float | None = None             # rows: mean distance between network lines across the rows (px)
    cell_length: float | None = None            # rows: mean distance between the cuts along the rows (px)
    cell_length_fixed: bool = False             # rows: cell_length was measured outside the mask, whose rows show no
    #                                             cell ends (the relief's 2-D cut): the one cell aspect a fit tries

    @property
    def period(self) -> float | None:
        """The shortest lattice vector's length (px), None without a lattice."""
        return float(min(math.hypot(*v) for v in self.vectors)) if self.vectors else None

    def scaled(self, factor: float) -> "Lattice":
        """The lattice as measured on the mask resized by `factor`: vectors and lengths scaled, the rest kept."""
        def sc(x):
            return None if x is None else float(x) * factor
        return replace(self, vectors=[(a * factor, b * factor) for a, b in self.vectors],
                       row_vector=None if self.row_vector is None else
                       (self.row_vector[0] * factor, self.row_vector[1] * factor),
                       row_spacing=sc(self.row_spacing), network_width=sc(self.network_width),
                       row_height=sc(self.row_height), cell_length=sc(self.cell_length))

    def to_dict(self) -> dict:
        """JSON-able form."""
        d = asdict(self)
        d["vectors"] = [[float(a), float(b)] for a, b in self.vectors]
        d["period"] = self.period
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "Lattice":
        """Inverse of ``to_dict``."""
        d = {k: v for k, v in d.items() if k in cls.__dataclass_fields__}
        d["vectors"] = [tuple(float(x) for x in v) for v in d.get("vectors", [])]
        if d.get("row_vector") is not None:
            d["row_vector"] = tuple(float(x) for x in d["row_vector"])
        return cls(**d)


def autocorrelation(mask: np.ndarray) -> np.ndarray:
    """Periodic autocorrelation of a mask, normalised to 1 at lag 0, fftshifted (lag 0 at (h // 2, w // 2))."""
    from .inpaint import masked_autocorrelation

    x = np.asarray(mask, dtype=np.float64)
    if float(x.std()) <= 1e-6:
        raise InputError("lattice: the mask is uniform, it has no layout to analyse")
    ac, _ = masked_autocorrelation(x[..., None], np.ones(x.shape, dtype=bool))
    return np.fft.fftshift(ac)


#: bound on the integer lattice coefficients enumerated (radius / shortest vector for any usable basis)
MAX_COEFF = 512


def _sample(ac: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Bilinear samples of the shifted autocorrelation at lags pts (n, 2) as (dx, dy), wrapping."""
    h, w = ac.shape
    return ndimage.map_coordinates(ac, [pts[:, 1] + h // 2, pts[:, 0] + w // 2], order=1, mode="grid-wrap")


def _lattice_points(basis: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Integer coefficients (n, 2) and lags (n, 2) of the lattice points 0 < |p| <= radius of a 2x2 basis (rows).

    A degenerate basis (a vector under half a pixel, or a cell under one pixel: a refinement can collapse one)
    has no usable points; coefficients are bounded (|a|, |b| <= MAX_COEFF) so memory stays small."""
    short = min(np.linalg.norm(basis[0]), np.linalg.norm(basis[1]))
    area = abs(np.linalg.det(basis))
    if short < 0.5 or area < 1.0:
        return np.zeros((0, 2)), np.zeros((0, 2))
    k = int(min(40, math.ceil(radius * max(np.linalg.norm(basis[0]), np.linalg.norm(basis[1])) / area) + 1))
    k = min(MAX_COEFF, max(k, int(math.ceil(radius / short)) + 1))
    a, b = np.meshgrid(np.arange(-k, k + 1), np.arange(-k, k + 1), indexing="ij")
    c = np.stack([a.ravel(), b.ravel()], axis=1).astype(np.float64)
    c = c[(c != 0).any(axis=1)]
    p = c @ basis
    keep = np.linalg.norm(p, axis=1) <= radius
    return c[keep], p[keep]


def radial_profile(ac: np.ndarray) -> np.ndarray:
    """(2, R) mean and standard deviation of the (shifted) autocorrelation over rings of integer radius: its
    isotropic part and how much it varies around that."""
    h, w = ac.shape
    yy, xx = np.mgrid[:h, :w]
    r = np.rint(np.hypot(yy - h // 2, xx - w // 2)).astype(np.int64).ravel()
    n = np.maximum(np.bincount(r), 1)
    mean = np.bincount(r, ac.ravel()) / n
    var = np.bincount(r, ac.ravel() ** 2) / n - mean ** 2
    return np.stack([mean, np.sqrt(np.maximum(var, 0.0))])


def _heights(ac: np.ndarray, prof: np.ndarray, pts: np.ndarray, z: bool = False) -> np.ndarray:
    """Height of the autocorrelation at each lag of pts above its ring mean at the same radius; with `z`, in
    units of the ring's standard deviation (floored at 0.02: a clean synthetic layout has almost no spread)."""
    r = np.linalg.norm(pts, axis=1)
    grid = np.arange(prof.shape[1])
    d = _sample(ac, pts) - np.interp(r, grid, prof[0])
    return d / np.maximum(np.interp(r, grid, prof[1]), 0.02) if z else d


def _contrast(ac: np.ndarray, prof: np.ndarray, pts: np.ndarray, z: bool = False) -> float:
    """Mean of ``_heights`` over the lags pts."""
    return float(_heights(ac, prof, pts, z).mean())


def _score(ac: np.ndarray, prof: np.ndarray, basis: np.ndarray, radius: float, z: bool = False) -> float:
    """Contrast of the lattice points within `radius` (and at most 2.2 times the longer basis vector: a
    jittered layout decorrelates with distance) against the ring mean: a repeat stands above the isotropic
    decay of the autocorrelation at its lattice points; a smooth blob field has only that decay; a lattice
    with extra points between the true ones (a smaller cell) averages in low values."""
    radius = min(radius, 2.2 * float(max(np.linalg.norm(basis[0]), np.linalg.norm(basis[1]))))
    _, p = _lattice_points(basis, radius)
    return _contrast(ac, prof, p, z) if len(p) else -1.0


def _peaks(ac: np.ndarray, cfg: LatticeConfig) -> np.ndarray:
    """Local maxima (dx, dy) of the autocorrelation in the upper half plane, strongest first."""
    h, w = ac.shape
    yy, xx = np.mgrid[:h, :w]
    dy, dx = yy - h // 2, xx - w // 2
    r = np.hypot(dx, dy)
    ok = (r >= cfg.min_period) & (r <= 0.5 * min(h, w)) & (ac > cfg.min_peak)
    ok &= (dy > 0) | ((dy == 0) & (dx > 0))
    peaks = ok & (ac >= ndimage.maximum_filter(ac, size=3, mode="wrap"))
    order = np.argsort(-ac[peaks], kind="stable")
    return np.stack([dx[peaks], dy[peaks]], axis=1)[order].astype(np.float64)


def _reduce(basis: np.ndarray) -> np.ndarray:
    """Lagrange-Gauss reduction: the shortest basis of the same lattice."""
    a, b = basis[0].copy(), basis[1].copy()
    for _ in range(64):
        if a @ a > b @ b:
            a, b = b, a
        mu = round(float(a @ b) / float(a @ a))
        if mu == 0:
            break
        b = b - mu * a
    return np.stack([a, b])


def _subpixel(ac: np.ndarray, lag: np.ndarray, win: int = 2) -> np.ndarray:
    """The autocorrelation maximum near `lag` (within +-win px), refined by a parabola per axis."""
    h, w = ac.shape
    cx, cy = int(round(lag[0])) + w // 2, int(round(lag[1])) + h // 2
    ys = np.arange(cy - win, cy + win + 1) % h
    xs = np.arange(cx - win, cx + win + 1) % w
    patch = ac[np.ix_(ys, xs)]
    iy, ix = np.unravel_index(int(np.argmax(patch)), patch.shape)
    out = np.array([cx - win + ix - w // 2, cy - win + iy - h // 2], dtype=np.float64)
    for axis, i, n in ((0, ix, patch.shape[1]), (1, iy, patch.shape[0])):
        if 0 < i < n - 1:
            l, c, r = (patch[iy, i - 1], patch[iy, i], patch[iy, i + 1]) if axis == 0 else \
                (patch[i - 1, ix], patch[i, ix], patch[i + 1, ix])
            out[axis] += _parabola_step(l, c, r)
    return out


def _parabola_step(left: float, centre: float, right: float) -> float:
    """Sub-sample offset (-0.5..0.5) of the maximum of the parabola through three equally spaced samples."""
    den = left - 2 * centre + right
    return float(np.clip(0.5 * (left - right) / den, -0.5, 0.5)) if den < 0 else 0.0


def _refine(ac: np.ndarray, basis: np.ndarray, radius: float) -> np.ndarray:
    """Least-squares basis from the sub-pixel peaks of all lattice points within radius (weighted by height)."""
    c, p = _lattice_points(basis, radius)
    if len(p) < 2:
        return basis
    obs = np.array([_subpixel(ac, q) for q in p])
    wgt = np.clip(_sample(ac, obs), 1e-3, None)
    good = np.linalg.norm(obs - p, axis=1) <= 1.5
    if good.sum() < 2 or np.linalg.matrix_rank(c[good]) < 2:
        return basis
    sw = np.sqrt(wgt[good])[:, None]
    sol, *_ = np.linalg.lstsq(c[good] * sw, obs[good] * sw, rcond=None)
    return sol


#: a lag whose autocorrelation halfway to it reaches this share of its height at it lies on a ridge through the
#: origin: along continuous lines (which keep matching themselves), not across them
RIDGE_DIP = 0.9


#: the repeat across continuous lines is the first peak of the profile across them that reaches this share of the
#: profile's highest
ACROSS_PEAK_SHARE = 0.5


def _across_lines(ac: np.ndarray, v: np.ndarray, radius: float, min_period: float) -> np.ndarray | None:
    """The repeat across continuous lines that run along v: the first autocorrelation peak along v's normal
    (sub-pixel), or None when v is not on a ridge through the origin or the normal shows no peak. Rows of
    overlapping slates, cut from one flank of their steps, are unbroken lines: the strongest lag runs along them
    (roof_slates_02 at 512 px: (14, 0) against the rows' (0, 19.6))."""
    if _sample(ac, 0.5 * v[None])[0] < RIDGE_DIP * _sample(ac, v[None])[0]:
        return None
    # the lines' direction: the ray near v's along which the autocorrelation stays highest
    t = np.arange(math.ceil(min_period), int(radius))
    angles = math.atan2(v[1], v[0]) + np.radians(np.arange(-6.0, 6.01, 0.25))
    dirs = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    rays = _sample(ac, (t[None, :, None] * dirs[:, None, :]).reshape(-1, 2)).reshape(len(angles), len(t))
    a = float(angles[int(np.argmax(rays.mean(axis=1)))])
    n = np.array([-math.sin(a), math.cos(a)])
    prof = _sample(ac, t[:, None] * n[None])
    # a peak is at least ACROSS_PEAK_SHARE of the highest: between clean lines the profile is flat, and its
    # rounding noise (or the wrap of a period that does not divide the mask) made "peaks" there (lines 2 px wide
    # every 16 px read as rows 5.9 px apart, every 24 px as 16 px)
    peak = np.flatnonzero((prof[1:-1] >= prof[:-2]) & (prof[1:-1] > prof[2:]) &
                          (prof[1:-1] >= ACROSS_PEAK_SHARE * prof.max())) + 1
    if not len(peak) or prof[:peak[0]].min() >= RIDGE_DIP * prof[peak[0]]:
        return None
    i = int(peak[0])
    # sub-pixel along the normal only: along a ridge the maximum is anywhere
    return (t[i] + _parabola_step(prof[i - 1], prof[i], prof[i + 1])) * n


def _rows_vector(ac: np.ndarray, prof: np.ndarray, cand: np.ndarray, cfg: LatticeConfig,
                 radius: float) -> tuple[np.ndarray, float]:
    """The best one-directional repeat: the candidate whose multiples carry the highest mean autocorrelation."""
    best, score = None, -1.0
    for v in cand[: cfg.max_peaks]:
        n = min(2, int(radius // max(np.linalg.norm(v), 1e-9)))
        if n < 2:           # a repeat shows at least twice within half the mask (4 times across it)
            continue
        s = _contrast(ac, prof, v[None] * np.arange(1, n + 1)[:, None])
        if s > score * 1.1 or (s > 0.9 * score and np.linalg.norm(v) < np.linalg.norm(best)):
            best, score = v, max(s, score)
    return best, score


#: a phase is one connected network when its largest connected piece holds this share of its pixels
NETWORK_PIECE_SHARE = 0.8


def largest_piece_share(mask: np.ndarray) -> float:
    """The share of a bool mask's white pixels in its largest (4-connected) piece; 0 when empty."""
    lab, n = ndimage.label(mask)
    if n == 0:
        return 0.0
    sizes = np.bincount(lab.ravel())[1:]
    return float(sizes.max() / sizes.sum())


def _network(mask: np.ndarray) -> tuple[float | None, bool | None]:
    """Width (px) and polarity of the phase that forms one connected network (mortar); (None, None) if neither."""
    from skimage.morphology import skeletonize

    out = []
    for white in (True, False):
        m = mask if white else ~mask
        _, n_other = ndimage.label(~m)
        if largest_piece_share(m) >= NETWORK_PIECE_SHARE and n_other >= 4:
            sk = skeletonize(m)
            dist = ndimage.distance_transform_edt(m)
            width = float(2.0 * np.median(dist[sk])) if sk.any() else None
            out.append((m.mean(), width, white))
    if not out:
        return None, None
    _, width, white = min(out)          # both connected (thin lines on a field): the smaller phase is the network
    return width, white


def analyse_lattice(mask, config: LatticeConfig | None = None) -> Lattice:
    """Lattice of a binary mask (HxW): basis vectors, regularity, rows, network width (see module doc); for rows,
    also their mean height (``mean_line_spacing`` across them: rows of random heights repeat far less often)."""
    lat = _analyse(mask, config)
    if lat.kind == "rows":
        m = np.asarray(mask)
        m = m > 0.5 if m.dtype != bool else m
        white = lat.network_is_white if lat.network_is_white is not None else lat.white_fraction < 0.5
        lat.row_height = mean_line_spacing(m, lat.vectors[0], bool(white))
        v = lat.vectors[0]
        lat.cell_length = mean_line_spacing(m, (v[1], -v[0]), bool(white), through_cells=CELL_PATH_SHARE)
    return lat


def _analyse(mask, config: LatticeConfig | None) -> Lattice:
    """analyse_lattice without the rows' mean height."""
    cfg = config or LatticeConfig()
    m = np.asarray(mask)
    if m.ndim != 2 or min(m.shape) < 16:
        raise InputError(f"lattice: expected an HxW mask of at least 16x16 pixels, got shape {m.shape}")
    m = m > 0.5 if m.dtype != bool else m
    ac = autocorrelation(m)
    prof = radial_profile(ac)
    radius = 0.5 * min(m.shape) - 1.0
    cand = _peaks(ac, cfg)
    width, white = _network(m)
    base = dict(white_fraction=float(m.mean()), network_width=width, network_is_white=white)
    pairs = []
    top = cand[: cfg.max_peaks]
    for i, j in itertools.combinations(range(len(top)), 2):
        b = np.stack([top[i], top[j]])
        area = abs(np.linalg.det(b))
        if area < cfg.min_period ** 2 or area > cfg.max_cell_share * m.size:
            continue
        b = _reduce(b)
        pairs.append((_score(ac, prof, b, radius), area, b))
    best2 = None
    if pairs:
        s_max = max(p[0] for p in pairs)
        near = [p for p in pairs if p[0] >= s_max - 0.1 * abs(s_max)]
        s, _, b = min(near, key=lambda p: p[1])
        b = _reduce(_refine(ac, b, radius))
        best2 = (_score(ac, prof, b, radius), b)
    v1, s1 = _rows_vector(ac, prof, cand, cfg, radius) if len(cand) else (None, -1.0)
    z2 = _score(ac, prof, best2[1], radius, z=True) if best2 is not None else -1.0
    if best2 is not None:   # the repeat's strength is the exact lattice's; a halved cell only describes it
        best2 = (best2[0], _finer(ac, prof, best2[1], radius))
    v = _refine_rows(ac, v1, radius) if v1 is not None else None
    z1 = _rows_z(ac, prof, v) if v is not None else -1.0
    # a repeat exists when the strongest vector or the best lattice stands out; it is 2-D when the lattice's
    # points carry at least rows_ratio of the strongest vector's contrast (real walls drift from row to row)
    if best2 is not None and _stands(max(z1, z2), best2[0], cfg) and best2[0] >= cfg.rows_ratio * s1:
        return _describe_2d(ac, prof, best2[1], best2[0], max(z1, z2), base, radius)
    if v is not None:
        if _stands(z1, s1, cfg):
            across = _across_lines(ac, v, radius, cfg.min_period)
            v = v if across is None else across
            ang = math.degrees(math.atan2(v[1], v[0])) + 90.0
            return Lattice(kind="rows", vectors=[(float(v[0]), float(v[1]))], regularity=float(s1),
                           significance=float(z1), row_spacing=float(np.linalg.norm(v)),
                           orientation_deg=float(ang % 180.0), **base)
    reg = max(best2[0] if best2 else 0.0, s1, 0.0)
    return Lattice(kind="none", vectors=[], regularity=float(reg), significance=float(max(z1, z2)), **base)


#: the points a finer lattice adds (index 2) must stand this share of the coarse lattice's points' height above
#: their ring mean (and STANDING_Z ring deviations) for the finer lattice to replace it
FINER_SHARE = 0.6
#: ... at their autocorrelation peak within this share of the short lattice vector of the added point
FINER_DRIFT = 0.2


def _finer(ac: np.ndarray, prof: np.ndarray, b: np.ndarray, radius: float) -> np.ndarray:
    """b, or the lattice with a course between b's courses when those stand: a cell of two courses is halved.

    The basis is chosen by its points' mean height, and courses offset by a drifting or uneven amount repeat
    exactly only every second course: metal_plate_02's seams at 256 px (the first layer of its automatic
    decomposition at 512 px, tests/data/structure_masks/metal_plate_courses.png: plates 43 px wide, courses 62 px
    apart, each offset by about half a plate) read (43, 0), (0, 125) with points at 0.47-0.59, the courses
    between at (+-21.8, 61.7) 0.44-0.46 high (3.0 ring deviations); with thinner seams the offsets are 0.43 and
    0.57 of a plate, peaks at (+-24.5, 61.5), 0.32 high against 0.48 (3.0). The plates came back as
    pavements of two-course cells cut into odd shapes. When the added coset's four points nearest the origin
    (b_long / 2 or (b_long + b_short) / 2 and their neighbours), each taken at its autocorrelation peak within
    FINER_DRIFT of the short vector, stand STANDING_Z ring deviations and FINER_SHARE of b's short points' mean
    height above their ring means, the halved cell is returned, its course offset the exact half step between
    the peaks (a running bond: the nearest layout a single cell can tile). Only a cell at least
    POINT_TEST_ELONGATION times longer across than along (two courses): a herringbone's half vectors match its
    rotated bricks almost as well as its lattice points (bench target 25, a 3:1 herringbone of cells 28 x 37 px:
    0.36 at its half vector against 0.35 at its points) and its cell is not elongated."""
    lengths = np.linalg.norm(b, axis=1)
    if lengths.max() < POINT_TEST_ELONGATION * lengths.min():
        return b
    short, long_ = (b[0], b[1]) if lengths[0] <= lengths[1] else (b[1], b[0])
    coarse = float(_heights(ac, prof, np.stack([b[0], b[1], b[0] + b[1], b[0] - b[1]])).mean())
    win = max(2, int(round(FINER_DRIFT * float(np.linalg.norm(short)))))
    best = None
    for h in (0.5 * long_, 0.5 * (long_ + short)):
        coset = h + np.array([[0, 0], [-1, 0], [0, -1], [-1, -1]], np.float64) @ np.stack([short, long_])
        peaks = np.array([_subpixel(ac, q, win) for q in coset])
        height = _heights(ac, prof, peaks)
        if _heights(ac, prof, peaks, z=True).min() >= STANDING_Z and height.min() >= FINER_SHARE * coarse:
            if best is None or float(height.mean()) > best[0]:
                best = (float(height.mean()), h)
    return b if best is None else _reduce(np.stack([short, best[1]]))


def _stands(z: float, regularity: float, cfg: LatticeConfig) -> bool:
    """Whether a repeat stands out: its points ``min_significance`` ring deviations above the ring mean, or
    ``regular_significance`` when its points stand ``regular_min`` of the autocorrelation high. A large period
    puts few points in the analysed disc, each on a ring of few pixels, so its significance is low however
    regular it is (a 3:1 herringbone of 50 px cells at 256 px: 2.24, regularity 0.32)."""
    return z >= cfg.min_significance or (z >= cfg.regular_significance and regularity >= cfg.regular_min)


def _rows_z(ac: np.ndarray, prof: np.ndarray, v: np.ndarray) -> float:
    """The autocorrelation's height at row vector v and twice it, in ring standard deviations (a repeat of rows)."""
    return _contrast(ac, prof, v[None] * np.arange(1, 3)[:, None], z=True)


#: ``rows_match`` looks for a mask's row repeat within this share of a target's row spacing and this many
#: degrees of its direction
ROWS_MATCH_LENGTH, ROWS_MATCH_ANGLE = 0.25, 10.0


def rows_match(mask: np.ndarray, lat: Lattice) -> tuple[float, float, float]:
    """(row spacing in px, angle error in degrees, strength) of `mask`'s strongest rows near those of `lat`
    (kind "rows"): the spacing (within ROWS_MATCH_LENGTH of the target's) and direction (within
    ROWS_MATCH_ANGLE) whose lines of lags (the row vector plus a span of one spacing either way along the rows,
    and twice that) carry the highest autocorrelation above its ring mean, in ring standard deviations
    (a ridge, not a peak: rows with random cuts repeat across the rows only). How a
    render is checked against a target of rows: its own analysis reports its strongest repeat, which for clean
    bricks with random row offsets is the bricks' length along the rows (a hand-built slate roof with the
    target's 9.8 px rows read as 12.9 px rows at 90 degrees), not the rows the target has."""
    v = np.asarray(lat.vectors[0], dtype=np.float64)
    n, phi0 = float(np.linalg.norm(v)), math.atan2(v[1], v[0])
    ac = autocorrelation(mask)
    prof = radial_profile(ac)
    lengths = n * np.linspace(1.0 - ROWS_MATCH_LENGTH, 1.0 + ROWS_MATCH_LENGTH, 41)
    angles = np.radians(np.linspace(-ROWS_MATCH_ANGLE, ROWS_MATCH_ANGLE, 41))
    ll, aa = (g.ravel() for g in np.meshgrid(lengths, angles, indexing="ij"))
    across = np.stack([np.cos(phi0 + aa), np.sin(phi0 + aa)], axis=-1)
    along = np.stack([-across[:, 1], across[:, 0]], axis=-1)
    span = np.linspace(-1.0, 1.0, 9)
    pts = np.concatenate([(m * ll)[:, None, None] * (across[:, None, :] + span[None, :, None] * along[:, None, :] / m)
                          for m in (1.0, 2.0)], axis=1).reshape(-1, 2)
    z = _heights(ac, prof, pts, z=True).reshape(len(ll), -1).mean(axis=1)
    k = int(np.argmax(z))
    return float(ll[k]), abs(math.degrees(float(aa[k]))), float(z[k])


#: a mask has a target's rows when ``rows_match`` finds them at least this strongly (a target's own rows:
#: 1.4-1.7 on synthetic rows with random cuts, 1.36 on a real slate roof; white noise and blobs: under 0.1)
ROWS_MIN_Z = 1.0


def compare_rows(target: Lattice, mask: np.ndarray) -> tuple[float, float]:
    """(period error, angle error in degrees) of `mask`'s rows against those of `target` (kind "rows"), by
    ``rows_match``; inf when the mask does not repeat there (strength under ROWS_MIN_Z)."""
    spacing, ang, z = rows_match(mask, target)
    n = float(np.linalg.norm(target.vectors[0]))
    return (abs(spacing - n) / n, ang) if z >= ROWS_MIN_Z else (math.inf, math.inf)


#: at most this many paths of at most this many pixels in ``mean_line_spacing`` (a few MB at any mask size)
MAX_PATHS, MAX_PATH_LENGTH = 1024, 4096


#: ``mean_line_spacing`` along the rows keeps this share of its paths, those least in the network: the paths
#: through the cells cross only their cuts (paths along a course's mortar line, or grazing the rounded corners of
#: the cells, cross none or many); measured cell lengths 40.6 and 20.3 px for 40.6 and 20.3 px ashlar and random
#: bricks (all paths: 35.8, 19.4)
CELL_PATH_SHARE = 0.25


def mean_line_spacing(mask: np.ndarray, direction, network_is_white: bool, step: int = 8,
                      through_cells: float = 1.0) -> float | None:
    """Mean distance (px) between the network lines that straight paths along `direction` cross (paths from
    every `step`-th pixel, 4x the mask's size long, wrapping): the length walked over the number of entries
    into the network. Across rows it is the mean row height, which the autocorrelation cannot give when rows
    have random heights (an ashlar of 35 px rows: 36.5 px here against a 114 px repeat in the autocorrelation;
    random bricks of 15.25 px rows: 15.9 px). With `through_cells` < 1, only that share of the paths, those
    least in the network (along the rows: the mean cell length). None when no line is crossed."""
    h, w = mask.shape
    u = np.asarray(direction, dtype=np.float64)
    u = u / max(float(np.linalg.norm(u)), 1e-12)
    net = mask if network_is_white else ~mask
    step = max(int(step), int(math.ceil(math.sqrt(h * w / MAX_PATHS))))     # bounded memory on large masks
    t = np.arange(min(4 * max(h, w), MAX_PATH_LENGTH), dtype=np.float64)
    ys, xs = np.meshgrid(np.arange(0, h, step), np.arange(0, w, step), indexing="ij")
    # floor before the wrap: a float modulo of a tiny negative step rounds up to h itself
    y = np.floor(ys.ravel()[:, None] + t[None, :] * u[1]).astype(np.int64) % h
    x = np.floor(xs.ravel()[:, None] + t[None, :] * u[0]).astype(np.int64) % w
    s = net[y, x]
    if through_cells < 1.0:
        share = s.mean(axis=1)
        s = s[share <= np.quantile(share, through_cells)]
    entries = int((s[:, 1:] & ~s[:, :-1]).sum())
    return float(s.size / entries) if entries else None


#: the rows' own repeat and their mean height differ by more than this when the rows have random heights
ROW_HEIGHT_GAP = 0.15


def _refine_rows(ac: np.ndarray, v: np.ndarray, radius: float) -> np.ndarray:
    """Sub-pixel row vector from the peaks at its multiples (least squares through the origin)."""
    n = int(radius // max(np.linalg.norm(v), 1e-9))
    ks = np.arange(1, n + 1, dtype=np.float64)
    obs = np.array([_subpixel(ac, v * k) for k in ks])
    good = np.linalg.norm(obs - v[None] * ks[:, None], axis=1) <= 1.5
    if not good.any():
        return v
    return (obs[good] * ks[good, None]).sum(axis=0) / (ks[good] ** 2).sum()


def _describe_2d(ac: np.ndarray, prof: np.ndarray, b: np.ndarray, score: float, z: float, base: dict,
                 radius: float) -> Lattice:
    """Rows, row offset and orientation of a reduced 2-D basis: rows run along the short lattice vector (basis,
    sum or difference) along which the autocorrelation stays highest between lattice points (continuous mortar
    lines of a brick course keep matching along the course, not across it). Rows only when the cuts along the
    rows are random (``_cuts_random``) or a short lattice point does not stand out (``_points_stand``)."""
    area = abs(float(np.linalg.det(b)))
    best = None
    for c in ((1, 0), (0, 1), (1, 1), (1, -1)):
        v = c[0] * b[0] + c[1] * b[1]
        ridge = float(_sample(ac, np.outer([0.25, 0.5, 0.75], v)).mean())
        if best is None or ridge > best[0] + 1e-9:
            best = (ridge, v)
    row = best[1]
    spacing = area / float(np.linalg.norm(row))
    other = b[1] if abs(float(row[0] * b[1][1] - row[1] * b[1][0])) > 1e-6 else b[0]
    t = float(other @ row) / float(row @ row)
    off = abs(t - round(t))
    ang = math.degrees(math.atan2(row[1], row[0])) % 180.0
    random_cuts = _cuts_random(ac, b, row, radius) and _point_z(ac, prof, b) < STANDING_Z
    if random_cuts or not _points_stand(ac, prof, b):
        normal = np.array([-row[1], row[0]]) / float(np.linalg.norm(row)) * spacing
        normal = normal if normal[1] > 0 or (normal[1] == 0 and normal[0] > 0) else -normal
        return Lattice(kind="rows", vectors=[(float(normal[0]), float(normal[1]))], regularity=float(score),
                       significance=float(z), row_vector=(float(row[0]), float(row[1])), row_spacing=float(spacing),
                       orientation_deg=float(ang), **base)
    return Lattice(kind="2d", vectors=[(float(b[0][0]), float(b[0][1])), (float(b[1][0]), float(b[1][1]))],
                   regularity=float(score), significance=float(z), row_vector=(float(row[0]), float(row[1])),
                   row_spacing=float(spacing), row_offset=float(off), orientation_deg=float(ang), **base)


#: every short point of a 2-D lattice (the basis vectors, their sum and difference) stands at least this many ring
#: standard deviations above its ring mean: rows of random heights (ashlars) repeat along the rows, and the lags
#: across them that happen to match in one draw make a lattice whose other points are not there (bench targets
#: 4 and 18: 0.3 and 0.5 at the sum of the basis, which a fresh draw of the same parameters does not repeat;
#: regular layouts of the bench and the real walls, roofs and plates: 1.3 or more)
POINT_Z = 1.0


#: the short-point test applies to bases whose long vector is at least this many times the short one (the chance
#: match of an ashlar's heights lies a few rows away; a noisy colour split of a brick wall has both vectors
#: about one brick long and weak points that are still its lattice)
POINT_TEST_ELONGATION = 2.0


#: a lattice whose every short point stands this many ring deviations above its ring mean is 2-D even where the
#: autocorrelation half a period along its rows is as high as at its points (``_cuts_random``): the zigzag mortar
#: of a 3:1 herringbone keeps matching along its rows (bench target 25: points at 3.5, its random-cut reading at
#: 0.08 of their height), while courses of random cuts and ashlars have weak points (bench 1.8 at most; the real
#: roof 1.2, castle 1.4-1.6)
STANDING_Z = 2.5


def _point_z(ac: np.ndarray, prof: np.ndarray, b: np.ndarray) -> float:
    """The lowest of the reduced basis b's short lattice points (basis, sum, difference), in ring deviations."""
    pts = np.stack([b[0], b[1], b[0] + b[1], b[0] - b[1]])
    return float(_heights(ac, prof, pts, z=True).min())


def _points_stand(ac: np.ndarray, prof: np.ndarray, b: np.ndarray) -> bool:
    """Every short lattice point of the reduced basis b stands POINT_Z ring deviations above its ring mean (or
    the basis is not elongated enough to be a chance match across rows: POINT_TEST_ELONGATION)."""
    lengths = np.linalg.norm(b, axis=1)
    if lengths.max() < POINT_TEST_ELONGATION * lengths.min():
        return True
    return _point_z(ac, prof, b) >= POINT_Z


#: a 2-D lattice whose points stand less than this share of their height above the row ridge is rows only
RIDGE_SHARE = 0.2


def _cuts_random(ac: np.ndarray, b: np.ndarray, row: np.ndarray, radius: float) -> bool:
    """True when the lattice's points barely rise above the ridge of their rows (the autocorrelation half a
    period along the row): courses repeat but the cuts along them do not (random brick lengths)."""
    _, p = _lattice_points(b, min(radius, 2.2 * float(max(np.linalg.norm(b[0]), np.linalg.norm(b[1])))))
    if not len(p):
        return False
    at, mid = _sample(ac, p), _sample(ac, p + 0.5 * row[None])
    return float((at - mid).mean()) < RIDGE_SHARE * max(float(np.abs(at).mean()), 1e-6)


# --------------------------------------------------------------------------------------------------------------
# PPTBF starting points
# --------------------------------------------------------------------------------------------------------------

#: translation lattices of each tiling family's layout in domain units (rows: basis vectors (x, y)); a
#: family may list alternatives (the 3:1 herringbones show different near-lattices at different aspect ratios).
#: Families 6-9 (random cuts along rows) repeat along their rows only. Checked against renders in tests.
Basis = tuple[tuple[float, float], tuple[float, float]]
DOMAIN_LATTICE: dict[int, tuple[Basis, ...]] = {}
#: how many of a family's first DOMAIN_LATTICE entries are its own (near-)lattices, matched without the
#: ALTERNATIVE_PENALTY of the later ones (1 unless listed)
NEAR_LATTICES: dict[int, int] = {}
#: families with a lattice of rows only (random cuts along each row): row spacing 1 domain unit along y
ROW_FAMILIES = (6, 7, 8, 9)
#: the row families whose rows keep one height (random bricks; the ashlars 6-7 cut rows at random heights too, so
#: they cannot sit on a 2-D lattice: on the castle's wall an ashlar start won by Gram statistics and lost the
#: courses)
FIXED_ROW_FAMILIES = (8, 9)


def _fill_domain_lattices() -> None:
    """Square grids, half and third bonds, herringbones, Pythagorean and pavement layouts (measured on renders
    with aspect ratios 0.8-1.3, written here; tests render each and compare)."""
    square = ((1.0, 0.0), (0.0, 1.0))
    DOMAIN_LATTICE.update({t: (square,) for t in (0, 1, 16, 17)})   # relaxed 2-3 are irregular
    # big and small squares repeat along (b, a), (-a, b) with (a, b) = (0.4, 0.2) (measured: the mirror image,
    # ((0.4, 0.2), (-0.2, 0.4)), is another lattice that no render has); the unit square repeats too
    pythagorean = ((0.2, 0.4), (-0.4, 0.2))
    DOMAIN_LATTICE.update({t: (pythagorean, square) for t in (14, 15)})
    herring2 = ((0.25, 0.25), (-0.5, 0.5))
    # the 2:1 herringbones (renders, aspects 0.6-2.5, periods 30-48 px) mostly show their exact lattice; at aspect
    # 2.5 and 48 px (and on bench target 8, split, aspect 1.79, 50 px) the index-2 near-lattice that adds half of
    # (-0.5, 0.5): both are the family's own (NEAR_LATTICES). The split one shows the square of its 0.25 pieces at
    # aspects 0.6-1.3, which a square grid holds as well: an alternative (a weaker match)
    herring2_half = ((0.25, 0.25), (0.0, 0.5))
    # the 3:1 herringbones: renders show either their exact lattice ((4/3, 1/3), (1/3, 4/3)) or one of three
    # near-lattices of a third of its cell, the index-3 sub-lattices of ((1/6, 1/6), (1/2, -1/2)) that hold
    # (1/2, 1/2), which one depending on aspect, period and rotation (at aspect 0.70, period 66 px: (-2/3, 1/3)
    # at rotation 0, (-5/6, 1/6) at 1.945, the exact one on another draw); all four are the family's own
    # (NEAR_LATTICES); at aspect 1.77 (bench target 25) one of the two index-2 sub-lattices that hold (1/3, 1/3)
    # and not (1/2, 1/2) shows instead, which one changing with a 0.1 % change of the layout: both are the
    # family's own too; the two coarser ones are alternatives
    s = 1.0 / 6.0
    herring3 = (((0.5, -0.5), (0.5, 0.5)), ((-3 * s, -3 * s), (4 * s, -2 * s)), ((3 * s, 3 * s), (2 * s, -4 * s)),
                ((8 * s, 2 * s), (2 * s, 8 * s)), ((2 * s, 2 * s), (0.5, -0.5)),
                ((-2.0 / 3.0, 1.0 / 3.0), (0.0, 1.0)), ((s, s), (0.5, -0.5)))
    DOMAIN_LATTICE.update({
        4: (((1.0, 0.0), (0.5, 1.0)),), 5: (((1.0, 0.0), (1.0 / 3.0, 1.0)),),
        10: (herring2, herring2_half), 11: (herring2, herring2_half, ((0.25, 0.0), (0.0, 0.25))),
        12: herring3, 13: herring3,
    })
    NEAR_LATTICES.update({10: 2, 11: 2, 12: 5, 13: 5})


_fill_domain_lattices()


def domain_period(tiling: int) -> float:
    """Length of the shortest cell-to-cell vector of a family's (first) lattice in domain units (1: rows)."""
    alts = DOMAIN_LATTICE.get(int(tiling))
    if not alts:
        return 1.0
    return float(min(math.hypot(*alts[0][0]), math.hypot(*alts[0][1])))


#: crisp cellular-window template (the layout's cells, no features): entries set on top of a base vector
CELL_TEMPLATE: dict[str, float] = {
    "jitter": 0.0, "distortion_base": 0.0, "distortion_amplitude": 0.0, "distortion_frequency": 0.0,
    "window_shape": 1, "window_arity": 4.0, "window_larp": 1.0, "window_norm": 2.0, "window_smoothness": 0.0,
    "window_blend": 1.0, "window_sigma": 4.0, "feature_mixture": 0, "feature_norm": 2.0,
    "feature_correlation": 0.0, "feature_aniso": 0.0, "feature_kernel_min": 1, "feature_kernel_max": 1,
    "feature_sigcos": 1.0, "feature_sigcosvar": 0.0, "feature_frequency": 0, "feature_phase_shift": 0.0,
    "feature_thickness": 0.1, "feature_curvature": 0.0, "feature_orientation": 0.0,
}


@dataclass
class LatticeMatch:
    """PPTBF layout parameters that put a tiling family's cells on the target lattice."""

    tiling: int
    resolution: float
    aspect: float
    rotation: float           # in the parameter's units (alpha / pi, in [0, 2))
    error: float              # relative error of the matched lattice (0 = exact)
    supercell: bool = False   # the target lattice is an index-2 super-lattice of the family's (a weaker match)


def _unimodular(k: int = 2) -> list[np.ndarray]:
    """Integer 2x2 matrices with entries in -k..k and determinant +-1."""
    out = []
    for a, b, c, d in itertools.product(range(-k, k + 1), repeat=4):
        if abs(a * d - b * c) == 1:
            out.append(np.array([[a, b], [c, d]], dtype=np.float64))
    return out


_UNIMODULAR = _unimodular(2)


def _layout_matrix(r: float, a: float, alpha: float) -> np.ndarray:
    """M = r R(-alpha) diag(a, 1): the layout (resolution r, aspect a, rotation alpha in radians) as the map from
    domain units to pixels (columns: the images of the domain axes)."""
    ca, sa = math.cos(alpha), math.sin(alpha)
    return np.array([[a * r * ca, r * sa], [-a * r * sa, r * ca]])


def _as_layout(M: np.ndarray) -> tuple[float, float, float]:
    """Closest (resolution, aspect, alpha) to a 2x2 map M (columns: images of the domain axes) of the form
    r R(-alpha) diag(a, 1): alpha from the best rotation fit, then the column lengths along it."""
    # R(-alpha) = [[c, s], [-s, c]]; columns of R(-alpha) diag(A, r) are A (c, -s) and r (s, c)
    m1, m2 = M[:, 0], M[:, 1]
    # rotation angle that best aligns (m1/|m1|, m2/|m2|) with ((c, -s), (s, c))
    u1, u2 = m1 / np.linalg.norm(m1), m2 / np.linalg.norm(m2)
    c = u1[0] + u2[1]
    s = -u1[1] + u2[0]
    alpha = math.atan2(s, c)
    ca, sa = math.cos(alpha), math.sin(alpha)
    A = float(m1 @ np.array([ca, -sa]))
    r = float(m2 @ np.array([sa, ca]))
    return r, A / r if r > 0 else -1.0, alpha


#: added to the error of a family's later lattice alternatives (the first is the family's own layout)
ALTERNATIVE_PENALTY = 0.01
#: pseudo error of row-family layouts fitted to a 2-D lattice (rows with random cuts only share its rows)
ROW_MATCH_ERROR = 0.05


def _row_layouts(lat: Lattice) -> list[LatticeMatch]:
    """Random-cut row families along the rows of a 2-D lattice: spacing = row spacing, aspect = the lattice's
    period along the row over the spacing (domain x runs along the rows: (cos a, -sin a) = row direction)."""
    if lat.row_vector is None or not lat.row_spacing:
        return []
    u = np.array(lat.row_vector, dtype=np.float64)
    alpha = math.atan2(-u[1], u[0])
    aspect = float(np.linalg.norm(u)) / lat.row_spacing
    return [LatticeMatch(t, lat.row_spacing, aspect, (alpha / math.pi) % 2.0, ROW_MATCH_ERROR)
            for t in FIXED_ROW_FAMILIES]


#: the family lattice itself and its index-2 super-lattices: a measured lattice can be one of those (a layout whose
#: offset alternates from row to row repeats every second row; 2:1 herringbones at some aspect ratios)
SUPERCELLS = (np.eye(2), np.diag([2.0, 1.0]), np.diag([1.0, 2.0]), np.array([[1.0, 1.0], [-1.0, 1.0]]))


def _layouts_for(T: np.ndarray, Dm: np.ndarray, tiling: int, max_error: float, width: int,
                 supercell: bool = False) -> list[LatticeMatch]:
    """Layouts (r, a, alpha) with r R(-alpha) diag(a, 1) Dm U = T for small unimodular U, within max_error."""
    out = []
    tn = float(np.linalg.norm(T))
    for U in _UNIMODULAR:
        M = T @ U @ np.linalg.inv(Dm)
        r, a, alpha = _as_layout(M)
        if r <= 1.0 or a <= 0.05 or a > 10.0 or r * max(a, 1.0) > 4 * width:
            continue
        Mf = _layout_matrix(r, a, alpha)
        err = float(np.linalg.norm(Mf @ Dm @ np.linalg.inv(U) - T)) / tn
        if err <= max_error:
            out.append(LatticeMatch(tiling, r, a, (alpha / math.pi) % 2.0, err, supercell))
    return out


#: cell aspects tried along rows (a one-directional repeat does not fix the cells' length; the screening of
#: workers.layout_fit picks among them)
ROW_ASPECTS = (1.0, 1.5, 2.0, 3.0, 0.75, 0.5)


#: families whose layout turned by 180 degrees is another layout on the same lattice (the 4x4 pavements: Gram
#: distance of the half-turned render 1.1-6x that of the render itself over 4 draws each; herringbone 13:
#: 1.2-1.5x). match_tilings returns one turn of each layout (the lattice is the same); ``half_turn`` gives the
#: other, which a fit must try too for these families
HALF_TURN_CHIRAL = frozenset({13, 16, 17})


def match_tilings(lat: Lattice, max_error: float = 0.06, width: int = 256) -> list[LatticeMatch]:
    """Tiling families and layouts whose cell lattice equals the target's within `max_error` (relative), best
    first, one per (family, resolution/aspect/rotation) found."""
    if lat.kind == "none":
        return []
    out: list[LatticeMatch] = []
    if lat.kind == "rows":
        v = np.array(lat.vectors[0])
        alpha = math.atan2(v[0], v[1])            # domain y axis (rows stacked along it) -> v
        r = float(np.linalg.norm(v))
        if lat.cell_length_fixed and lat.cell_length:
            aspects: tuple = ()                    # the cells' length is known: no other aspect
        elif lat.row_vector is None:
            aspects = ROW_ASPECTS
        else:
            aspects = (float(np.linalg.norm(lat.row_vector)) / r,) + ROW_ASPECTS
        h = lat.row_height
        if h and abs(h - r) > ROW_HEIGHT_GAP * r:      # rows of random heights: the ashlars at the mean height
            own = (lat.cell_length / h,) if lat.cell_length else ()    # the measured cells first
            out += [LatticeMatch(t, h, aspect, (alpha / math.pi) % 2.0, 0.0) for aspect in own + aspects
                    for t in ROW_FAMILIES if t not in FIXED_ROW_FAMILIES]
        if lat.cell_length:
            aspects = (lat.cell_length / r,) + aspects
        for aspect in aspects:
            for t in ROW_FAMILIES + (4, 0):
                out.append(LatticeMatch(t, r, aspect, (alpha / math.pi) % 2.0, 0.0))
        return out
    T = np.array(lat.vectors, dtype=np.float64).T                 # columns: target basis (pixels)
    out += _row_layouts(lat)
    for t, alts in DOMAIN_LATTICE.items():
        for j, D in enumerate(alts):
            for k, S in enumerate(SUPERCELLS):
                found = _layouts_for(T, np.array(D, dtype=np.float64).T @ S, t, max_error, width, k > 0)
                pen = ALTERNATIVE_PENALTY * max(0, j + 1 - NEAR_LATTICES.get(t, 1))
                out += [replace(m, error=m.error + pen) for m in found]
    out = [_integer_period(m) for m in out]
    out.sort(key=lambda m: (m.supercell, round(m.error, 3), not _plausible(m), _misalignment(m, lat),
                            m.aspect + 1.0 / m.aspect))
    uniq: list[LatticeMatch] = []
    for m in out:   # the same layout reached through several bases: keep one
        if not any(u.tiling == m.tiling and abs(u.resolution - m.resolution) < 0.02 * m.resolution
                   and abs(u.aspect - m.aspect) < 0.02 * m.aspect
                   and min(abs(u.rotation - m.rotation) % 1.0, 1.0 - abs(u.rotation - m.rotation) % 1.0) < 0.01
                   for u in uniq):
            uniq.append(m)
    return _round_robin(uniq)


#: families whose layout turned by 90 degrees, with the aspect ratio inverted, is the same layout and is written
#: the way round of ``_integer_period``: the square grid. Its split sibling (1) is symmetric too but is left as
#: matched: on the real metal plate seams (a 42.7 x 122.8 px lattice) its 123 px form (rounding 0.16 % against
#: 0.56 %) led the fit to plates twice the input's height, VGG-19 Gram 0.95x the hand-built's against 0.76x
QUARTER_TURN_SYMMETRIC = frozenset({0})


def _rounding(period: float) -> float:
    """Relative error of a period written as a whole number of pixels (``layout_params``)."""
    return abs(period - max(2, round(period))) / period


def _integer_period(m: LatticeMatch) -> LatticeMatch:
    """A square grid's match (QUARTER_TURN_SYMMETRIC) written the way round whose resolution is nearest a whole
    number of pixels: cells r x a*r turned by 90 degrees are cells a*r x r (resolution a*r, aspect 1/a, rotation
    + 1/2), and the period is written as whole pixels (``layout_params``) while the other side stays exact. On
    bench target 0's 35.0 x 28.2 px grid, resolution 28 is 0.7 % short, which over the mask's nine periods moves
    the cells by a quarter of one: VGG-19 Gram + layout loss 0.019 against 0.013 at resolution 35, same cell shape."""
    if m.tiling not in QUARTER_TURN_SYMMETRIC or _rounding(m.resolution * m.aspect) >= _rounding(m.resolution):
        return m
    return replace(m, resolution=m.resolution * m.aspect, aspect=1.0 / m.aspect, rotation=(m.rotation + 0.5) % 2.0)


#: cells stretched beyond this aspect ratio (either way) rank after equally good matches: the more near-lattices
#: a family lists, the more layouts fit a measured lattice by stretching its cells (a 3:1 herringbone at aspect
#: 0.70 is matched equally well by one at 4.48, 13:1 sticks, which no brick or tile layout has)
PLAUSIBLE_ASPECT = 4.0


def _plausible(m: LatticeMatch) -> bool:
    """The match's cells are within PLAUSIBLE_ASPECT of square."""
    return 1.0 / PLAUSIBLE_ASPECT <= m.aspect <= PLAUSIBLE_ASPECT


def _misalignment(m: LatticeMatch, lat: Lattice) -> float:
    """Angle (radians, 0..pi/2) between a layout's rows (domain x axis) and the lattice's row direction: among
    equally good layouts, bricks lie along the courses."""
    if lat.row_vector is None:
        return 0.0
    a = math.pi * m.rotation
    d = abs(math.atan2(-math.sin(a), math.cos(a)) - math.atan2(lat.row_vector[1], lat.row_vector[0])) % math.pi
    return min(d, math.pi - d)


def _round_robin(matches: list[LatticeMatch], per_round: int = 2) -> list[LatticeMatch]:
    """Matches reordered so that the first ones cover different kinds of layout (TILING_GROUPS), `per_round`
    of each kind at a time: a lattice that a square grid matches is often matched by a half bond, a
    herringbone... and the same lattice by a layout turned by 90 degrees; the loss must see each."""
    groups: dict[str, list[LatticeMatch]] = {g: [] for g in GROUP_ORDER}
    for m in matches:
        groups[TILING_GROUPS[m.tiling]].append(m)
    out: list[LatticeMatch] = []
    queues = sorted((q for q in groups.values() if q),
                    key=lambda q: (q[0].supercell, round(q[0].error, 3), not _plausible(q[0])))
    while any(queues):
        for q in queues:
            out += q[:per_round]
            del q[:per_round]
    return out


#: the crisp template with straight borders: 2^6 = 64 sectors put a vertex of the cell's border polygon every
#: 5.6 degrees, so a rectangular cell stays a rectangle at any cut. The template's 16 sectors (arity 4) cut the
#: corners with chords: octagons with bowed sides (metal_plate_02's plates came back as barrels). A mask fit
#: prefers the rounder cells (the decomposition's masks are ragged: started from 64-sector cells, the README
#: roof's fit left the network for white cell centres, validation loss 1.05, where from 16 it kept it, 0.96), the
#: material the straight ones (``recompose.choose_cells``), so the fit starts from CELL_TEMPLATE and the
#: material is offered STRAIGHT_CELLS.
STRAIGHT_CELLS: dict[str, float] = {**CELL_TEMPLATE, "window_arity": 6.0}


def template_cells(params, template: dict[str, float] = CELL_TEMPLATE) -> np.ndarray:
    """``params`` (a 29-vector) with the crisp cell template's entries (``CELL_TEMPLATE``, or ``STRAIGHT_CELLS``):
    the same layout and threshold, cells with no features, jitter or distortion."""
    p = np.array(params, dtype=np.float64)
    for name, v in template.items():
        p[_I[name]] = v
    return p


def layout_params(m: LatticeMatch, white_fraction: float, larp: float = 1.0,
                  base: np.ndarray | None = None) -> np.ndarray:
    """A 29-vector with the match's layout and the crisp cell template (threshold = white fraction)."""
    p = template_cells(np.zeros(pp.N_PARAMS) if base is None else base)
    p[_I["threshold"]] = white_fraction
    p[_I["tiling"]] = m.tiling
    res = max(2, int(round(m.resolution)))      # the period is an integer number of pixels (decode truncates)
    p[_I["resolution"]] = res + 0.25
    p[_I["aspect_ratio"]] = m.aspect * m.resolution / res
    p[_I["rotation"]] = m.rotation
    p[_I["window_larp"]] = larp
    return pp.clip_params(p)


#: each family with cells split at random (probability 0.5) and its unsplit sibling: the same placement of cells
SPLIT_SIBLING: dict[int, int] = {a: b for x, y in ((0, 1), (6, 7), (8, 9), (10, 11), (12, 13), (14, 15), (16, 17))
                                 for a, b in ((x, y), (y, x))}
#: the families that split their cells at random (the second of each pair above)
SPLIT_FAMILIES = frozenset({1, 7, 9, 11, 13, 15, 17})


def split_sibling(params: np.ndarray) -> np.ndarray | None:
    """The vector with its tiling's split (or unsplit) sibling (SPLIT_SIBLING), None when it has none."""
    t = SPLIT_SIBLING.get(int(params[_I["tiling"]]))
    if t is None:
        return None
    out = np.array(params, dtype=np.float64)
    out[_I["tiling"]] = t
    return out


def half_turn(params: np.ndarray) -> np.ndarray | None:
    """The vector turned by 180 degrees when its tiling is in HALF_TURN_CHIRAL (a different layout on the same
    lattice), else None (the same layout)."""
    if int(params[_I["tiling"]]) not in HALF_TURN_CHIRAL:
        return None
    out = np.array(params, dtype=np.float64)
    out[_I["rotation"]] = (out[_I["rotation"]] + 1.0) % 2.0
    return out


def pptbf_starts(lat: Lattice, width: int, max_matches: int = 16) -> list[np.ndarray]:
    """Starting vectors for a mask `width` px wide: the best lattice matches with the crisp cell template."""
    return [layout_params(m, lat.white_fraction) for m in match_tilings(lat, width=width)[:max_matches]]


# --------------------------------------------------------------------------------------------------------------
# Comparing layouts
# --------------------------------------------------------------------------------------------------------------

#: tiling families that make the same kind of layout (a fit in the same group has the target's family)
TILING_GROUPS: dict[int, str] = {0: "square", 1: "square", 2: "relaxed", 3: "relaxed", 4: "half-bond",
                                 5: "third-bond", 6: "rows", 7: "rows", 8: "rows", 9: "rows",
                                 10: "herringbone", 11: "herringbone", 12: "herringbone", 13: "herringbone",
                                 14: "pythagorean", 15: "pythagorean", 16: "pavement", 17: "pavement"}


#: preference among layout kinds that match a lattice equally well (starts are tried in this order)
GROUP_ORDER = ("square", "half-bond", "third-bond", "herringbone", "pavement", "pythagorean", "rows", "relaxed")


def same_family(a: int, b: int) -> bool:
    """Tilings a and b make the same kind of layout (TILING_GROUPS)."""
    return TILING_GROUPS[int(a)] == TILING_GROUPS[int(b)]


def _short_vectors(lat: Lattice) -> np.ndarray:
    """The lattice's short vectors (basis, their sum and difference, and negatives), (n, 2)."""
    v = np.array(lat.vectors, dtype=np.float64)
    if len(v) == 2:
        v = _reduce(v)
        v = np.concatenate([v, [v[0] + v[1], v[0] - v[1]]])
    return np.concatenate([v, -v])


def layout_map(params) -> np.ndarray:
    """The 2x2 map M = r R(-alpha) diag(a, 1) of a parameter vector: domain units -> pixels (at the width the
    vector refers to; jitter and turbulence move cells, not their lattice)."""
    p = np.asarray(params, dtype=np.float64)
    return _layout_matrix(float(max(1, int(math.trunc(p[_I["resolution"]])))), float(p[_I["aspect_ratio"]]),
                          math.pi * float(p[_I["rotation"]]))


def layout_lattices(params) -> list[Lattice]:
    """The lattices the parameters' layout puts its cells on, in pixels: the family's own (near-)lattices of
    DOMAIN_LATTICE mapped by ``layout_map`` ("2d"); for the random-cut row families the rows (one domain unit
    apart along y, running along the domain x axis); [] for the relaxed families (no lattice). What a fit of
    known parameters is compared on when a realisation's own lattice is a matter of chance (rows of random
    heights, split herringbones: their fresh realisations often read as no lattice, the truth's too)."""
    t = int(np.asarray(params)[_I["tiling"]])
    M = layout_map(params)
    if t in ROW_FAMILIES:
        across, along = M @ np.array([0.0, 1.0]), M @ np.array([1.0, 0.0])
        spacing = abs(float(np.linalg.det(M))) / float(np.linalg.norm(along))
        return [Lattice(kind="rows", vectors=[(float(across[0]), float(across[1]))], regularity=1.0,
                        row_vector=(float(along[0]), float(along[1])), row_spacing=spacing,
                        orientation_deg=math.degrees(math.atan2(along[1], along[0])) % 180.0)]
    out = []
    for D in DOMAIN_LATTICE.get(t, ())[:max(1, NEAR_LATTICES.get(t, 1))]:
        b = _reduce(np.stack([M @ np.array(D[0]), M @ np.array(D[1])]))
        out.append(Lattice(kind="2d", vectors=[tuple(map(float, b[0])), tuple(map(float, b[1]))], regularity=1.0))
    return out


def compare_layouts(truth, fit) -> tuple[float, float]:
    """(period error, angle error in degrees) of the lattice of parameter vector `fit`'s layout against
    `truth`'s (``layout_lattices``; the pair of their own lattices closest in units of the acceptance's 5 % and
    3 degrees); inf when either has none or one is rows and the other 2-D."""
    pairs = [compare_lattices(a, b) for a in layout_lattices(truth) for b in layout_lattices(fit)]
    return min(pairs, key=lambda e: (max(e[0] / 0.05, e[1] / 3.0), e), default=(math.inf, math.inf))


def cell_area_error(target: Lattice, params) -> float:
    """Relative difference between `target`'s 2-D cell area and the nearest cell area of the lattices parameter
    vector `params`' layout puts its cells on (``layout_lattices``); inf when either has no 2-D lattice. A cell of
    two courses where the target has one is 100 % off whatever the period (``compare_lattices`` compares the
    shortest vectors)."""
    if target.kind != "2d":
        return math.inf
    area = abs(float(np.linalg.det(np.array(target.vectors))))
    return min((abs(abs(float(np.linalg.det(np.array(x.vectors)))) - area) / area for x in layout_lattices(params)
                if len(x.vectors) == 2), default=math.inf)


def compare_lattices(target: Lattice, other: Lattice) -> tuple[float, float]:
    """(relative error of the period, angle error in degrees) of `other`'s lattice against `target`'s, both
    ways: each reduced basis vector of one against the closest short vector of the other; the worst (a denser
    or sparser lattice that shares some vectors fails). When either is rows (random cuts), the row spacing and
    the rows' orientation. inf when either has no lattice or their kinds differ otherwise."""
    if "rows" in (target.kind, other.kind) and target.row_spacing and other.row_spacing:
        # courses with random cuts: what repeats is the row spacing and the rows' direction
        d = abs(float(target.orientation_deg) - float(other.orientation_deg)) % 180.0
        return abs(other.row_spacing - target.row_spacing) / target.row_spacing, min(d, 180.0 - d)
    if not target.vectors or not other.vectors or len(target.vectors) != len(other.vectors):
        return math.inf, math.inf
    p1, a1 = _one_way(target, other)
    p2, a2 = _one_way(other, target)
    return max(p1, p2), max(a1, a2)


def _one_way(target: Lattice, other: Lattice) -> tuple[float, float]:
    """compare_lattices in one direction: target's reduced basis against other's short vectors."""
    cand = _short_vectors(other)
    tv = np.array(target.vectors, dtype=np.float64)
    tv = _reduce(tv) if len(tv) == 2 else tv
    per, ang = 0.0, 0.0
    for t in tv:
        k = int(np.argmin(np.linalg.norm(cand - t[None], axis=1)))
        c = cand[k]
        per = max(per, abs(np.linalg.norm(c) - np.linalg.norm(t)) / np.linalg.norm(t))
        d = abs(math.degrees(math.atan2(c[1], c[0]) - math.atan2(t[1], t[0]))) % 360.0
        ang = max(ang, min(d, 360.0 - d))
    return float(per), float(ang)
