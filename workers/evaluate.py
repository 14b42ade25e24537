"""Quality scorecard of one material: procedural output vs the input, next to three baselines.

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

* **gram** = the pretrained VGG-19 Gram distance (pptbf_db.features: relu1_1..relu4_1, mean relative Frobenius
  distance) to the reference, the paper's texture statistic; unlike the other metrics it sees structure
  (bricks, seams) that random-phase noise loses. Maps are shown to the network as a person sees them: albedo in
  sRGB, normals as (n + 1) / 2, height scaled by the reference's range, roughness / metallic as they are;
  renders per light, distances averaged. :func:`gram_ratios` divides by the half row (the input's own
  left-to-right distance): 1.0 = as close as two halves of the input.

Lower is better for every metric; ``ratio to half`` (method / half, geometric mean over rows) is 1 at the floor.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from workers.metrics import flat_mean, random_phase_noise, split_halves, texture_metrics

MAP_ORDER = ("albedo", "normal", "roughness", "height", "metallic")
METHODS = ("procedural", "rpn", "half", "flat")
METRICS = ("swd", "spectrum", "histogram", "gram")
BASELINES = ("rpn", "flat")
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
    gram: float = float("nan")

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


def vgg_image(name: str, a: np.ndarray, height_range: tuple[float, float] | None = None) -> np.ndarray:
    """A map as the image a person looks at, HxWx(1|3) in [0, 1]: albedo sRGB, normal (n + 1) / 2, height by
    ``height_range`` (the reference's), the others clipped."""
    from workers.maps import linear_to_srgb

    a = _hwc(a)
    if name == "albedo":
        return np.clip(linear_to_srgb(np.clip(a[..., :3], 0.0, 1.0)), 0.0, 1.0).astype(np.float32)
    if name == "normal":
        return np.clip(a[..., :3] * 0.5 + 0.5, 0.0, 1.0).astype(np.float32)
    if name == "height":
        lo, hi = height_range if height_range is not None else (float(a.min()), float(a.max()))
        return np.clip((a[..., :1] - lo) / max(hi - lo, 1e-6), 0.0, 1.0).astype(np.float32)
    return np.clip(a[..., :1], 0.0, 1.0).astype(np.float32)


def vgg_grams(images: np.ndarray) -> list:
    """VGG-19 Gram matrices of images (N, H, W, C in [0, 1], C = 1 or 3), per layer (N, c, c); no gradients."""
    import torch

    from pptbf_db.features import GramExtractor

    x = torch.from_numpy(np.ascontiguousarray(np.asarray(images, np.float32).transpose(0, 3, 1, 2)))
    ex = GramExtractor.vgg19(x.shape[1])
    with torch.no_grad():
        return ex.grams(x)


def gram_distance_images(ref: np.ndarray, cand: np.ndarray) -> float:
    """Mean over images of the VGG-19 Gram distance of cand[i] to ref[i] (N, H, W, C arrays)."""
    from pptbf_db.features import gram_distance

    return float(gram_distance(vgg_grams(cand), vgg_grams(ref)).mean())


def score_views(ref: np.ndarray, cand: np.ndarray, seed: int) -> dict[str, float]:
    """Metrics averaged over the light views (L, H, W, 3)."""
    per = [texture_metrics(r, c, seed=seed + i) for i, (r, c) in enumerate(zip(ref, cand))]
    out = {m: float(np.mean([p[m] for p in per])) for m in METRICS if m != "gram"}
    out["gram"] = gram_distance_images(ref, cand)
    return out


def score_map(name: str, ref: np.ndarray, cand: np.ndarray, seed: int) -> dict[str, float]:
    """Metrics of one map: the texture metrics and the VGG-19 Gram distance of the map as an image."""
    out = dict(texture_metrics(ref, cand, seed=seed))
    hr = (float(ref.min()), float(ref.max())) if name == "height" else None
    out["gram"] = gram_distance_images(vgg_image(name, ref, hr)[None], vgg_image(name, cand, hr)[None])
    return out


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
            vals = _nan_metrics() if c is None else score_map(name, ref[name], c, seed)
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


def gram_ratios(rows: list[MetricRow]) -> list[dict]:
    """Per (material, map): each method's VGG-19 Gram distance over the half row's (1.0 = the input's own
    left-to-right distance), e.g. {"material", "map", "procedural", "rpn", "flat"}."""
    half = {(r.material, r.map): r.gram for r in rows if r.method == "half"}
    table: dict[tuple[str, str], dict] = {}
    for r in rows:
        if r.method == "half" or (r.material, r.map) not in half or math.isnan(r.gram):
            continue
        d = table.setdefault((r.material, r.map), {"material": r.material, "map": r.map})
        d[r.method] = float(r.gram / max(half[(r.material, r.map)], 1e-9))
    return list(table.values())


def gram_summary(rows: list[MetricRow]) -> dict:
    """Over the (material, map) pairs (maps only; renders reported apart): the median Gram ratio to the floor of
    the procedural maps and of each baseline, and the share of pairs where procedural beats random-phase."""
    table = gram_ratios(rows)
    out: dict = {}
    for scope, sel in (("maps", [d for d in table if d["map"] != "render"]),
                       ("render", [d for d in table if d["map"] == "render"])):
        d: dict = {"pairs": len(sel)}
        for method in ("procedural", *BASELINES):
            vals = [t[method] for t in sel if method in t]
            d[f"median_{method}"] = float(np.median(vals)) if vals else float("nan")
        both = [t for t in sel if "procedural" in t and "rpn" in t]
        d["beats_rpn"] = float(np.mean([t["procedural"] < t["rpn"] for t in both])) if both else float("nan")
        out[scope] = d
    return out


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
            vals = [getattr(r, m) for r in mine if not math.isnan(getattr(r, m))]
            d[m] = float(np.mean(vals)) if vals else float("nan")
        for m in METRICS:
            ratios = [(getattr(r, m) + 1e-9) / (getattr(half[(r.material, r.map)], m) + 1e-9)
                      for r in mine if (r.material, r.map) in half and not math.isnan(getattr(r, m))
                      and not math.isnan(getattr(half[(r.material, r.map)], m))]
            d[f"{m}_ratio_to_half"] = float(np.exp(np.mean(np.log(ratios)))) if ratios else float("nan")
        out.append(d)
    return out
