"""The structural first split of an automatic decomposition: the thin network of a layout (mortar, grout, panel
seams, slate edges), found in the relief before any colour.

A brick wall's first split is mortar vs bricks, not "dark" vs "light": a colour split puts dark stains with the
mortar and loses the seams of a metal plate. Candidates are binary masks cut from *structure sources*: the relief
(height from the normals, high-passed at a fine and a coarse scale, low = a groove; the normals' tilt, high = an
edge or a step; each high-passed normal slope component, one sign at a time = steps facing one way: the lower
edges of overlapping slates or shingles, which the tilt mixes with the wood grain inside them) and, when the
relief shows no layout, the albedo's high-passed luminance (dark lines). Each source is cut at a few shares of the
pixels and the lattice analysis (workers.lattice) scores every cut; the cut with a significant 2-D lattice whose
autocorrelation repeats most (regularity) shows the layout, or rows that repeat far more clearly (``layout_rank``;
a one-directional repeat is often a harmonic of the layout: roof_slates_02's fine grooves repeat at half the
slates' spacing); the split is the thinnest cut of that layout ranked nearly as high (``_thinnest``: wider bands
repeat more smoothly than the network itself). A cut that the median filter thins to under ``min_kept`` of its
share is lines thinner than the filter (the two 1 px flanks of a 2 px groove in the tilt): its remnant can repeat
very regularly while it misses most of the network (a running bond of 8 px courses: IoU 0.41 with the mortar
against 0.65), so it is not a candidate. The chosen cut's white pixels are layer 0 (the network), the rest layer
1. Sources and cuts are analysed at no more than ``analysis_size`` px (area-averaged), the chosen cut is made at
full size. Materials without a layout (rust, sand, plaster) return None and keep the colour matting.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Mapping, NamedTuple

import numpy as np
from scipy import ndimage

from .lattice import Lattice, LatticeConfig, analyse_lattice

logger = logging.getLogger(__name__)

_LUMA = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)


@dataclass
class StructureConfig:
    """Where and how the structure is looked for."""

    shares: tuple[float, ...] = (0.08, 0.15, 0.25, 0.35)   # shares of the pixels a cut keeps as the network
    sigmas: tuple[float, ...] = (3.0 / 512, 12.0 / 512)   # high-pass scales, as fractions of the working width
    analysis_size: int = 512                               # longer side of the lattice analysis (256 px changed
    #                                                        the kind of thin cuts: the bricks came out as rows)
    median: int = 3                                        # median filter of a cut (px at full size; 0 = none)
    min_kept: float = 0.45                                 # a cut the median filter thins below this share of
    #                                                        its pixels is hairlines, not a network: skipped
    thin_margin: float = 0.9                               # the thinnest cut of the same layout ranked within this
    #                                                        share of the best is the split (see _thinnest)


@dataclass
class StructureSplit:
    """The chosen cut: mask (HxW bool, the network), its source and share, its lattice, every candidate's score."""

    mask: np.ndarray
    source: str
    share: float
    lattice: Lattice
    candidates: list[dict] = field(default_factory=list)
    cell_length: float | None = None      # rows: the cells' length along the rows (px), from another cut
    cell_source: str | None = None        # that cut ("tilt@0.15")

    def describe(self) -> dict:
        """JSON-able summary (no pixels)."""
        return {"source": self.source, "share": self.share, "coverage": float(self.mask.mean()),
                "lattice": {"kind": self.lattice.kind, "period": self.lattice.period,
                            "regularity": self.lattice.regularity, "significance": self.lattice.significance},
                "cell_length": self.cell_length, "cell_source": self.cell_source,
                "candidates": self.candidates}


#: sources that show one flank of a groove: on a clean groove they repeat as regularly as the groove itself
#: (a synthetic running bond: 0.97 against 0.96) while only half the network; they win only where they repeat
#: ONE_SIDED_MARGIN times more clearly than every two-sided source (roof_slates_02: 2.8-3.3 times), and only
#: where a two-sided source shows a layout too (on layout-free relief, 16 more cuts find more chance lattices)
ONE_SIDED = "slope"
ONE_SIDED_MARGIN = 2.0


#: sources whose cut is a band wider than the network: the normals' tilt is high on both bevels of a groove
BAND_SOURCES = frozenset({"tilt"})


def cut_is_band(structure: Mapping | None) -> bool:
    """Whether a structural split (``StructureSplit.describe()``, as the decomposition's root records it) was cut
    from a BAND_SOURCES map: its network is wider than the input's lines (workers.recompose cuts it thinner where
    the material prefers)."""
    source = str((structure or {}).get("source", ""))
    return source.split(":")[-1] in BAND_SOURCES


def _highpass(x: np.ndarray, sigma: float) -> np.ndarray:
    return x - ndimage.gaussian_filter(x, sigma, mode="wrap")


def structure_sources(albedo: np.ndarray | None, height: np.ndarray | None, normal: np.ndarray | None,
                      config: StructureConfig = StructureConfig()) -> dict[str, dict[str, np.ndarray]]:
    """{"relief": {name: map}, "albedo": {name: map}}: HxW float maps where high = the network."""
    relief: dict[str, np.ndarray] = {}
    width = None
    for a in (height, normal, albedo):
        if a is not None:
            width = a.shape[1]
            break
    if width is None:
        return {"relief": {}, "albedo": {}}
    sig = [max(1.0, s * width) for s in config.sigmas]
    if height is not None:
        h = np.asarray(height, np.float32)
        h = h[..., 0] if h.ndim == 3 else h
        for s in sig:
            relief[f"groove{s:.3g}"] = -_highpass(h, s)
    if normal is not None:
        n = np.asarray(normal, np.float32)[..., :3]
        relief["tilt"] = 1.0 - n[..., 2] / np.maximum(np.linalg.norm(n, axis=-1), 1e-6)
        for axis, name in ((0, "x"), (1, "y")):   # steps facing one way (see the module doc)
            slope = _highpass(n[..., axis], sig[-1])
            relief[f"{ONE_SIDED}{name}+"], relief[f"{ONE_SIDED}{name}-"] = slope, -slope
    colour: dict[str, np.ndarray] = {}
    if albedo is not None:
        a = np.asarray(albedo, np.float32)
        lum = a[..., :3] @ _LUMA if a.ndim == 3 and a.shape[2] >= 3 else a.reshape(a.shape[:2])
        colour[f"dark{sig[-1]:.3g}"] = -_highpass(lum, sig[-1])
    return {"relief": relief, "albedo": colour}


#: a 2-D lattice counts this many times its regularity against rows: it shows more of a layout than a
#: one-directional repeat, unless the rows repeat far more clearly (roof_slates_02: the tilt's barely significant
#: 2-D lattice of wood grain and slate ends at regularity 0.03-0.05 against the slate rows' 0.5-0.6; the castle's
#: and the plate's 2-D cuts stay ahead of their rows, at 2.2x and 1.1x at most)
TWO_D_WEIGHT = 4.0


def layout_rank(lat: Lattice) -> float:
    """How strongly a mask shows a layout: the autocorrelation's regularity, TWO_D_WEIGHT times for a 2-D lattice,
    -1 without one. Orders the candidate cuts here and, in workers.decompose, the structural split against the
    colour split."""
    if lat.kind == "none":
        return -1.0
    return float(lat.regularity) * (TWO_D_WEIGHT if lat.kind == "2d" else 1.0)


def _cut(src: np.ndarray, share: float, median: int) -> np.ndarray:
    m = src > np.quantile(src, 1.0 - share)
    return ndimage.median_filter(m, median, mode="wrap") if median > 1 else m


def _small(src: np.ndarray, size: int) -> tuple[np.ndarray, float]:
    """src area-averaged so its longer side is <= size, and the factor (small / full)."""
    h, w = src.shape
    k = min(1.0, size / float(max(h, w)))
    if k >= 1.0:
        return src, 1.0
    return ndimage.zoom(ndimage.uniform_filter(src, max(1, int(round(1 / k))), mode="wrap"), k, order=1), k


#: two cuts show the same layout when their lattices are of one kind and their periods within this share
SAME_PERIOD = 0.10
#: a source's cuts ranked within this share of its best are equally regular (see _thinnest)
SOURCE_FLAT = 0.02
#: a wider cut of a flat source must still be a repeat by itself: its lattice points as many ring deviations up as
#: the lattice analysis asks of a repeat (see _thinnest)
FLAT_SIGNIFICANCE = LatticeConfig.min_significance


class RankedCut(NamedTuple):
    """One candidate cut of a structure source, as :func:`_thinnest` compares them."""

    rank: float             # layout_rank of its lattice
    source: str
    share: float
    kind: str               # lattice kind: "2d" or "rows"
    period: float           # at full size (px)
    significance: float     # the lattice points' height in ring standard deviations


def _thinnest(ranked: list[RankedCut], margin: float) -> RankedCut | None:
    """Of the ranked cuts: the split, or None for an empty list.

    Each source's cut is its best ranked share, or the widest share of the same layout ranked within SOURCE_FLAT
    of it (a regularity flat across shares means the wider cut is still inside the network) that still stands as
    a repeat by itself, when any does (significance >= FLAT_SIGNIFICANCE: past the network the extra band blurs
    the repeat while the regularity stays flat; roof_slates_02 from 512 px maps at 256 px: slope cuts 25 % / 35 %
    ranked 0.5169 / 0.5171 at significance 2.56 / 2.21, and the 35 % cut's thick broken lines were fitted as
    vertical dashes where the 25 % cut comes back as slate rows). Of those, the split is the thinnest cut whose
    layout is the best cut's (same kind, period within SAME_PERIOD) ranked within ``margin`` of it: regularity
    grows with the width of the lines, so across sources the best ranked cut is often a wider band than the
    network. metal_plate_02 at 512 px ranks the normals' tilt at 25 % first (0.549; the bevels on both sides of
    each seam, bands 12-20 px wide) while the fine groove's 8 % cut (0.527) has the input's 2-3 px seams on the
    same lattice. The castle's mortar keeps its cut."""
    if not ranked:
        return None
    def same_layout(a: RankedCut, b: RankedCut) -> bool:
        return a.kind == b.kind and abs(a.period - b.period) <= SAME_PERIOD * b.period

    picks = []
    for name in {r.source for r in ranked}:
        own = [r for r in ranked if r.source == name]
        peak = max(own, key=lambda r: r.rank)
        flat = [r for r in own if r.rank >= (1.0 - SOURCE_FLAT) * peak.rank and same_layout(r, peak)]
        repeats = [r for r in flat if r.significance >= FLAT_SIGNIFICANCE]
        picks.append(max(repeats or flat, key=lambda r: r.share))
    top = max(ranked, key=lambda r: r.rank)
    same = [r for r in picks if same_layout(r, top) and r.rank >= margin * top.rank]
    return min(same, key=lambda r: (r.share, -r.rank)) if same else top


#: a 2-D cut's rows are the split's rows when their spacing is within SAME_PERIOD and their direction within this
#: many degrees
ROW_ANGLE_DEG = 5.0
#: a cell length read off a 2-D cut lies within these multiples of the rows' spacing (else it is a harmonic)
CELL_RANGE = (0.5, 4.0)


class TwoDCut(NamedTuple):
    """A candidate cut with a significant 2-D lattice, kept for the cells' length of a rows split."""

    source: str
    share: float
    lattice: Lattice        # at full size


def cells_along_rows(rows: Lattice, cuts: list[TwoDCut]) -> tuple[float, str] | None:
    """The cells' length (full-size px) along a rows split's rows, and the cut it comes from, or None.

    A network of rows alone (roof_slates_02's lower slate edges, a one-sided slope cut) says nothing of where the
    cells end: a fit of it chose slates 2.4 times as long as the input's (41 px against about 20 at 512 px),
    which showed as wide patches of one tone. Where another cut of the relief has a significant 2-D lattice with
    the same rows (the normals' tilt, which holds the slate ends between the edges: vectors (22, 0) and (-8, 20)
    on 19.6 px rows), its period along the rows is the cells' length: of such cuts, the most significant one of a
    two-sided source, else of a one-sided one (a one-sided slope holds only the steps facing its way: on the roof
    its 2-D cut reads 26 px cells where the tilt reads 22 px at 512 px and 20 px at 256 px, and the input's
    slates are about 20 px)."""
    if rows.kind != "rows" or not rows.vectors:
        return None
    across = np.array(rows.vectors[0], dtype=np.float64)
    spacing = float(np.linalg.norm(across))
    best = None
    for c in cuts:
        for along, row_spacing in _rows_readings(c.lattice):
            length = float(np.linalg.norm(along))
            cos = abs(float(along @ across)) / (length * spacing)
            if abs(row_spacing - spacing) > SAME_PERIOD * spacing or \
                    cos > np.sin(np.radians(ROW_ANGLE_DEG)) or not CELL_RANGE[0] <= length / spacing <= CELL_RANGE[1]:
                continue
            key = (not c.source.startswith(ONE_SIDED), float(c.lattice.significance))
            if best is None or key > best[0]:
                best = (key, length, f"{c.source}@{c.share:g}")
    return None if best is None else (best[1], best[2])


def _rows_readings(lat: Lattice) -> list[tuple[np.ndarray, float]]:
    """Each way a 2-D lattice reads as rows along one of its basis vectors: (that vector, the spacing of the rows
    it makes: |det| / its length). Both vectors are read, not only the lattice's own ``row_vector``: the README
    roof's tilt cut at 256 px, (10.0, 0) and (4.0, 9.9), describes its rows along the second one, while the
    slates' rows run along the first."""
    if lat.kind != "2d" or len(lat.vectors) < 2:
        return []
    basis = np.array(lat.vectors[:2], dtype=np.float64)
    area = abs(float(np.linalg.det(basis)))
    return [(v, area / float(np.linalg.norm(v))) for v in basis if np.linalg.norm(v) > 0]


def find_structure(albedo: np.ndarray | None, height: np.ndarray | None, normal: np.ndarray | None,
                   config: StructureConfig | None = None) -> StructureSplit | None:
    """The structural first split (see the module doc), or None when neither relief nor albedo has a layout."""
    cfg = config or StructureConfig()
    groups = structure_sources(albedo, height, normal, cfg)
    cands: list[dict] = []
    for group in ("relief", "albedo"):
        ranked: dict[bool, list[RankedCut]] = {True: [], False: []}
        two_d: list[TwoDCut] = []
        for name, src in groups[group].items():
            small, k = _small(src, cfg.analysis_size)
            med = max(1, int(round(cfg.median * k))) if cfg.median > 1 else 0
            for share in cfg.shares:
                m = _cut(small, share, med if med > 1 else 0)
                if m.all() or not m.any():
                    continue
                lat = analyse_lattice(m)
                kept = float(m.mean()) / share
                cands.append({"group": group, "source": name, "share": share, "kind": lat.kind,
                              "kept": round(kept, 3),
                              "regularity": round(float(lat.regularity), 4),
                              "significance": round(float(lat.significance), 3),
                              "period_full": None if lat.period is None else round(lat.period / k, 2)})
                if lat.kind == "none" or kept < cfg.min_kept:
                    continue
                if lat.kind == "2d" and lat.significance >= FLAT_SIGNIFICANCE:
                    two_d.append(TwoDCut(name, share, lat.scaled(1.0 / k)))
                ranked[name.startswith(ONE_SIDED)].append(RankedCut(layout_rank(lat), name, share, lat.kind,
                                                                     lat.period / k, float(lat.significance)))
        best = _thinnest(ranked[False], cfg.thin_margin)
        one_sided = _thinnest(ranked[True], cfg.thin_margin)
        if one_sided is not None and best is not None and \
                max(r.rank for r in ranked[True]) > ONE_SIDED_MARGIN * max(r.rank for r in ranked[False]):
            best = one_sided
        if best is not None:
            name, share = best.source, best.share
            mask = _cut(groups[group][name], share, cfg.median)
            lat = analyse_lattice(mask)
            if lat.kind == "none":
                logger.info("structure: %s at %.2f lost its lattice at full size; next source group", name, share)
                continue
            cells = cells_along_rows(lat, two_d)
            logger.info("structure: first split from %s (%s) at share %.2f: %s lattice, period %.1f px%s",
                        group, name, share, lat.kind, lat.period or 0.0,
                        f", cells {cells[0]:.1f} px long ({cells[1]})" if cells else "")
            return StructureSplit(mask=mask, source=f"{group}:{name}", share=float(share), lattice=lat,
                                  candidates=cands, cell_length=cells[0] if cells else None,
                                  cell_source=cells[1] if cells else None)
    logger.info("structure: no layout in the relief or the albedo; colour matting")
    return None
