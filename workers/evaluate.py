"""Quality scorecard of one material: procedural output vs the input, next to three baselines (issue 9 part 1).

Protocol (fair by construction; every candidate is compared against the same reference at the same size):

* **reference** = the *left half* of each input map (W/2 x H). Metrics compare statistics, not pixels.
* **procedural** = the graph's maps at the reference size, regenerated from the graph JSON alone with a seed
  other than the fitting seed (the caller evaluates it; larger maps are cropped to their top-left corner).
* **half** = the input's *right half*: another realisation of the same material, the floor any method can
  reach (an exemplar-free generator cannot look more like the left half than the right half does).
* **rpn** = random phase noise (Galerne et al. 2011) of each *whole* input map (the same pixels the procedural
  model was fitted on), then its left W/2 x H part. Colour/vector maps share one random phase over their
  channels. Normal: RPN of the normal map's three channels, z clamped to >= 1e-3, renormalised to unit length
  (not derived from an RPN of the height). Albedo, roughness and metallic are clipped to [0, 1]; height is not.
* **flat** = the mean of each whole input map (normal: the mean normal renormalised).
* **render** rows: each candidate and the reference rendered (workers.render, GGX) under the paper's 16 lights
  on a plane as wide as the half (``PLANE_WIDTH * (W/2) / W``, so a pixel covers the same area as in a render
  of the whole map), tonemapped to sRGB, metrics averaged over the lights.

Lower is better for every metric; ``ratio to half`` (method / half, geometric mean over rows) is 1 at the floor.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from workers.metrics import flat_mean, random_phase_noise, split_halves, texture_metrics

MAP_ORDER = ("albedo", "normal", "roughness", "height", "metallic")
METHODS = ("procedural", "rpn", "half", "flat")
METRICS = ("swd", "spectrum", "histogram")
_UNIT_MAPS = ("albedo", "roughness", "metallic")


@dataclass
class EvalConfig:
    """What to score: the maps (those present in the input), renders on/off, how many of the paper's lights."""

    maps: tuple[str, ...] = MAP_ORDER
    render: bool = True
    lights: int = 16


@dataclass
class MetricRow:
    """One line of the scorecard (NaN metrics: the candidate lacks the map)."""

    material: str
    map: str
    method: str
    swd: float
    spectrum: float
    histogram: float

    def to_dict(self) -> dict:
        return asdict(self)


def _hwc(a: np.ndarray) -> np.ndarray:
    """HxW or HxWxC -> float32 HxWxC."""
    a = np.asarray(a, dtype=np.float32)
    return a[..., None] if a.ndim == 2 else a


def _unit(n: np.ndarray) -> np.ndarray:
    """Normal vectors with z >= 1e-3, renormalised."""
    n = n.copy()
    n[..., 2] = np.maximum(n[..., 2], 1e-3)
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


def input_maps(maps: dict[str, np.ndarray], config: EvalConfig = EvalConfig()) -> dict[str, np.ndarray]:
    """The scored maps of an input dict (present, not None), as float32 HxWxC of one size."""
    out = {k: _hwc(maps[k]) for k in config.maps if maps.get(k) is not None}
    if "albedo" not in out:
        raise ValueError(f"input maps need an albedo, got {sorted(k for k, v in maps.items() if v is not None)}")
    shape = out["albedo"].shape[:2]
    bad = {k: v.shape[:2] for k, v in out.items() if v.shape[:2] != shape}
    if bad:
        raise ValueError(f"input maps differ in size from albedo {shape}: {bad}")
    if shape[1] < 16 or shape[0] < 8:
        raise ValueError(f"input maps are {shape[1]}x{shape[0]}: too small to split in halves and score")
    return out


def reference_size(maps: dict[str, np.ndarray]) -> tuple[int, int]:
    """(width, height) of the reference (left half): the size to evaluate the procedural material at."""
    h, w = _hwc(maps["albedo"]).shape[:2]
    return w // 2, h


def crop_to(maps: dict[str, np.ndarray], size: tuple[int, int]) -> dict[str, np.ndarray]:
    """Top-left ``size`` (w, h) crop of every map; ValueError if a map is smaller."""
    w, h = size
    out = {}
    for k, v in maps.items():
        if v is None:
            continue
        v = _hwc(v)
        if v.shape[0] < h or v.shape[1] < w:
            raise ValueError(f"map {k!r} is {v.shape[1]}x{v.shape[0]}, smaller than the reference {w}x{h}")
        out[k] = v[:h, :w]
    return out


def baselines(full: dict[str, np.ndarray], seed: int = 0) -> dict[str, dict[str, np.ndarray]]:
    """The reference (left half) and the three baselines at its size, from full-size input maps."""
    size = reference_size(full)
    ref = {k: split_halves(v)[0] for k, v in full.items()}
    half = {k: split_halves(v)[1] for k, v in full.items()}
    rpn, flat = {}, {}
    for i, (k, v) in enumerate(sorted(full.items())):
        r = random_phase_noise(v, seed=seed + 7919 * (i + 1))
        f = flat_mean(v)
        if k == "normal":
            r, f = _unit(r), _unit(f)
        elif k in _UNIT_MAPS:
            r = np.clip(r, 0.0, 1.0)
        rpn[k], flat[k] = r, f
    return {"reference": ref, "half": half, "rpn": crop_to(rpn, size), "flat": crop_to(flat, size)}


def render_views(maps: dict[str, np.ndarray], plane_width: float, lights: int = 16) -> np.ndarray:
    """Tonemapped sRGB renders (L, H, W, 3) of the maps under the first ``lights`` of the paper's lights."""
    import torch

    from workers.render import paper_lights, render, tonemap

    def t(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(_hwc(a)))

    alb = _hwc(maps["albedo"])
    alb = np.repeat(alb, 3, axis=2) if alb.shape[2] == 1 else alb[..., :3]
    h, w = alb.shape[:2]
    nrm = maps.get("normal")
    nrm = np.broadcast_to(np.float32([0, 0, 1]), (h, w, 3)) if nrm is None else _hwc(nrm)[..., :3]
    rough = maps.get("roughness")
    rough = np.full((h, w, 1), 0.5, np.float32) if rough is None else _hwc(rough)[..., :1]
    met = maps.get("metallic")
    with torch.no_grad():
        rad = render(t(alb), t(nrm), t(rough), paper_lights()[:lights],
                     None if met is None else t(_hwc(met)[..., :1]), plane_width=plane_width)
        return tonemap(rad).numpy().astype(np.float32)


def _nan_metrics() -> dict[str, float]:
    return {m: float("nan") for m in METRICS}


def score_views(ref: np.ndarray, cand: np.ndarray, seed: int) -> dict[str, float]:
    """Metrics averaged over the light views (L, H, W, 3)."""
    per = [texture_metrics(r, c, seed=seed + i) for i, (r, c) in enumerate(zip(ref, cand))]
    return {m: float(np.mean([p[m] for p in per])) for m in METRICS}


def evaluate_material(inputs: dict[str, np.ndarray], procedural: dict[str, np.ndarray], seed: int = 0,
                      material: str = "", config: EvalConfig = EvalConfig()) -> list[MetricRow]:
    """Scorecard rows (map x method) of one material: ``inputs`` full size, ``procedural`` at least half size."""
    from workers.render import PLANE_WIDTH

    full = input_maps(inputs, config)
    size = reference_size(full)
    cands = baselines(full, seed)
    ref = cands.pop("reference")
    cands["procedural"] = crop_to({k: v for k, v in procedural.items() if k in full}, size)
    rows: list[MetricRow] = []
    for name in [m for m in MAP_ORDER if m in full]:
        for method in METHODS:
            c = cands[method].get(name)
            vals = _nan_metrics() if c is None else texture_metrics(ref[name], c, seed=seed)
            rows.append(MetricRow(material, name, method, **vals))
    if config.render:
        plane = PLANE_WIDTH * size[0] / full["albedo"].shape[1]
        views = {"reference": render_views(ref, plane, config.lights)}
        for method in METHODS:
            c = cands[method]
            vals = _nan_metrics() if "albedo" not in c else score_views(
                views["reference"], render_views(c, plane, config.lights), seed)
            rows.append(MetricRow(material, "render", method, **vals))
    return rows


def summarise(rows: list[MetricRow]) -> list[dict]:
    """Per method: mean of each metric over all rows, and the geometric-mean ratio to the 'half' floor."""
    half = {(r.material, r.map): r for r in rows if r.method == "half"}
    out = []
    for method in METHODS:
        mine = [r for r in rows if r.method == method and not math.isnan(r.swd)]
        if not mine:
            continue
        d: dict = {"method": method, "rows": len(mine)}
        for m in METRICS:
            d[m] = float(np.mean([getattr(r, m) for r in mine]))
        for m in METRICS:
            ratios = [(getattr(r, m) + 1e-9) / (getattr(half[(r.material, r.map)], m) + 1e-9)
                      for r in mine if (r.material, r.map) in half]
            d[f"{m}_ratio_to_half"] = float(np.exp(np.mean(np.log(ratios)))) if ratios else float("nan")
        out.append(d)
    return out
