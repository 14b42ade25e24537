"""PPTBF (Point Process Texture Basis Functions, Guehl et al. 2020): parameter space and vectorised numpy evaluation.

Re-derived from the project spec SPEC-pptbf.md (in ../shared beside the repository; no reference code copied);
the numeric tables are in tables.py.
The evaluation is split in two parts so that the torch version (pptbf_torch.py) can share the discrete work:

* the *structure* (numpy, float64, not differentiable): domain coordinates -> tiles -> (relaxed) point sets ->
  per-point random draws -> per-pixel ranking of the 18 nearest points -> cellular-window border radii;
* the *shading* (windows, cellular window, features, mixture), written once in numpy here and once in torch.

Deviations from the reference (all documented in the spec or noted here):
* y0 = j / W (not j / H): non-square outputs extend the pattern instead of stretching it (spec §5.11).
* each kernel takes 6 PRNG draws (v, pr, lx, ly, th, s), as the shader does; the spec's "7" is a miscount.
* hashes truncate with floor (identical to the reference's int casts for the positive coordinates it produces).
* with `ref_width`/`pixel_scale` the pattern is defined at a reference width (see `evaluate`).
* the cellular window's border radius is solved exactly (border.py) instead of marched (the march's resolution is
  0.2/64 and it never reports less than 0.1), among the BORDER_NEIGHBOURS points nearest to p0 in the whole point
  table (which gets a ring of cells around the image) rather than among the pixel's 3x3-tile candidates: radii
  are those of p0's true cell, keyed by (point, sector) and independent of the image extent. Where no point ever
  wins along the ray the reference march ends at 1.35, which is kept (NO_EXIT).
* kernels too far to change the float32 output are skipped (exp(-ddist) < 1e-10 where added to a base, < 1e-38
  elsewhere; mixture 3 uses only ddist < 1 anyway).
* exact ties in the ranking go to the lower candidate index (as the reference's strict minimum search).

Cost: see bench/pptbf.py (`--dist 100`: 100 database-like vectors at 512 px, ref_width 128, on this 2-core machine:
median 0.47 s on 1 thread, 0.34 s on 2, p90 1.25 s / 0.96 s; the slow tail is periods of 8-10 px, 4x denser
than the database's). Shares of a 1-thread run: cell borders ~22 %, kernels ~22 %, ranking ~20 %, structure ~14 %.
"""
from __future__ import annotations

import logging
import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial

import numpy as np
from scipy.spatial import cKDTree

from pptbf_db import tables
from pptbf_db.border import first_exit

logger = logging.getLogger(__name__)

#: version of the rendered field, stored with every database (2: exact cell borders, kernel cut-off)
GENERATOR = "pptbf/2"


# --------------------------------------------------------------------------------------------------------------
# Parameter space
# --------------------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ParamSpec:
    """One entry of the 29-vector: name, kind ("cont" | "disc") and range (inclusive)."""

    name: str
    kind: str
    lo: float
    hi: float


PARAM_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("threshold", "cont", 0.0, 1.0),
    ParamSpec("tiling", "disc", 0, 17),
    ParamSpec("jitter", "cont", 0.0, 1.0),
    ParamSpec("resolution", "cont", 1.0, 1000.0),
    ParamSpec("rotation", "cont", 0.0, 2.0),
    ParamSpec("aspect_ratio", "cont", 0.01, 10.0),
    ParamSpec("distortion_base", "cont", 0.0, 0.25),
    ParamSpec("distortion_amplitude", "cont", 0.0, 4.0),
    ParamSpec("distortion_frequency", "cont", 0.0, 2.0),
    ParamSpec("window_shape", "disc", 0, 3),
    ParamSpec("window_arity", "cont", 2.0, 10.0),
    ParamSpec("window_larp", "cont", 0.0, 1.0),
    ParamSpec("window_norm", "cont", 1.0, 3.0),
    ParamSpec("window_smoothness", "cont", 0.0, 2.0),
    ParamSpec("window_blend", "cont", 0.0, 1.0),
    ParamSpec("window_sigma", "cont", 0.01, 4.0),
    ParamSpec("feature_mixture", "disc", 0, 4),
    ParamSpec("feature_norm", "cont", 1.0, 3.0),
    ParamSpec("feature_correlation", "cont", 0.0, 1.0),
    ParamSpec("feature_aniso", "cont", 0.0, 5.0),
    ParamSpec("feature_kernel_min", "disc", 0, 16),
    ParamSpec("feature_kernel_max", "disc", 0, 16),
    ParamSpec("feature_sigcos", "cont", 0.0, 10.0),
    ParamSpec("feature_sigcosvar", "cont", 0.0, 1.0),
    ParamSpec("feature_frequency", "disc", 0, 16),
    ParamSpec("feature_phase_shift", "cont", 0.0, 1.0),
    ParamSpec("feature_thickness", "cont", 0.001, 1.0),
    ParamSpec("feature_curvature", "cont", 0.0, 1.0),
    ParamSpec("feature_orientation", "cont", 0.0, 0.5),
)
N_PARAMS = len(PARAM_SPECS)
PARAM_NAMES: tuple[str, ...] = tuple(s.name for s in PARAM_SPECS)
PARAM_INDEX: dict[str, int] = {n: i for i, n in enumerate(PARAM_NAMES)}
CONTINUOUS_IDX = np.array([i for i, s in enumerate(PARAM_SPECS) if s.kind == "cont"], dtype=np.int64)
DISCRETE_IDX = np.array([i for i, s in enumerate(PARAM_SPECS) if s.kind == "disc"], dtype=np.int64)
_LO = np.array([s.lo for s in PARAM_SPECS], dtype=np.float64)
_HI = np.array([s.hi for s in PARAM_SPECS], dtype=np.float64)

#: thresholds used by the reference database (folder tokens 0 / 1 / other)
DATABASE_THRESHOLDS = (0.2, 0.5, 0.8)
#: sampling ranges narrower than the valid ranges where the full range is degenerate at database sizes
SAMPLE_RANGES: dict[str, tuple[float, float]] = {
    "aspect_ratio": (0.25, 4.0),          # log-uniform; 0.01..10 gives 1-pixel stripes
    "distortion_base": (0.0, 0.05),       # 0.25 image widths with gain 4 is pure noise
    "distortion_amplitude": (0.0, 1.0),
    "distortion_frequency": (0.0, 1.0),   # documented range of the file format
    "feature_kernel_min": (0, 8),         # file-format range, keeps database renders cheap
    "feature_kernel_max": (0, 8),
    "feature_sigcos": (0.0, 6.0),
    "feature_frequency": (0, 8),
}


def _as_params(params) -> np.ndarray:
    """Validate a parameter vector: 29 finite numbers (raises ValueError naming the problem)."""
    p = np.asarray(params, dtype=np.float64).reshape(-1)
    if p.size != N_PARAMS:
        raise ValueError(f"PPTBF parameter vector must have {N_PARAMS} entries ({', '.join(PARAM_NAMES)}), "
                         f"got {p.size}")
    bad = ~np.isfinite(p)
    if bad.any():
        names = [PARAM_NAMES[i] for i in np.flatnonzero(bad)]
        raise ValueError(f"PPTBF parameters not finite: {names}")
    return p


def clip_params(params) -> np.ndarray:
    """Clamp into the ranges, truncate discrete entries to ints and order kernel min <= max (1-D or (n, 29))."""
    p = np.array(params, dtype=np.float64)
    single = p.ndim == 1
    p = np.atleast_2d(p)
    if p.shape[-1] != N_PARAMS:
        raise ValueError(f"PPTBF parameter vectors must have {N_PARAMS} entries, got {p.shape[-1]}")
    p = np.clip(np.nan_to_num(p, nan=0.0), _LO, _HI)
    p[:, DISCRETE_IDX] = np.floor(p[:, DISCRETE_IDX])
    i0, i1 = PARAM_INDEX["feature_kernel_min"], PARAM_INDEX["feature_kernel_max"]
    lo, hi = np.minimum(p[:, i0], p[:, i1]), np.maximum(p[:, i0], p[:, i1])
    p[:, i0], p[:, i1] = lo, hi
    return p[0] if single else p


#: the "crisp cells" part of a database: regular layouts shaded by the cellular window alone, sharp-edged
CRISP_RANGES: dict[str, tuple[float, float]] = {
    "threshold": (0.1, 0.9),
    "jitter": (0.0, 0.15),
    "aspect_ratio": (0.4, 2.5),
    "distortion_base": (0.0, 0.005),
    "distortion_amplitude": (0.0, 0.05),
    "window_larp": (0.0, 1.0),
    "window_smoothness": (0.0, 0.2),
    "window_blend": (0.9, 1.0),
    "window_sigma": (2.0, 4.0),
}
CRISP_FIXED: dict[str, float] = {"window_shape": 1, "feature_mixture": 0}

#: the "regular" part of a database: nearly unjittered, undistorted layouts (bricks, tiles, plates)
REGULAR_RANGES: dict[str, tuple[float, float]] = {
    "jitter": (0.0, 0.1),
    "distortion_base": (0.0, 0.005),
    "distortion_amplitude": (0.0, 0.05),
}


def stratum_indices(n: int, regular_share: float, crisp_share: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the "regular" and "crisp cells" vectors among n, each spread evenly over 0..n-1 (so every
    chunk of a build gets its share); the rest are sampled uniformly."""
    n_reg, n_crisp = int(round(regular_share * n)), int(round(crisp_share * n))
    reg = np.unique(np.round(np.linspace(0, n - 1, n_reg)).astype(np.int64)) if n_reg else np.zeros(0, np.int64)
    rest = np.setdiff1d(np.arange(n), reg)
    crisp = (rest[np.unique(np.round(np.linspace(0, len(rest) - 1, n_crisp)).astype(np.int64))]
             if n_crisp and len(rest) else np.zeros(0, np.int64))
    return reg, crisp


def sample_params(rng: np.random.Generator, n: int, *, ref_width: int = 128,
                  thresholds=DATABASE_THRESHOLDS, regular_share: float = 0.0, crisp_share: float = 0.0,
                  balanced_tiling: bool = False) -> np.ndarray:
    """Draw n parameter vectors covering the space, for a database rendered at `ref_width` pixels.

    Uniform per parameter (ranges of PARAM_SPECS, narrowed by SAMPLE_RANGES where degenerate), threshold from
    `thresholds`, resolution (period in pixels) log-uniform in [ref_width/16, ref_width/2], and the flat
    combination mixture 0 + window shape 0 replaced by shapes 1..3. round(regular_share * n) vectors, evenly
    spread, draw jitter and distortion from REGULAR_RANGES: uniform sampling makes such layouts ~0.5 % of a database
    (P(jitter < 0.1) * P(distortion < 0.05)), too rare for the structured materials users bring.
    round(crisp_share * n) further vectors (disjoint from those) are crisp cells (CRISP_RANGES, CRISP_FIXED):
    regular layouts whose cellular window gives sharp-edged bricks, tiles and plates with no feature noise, and
    any white fraction. `balanced_tiling` gives every tiling family the same number of vectors (+-1), shuffled.
    """
    if not 0.0 <= regular_share <= 1.0 or not 0.0 <= crisp_share <= 1.0 - regular_share:
        raise ValueError(f"regular_share ({regular_share}) and crisp_share ({crisp_share}) must be in [0, 1] "
                         f"with a sum of at most 1")
    out = np.empty((n, N_PARAMS), dtype=np.float64)
    for i, s in enumerate(PARAM_SPECS):
        lo, hi = SAMPLE_RANGES.get(s.name, (s.lo, s.hi))
        if s.kind == "disc":
            out[:, i] = rng.integers(int(lo), int(hi) + 1, size=n)
        elif s.name == "aspect_ratio":
            out[:, i] = np.exp(rng.uniform(math.log(lo), math.log(hi), size=n))
        else:
            out[:, i] = rng.uniform(lo, hi, size=n)
    out[:, 0] = rng.choice(np.asarray(thresholds, dtype=np.float64), size=n)
    out[:, 3] = np.floor(np.exp(rng.uniform(math.log(ref_width / 16.0), math.log(ref_width / 2.0), size=n)))
    flat = (out[:, PARAM_INDEX["feature_mixture"]] == 0) & (out[:, PARAM_INDEX["window_shape"]] == 0)
    out[flat, PARAM_INDEX["window_shape"]] = rng.integers(1, 4, size=int(flat.sum()))
    sel, sel_c = stratum_indices(n, regular_share, crisp_share)
    if sel.size:  # drawn last: share 0 = the vectors of databases built before strata
        for name, (lo, hi) in REGULAR_RANGES.items():
            out[sel, PARAM_INDEX[name]] = rng.uniform(lo, hi, size=sel.size)
    if sel_c.size:
        for name, (lo, hi) in CRISP_RANGES.items():
            out[sel_c, PARAM_INDEX[name]] = rng.uniform(lo, hi, size=sel_c.size)
        # periods of 1/12 .. 1/3 of the width (at least 3 cells across, mortar of a few pixels)
        out[sel_c, 3] = np.floor(np.exp(rng.uniform(math.log(ref_width / 12.0), math.log(ref_width / 3.0),
                                                    size=sel_c.size)))
        for name, v in CRISP_FIXED.items():
            out[sel_c, PARAM_INDEX[name]] = v
    if balanced_tiling:
        lo, hi = PARAM_SPECS[PARAM_INDEX["tiling"]].lo, PARAM_SPECS[PARAM_INDEX["tiling"]].hi
        fams = np.arange(int(lo), int(hi) + 1)
        out[:, PARAM_INDEX["tiling"]] = rng.permutation(np.resize(fams, n))
    return clip_params(out)


@dataclass(frozen=True)
class Decoded:
    """The parameter vector converted to the quantities the evaluation uses (spec §1 conversions)."""

    threshold: float
    tiling: int
    jitter: float
    res: int
    alpha: float
    aspect: float
    dist_a: float
    dist_g: float
    dist_f: float
    shape: int
    n_sectors: int
    larp: float
    wnorm: float
    smooth: float
    beta: float
    sigma_w: float
    mixture: int
    fnorm: float
    corr: float
    aniso: float
    npmin: int
    npmax: int
    sigcos: float
    sigcosvar: float
    freq: int
    phi: float
    thick: float
    curv: float
    theta_max: float

    @property
    def delta(self) -> float:
        """Angular sector width of the cellular window."""
        return 2.0 * math.pi / self.n_sectors

    @property
    def footprint(self) -> float:
        """Window footprint F (1.5 for shape 0, 1 otherwise; x0.4 for the small tiles of types >= 10)."""
        f = 1.5 if self.shape == 0 else 1.0
        return f * 0.4 if self.tiling >= 10 else f

    @property
    def kmax(self) -> int:
        """Largest possible kernel count per point."""
        return max(self.npmin, self.npmax, 0)


def decode(params) -> Decoded:
    """Convert a 29-vector (validated; discrete entries truncated like the C host) into `Decoded`."""
    p = _as_params(params)

    def disc(name: str, lo: int, hi: int) -> int:
        v = int(math.trunc(p[PARAM_INDEX[name]]))
        if not lo <= v <= hi:
            raise ValueError(f"PPTBF parameter '{name}' (index {PARAM_INDEX[name]}) = {v} outside {lo}..{hi}")
        return v

    res = max(1, int(math.trunc(p[3])))
    aspect = float(p[5])
    if abs(aspect) < 1e-6:
        raise ValueError("PPTBF parameter 'aspect_ratio' (index 5) must not be 0")
    return Decoded(
        threshold=float(p[0]), tiling=disc("tiling", 0, 17), jitter=float(p[2]), res=res,
        alpha=math.pi * float(p[4]), aspect=aspect, dist_a=float(p[6]), dist_g=float(p[7]), dist_f=float(p[8]),
        shape=disc("window_shape", 0, 3), n_sectors=2 ** int(math.floor(max(float(p[10]), 0.0) + 0.5)),
        larp=float(p[11]), wnorm=float(p[12]), smooth=float(p[13]), beta=float(p[14]), sigma_w=float(p[15]),
        mixture=disc("feature_mixture", 0, 5), fnorm=float(p[17]), corr=float(p[18]), aniso=float(p[19]),
        npmin=disc("feature_kernel_min", 0, 20), npmax=disc("feature_kernel_max", 0, 20),
        sigcos=float(p[22]), sigcosvar=float(p[23]), freq=int(math.trunc(p[24])),
        phi=0.5 * math.pi * float(p[25]), thick=float(p[26]), curv=float(p[27]), theta_max=math.pi * float(p[28]))


# --------------------------------------------------------------------------------------------------------------
# Hash PRNG and value noise (spec §2.1)
# --------------------------------------------------------------------------------------------------------------

PERM = np.asarray(tables.PERM, dtype=np.int64)
NOISE = np.asarray(tables.NOISE, dtype=np.float64)
_MULT = 3039177861
MAX_DRAWS = 6 * 20 + 4
MPOW = np.array([pow(_MULT, n, 2 ** 32) for n in range(MAX_DRAWS + 1)], dtype=np.uint64)
_MASK32 = np.uint64(0xFFFFFFFF)


def hash_seed(x, y) -> np.ndarray:
    """Reference seeding(x, y, 0): two permutation chains combined into a < 2^25 integer seed."""
    x = np.asarray(x, dtype=np.int64)
    y = np.asarray(y, dtype=np.int64)
    p0 = PERM[0]
    a = PERM[(x + PERM[(y + p0) & 1023]) & 1023]          # & 1023 = mod 1024 (negative too), cheaper
    b = PERM[(3 * x + PERM[(4 * y + p0) & 1023]) & 1023]
    return a + 32768 * b


def draw(seed, n) -> np.ndarray:
    """The n-th (1-based) draw U in [-1, 1) after seeding: seed * M^n mod 2^32 (random access)."""
    s = (np.asarray(seed, dtype=np.int64).astype(np.uint64) * MPOW[np.asarray(n)]) & _MASK32
    return s.astype(np.float64) * (2.0 / 4294967296.0) - 1.0


def _lattice(i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Value-noise lattice value at integer (i, j)."""
    return NOISE[(PERM[i & 1023] + 3 * PERM[j & 1023] + 5 * PERM[0]) & 1023]


def value_noise(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear value noise with smoothstep weights, in [-1, 1]."""
    fx, fy = np.floor(x), np.floor(y)
    ix, iy = fx.astype(np.int64), fy.astype(np.int64)
    tx, ty = x - fx, y - fy
    sx, sy = tx * tx * (3.0 - 2.0 * tx), ty * ty * (3.0 - 2.0 * ty)
    v0 = _lattice(ix, iy) + (_lattice(ix, iy + 1) - _lattice(ix, iy)) * sy
    v1 = _lattice(ix + 1, iy) + (_lattice(ix + 1, iy + 1) - _lattice(ix + 1, iy)) * sy
    return v0 + (v1 - v0) * sx


# --------------------------------------------------------------------------------------------------------------
# Coordinates (spec §2.2)
# --------------------------------------------------------------------------------------------------------------

OCTAVE_FACTORS = (0.5, 1.0, 2.0, 4.0)


def base_coords(width: int, height: int, shift=(0.0, 0.0), pixel_scale: float = 1.0,
                ref_width: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(x0 (1, W), y0 (H, 1)) of the pixels in reference image widths: i / (ref_width * pixel_scale) + shift."""
    unit = float(ref_width or width) * float(pixel_scale)
    x0 = np.arange(width, dtype=np.float64) / unit + float(shift[0])
    y0 = np.arange(height, dtype=np.float64) / unit + float(shift[1])
    return x0[None, :], y0[:, None]


def domain_coords(x0: np.ndarray, y0: np.ndarray, d: Decoded, zoom: float) -> tuple[np.ndarray, np.ndarray]:
    """Turbulence then rotation / aspect / zoom: pixel coordinates -> domain units (1 unit = 1 period).

    x0, y0 broadcast against each other ((1, W) and (H, 1) make the noise lattice lookups separable).
    """
    x1, y1 = x0, y0
    if d.dist_a != 0.0:
        fz = d.dist_f * zoom
        for o, m in enumerate(OCTAVE_FACTORS):
            amp = d.dist_a * d.dist_g ** o
            if amp == 0.0:
                continue
            x1 = x1 + amp * value_noise(fz * m * x0 + 2.0, fz * m * y0)
            y1 = y1 + amp * value_noise(fz * m * x0, fz * m * y0 + 5.0)
    ca, sa = math.cos(d.alpha), math.sin(d.alpha)
    x = 100.0 + zoom * (x1 * ca - y1 * sa) / d.aspect
    y = 100.0 + zoom * (x1 * sa + y1 * ca)
    return np.broadcast_arrays(x, y)


# --------------------------------------------------------------------------------------------------------------
# Tilings (spec §2.3)
# --------------------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class TilingType:
    """One of the 18 point-process types: base tiling family, subdivision probability, row shift, relaxation."""

    family: str          # "pave" | "cross" | "bisquare" | "apave"
    p_sub: float
    rand_x: float = 0.0  # PAVE random cut amplitudes
    rand_y: float = 0.0
    shift: int = 1       # PAVE row shift D
    n: int = 0           # CROSS brick length N
    relax: int = 0


TILING_TYPES: tuple[TilingType, ...] = (
    TilingType("pave", 0.0), TilingType("pave", 0.5), TilingType("pave", 1.0, relax=5),
    TilingType("pave", 0.5, relax=5), TilingType("pave", 0.0, shift=2), TilingType("pave", 0.0, shift=3),
    TilingType("pave", 0.0, 0.8, 0.8), TilingType("pave", 0.5, 0.8, 0.8),
    TilingType("pave", 0.0, 0.8, 0.0), TilingType("pave", 0.5, 0.8, 0.0),
    TilingType("cross", 0.0, n=2), TilingType("cross", 0.5, n=2),
    TilingType("cross", 0.0, n=3), TilingType("cross", 0.5, n=3),
    TilingType("bisquare", 0.0), TilingType("bisquare", 0.5),
    TilingType("apave", 0.0), TilingType("apave", 0.5),
)
TILING_NAMES = ("square", "square-split", "relaxed-split", "relaxed-random", "running-bond", "thirds-bond",
                "ashlar", "ashlar-split", "random-bricks", "random-bricks-split", "herringbone2",
                "herringbone2-split", "herringbone3", "herringbone3-split", "pythagorean", "pythagorean-split",
                "apavement", "apavement-split")
TILING_FAMILIES = {"PAVE": (0, 1, 2, 3, 4, 5, 6, 7, 8, 9), "CROSS": (10, 11, 12, 13), "BISQUARE": (14, 15),
                   "APAVEMENT": (16, 17)}


def _cross_table(N: int) -> np.ndarray:
    """(4N^2, 9, 4) centre offsets and half-sizes (units) of the 9 herringbone tiles per sub-cell (qx, qy)."""
    n2 = 2 * N

    def hor(a, b):
        return ((a + N / 2) / n2, (b + 0.5) / n2, (N / 2) / n2, 0.5 / n2)

    def ver(a, b):
        return ((a + 0.5) / n2, (b + N / 2) / n2, 0.5 / n2, (N / 2) / n2)

    tab = np.zeros((n2 * n2, 9, 4))
    for qx in range(n2):
        for qy in range(n2):
            tiles = []
            if qy <= qx <= qy + N - 1 or qy - n2 <= qx <= qy + N - 1 - n2:
                rx, ry = (qy if qy <= qx <= qy + N - 1 else qy - n2), qy
                for t in (-1, 0, 1):
                    tiles += [hor(rx + t, ry + t), ver(rx + t - 1, ry + t), ver(rx + t + N, ry + t + 1 - N)]
            else:
                rx, ry = qx, (qx + 1 if qx + 1 <= qy <= qx + N else qx + 1 - n2)
                for t in (-1, 0, 1):
                    tiles += [ver(rx + t, ry + t), hor(rx + t, ry + t - 1), hor(rx + t - N, ry + t + N - 1)]
            tab[qx * n2 + qy] = tiles
    return tab


def _bisquare_table() -> np.ndarray:
    """(25, 9, 4) tiles of the Pythagorean tiling (2x2 and 1x1 squares on a 1/5 grid) per sub-cell."""
    def big(a, b):
        return ((a + 1) / 5, (b + 1) / 5, 1 / 5, 1 / 5)

    def small(a, b):
        return ((a + 0.5) / 5, (b + 0.5) / 5, 0.5 / 5, 0.5 / 5)

    e1, e2 = (2, -1), (1, 2)
    tab = np.full((25, 9, 4), np.nan)
    for qx in range(5):
        for qy in range(5):
            tiles = None
            for i in range(3):
                for j in range(3):
                    bx, by = -2 + 2 * i + j, 1 - i + 2 * j
                    if tiles is None and bx <= qx <= bx + 1 and by <= qy <= by + 1:
                        offs = [(-e1[0], -e1[1]), (-e2[0], -e2[1]), (0, 0), e2, e1]
                        tiles = [big(bx + ox, by + oy) for ox, oy in offs]
                        tiles += [small(bx - 1, by), small(bx, by + 2), small(bx + 2, by + 1), small(bx + 1, by - 1)]
            for i in range(3):
                for j in range(2):
                    if tiles is None and qx == 2 * i + j and qy == 2 + 2 * j - i:
                        tiles = [small(qx, qy), small(qx - 2, qy + 1), small(qx + 1, qy + 2),
                                 small(qx - 1, qy - 2), small(qx + 2, qy - 1)]
                        tiles += [big(qx - 2, qy - 1), big(qx - 1, qy + 1), big(qx + 1, qy), big(qx, qy - 2)]
            if tiles is None:
                raise AssertionError(f"BISQUARE sub-cell ({qx}, {qy}) not covered")
            tab[qx * 5 + qy] = tiles
    return tab


def _apave_region(qx: int, qy: int) -> int:
    """APAVEMENT region code of a quarter cell (spec §2.3 table)."""
    if 1 <= qx <= 2 and 1 <= qy <= 2:
        return 0
    if qy == 3 and qx <= 2:
        return 1
    if qx == 3:
        return 2 + (3 - qy)
    if qy == 0 and qx >= 1:
        return 6
    return 7 if qy <= 1 else 8


def _apave_table() -> np.ndarray:
    """(16, 9, 4) APAVEMENT tiles per quarter cell, from the reference tables (defects kept, spec §5.5)."""
    sx, sy = np.array(tables.APAVE_SX), np.array(tables.APAVE_SY)
    ddx, ddy = np.array(tables.APAVE_DDX), np.array(tables.APAVE_DDY)
    tab = np.zeros((16, 9, 4))
    for qx in range(4):
        for qy in range(4):
            r = _apave_region(qx, qy)
            hx, hy = sx[r] / 4.0, sy[r] / 4.0
            tab[qx * 4 + qy] = np.stack([ddx[r] / 4.0 + hx, ddy[r] / 4.0 + hy, hx, hy], axis=-1)
    return tab


_TABLES = {("cross", 2): (4, _cross_table(2)), ("cross", 3): (6, _cross_table(3)),
           ("bisquare", 0): (5, _bisquare_table()), ("apave", 0): (4, _apave_table())}


def _table_for(tt: TilingType) -> tuple[int, np.ndarray] | None:
    """(sub-units per period, tile table) of a table-driven family, None for PAVE."""
    return None if tt.family == "pave" else _TABLES[(tt.family, tt.n)]


def cell_codes(x: np.ndarray, y: np.ndarray, tt: TilingType) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ix, iy, q): the integer data the 9 tiles of a point depend on (q = sub-cell, 0 for PAVE)."""
    fx, fy = np.floor(x), np.floor(y)
    ix, iy = fx.astype(np.int64), fy.astype(np.int64)
    tab = _table_for(tt)
    if tab is None:
        return ix, iy, np.zeros_like(ix)
    n = tab[0]
    qx = np.clip(np.floor((x - fx) * n).astype(np.int64), 0, n - 1)
    qy = np.clip(np.floor((y - fy) * n).astype(np.int64), 0, n - 1)
    return ix, iy, qx * n + qy


_DI = np.array([-1, 0, 1] * 3, dtype=np.int64)
_DJ = np.repeat(np.array([-1, 0, 1], dtype=np.int64), 3)


def tiles_from_codes(ix: np.ndarray, iy: np.ndarray, q: np.ndarray, tt: TilingType):
    """The 9 candidate tiles (cx, cy, hx, hy), each shape ix.shape + (9,)."""
    tab = _table_for(tt)
    if tab is not None:
        t = tab[1][q]
        return ix[..., None] + t[..., 0], iy[..., None] + t[..., 1], t[..., 2].copy(), t[..., 3].copy()
    a = ix[..., None] + _DI
    b = iy[..., None] + _DJ
    o = np.mod(b, tt.shift) / tt.shift
    zero = np.zeros(a.shape)
    left = 0.5 * tt.rand_x * draw(hash_seed(a + 5, b + 10), 1) if tt.rand_x else zero
    right = 0.5 * tt.rand_x * draw(hash_seed(a + 6, b + 10), 1) if tt.rand_x else zero
    bottom = 0.5 * tt.rand_y * draw(hash_seed(np.full_like(b, 3), b + 10), 1) if tt.rand_y else zero
    top = 0.5 * tt.rand_y * draw(hash_seed(np.full_like(b, 3), b + 11), 1) if tt.rand_y else zero
    hx = 0.5 * (right + 1.0 - left)
    hy = 0.5 * (top + 1.0 - bottom)
    return a + o + left + hx, b + bottom + hy, hx, hy


def tiles_at(x: np.ndarray, y: np.ndarray, tt: TilingType):
    """The 9 candidate tiles of domain points (x, y)."""
    return tiles_from_codes(*cell_codes(x, y, tt), tt)


# --------------------------------------------------------------------------------------------------------------
# Point sets: subdivision, jitter, relaxation (spec §2.3)
# --------------------------------------------------------------------------------------------------------------

def point_sets(cx, cy, hx, hy, p_sub: float) -> dict[str, np.ndarray]:
    """Per tile: up to 4 (sub)cells with their un-jittered points p*; arrays of shape cx.shape + (4,)."""
    cx, cy, hx, hy = (np.asarray(v, dtype=np.float64) for v in (cx, cy, hx, hy))
    s = hash_seed(np.floor(15.0 * cx).astype(np.int64) + 10, np.floor(10.0 * cy).astype(np.int64) + 3)
    q = 0.5 * draw(s, 1) + 0.5
    dr = [None] + [draw(s, n) for n in range(1, 12)]
    split = q < p_sub
    s4 = split & (np.abs(hx - hy) < 0.1)
    sx = split & ~s4 & (hx > hy + 0.1)
    sy = split & ~s4 & ~sx & (hy > hx + 0.1)
    shape = cx.shape + (4,)
    out = {k: np.zeros(shape) for k in ("px", "py", "ccx", "ccy", "chx", "chy")}
    valid = np.zeros(shape, dtype=bool)

    def put(mask, slot, ccx, ccy, chx, chy, ux, uy):
        for key, val in (("ccx", ccx), ("ccy", ccy), ("chx", chx), ("chy", chy),
                         ("px", ccx + 0.9 * chx * ux), ("py", ccy + 0.9 * chy * uy)):
            out[key][..., slot] = np.where(mask, val, out[key][..., slot])
        valid[..., slot] |= mask

    single = ~(s4 | sx | sy)
    put(single, 0, cx, cy, hx, hy, dr[2], dr[3])
    # four-way split at (cut_x, cut_y): lower-left, lower-right, upper-left, upper-right
    ctx, cty = 0.5 + 0.18 * dr[2], 0.5 + 0.18 * dr[3]
    x0, y0 = cx - hx, cy - hy
    for slot, (right, upper) in enumerate(((0, 0), (1, 0), (0, 1), (1, 1))):
        chx = np.where(right, 1.0 - ctx, ctx) * hx
        chy = np.where(upper, 1.0 - cty, cty) * hy
        ccx = x0 + (2.0 * ctx * hx if right else 0.0) + chx
        ccy = y0 + (2.0 * cty * hy if upper else 0.0) + chy
        put(s4, slot, ccx, ccy, chx, chy, dr[4 + 2 * slot], dr[5 + 2 * slot])
    cut = 0.4 + 0.2 * (0.5 * dr[2] + 0.5)
    for slot in (0, 1):
        chx = (cut if slot == 0 else 1.0 - cut) * hx
        put(sx, slot, x0 + (2.0 * cut * hx if slot else 0.0) + chx, cy, chx, hy, dr[3 + 2 * slot], dr[4 + 2 * slot])
        chy = (cut if slot == 0 else 1.0 - cut) * hy
        put(sy, slot, cx, y0 + (2.0 * cut * hy if slot else 0.0) + chy, hx, chy, dr[3 + 2 * slot], dr[4 + 2 * slot])
    out["valid"] = valid
    return out


def _nearest3(mx: np.ndarray, my: np.ndarray, mid: np.ndarray, px: np.ndarray, py: np.ndarray, valid: np.ndarray):
    """For movers (T, m) at columns mid among (T, n) points: offsets and distances (T, m, 3) to the 3 nearest other
    valid points (stable order: ties to the lower column)."""
    ddx = px[:, None, :] - mx[:, :, None]
    ddy = py[:, None, :] - my[:, :, None]
    dist = np.sqrt(ddx * ddx + ddy * ddy)
    other = valid[:, None, :] & (np.arange(px.shape[1]) != mid[:, :, None])
    idx = np.argsort(np.where(other, dist, np.inf), axis=-1, kind="stable")[..., :3]
    dist = np.where(other, dist, np.inf)
    return (np.take_along_axis(ddx, idx, -1), np.take_along_axis(ddy, idx, -1),
            np.take_along_axis(dist, idx, -1))


def relaxed_sets(tcx, tcy, thx, thy, tt: TilingType) -> dict[str, np.ndarray]:
    """Relaxed point sets of tiles (T,): the points of the 9 tiles around each, relaxed, kept inside it (T, 36).

    Only the points inside the central tile move (the others are clamped to their own cells, outside it), so
    the 3-nearest search runs for those (<= 4 per tile) against all 36.
    """
    ncx, ncy, nhx, nhy = tiles_at(tcx, tcy, tt)
    ps = point_sets(ncx, ncy, nhx, nhy, tt.p_sub)
    ps = {k: v.reshape(v.shape[0], -1) for k, v in ps.items()}
    px, py, valid = ps["px"].copy(), ps["py"].copy(), ps["valid"]
    bx, by, bdx, bdy = (v[:, None] for v in (tcx, tcy, thx, thy))

    def inside(x, y, ok):
        return ok & (x >= bx - bdx) & (x <= bx + bdx) & (y >= by - bdy) & (y <= by + bdy)

    mid = _compact(inside(px, py, valid))                     # (T, m) columns of the movers
    mval = np.take_along_axis(valid, mid, -1)
    lo_x, hi_x, lo_y, hi_y = (np.take_along_axis(v, mid, -1) for v in (
        ps["ccx"] - ps["chx"] + 0.05, ps["ccx"] + ps["chx"] - 0.05, ps["ccy"] - ps["chy"] + 0.05,
        ps["ccy"] + ps["chy"] - 0.05))
    for _ in range(tt.relax):
        mx, my = np.take_along_axis(px, mid, -1), np.take_along_axis(py, mid, -1)
        move = inside(mx, my, mval)
        ddx, ddy, no = _nearest3(mx, my, mid, px, py, valid)
        no = np.where(no == 0.0, 1.0, no)
        dirx = (ddx / (no * no)).sum(-1)
        diry = (ddy / (no * no)).sum(-1)
        nrm = np.sqrt(dirx * dirx + diry * diry)
        nrm = np.where(nrm == 0.0, 1.0, nrm)
        nx = np.minimum(np.maximum(mx - dirx / nrm * 0.05, lo_x), hi_x)
        ny = np.maximum(my - diry / nrm * 0.05, lo_y)
        ny = np.where(ny > by + bdy, hi_y, ny)
        np.put_along_axis(px, mid, np.where(move, nx, mx), -1)
        np.put_along_axis(py, mid, np.where(move, ny, my), -1)
    ps["px"], ps["py"], ps["valid"] = px, py, inside(px, py, valid)
    return ps


def _compact(valid: np.ndarray, max_len: int | None = None) -> np.ndarray:
    """Stable order putting valid entries first along the last axis (indices), truncated to the max count."""
    order = np.argsort(~valid, axis=-1, kind="stable")
    n = int(valid.sum(-1).max(initial=0))
    if max_len is not None:
        n = min(n, max_len)
    return order[..., :max(n, 1)]


# --------------------------------------------------------------------------------------------------------------
# Structure: everything discrete / hashed (shared by the numpy and torch shading)
# --------------------------------------------------------------------------------------------------------------

MAX_CANDIDATES = 36
MAX_NEIGHBOURS = 18


@dataclass
class PointTable:
    """All candidate points of an image: un-jittered p*, cell centre / half-size and jittered p (N,)."""

    pstar_x: np.ndarray
    pstar_y: np.ndarray
    ccx: np.ndarray
    ccy: np.ndarray
    chx: np.ndarray
    chy: np.ndarray
    px: np.ndarray
    py: np.ndarray
    rot_u: np.ndarray     # u in [0,1): rot = delta * rot_u
    nk: np.ndarray        # kernel count per point
    kdraw: np.ndarray     # (N, kmax, 6) raw draws U of the kernels (v, pr, lx, ly, th, s)
    inv: tuple = ()       # side_inverses of the jittered points (larp term of D)
    cell: np.ndarray | None = None   # (N,) the point's cell key: a 24-bit integer (see cell_keys)


@dataclass
class Structure:
    """Discrete data of one render: per-pixel cell code, per-code candidates (Ncode, C) and the point table."""

    code: np.ndarray          # (H, W) index into cand
    cand: np.ndarray          # (Ncode, C) point ids
    cand_valid: np.ndarray    # (Ncode, C)
    points: PointTable
    border: BorderTable | None = None      # the cell-border neighbourhoods (cellular window only)


def cell_keys(sa) -> np.ndarray:
    """A point's cell key: the top 24 bits of the third state of its seed ``sa`` (the first two give its rotation
    and kernel count), an integer that a float32 shader reproduces exactly; it names the cell a pixel is in."""
    return ((np.asarray(sa, dtype=np.int64).astype(np.uint64) * MPOW[3]) & _MASK32).astype(np.int64) >> 8


def point_randoms(px, py, ccx, ccy, d: Decoded, stable: bool = False):
    """Per point: rot u, kernel count, the 6 draws of each kernel (hashing p, or the cell centre if stable) and
    the cell key (:func:`cell_keys`)."""
    if stable:
        sa = hash_seed(np.floor(24.0 * ccx).astype(np.int64) + 7, np.floor(24.0 * ccy).astype(np.int64) + 1)
        sb = hash_seed(np.floor(24.0 * ccx).astype(np.int64) + 2, np.floor(24.0 * ccy).astype(np.int64) + 5)
    else:
        sa = hash_seed(np.floor(12.0 * px + 7.0).astype(np.int64), np.floor(12.0 * py + 1.0).astype(np.int64))
        sb = hash_seed(np.floor(15.0 * px + 2.0).astype(np.int64), np.floor(15.0 * py + 5.0).astype(np.int64))
    rot_u = 0.5 * draw(sa, 1) + 0.5
    nk = d.npmin + np.trunc((d.npmax - d.npmin) * (0.5 * draw(sa, 2) + 0.5)).astype(np.int64)
    km = d.kmax
    kdraw = draw(sb[:, None], np.arange(1, 6 * km + 1)[None, :]).reshape(-1, km, 6) if km else \
        np.zeros((sa.shape[0], 0, 6))
    return rot_u, nk, kdraw, cell_keys(sa)


def unique_inverse(key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(key, return_inverse=True)`` for integer keys; O(N) by a presence table when their span is small."""
    k = key.ravel()
    if k.size == 0:
        return np.unique(k, return_inverse=True)
    lo = int(k.min())
    span = int(k.max()) - lo + 1
    if span > 4 * k.size + 4096:  # sparse keys: a sort is cheaper than a huge table
        return np.unique(k, return_inverse=True)
    present = np.zeros(span, dtype=bool)
    present[k - lo] = True
    rank = np.cumsum(present, dtype=np.int64) - 1
    return np.flatnonzero(present) + lo, rank[k - lo]


def unique_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(first index, inverse) of the distinct rows of an int64 (N, C) array, like ``np.unique(axis=0)``."""
    lo = rows.min(axis=0)
    span = rows.max(axis=0) - lo + 1
    if float(np.prod(span.astype(np.float64))) >= 2.0 ** 62:  # keys would overflow: sort the rows
        _, first, inv = np.unique(rows, axis=0, return_index=True, return_inverse=True)
        return first, inv.ravel()
    key = np.zeros(rows.shape[0], dtype=np.int64)
    for c in range(rows.shape[1]):  # mixed-radix scalar key, same order as the lexicographic row order
        key = key * int(span[c]) + (rows[:, c] - lo[c])
    ukey, inv = unique_inverse(key)
    first = np.full(ukey.shape[0], rows.shape[0], dtype=np.int64)
    np.minimum.at(first, inv, np.arange(rows.shape[0], dtype=np.int64))
    return first, inv


def build_structure(x: np.ndarray, y: np.ndarray, d: Decoded, stable: bool = False, threads: int = 1) -> Structure:
    """Deduplicate the tile neighbourhoods of all pixels and build their candidate point lists once."""
    tt = TILING_TYPES[d.tiling]
    ix, iy, q = cell_codes(x, y, tt)
    ix0, iy0 = int(ix.min()), int(iy.min())
    nyr, nq = int(iy.max()) - iy0 + 1, 16 * 36
    key = ((ix - ix0) * nyr + (iy - iy0)) * nq + q
    ukey, code = unique_inverse(key)
    code = code.reshape(x.shape)
    cq = ukey % nq
    ciy = (ukey // nq) % nyr + iy0
    cix = (ukey // nq) // nyr + ix0
    n_code = ukey.shape[0]
    if uses_cellular(d):   # the cell borders need every point near p0: add the tiles of a ring of cells around
        rix, riy, rq = _ring_codes(cix, ciy, tt)
        cix, ciy, cq = np.concatenate([cix, rix]), np.concatenate([ciy, riy]), np.concatenate([cq, rq])
    tcx, tcy, thx, thy = tiles_from_codes(cix, ciy, cq, tt)                       # (Ncode + ring, 9)
    tkey = np.round(np.stack([tcx, tcy, thx, thy], -1).reshape(-1, 4) * 240.0).astype(np.int64)
    first, tinv = unique_rows(tkey)
    tinv = tinv.reshape(tcx.shape)
    ux, uy, uhx, uhy = (v.reshape(-1)[first] for v in (tcx, tcy, thx, thy))    # unique tiles (T,)
    if tt.relax:
        ps = relaxed_sets(ux, uy, uhx, uhy, tt)
    else:
        ps = point_sets(ux, uy, uhx, uhy, tt.p_sub)
    sel = _compact(ps["valid"])
    ps = {k: np.take_along_axis(v, sel, -1) for k, v in ps.items()}
    n_slots = sel.shape[-1]
    # candidates of each code: its 9 tiles x slots, valid first (stable), at most 36
    tinv = tinv[:n_code]
    pid = (tinv[..., None] * n_slots + np.arange(n_slots)).reshape(tinv.shape[0], -1)
    pvalid = ps["valid"].reshape(-1)[pid]
    keep = _compact(pvalid, MAX_CANDIDATES)
    cand = np.take_along_axis(pid, keep, -1)
    cand_valid = np.take_along_axis(pvalid, keep, -1)
    flat = {k: v.reshape(-1) for k, v in ps.items()}
    J = d.jitter
    px = J * flat["px"] + (1.0 - J) * flat["ccx"]
    py = J * flat["py"] + (1.0 - J) * flat["ccy"]
    rot_u, nk, kdraw, cell = point_randoms(px, py, flat["ccx"], flat["ccy"], d, stable)
    pts = PointTable(flat["px"], flat["py"], flat["ccx"], flat["ccy"], flat["chx"], flat["chy"], px, py,
                     rot_u, nk, kdraw, side_inverses(px, py, flat["ccx"], flat["ccy"], flat["chx"], flat["chy"]),
                     cell)
    logger.debug("pptbf structure: %d codes, %d tiles, %d slots, %d candidates", cand.shape[0], ux.shape[0],
                 n_slots, cand.shape[1])
    st = Structure(code, cand, cand_valid, pts)
    if uses_cellular(d):
        st.border = border_table(pts, flat["valid"], np.unique(cand[cand_valid]), threads)
    return st


#: cells added around the pixels' cells when the cellular window is used: every point within about 3 periods of
#: a possible p0 is in the point table, so its border neighbours do not depend on the image extent
BORDER_RING = 2


def _ring_codes(cix: np.ndarray, ciy: np.ndarray, tt: TilingType) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cell codes (every sub-cell) of the cells within BORDER_RING of the given cells and not among them (sparse:
    a rotated, stretched domain can have a bounding box of cells far larger than the image)."""
    r = np.arange(-BORDER_RING, BORDER_RING + 1)
    ox, oy = (v.ravel() for v in np.meshgrid(r, r, indexing="ij"))
    x0, y0 = int(cix.min()) - BORDER_RING, int(ciy.min()) - BORDER_RING
    span = int(ciy.max()) - y0 + BORDER_RING + 1
    cells = np.unique((cix - x0) * span + (ciy - y0))
    near = np.unique(((cells // span)[:, None] + ox) * span + (cells % span)[:, None] + oy)
    ring = near[~np.isin(near, cells, assume_unique=True)]
    rx, ry = ring // span + x0, ring % span + y0
    tab = _table_for(tt)
    nsub = 1 if tab is None else tab[0] ** 2
    return (np.repeat(rx, nsub).astype(np.int64), np.repeat(ry, nsub).astype(np.int64),
            np.tile(np.arange(nsub, dtype=np.int64), rx.size))


#: float32 on positions relative to p0: 3-4x faster than float64, radii within 3e-5 relative (the march: 3e-3)
BORDER_DTYPE = np.float32


@dataclass
class BorderTable:
    """For every point that can be a pixel's closest (row[point] >= 0), its BORDER_NEIGHBOURS nearest other valid
    points (nearest first), as the border solver takes them: positions relative to the point and inverse side
    distances in BORDER_DTYPE."""

    row: np.ndarray        # (N,) row of each point id, -1 for points no pixel ranks
    nbr: np.ndarray        # (R, B) point ids (the point itself where fewer exist)
    valid: np.ndarray      # (R, B)
    rx: np.ndarray         # (R, B)
    ry: np.ndarray
    inv: tuple             # 4 x (R, B)
    inv0: tuple            # 4 x (R,) the point's own


def border_table(P: PointTable, valid: np.ndarray, centres: np.ndarray, threads: int = 1) -> BorderTable:
    """Nearest valid neighbours (k-d tree, L2) of the `centres` point ids and their data for the border solver."""
    n = P.px.shape[0]
    ids = np.flatnonzero(valid)
    k = min(BORDER_NEIGHBOURS + 1, max(ids.size, 1))
    xy = np.stack([P.px[ids], P.py[ids]], axis=-1)
    if ids.size:
        _, j = cKDTree(xy).query(np.stack([P.px[centres], P.py[centres]], axis=-1), k=k, workers=threads)
        nbr = ids[j.reshape(centres.size, k)]
    else:
        nbr = centres[:, None].repeat(k, 1)
    own = nbr == centres[:, None]
    drop = np.where(own.any(axis=1), np.argmax(own, axis=1), k - 1)   # the point itself (else the farthest)
    keep = np.ones(nbr.shape, dtype=bool)
    keep[np.arange(centres.size), drop] = False
    nbr = nbr[keep].reshape(centres.size, k - 1)
    if k - 1 < BORDER_NEIGHBOURS:    # fewer points than neighbours: pad with the point itself (invalid)
        nbr = np.concatenate([nbr, centres[:, None].repeat(BORDER_NEIGHBOURS - k + 1, 1)], axis=1)
    ok = valid[nbr] & (nbr != centres[:, None])
    f = BORDER_DTYPE
    rx = (P.px[nbr] - P.px[centres][:, None]).astype(f)
    ry = (P.py[nbr] - P.py[centres][:, None]).astype(f)
    inv = tuple(np.minimum(v[nbr], 1e10).astype(f) for v in P.inv)
    inv0 = tuple(np.minimum(v[centres], 1e10).astype(f) for v in P.inv)
    row = np.full(n, -1, dtype=np.int64)
    row[centres] = np.arange(centres.size)
    return BorderTable(row, nbr, ok, rx, ry, inv, inv0)


def _minkowski(ax: np.ndarray, ay: np.ndarray, p: float) -> np.ndarray:
    """(|ax|^p + |ay|^p)^(1/p) for non-negative ax, ay, as m (1 + (n/m)^p)^(1/p) (m, n = max, min): two powers."""
    if p == 2.0:
        return np.sqrt(ax * ax + ay * ay)
    if p == 1.0:
        return ax + ay
    m, n = np.maximum(ax, ay), np.minimum(ax, ay)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = n / m
    return np.where(m > 0.0, m * (1.0 + r ** p) ** (1.0 / p), m)


def _trig(name: str, a) -> np.ndarray:
    """float64 cos / sin through torch's vectorised kernels: numpy's float64 sin and cos measured 7.7 ns per
    element here against 1.3 ns (both within 1 ulp); the PPTBF's stripes and cell polygons are full of them."""
    import torch

    arr = np.ascontiguousarray(a, dtype=np.float64)
    out = np.empty_like(arr)
    src, dst, fn = torch.from_numpy(arr).reshape(-1), torch.from_numpy(out).reshape(-1), getattr(torch, name)
    for s in range(0, src.shape[0], _TRIG_PIECE):   # below torch's grain size: no intra-op threads, which
        fn(src[s:s + _TRIG_PIECE], out=dst[s:s + _TRIG_PIECE])   # competed with our chunk threads (measured)
    return out


_TRIG_PIECE = 32768


def _cos(a) -> np.ndarray:
    """cos(a) in float64 (see _trig)."""
    return _trig("cos", a)


def _sin(a) -> np.ndarray:
    """sin(a) in float64 (see _trig)."""
    return _trig("sin", a)


_BIG = 1e30


def _inv_side(den: np.ndarray) -> np.ndarray:
    """1 / den with 0 -> 1e30 (so that 0 * it = 0 and a * it is huge: the reference's 0/0, a/0 without NaN)."""
    return 1.0 / np.where(den == 0.0, 1.0 / _BIG, den)


def side_inverses(px, py, ccx, ccy, chx, chy) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Inverse distances from points to their cell sides (left, right, bottom, top), for the larp term of D."""
    return (_inv_side(px - ccx + chx), _inv_side(ccx + chx - px), _inv_side(py - ccy + chy),
            _inv_side(ccy + chy - py))


def rank_distance(dx, dy, inv, norm: float, larp: float) -> np.ndarray:
    """Ranking distance D(q, p) = (1 - larp) ||q - p||_norm + larp max(e_x, e_y) from d = q - p (spec §2.3).

    inv = side_inverses of p's cell: e_x = |d_x| / (distance from p to the cell side facing q).
    """
    ax, ay = np.abs(dx), np.abs(dy)
    out = (1.0 - larp) * _minkowski(ax, ay, norm) if larp != 1.0 else 0.0
    if larp != 0.0:
        ex = ax * np.where(dx < 0.0, inv[0], inv[1])
        ey = ay * np.where(dy < 0.0, inv[2], inv[3])
        out = out + larp * np.maximum(ex, ey)
    return out


@dataclass
class PixelStructure:
    """Per-pixel discrete data of a chunk: neighbour point ids, and the cellular sector / border radii."""

    nbr: np.ndarray           # (h, w, K) point ids (0 where invalid)
    nbr_valid: np.ndarray     # (h, w, K)
    ka: np.ndarray | None = None        # (h, w) sector index
    up: np.ndarray | None = None        # (h, w) bool: the ray passes the upper half (third radius at ka+2, else ka-1)
    rho: np.ndarray | None = None       # (h, w, 3) border radii at sectors ka, ka+1 and ka+2 (up) / ka-1
    rho_comp: np.ndarray | None = None  # (h, w, 3) point id of the competing point at each border (-1: none)

    def rows(self, sl: slice) -> "PixelStructure":
        """The same data for a range of the chunk's rows (views)."""
        return PixelStructure(*(None if v is None else v[sl] for v in (self.nbr, self.nbr_valid, self.ka, self.up,
                                                                      self.rho, self.rho_comp)))


def rank_pixels(x: np.ndarray, y: np.ndarray, code: np.ndarray, st: Structure, d: Decoded) -> PixelStructure:
    """Each pixel's nearest min(n_c, 18) candidates by D, the closest first (the others in no particular order:
    the shading sums over them; a full sort measured ~20 % of the ranking)."""
    cand, cval = st.cand[code], st.cand_valid[code]
    P = st.points
    inv = tuple(v[cand] for v in P.inv) if d.larp != 0.0 else ()
    D = rank_distance(x[..., None] - P.px[cand], y[..., None] - P.py[cand], inv, d.wnorm, d.larp)
    D = np.where(cval, D, np.inf)
    C = cand.shape[-1]
    k = min(C, MAX_NEIGHBOURS)
    if C > k:
        # ties -> lower index (as the reference's strict minimum search)
        D = D + np.arange(C) * 1e-13
        order = np.argpartition(D, k - 1, axis=-1)[..., :k]
        Dk = np.take_along_axis(D, order, -1)
    else:
        order = np.broadcast_to(np.arange(C), D.shape).copy()
        Dk = D
    first = np.argmin(Dk, axis=-1)[..., None]          # the closest to the front (ties: lowest index)
    lead = np.take_along_axis(order, first, -1)
    np.put_along_axis(order, first, order[..., :1], -1)
    order[..., :1] = lead
    nbr_valid = np.take_along_axis(cval, order, -1)
    nbr = np.where(nbr_valid, np.take_along_axis(cand, order, -1), 0)
    return PixelStructure(nbr, nbr_valid)


#: points searched for the border of p0's cell: its nearest (L2). With larp a farther point can win (p0 close to a
#: side of its own cell); measured on database parameters at 256 px, the share of radii that differ from using
#: 48: 1.1 % with 12, 0.26 % with 16, 0.02 % with 24 (max 0.3 %), 0 with 36; 24 costs 15 % more than 16
BORDER_NEIGHBOURS = 24


class BorderMemo:
    """Border radii of the last finished chunk, by query key (point, sector), shared by the chunks of one
    evaluation. A cell spans many row chunks (e.g. 192 rows at 1024 px against 4-row chunks), and a key gives the
    same radius in every chunk, so most keys are looked up instead of solved again. Identical results;
    thread-safe (a chunk reads one published snapshot and publishes a new one)."""

    def __init__(self) -> None:
        self.latest: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def lookup(self, ukey: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """(hit mask, rho, comp) for sorted unique keys; None before the first chunk is published."""
        return _lookup(self.latest, ukey)

    def publish(self, parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> None:
        """Make this chunk's (keys, rho, comp) parts the snapshot the next chunks look up."""
        if not parts:
            return
        keys = np.concatenate([q[0] for q in parts])
        _, first = np.unique(keys, return_index=True)
        self.latest = (keys[first], np.concatenate([q[1] for q in parts])[first],
                       np.concatenate([q[2] for q in parts])[first])


def _lookup(snap, ukey: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(hit mask, rho, comp) of keys in a (sorted keys, rho, comp) snapshot; None for no snapshot."""
    if snap is None or snap[0].size == 0:
        return None
    keys, rho, comp = snap
    i = np.minimum(np.searchsorted(keys, ukey), keys.size - 1)
    return keys[i] == ukey, rho[i], comp[i]


def _border_queries(p0, j, st: Structure, d: Decoded, need_comp: bool, memo: BorderMemo | None = None,
                    pending: list | None = None):
    """Border radii for per-pixel queries (point p0, sector j), deduplicated, looked up from the memo's previous
    chunk and from this chunk's earlier queries (``pending``, to which the results are appended), the rest solved.
    """
    nsec = d.n_sectors + 4
    key = p0[..., None].astype(np.int64) * nsec + (j + 1)
    ukey, inv = unique_inverse(key)
    rho = np.empty(ukey.shape[0])
    comp = np.empty(ukey.shape[0], dtype=np.int64)
    todo = np.arange(ukey.shape[0])
    finders = ([memo.lookup] if memo is not None else []) + [partial(_lookup, snap) for snap in pending or ()]
    for find in finders:
        found = find(ukey[todo])
        if found is not None:
            hit, r, c = found
            rho[todo[hit]], comp[todo[hit]] = r[hit], c[hit]
            todo = todo[~hit]
    if todo.size:
        rho[todo], comp[todo] = _border_keys(ukey[todo], st, d)
    if pending is not None:
        pending.append((ukey, rho, comp))
    rho_px = rho[inv].reshape(j.shape)
    return (rho_px, comp[inv].reshape(j.shape)) if need_comp else (rho_px, None)


BORDER_BLOCK = 2048   # queries solved at once (cache-sized temporaries: measured 4x faster than one pass)


def _border_keys(ukey: np.ndarray, st: Structure, d: Decoded) -> tuple[np.ndarray, np.ndarray]:
    """Exact border radii of unique (point, sector) keys and the competing point at each (-1: none)."""
    T, P = st.border, st.points
    nsec = d.n_sectors + 4
    rho = np.empty(ukey.shape[0])
    comp = np.empty(ukey.shape[0], dtype=np.int64)
    larp = d.larp != 0.0
    for s in range(0, ukey.shape[0], BORDER_BLOCK):
        k = ukey[s:s + BORDER_BLOCK]
        p0, sec = k // nsec, k % nsec - 1
        r0 = T.row[p0]
        # float32 trig is vectorised in numpy (the solver runs in BORDER_DTYPE anyway)
        th = (sec * d.delta + d.delta * P.rot_u[p0]).astype(BORDER_DTYPE)
        r, c = first_exit(np.cos(th), np.sin(th), T.rx[r0], T.ry[r0],
                          tuple(v[r0] for v in T.inv) if larp else (), T.valid[r0],
                          tuple(v[r0] for v in T.inv0) if larp else (), d.larp)
        rho[s:s + BORDER_BLOCK] = r
        comp[s:s + BORDER_BLOCK] = np.where(c >= 0, T.nbr[r0, np.maximum(c, 0)], -1)
    return rho, comp


def upper_branch(alpha, p0x, p0y, ta, rho_a, rho_b, delta: float) -> np.ndarray:
    """Whether the ray at angle alpha lies past the midpoint M of the sector's border points A, B (spec §2.6)."""
    ax, ay = p0x + rho_a * _cos(ta), p0y + rho_a * _sin(ta)
    bx, by = p0x + rho_b * _cos(ta + delta), p0y + rho_b * _sin(ta + delta)
    mx, my = 0.5 * (ax + bx), 0.5 * (ay + by)
    am = np.mod(np.arctan2(my - p0y, mx - p0x), 2.0 * math.pi)
    far = np.abs(alpha - am) > 2.0 * delta
    am = np.where(far & (alpha < 2.0 * delta), am - 2.0 * math.pi,
                  np.where(far & (alpha > 2.0 * math.pi - 2.0 * delta), am + 2.0 * math.pi, am))
    return alpha > am


def pixel_sectors(x, y, ps: PixelStructure, st: Structure, d: Decoded) -> tuple[np.ndarray, np.ndarray]:
    """(alpha, ka): each pixel's angle about its closest point and the cellular window's sector it lies in."""
    P = st.points
    p0 = ps.nbr[..., 0]
    alpha = np.mod(np.arctan2(y - P.py[p0], x - P.px[p0]), 2.0 * math.pi)
    palpha = alpha - d.delta * P.rot_u[p0]
    palpha = np.where(palpha < 0.0, palpha + 2.0 * math.pi, palpha)
    return alpha, np.floor(palpha / d.delta).astype(np.int64)


def cellular_sectors(x, y, ps: PixelStructure, st: Structure, d: Decoded, need_comp: bool = False,
                     memo: BorderMemo | None = None) -> None:
    """Fill ps.ka / up / rho / rho_comp: the closest cell's border radii at sectors ka, ka+1 and ka+2 or ka-1."""
    pending: list = []
    P = st.points
    p0 = ps.nbr[..., 0]
    p0x, p0y = P.px[p0], P.py[p0]
    alpha, ka = pixel_sectors(x, y, ps, st, d)
    delta = d.delta
    rot = delta * P.rot_u[p0]
    rho_ab, comp_ab = _border_queries(p0, ka[..., None] + np.arange(2), st, d, need_comp, memo, pending)
    ta = ka * delta + rot
    up = upper_branch(alpha, p0x, p0y, ta, rho_ab[..., 0], rho_ab[..., 1], delta)
    rho_c, comp_c = _border_queries(p0, np.where(up, ka + 2, ka - 1)[..., None], st, d, need_comp, memo, pending)
    if memo is not None:
        memo.publish(pending)
    ps.ka, ps.up = ka, up
    ps.rho = np.concatenate([rho_ab, rho_c], axis=-1)
    if need_comp:
        ps.rho_comp = np.concatenate([comp_ab, comp_c], axis=-1)


def pixel_structure(x, y, code, st: Structure, d: Decoded, need_comp: bool = False,
                    memo: BorderMemo | None = None) -> PixelStructure:
    """Ranking plus (when the cellular window is used) the border radii (and competitors) for a chunk of pixels;
    ``memo`` (one per evaluation) reuses the previous chunk's border radii."""
    ps = rank_pixels(x, y, code, st, d)
    if uses_cellular(d):
        cellular_sectors(x, y, ps, st, d, need_comp, memo)
    return ps


def uses_cellular(d: Decoded) -> bool:
    """The cellular window matters only with beta > 0 and a windowed mixture."""
    return d.beta != 0.0 and d.mixture not in (3, 4)


# --------------------------------------------------------------------------------------------------------------
# Shading (numpy): windows, cellular window, features, mixtures (spec §2.5-2.7)
# --------------------------------------------------------------------------------------------------------------

def _wnorm(ax: np.ndarray, ay: np.ndarray, p: float) -> np.ndarray:
    """Minkowski norm blended towards L-inf for p > 2 (windows and features)."""
    r = _minkowski(ax, ay, p)
    if p > 2.0:
        r = (p - 2.0) * np.maximum(ax, ay) + (3.0 - p) * r
    return r


def classical_window(r: np.ndarray, d: Decoded) -> np.ndarray:
    """g_k(r) for the 4 window shapes, clamped to [0, 1]."""
    F = d.footprint
    if d.shape in (0, 1):
        g = (np.exp(-2.0 * r) - math.exp(-2.0 * F)) / (1.0 - math.exp(-2.0 * F))
    elif d.shape == 2:
        g = 1.0 - r / F
    else:
        g = (r <= F).astype(np.float64)
    return np.clip(g, 0.0, 1.0)


def _lam(p0x, p0y, wx, wy, ax, ay, bx, by):
    """Ray (p0 + lam w) / line (A, B) intersection parameter."""
    ux, uy = bx - ax, by - ay
    n = np.sqrt(ux * ux + uy * uy)
    ux, uy = ux / n, uy / n
    return (ux * (p0y - ay) - uy * (p0x - ax)) / (wx * uy - wy * ux)


def cellular_cv(qx, qy, p0x, p0y, rot, ka, up, rho, d: Decoded) -> np.ndarray:
    """Cellular coordinate cv in [0, 1] of the closest cell (polygon / midpoint polygon / Bezier blend)."""
    delta = d.delta
    dx, dy = qx - p0x, qy - p0y
    sdd = np.sqrt(dx * dx + dy * dy)
    with np.errstate(divide="ignore", invalid="ignore"):
        wx, wy = dx / sdd, dy / sdd
        ta = ka * delta + rot

        def pt(r, t):
            return p0x + r * _cos(t), p0y + r * _sin(t)

        ax, ay = pt(rho[..., 0], ta)
        bx, by = pt(rho[..., 1], ta + delta)
        mx, my = 0.5 * (ax + bx), 0.5 * (ay + by)
        cx_, cy_ = pt(rho[..., 2], np.where(up, ta + 2.0 * delta, ta - delta))
        nx, ny = np.where(up, 0.5 * (bx + cx_), 0.5 * (ax + cx_)), np.where(up, 0.5 * (by + cy_), 0.5 * (ay + cy_))
        # segment (s0 -> s1) of the midpoint polygon crossed by the ray, Bezier control point ctl
        s0x, s0y = np.where(up, mx, nx), np.where(up, my, ny)
        s1x, s1y = np.where(up, nx, mx), np.where(up, ny, my)
        ctlx, ctly = np.where(up, bx, ax), np.where(up, by, ay)
        lam = _lam(p0x, p0y, wx, wy, s0x, s0y, s1x, s1y)
        sx, sy = p0x + lam * wx, p0y + lam * wy
        t = np.hypot(sx - s0x, sy - s0y) / np.hypot(s1x - s0x, s1y - s0y)
        qbx = (1 - t) ** 2 * s0x + 2 * t * (1 - t) * ctlx + t * t * s1x
        qby = (1 - t) ** 2 * s0y + 2 * t * (1 - t) * ctly + t * t * s1y
        r0 = _lam(p0x, p0y, wx, wy, ax, ay, bx, by)
        r1 = np.hypot(sx - p0x, sy - p0y)
        r2 = np.hypot(qbx - p0x, qby - p0y)
        sm = d.smooth
        if sm < 1.0:
            cv = (1.0 - sm) * (1.0 - sdd / r0) + sm * (1.0 - sdd / r1)
        elif sm < 2.0:
            cv = (2.0 - sm) * (1.0 - sdd / r1) + (sm - 1.0) * (1.0 - sdd / r2)
        else:
            cv = 1.0 - sdd / r2
    cv = np.clip(np.nan_to_num(cv, nan=0.0), 0.0, 1.0)
    return np.where(sdd < 1e-4, 1.0, cv)


def cellular_weight(cv: np.ndarray, sigma: float) -> np.ndarray:
    """Wc = (exp(sigma (cv - 1)) - exp(-sigma)) / (1 - exp(-sigma)) (-> cv as sigma -> 0)."""
    if sigma < 1e-6:
        return cv
    return (np.exp(sigma * (cv - 1.0)) - math.exp(-sigma)) / (1.0 - math.exp(-sigma))


@dataclass
class KernelTable:
    """Per kernel index and point (kmax, N): the kernel frame as an affine map of the pixel, decay and weight.

    u = au x + bu y + cu and v = av x + bv y + cv are the cell-normalised, rotated (and aniso-scaled) offsets of
    the spec's dl; s is the decay over the footprint; w the signed value (mixture 1) or the priority (mixture 3).
    """

    au: np.ndarray
    bu: np.ndarray
    cu: np.ndarray
    av: np.ndarray
    bv: np.ndarray
    cv: np.ndarray
    s: np.ndarray
    w: np.ndarray

    @property
    def kmax(self) -> int:
        """Kernel slots per point."""
        return self.au.shape[0]


def kernel_table(P: PointTable, d: Decoded) -> KernelTable:
    """Everything about the kernels that does not depend on the pixel, computed once per point."""
    kd = P.kdraw
    lx = P.ccx[:, None] + 0.99 * kd[..., 2] * P.chx[:, None]
    ly = P.ccy[:, None] + 0.99 * kd[..., 3] * P.chy[:, None]
    lx = d.corr * P.px[:, None] + (1.0 - d.corr) * lx
    ly = d.corr * P.py[:, None] + (1.0 - d.corr) * ly
    th = d.theta_max * kd[..., 4]
    ct, st_ = np.cos(th), np.sin(th)
    with np.errstate(divide="ignore", invalid="ignore"):
        ihx, ihy = 1.0 / P.chx[:, None], 1.0 / P.chy[:, None]
        sv = 2.0 ** -d.aniso
        au, bu = ihx * ct, -ihy * st_
        av, bv = ihx * st_ * sv, ihy * ct * sv
        cu, cv = -(au * lx + bu * ly), -(av * lx + bv * ly)
    s = d.sigcos * (1.0 + (0.5 * kd[..., 5] + 0.5) * d.sigcosvar) / d.footprint
    if d.mixture == 3:
        w = 0.5 * kd[..., 1] + 0.5
    else:
        w = np.where(kd[..., 0] < 0.0, -0.25 + 0.75 * kd[..., 0], 0.25 + 0.75 * kd[..., 0])
    return KernelTable(*(np.ascontiguousarray(a.T) for a in (au, bu, cu, av, bv, cv, s, w)))


#: decay beyond which a kernel is dropped where its value is added to the 0.5 base of mixture 1 (or to the sin^2
#: phi base of mixture 2): exp(-23) = 1e-10, invisible in the float32 output; elsewhere 87 (float32 underflow)
DDIST_CUT_BASED = 23.0
DDIST_CUT = 87.0


def _stripes(u: np.ndarray, v: np.ndarray, d: Decoded) -> np.ndarray:
    """Feature stripes ff = (0.5 + 0.5 cos(pi freq sqrt((curv u)^2 + v^2)))^(1 / (1e-4 + thick))."""
    if d.freq == 0:
        return np.ones_like(u)
    cu = d.curv * u
    return (0.5 + 0.5 * _cos(math.pi * d.freq * np.sqrt(cu * cu + v * v))) ** (1.0 / (1e-4 + d.thick))


def _ddist_cut(d: Decoded) -> float:
    """Decay beyond which kernels cannot change the float32 output (mixture 3 uses only ddist < 1)."""
    if d.mixture == 3:
        return 1.0
    if d.mixture == 1 or (d.mixture == 2 and math.sin(d.phi) ** 2 > 1e-3):
        return DDIST_CUT_BASED
    return DDIST_CUT


def pair_features(qx, qy, pid, P: PointTable, K: KernelTable, d: Decoded):
    """Kernel sums of (pixel, point) pairs, kernel index by kernel index over the pairs that have it.

    Returns per pair: sum ff val exp(-ddist) (mixture 1), sum ff exp(-ddist) (2), max ff exp(-ddist) (4), or
    (mixture 3) the (priority, 2 (ff - 0.5) exp(-ddist)) of its first highest-priority kernel with ddist < 1 and
    ff > 0.5 (priority -1: none).
    """
    nk = P.nk[pid]
    order = np.argsort((K.kmax - nk).astype(np.int8), kind="stable")   # radix sort; more kernels first
    qx, qy, ps = qx[order], qy[order], pid[order]
    counts = np.bincount(nk, minlength=K.kmax + 1)[::-1].cumsum()[::-1]   # counts[i] = #pairs with nk >= i
    acc = np.full(pid.shape[0], -1.0 if d.mixture == 3 else 0.0)      # mixture 3: best priority, -1 = none
    val = np.zeros(pid.shape[0]) if d.mixture == 3 else None
    cut = _ddist_cut(d)
    for i in range(K.kmax):
        c = int(counts[i + 1])
        if c == 0:
            break
        p, x, y = ps[:c], qx[:c], qy[:c]
        u = K.au[i][p] * x + K.bu[i][p] * y + K.cu[i][p]
        v = K.av[i][p] * x + K.bv[i][p] * y + K.cv[i][p]
        dd = _wnorm(np.abs(u), np.abs(v), d.fnorm) * K.s[i][p]
        near = dd < cut
        tgt: slice | np.ndarray = slice(0, c)
        if np.count_nonzero(near) < 0.75 * c:      # most kernels too far: the stripes only where they matter
            tgt = np.flatnonzero(near)
            u, v, dd, p = u[tgt], v[tgt], dd[tgt], p[tgt]
        ff = _stripes(u, v, d)
        e = np.exp(-dd)
        if d.mixture == 1:
            acc[tgt] += ff * e * K.w[i][p]
        elif d.mixture == 2:
            acc[tgt] += ff * e
        elif d.mixture == 4:
            acc[tgt] = np.maximum(acc[tgt], ff * e)
        else:
            pr, cur = K.w[i][p], acc[tgt]
            upd = (dd < 1.0) & (ff > 0.5) & (pr > cur)
            acc[tgt] = np.where(upd, pr, cur)
            val[tgt] = np.where(upd, 2.0 * (ff - 0.5) * e, val[tgt])
    back = np.empty_like(order)
    back[order] = np.arange(order.shape[0])
    return acc[back] if val is None else (acc[back], val[back])


def _mixture_value(x, y, pix, pid, win_sel, P: PointTable, K: KernelTable, d: Decoded, n_pix: int) -> np.ndarray:
    """V per pixel (flat) of mixtures 1-4 from the selected (pixel, point) pairs (pixel-major order)."""
    feats = pair_features(x.reshape(-1)[pix], y.reshape(-1)[pix], pid, P, K, d)
    V = np.zeros(n_pix)
    if d.mixture in (1, 2):
        F = 0.5 + 0.5 * feats if d.mixture == 1 else feats / max(d.npmax // 2, 1)
        cp, sp = math.cos(d.phi) ** 2, math.sin(d.phi) ** 2
        F = F * cp + (1.0 - F) * sp
        return np.bincount(pix, weights=win_sel * F, minlength=n_pix)
    if d.mixture == 4:
        np.maximum.at(V, pix, feats)
        return V
    pr, value = feats
    ok = np.flatnonzero(pr >= 0.0)
    if ok.size:
        top = np.full(n_pix, -1.0)
        np.maximum.at(top, pix[ok], pr[ok])
        hit = ok[pr[ok] == top[pix[ok]]]
        upix, first = np.unique(pix[hit], return_index=True)    # ties: the first pair in neighbour order
        V[upix] = value[hit[first]]
    return V


def shade(x, y, ps: PixelStructure, P: PointTable, d: Decoded, K: KernelTable | None = None) -> np.ndarray:
    """PPTBF value V of a chunk of pixels from its structure (numpy reference of the shading)."""
    h, w = x.shape
    nbr, val = ps.nbr, ps.nbr_valid
    win = np.zeros(nbr.shape)
    if d.mixture not in (3, 4):
        dx, dy = x[..., None] - P.px[nbr], y[..., None] - P.py[nbr]
        win = np.where(val, (1.0 - d.beta) * classical_window(_wnorm(np.abs(dx), np.abs(dy), d.wnorm), d), 0.0)
        if uses_cellular(d):
            p0 = nbr[..., 0]
            cv = cellular_cv(x, y, P.px[p0], P.py[p0], d.delta * P.rot_u[p0], ps.ka, ps.up, ps.rho, d)
            win[..., 0] += d.beta * cellular_weight(cv, d.sigma_w)
    if d.mixture in (0, 5):
        V = win.sum(-1) * (1.0 if d.mixture == 0 else math.cos(d.phi) ** 2)
    else:
        sel = val & (win != 0.0) if d.mixture in (1, 2) else val
        pix, kk = np.nonzero(sel.reshape(h * w, -1))
        pid = nbr.reshape(h * w, -1)[pix, kk]
        K = kernel_table(P, d) if K is None else K
        V = _mixture_value(x, y, pix, pid, win.reshape(h * w, -1)[pix, kk], P, K, d, h * w).reshape(h, w)
    if d.mixture not in (3, 4) and d.shape == 0:
        ws = win.sum(-1)
        V = np.where(ws > 0.0, V / np.where(ws > 0.0, ws, 1.0), V)
    return np.maximum(V, 0.0)


#: sectors on either side of a pixel's own whose polygon sides the border distance also measures (see
#: border_distance): a pixel within w of a side sees it within asin(w / r) of its own direction from the point
BORDER_FAN = 3


def border_distance(x, y, ps: PixelStructure, st: Structure, d: Decoded, zoom: float,
                    memo: BorderMemo | None = None) -> np.ndarray:
    """Distance (in reference widths, inside > 0) from each pixel to the border of its closest point's cell: the
    polygon through the cellular window's border points (the radii at the sector rays), measured in the image.

    The cellular window's coordinate is the cell scaled about its point (``cellular_cv``): cut at one level, the
    band it leaves along a side is as wide as that side's distance from the point, so the bed joints of bricks
    twice as long as high came out half as wide as the head joints. Cut at one level, this distance leaves a
    band of one width along every side. The sides measured are those of the pixel's sector and BORDER_FAN
    sectors either side (a pixel near a corner is nearer the other side than its own), each side's distance
    taken through the domain's rotation and aspect (distortion is not followed: crisp cells have none), the
    smallest kept. Needs the cellular window (``uses_cellular``)."""
    P = st.points
    p0 = ps.nbr[..., 0]
    p0x, p0y = P.px[p0], P.py[p0]
    rot = d.delta * P.rot_u[p0]
    j = pixel_sectors(x, y, ps, st, d)[1][..., None] + np.arange(-BORDER_FAN, BORDER_FAN + 2)
    pending: list = []
    rho, _ = _border_queries(p0, np.mod(j, d.n_sectors), st, d, False, memo, pending)
    if memo is not None:
        memo.publish(pending)
    t = j * d.delta + rot[..., None]
    vx, vy = p0x[..., None] + rho * _cos(t), p0y[..., None] + rho * _sin(t)
    ex, ey = vx[..., 1:] - vx[..., :-1], vy[..., 1:] - vy[..., :-1]            # sides, counter-clockwise
    cross = ex * (y[..., None] - vy[..., :-1]) - ey * (x[..., None] - vx[..., :-1])   # > 0 inside
    scale = zoom * np.hypot(ey / d.aspect, ex)      # |J^T e_perp|: domain -> image distance across the side
    with np.errstate(divide="ignore", invalid="ignore"):
        dist = np.where(scale > 0.0, cross / scale, np.inf)
    return dist.min(-1)


# --------------------------------------------------------------------------------------------------------------
# Public API
# --------------------------------------------------------------------------------------------------------------

#: what ``evaluate`` returns per pixel: the PPTBF value V, or the distance to the cell's border
FIELDS = ("value", "border")

CHUNK_ELEMS = 1 << 19   # measured: smaller chunks are faster (cache), 2^19..2^20 best


def _chunk_rows(width: int, per_pixel: int) -> int:
    """Rows per chunk so that a chunk holds about CHUNK_ELEMS per-pixel-candidate elements."""
    return max(1, CHUNK_ELEMS // max(1, width * per_pixel))


def chunk_plan(width: int, n_cand: int, d: Decoded) -> tuple[int, int]:
    """(rows of a structure chunk: ranking + borders over n_cand candidates, rows of its shading sub-chunks:
    18 neighbours x kmax kernels). Larger structure chunks batch more border rays per solver call (measured: the
    per-call overhead dominated with the shading's 3-4 row chunks at 512 px)."""
    sub = _chunk_rows(width, n_cand * max(1, d.kmax))
    rows = max(sub, _chunk_rows(width, n_cand))
    return rows - rows % sub, sub


def prepare(params, width: int, height: int | None = None, *, shift=(0.0, 0.0), pixel_scale: float = 1.0,
            ref_width: int | None = None, stable: bool = False, threads: int = 1):
    """Decode params, compute domain coordinates and the structure (shared by numpy and torch evaluation)."""
    height = width if height is None else height
    if width < 1 or height < 1:
        raise ValueError(f"PPTBF image size must be positive, got {width}x{height}")
    if pixel_scale <= 0:
        raise ValueError(f"PPTBF pixel_scale must be > 0, got {pixel_scale}")
    d = decode(params)
    zoom = float(ref_width or width) / d.res
    x0, y0 = base_coords(width, height, shift, pixel_scale, ref_width)
    x, y = domain_coords(x0, y0, d, zoom)
    return d, zoom, x, y, build_structure(x, y, d, stable, threads)


def default_threads() -> int:
    """Threads for chunked evaluation: the CPUs Ray gave this task (OMP_NUM_THREADS), else all, at most 4."""
    env = os.environ.get("OMP_NUM_THREADS", "")
    n = int(env) if env.isdigit() and int(env) > 0 else (os.cpu_count() or 1)
    return max(1, min(n, 4))


def evaluate(params, width: int, height: int | None = None, *, shift=(0.0, 0.0), pixel_scale: float = 1.0,
             ref_width: int | None = None, threads: int | None = None, cells: bool = False,
             field: str = "value"):
    """Raw PPTBF V (H, W) float32 (``field="border"``: instead the distance to the cell's border,
    :func:`border_distance`, for cellular windows).

    `ref_width` is the width at which the parameters are defined (default: width): the period is
    int(resolution) * pixel_scale pixels whatever the output width, so a larger width extends the pattern and
    pixel_scale=2 doubles its size (the distortion follows). `shift` (in reference widths) picks the realisation.
    Row chunks are independent and numpy releases the GIL in them: `threads` (default `default_threads()`)
    evaluate them in parallel with the same result (measured at 512 px: median 0.47 s -> 0.34 s on 2 cores).
    ``cells``: also return each pixel's cell key (H, W) int64, the :func:`cell_keys` of its closest point.
    """
    threads = default_threads() if threads is None else max(1, int(threads))
    if field not in FIELDS:
        raise ValueError(f"PPTBF field must be one of {', '.join(FIELDS)}, got {field!r}")
    d, zoom, x, y, st = prepare(params, width, height, shift=shift, pixel_scale=pixel_scale, ref_width=ref_width,
                                threads=threads)
    border = field == "border"
    if border and not uses_cellular(d):
        raise ValueError("the PPTBF border field needs the cellular window (window_blend > 0, a windowed mixture)")
    out = np.empty(x.shape, dtype=np.float32)
    keys = np.empty(x.shape, dtype=np.int64) if cells else None
    K = kernel_table(st.points, d)
    rows, sub = chunk_plan(x.shape[1], st.cand.shape[1], d)
    memo = BorderMemo()

    def run(r0: int) -> None:
        sl = slice(r0, r0 + rows)
        if border:     # the ranking only: the border distance solves its own sectors' radii
            ps = rank_pixels(x[sl], y[sl], st.code[sl], st, d)
            out[sl] = border_distance(x[sl], y[sl], ps, st, d, zoom, memo)
        else:
            ps = pixel_structure(x[sl], y[sl], st.code[sl], st, d, memo=memo)
            for s0 in range(0, ps.nbr.shape[0], sub):
                s1 = slice(s0, s0 + sub)
                out[r0 + s0:r0 + s0 + sub] = shade(x[sl][s1], y[sl][s1], ps.rows(s1), st.points, d, K)
        if keys is not None:
            keys[sl] = st.points.cell[ps.nbr[..., 0]]

    starts = range(0, x.shape[0], rows)
    n = min(len(starts), threads)
    if n <= 1:
        for r0 in starts:
            run(r0)
    else:
        with ThreadPoolExecutor(n) as pool:
            list(pool.map(run, starts))
    return (out, keys) if cells else out


#: for the border field: the cut moves into a gap between values at least this wide (reference widths), by at
#: most GAP_SHARE of the pixels (see cut_level: on straight cells one side of every cell in a row of cells has
#: one distance, a few % of the pixels)
BORDER_GAP = 1e-5
GAP_SHARE = 0.05


def field_gap(field: str) -> float:
    """The gap a cut of ``field`` sits in (:func:`cut_level`): the border distance's sides are near plateaus."""
    return BORDER_GAP if field == "border" else 0.0


def cut_level(values: np.ndarray, threshold: float, gap: float = 0.0) -> float:
    """The level ``binarize`` cuts at: quantile(V, 1 - T) over the finite values (inf when there are none).

    With ``gap`` > 0, the middle of the nearest gap between consecutive values at least ``gap`` wide, within
    GAP_SHARE of the pixels of that quantile (the quantile itself where there is none). A crisp cell's border
    distance is nearly one value along a whole side (within 1e-7), and along the same side of every cell in a row
    of straight cells, so the quantile falls inside such a cluster and a float32 shader put part of a side on
    either side of it (a running bond: 99.3 % of pixels equal numpy's); a cut in a gap keeps every side whole in
    both, at a share that can differ from T by such a cluster."""
    v = np.asarray(values, dtype=np.float64)
    finite = np.sort(v[np.isfinite(v)], axis=None)
    if not finite.size:
        return float("inf")
    q = min(max(1.0 - float(threshold), 0.0), 1.0)
    cut = float(np.quantile(finite, q))
    if gap <= 0.0 or finite.size < 2:
        return cut
    k = int(np.searchsorted(finite, cut, side="right")) - 1          # the last value <= cut
    reach = max(1, int(GAP_SHARE * finite.size))
    lo, hi = max(0, k - reach), min(finite.size - 1, k + reach)
    steps = np.diff(finite[lo:hi + 1])
    wide = np.nonzero(steps >= gap)[0]
    if not wide.size:
        return cut
    j = lo + wide[np.argmin(np.abs(lo + wide - k))]
    return 0.5 * (finite[j] + finite[j + 1])


def binarize(values: np.ndarray, threshold: float, gap: float = 0.0) -> np.ndarray:
    """Percentile threshold (spec §3): white = V > quantile(V, 1 - T), so T ~ white fraction; non-finite -> 0.
    ``gap``: the cut is moved into a gap between values (:func:`cut_level`)."""
    v = np.asarray(values, dtype=np.float64)
    finite = np.isfinite(v)
    if not finite.any():
        return np.zeros(v.shape, dtype=bool)
    return finite & (np.where(finite, v, -np.inf) > cut_level(v, threshold, gap))


def render_mask(params, width: int, height: int | None = None, **kw) -> np.ndarray:
    """Binary PPTBF mask: evaluate then binarize with the vector's own threshold (entry 0)."""
    p = _as_params(params)
    return binarize(evaluate(p, width, height, **kw), p[0], field_gap(kw.get("field", "value")))


def evaluate_torch(params, width: int, height: int | None = None, *, shift=(0.0, 0.0), pixel_scale: float = 1.0,
                   ref_width: int | None = None, stable: bool = False, device=None, dtype=None):
    """Differentiable torch PPTBF (H, W) tensor; equals `evaluate` in float64 exact mode (see pptbf_torch.py)."""
    from pptbf_db.pptbf_torch import evaluate_torch as _evaluate_torch

    return _evaluate_torch(params, width, height, shift=shift, pixel_scale=pixel_scale, ref_width=ref_width,
                           stable=stable, device=device, dtype=dtype)
