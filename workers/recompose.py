"""Recomposition (paper 5.3): optimise the filter parameters of an assembled material graph
(:mod:`workers.assemble`) against the input maps.

:func:`optimise` fits the continuous filter parameters of that graph to the target maps by gradient descent:

* The graph is re-evaluated in torch (:class:`workers.torch_graph.TorchGraph`): each node type gives its torch
  form (:mod:`workers.nodes`); the fixed parts (PPTBF / instance masks, any node type without a torch form) are
  evaluated once with numpy at the target's size. Filter-stack generators (``noise``, :mod:`workers.nodes.stack`)
  are split into ``matched``, ``base`` and layers ``L_k``; the split is checked against the node's own output
  before it is trusted (else: kept fixed).
* The free parameters are leaf tensors: per layer ``a_k``, ``sigma_k`` of
  ``O = matched + sum_k (blur(a_k L_k + b_k; sigma_k) - L_k) + (c - 1) base + d`` and ``d``, the ``blend``
  sigmas (``sum_i blur(mask_i; sigma_i) child_i``), optionally ``level`` a/d and ``blur`` sigma: every declared
  parameter of a type whose group is in ``RecomposeConfig.optimise``.
* ``b_k`` and ``c`` of a noise node shift the map exactly like ``d`` (its base is a constant colour): by default
  only ``d`` is optimised (``collinear_offsets=True`` adds them); all values are written back.
* Loss: Gram L1 (:class:`pptbf_db.features.GramExtractor`, normalised per layer by the target Gram) on albedo,
  normal (torch Sobel of height, as graph.evaluate), roughness, height (+ metallic) and on tone-mapped renders
  under ``lights_per_step`` lights drawn (seeded) from a pool of random lights, plus ``beta * (1 - SSIM)`` of the
  renders and maps. Adam (default, lr 0.02, cosine decay, per-group step scales) or L-BFGS (fixed lights,
  strong Wolfe line search).
* ``loss_before`` / ``loss_after`` use a fixed evaluation loss (the paper's 16 lights); if the optimised
  parameters are not better the original ones are kept.

Measured (bench/recompose.py, castle_brick 256 px, 3 leaves, 100 steps, 2 torch threads on an idle 16-core box):
Adam 57 s, loss 1.79 -> 0.76; L-BFGS 93 s, -> 0.75; on an H100 12 s / 27 s with the same losses (CPU = CUDA).
"""
from __future__ import annotations

import copy
import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Collection, Mapping

import numpy as np
import torch
from tqdm import tqdm

from pptbf_db import pptbf as pp
from pptbf_db.features import GramExtractor, ssim

from . import graph as G
from .assemble import graph_id
from .errors import InputError
from .lattice import NETWORK_PIECE_SHARE, STRAIGHT_CELLS, Lattice, largest_piece_share, template_cells
from .layout_fit import mask_shows_lattice
from .render import paper_lights, random_lights, render, tonemap
from .torch_graph import TorchGraph

logger = logging.getLogger(__name__)



# ----------------------------------------------------------------------------- config / result


@dataclass
class RecomposeConfig:
    """Optimisation settings. ``iterations`` steps of ``optimizer`` ("adam" | "lbfgs")."""

    iterations: int = 100
    optimizer: str = "adam"
    lr: float = 0.02
    sigma_lr_scale: float = 5.0          # Adam: sigma (pixels) moves this many times faster than a
    offset_lr_scale: float = 0.25        # Adam: offsets (d) move slower: Gram losses are very sensitive to the mean
    lr_final: float = 0.1                # Adam: cosine decay of the step to this fraction (L1 keeps full gradients)
    collinear_offsets: bool = False      # also optimise b_k and c: for a noise node (constant base colour) they
                                         # shift the map exactly like d, so they only multiply d's step
    lbfgs_lr: float = 0.5
    lights_per_step: int = 4
    light_pool: int = 32                 # random lights whose target renders are precomputed
    beta: float = 0.1                    # weight of (1 - SSIM) on the renders (and on the maps, see ssim_maps)
    ssim_maps: bool = True               # SSIM also on albedo / roughness / height (pixel-aligned targets)
    weights: dict = field(default_factory=lambda: {"albedo": 1.0, "normal": 1.0, "roughness": 1.0,
                                                   "height": 1.0, "metallic": 1.0, "renders": 1.0})
    features: str = "vgg19"              # Gram features of the loss: "vgg19" (pretrained, the paper's) | "random"
    vgg_layers: int = 3                  # VGG-19 Gram layers used: relu1_1.. (3: up to relu3_1; 4: relu4_1). 4, as
                                         # the evaluation scores, was measured on the six materials at 512: 15 of 24
                                         # maps nearer the input (plastered albedo 1.62 -> 1.38, roof albedo 5.59 ->
                                         # 4.05) but castle normal 2.47 -> 3.18 and coast roughness 1.93 -> 2.28,
                                         # median 2.03 -> 2.12, and recomposition ~1.3x slower (257 s mean): not default
    loss_size: int | None = None         # maps and renders area-averaged to this longer side before the Gram
                                         # and SSIM terms (None: half the maps' longer side, at least 128; 0: full
                                         # size); the graph itself runs at full size. At a quarter of 512 px the
                                         # loss no longer saw the noise's 3-6 px grain and boosted it (castle:
                                         # VGG-19 Gram / floor 4.98 on albedo against 3.42 before the step)
    as_seen: bool = True                 # maps enter the loss as a person (and the evaluation) sees them: albedo
                                         # through the sRGB curve, height scaled by the target's range
    widths: tuple[int, ...] = (16, 32, 32, 64)  # widths of the "random" features
    feature_seed: int = 0
    seed: int = 0
    device: str = "auto"
    sigma_init: float = 0.25             # a sigma stored as 0 starts here: blur weight 3e-4, but a sigma gradient
    sigma_max: float = 16.0
    optimise: tuple[str, ...] = ("filters", "blend")  # node groups freed; also "level" (a, d), "blur", "warp"
    check_tol: float = 2e-3              # max |torch - graph| accepted for a filter-stack split
    progress: bool = False

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "RecomposeConfig":
        """Build from a manifest dict (unknown keys are an InputError naming them)."""
        d = dict(d or {})
        known = set(cls.__dataclass_fields__)
        bad = sorted(set(d) - known)
        if bad:
            raise InputError(f"recompose config: unknown keys {bad} (known: {sorted(known)})")
        for k in ("widths", "optimise"):
            if k in d:
                d[k] = tuple(d[k])
        cfg = cls(**d)
        groups = optimise_groups()
        if not set(cfg.optimise) <= set(groups):
            raise InputError(f"recompose.optimise: {sorted(set(cfg.optimise) - set(groups))} not among the node "
                             f"groups the recomposition can free ({', '.join(groups)})")
        if cfg.features not in ("vgg19", "random"):
            raise InputError(f"recompose.features must be 'vgg19' or 'random', got {cfg.features!r}")
        if not 1 <= int(cfg.vgg_layers) <= 4:
            raise InputError(f"recompose.vgg_layers must be 1..4, got {cfg.vgg_layers!r}")
        if cfg.loss_size is not None and int(cfg.loss_size) != 0 and int(cfg.loss_size) < 32:
            raise InputError(f"recompose.loss_size must be null (half the maps' size), 0 (full size) or >= 32, "
                             f"got {cfg.loss_size!r}")
        return cfg


def optimise_groups() -> tuple[str, ...]:
    """The names ``RecomposeConfig.optimise`` accepts: the groups of the node types' optimisable parameters."""
    return tuple(sorted({t.group for t in G.NODE_TYPES.values() if t.group}))


@dataclass
class RecomposeResult:
    """Optimised material (a copy, parameters written back) and the loss bookkeeping."""

    material: G.ProceduralMaterial
    loss_before: float
    loss_after: float
    history: list[float]
    seconds: float
    device: str
    iterations: int
    params_before: dict[str, Any] = field(default_factory=dict)
    params_after: dict[str, Any] = field(default_factory=dict)
    kept_original: bool = False

    def report(self) -> dict:
        """JSON-able summary."""
        return {"loss_before": self.loss_before, "loss_after": self.loss_after, "seconds": round(self.seconds, 3),
                "device": self.device, "iterations": self.iterations, "kept_original": self.kept_original,
                "history": [round(h, 6) for h in self.history], "params_before": self.params_before,
                "params_after": self.params_after}


def pick_device(device: str = "auto") -> torch.device:
    """``auto``: CUDA when torch sees one, else CPU."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


# ----------------------------------------------------------------------------- loss


def _target_maps(target: Any) -> dict[str, np.ndarray]:
    """Maps dict from a workers.maps.Material or a dict of HxW(xC) arrays."""
    maps = target.maps() if hasattr(target, "maps") and callable(target.maps) else dict(target)
    maps = {k: np.asarray(v, dtype=np.float32) for k, v in maps.items() if v is not None}
    maps = {k: (v[..., None] if v.ndim == 2 else v) for k, v in maps.items()}
    if "albedo" not in maps:
        raise InputError(f"recompose target needs an albedo map, got {sorted(maps)}")
    return maps


def _chw(x: torch.Tensor) -> torch.Tensor:
    """HxWxC -> 1xCxHxW (LxHxWxC -> LxCxHxW)."""
    return x.permute(2, 0, 1)[None] if x.dim() == 3 else x.permute(0, 3, 1, 2)


class _Features:
    """Gram matrices of the loss: the first ``layers`` VGG-19 taps (the network stops after the last one used),
    or the seeded random extractor."""

    def __init__(self, ex: GramExtractor, layers: int | None = None):
        self.ex = ex
        self.layers = layers

    def grams(self, x: torch.Tensor) -> list[torch.Tensor]:
        return self.ex.grams(x, layers=self.layers if self.ex.vgg else None)


def _extractors(cfg: RecomposeConfig, device: torch.device) -> tuple[_Features, _Features]:
    """(3-channel, 1-channel) loss features on ``device``."""
    if cfg.features == "vgg19":
        ex3, ex1 = GramExtractor.vgg19(3), GramExtractor.vgg19(1)
        if device.type != "cpu":   # the shared instances stay on the CPU
            ex3, ex1 = copy.deepcopy(ex3).to(device), copy.deepcopy(ex1).to(device)
        return _Features(ex3, cfg.vgg_layers), _Features(ex1, cfg.vgg_layers)
    return (_Features(GramExtractor(3, seed=cfg.feature_seed, widths=cfg.widths).to(device)),
            _Features(GramExtractor(1, seed=cfg.feature_seed + 1, widths=cfg.widths).to(device)))


class RecomposeLoss:
    """Gram (+ SSIM) loss against fixed target maps and a pool of target renders, at ``cfg.loss_size``."""

    def __init__(self, target: dict[str, torch.Tensor], cfg: RecomposeConfig, device: torch.device):
        self.cfg, self.device = cfg, device
        self.ex3, self.ex1 = _extractors(cfg, device)
        self.target = target
        self.names = [m for m in ("albedo", "normal", "roughness", "height", "metallic")
                      if m in target and cfg.weights.get(m, 0.0) > 0]
        h = target.get("height")
        self.height_range = (float(h.min()), float(h.max()) - float(h.min())) if h is not None else (0.0, 1.0)
        with torch.no_grad():
            self.tgrams = {m: self._ex(m).grams(self._img(m, target[m])) for m in self.names}
        g = torch.Generator().manual_seed(cfg.seed)
        self.pool = random_lights(cfg.light_pool, g).to(device)
        self.eval_lights = paper_lights().to(device)
        self.render_ok = "normal" in target and cfg.weights.get("renders", 0.0) > 0
        if self.render_ok:
            with torch.no_grad():
                self.pool_renders = self._renders(target, self.pool)
                self.pool_grams = self.ex3.grams(self.pool_renders)
                self.eval_renders = self._renders(target, self.eval_lights)
                self.eval_grams = self.ex3.grams(self.eval_renders)

    def _ex(self, m: str) -> _Features:
        return self.ex3 if m in ("albedo", "normal") else self.ex1

    def _small(self, x: torch.Tensor) -> torch.Tensor:
        """BxCxHxW area-averaged so the longer side is at most the loss size (see RecomposeConfig.loss_size)."""
        h, w = x.shape[-2:]
        n = int(self.cfg.loss_size) if self.cfg.loss_size is not None else max(128, max(h, w) // 2)
        if n <= 0 or max(h, w) <= n:
            return x
        k = max(h, w) / float(n)
        return torch.nn.functional.adaptive_avg_pool2d(x, (max(8, round(h / k)), max(8, round(w / k))))

    def _img(self, m: str, x: torch.Tensor) -> torch.Tensor:
        """Map as 1xCxHxW in [0, 1] for the extractor (normals remapped from [-1, 1]), at the loss size; with
        ``as_seen`` as workers.evaluate.vgg_image shows it (albedo sRGB, height by the target's range): in linear
        albedo the dark half of the values is squeezed into a few percent of the range, so the loss hardly sees
        the speckle a boost of the fine noise layers puts into dark bricks."""
        if m == "normal":
            x = x * 0.5 + 0.5
        elif self.cfg.as_seen and m == "albedo":
            x = tonemap(x)
        elif self.cfg.as_seen and m == "height":
            x = (x - self.height_range[0]) / max(self.height_range[1], 1e-6)
        return self._small(_chw(x))

    def _renders(self, maps: Mapping[str, torch.Tensor], lights: torch.Tensor) -> torch.Tensor:
        rough = maps.get("roughness")
        if rough is None:
            rough = torch.full_like(maps["albedo"][..., :1], 0.5)
        return self._small(_chw(tonemap(render(maps["albedo"], maps["normal"], rough, lights,
                                                maps.get("metallic")))))

    @staticmethod
    def _gram_dist(gx: list[torch.Tensor], gt: list[torch.Tensor]) -> torch.Tensor:
        """Mean over layers of L1(Gram) / mean|target Gram| (every layer weighs about the same)."""
        return sum((a - b).abs().mean() / (b.abs().mean() + 1e-8) for a, b in zip(gx, gt)) / len(gx)

    def __call__(self, out: Mapping[str, torch.Tensor], light_idx: torch.Tensor | None) -> torch.Tensor:
        """Loss of the output maps; ``light_idx`` picks pool lights, None = the fixed evaluation lights."""
        w = self.cfg.weights
        total = torch.zeros((), device=self.device)
        for m in self.names:
            if m in out:
                x = self._img(m, out[m])
                total = total + w[m] * self._gram_dist(self._ex(m).grams(x), self.tgrams[m])
                if self.cfg.beta > 0 and self.cfg.ssim_maps and m != "normal":
                    total = total + self.cfg.beta * (1.0 - ssim(x, self._img(m, self.target[m])))
        if self.render_ok and "normal" in out:
            if light_idx is None:
                lights, tr, tg = self.eval_lights, self.eval_renders, self.eval_grams
            else:
                lights, tr = self.pool[light_idx], self.pool_renders[light_idx]
                tg = [g[light_idx] for g in self.pool_grams]
            r = self._renders(out, lights)
            total = total + w.get("renders", 1.0) * self._gram_dist(self.ex3.grams(r), tg)
            if self.cfg.beta > 0:
                total = total + self.cfg.beta * (1.0 - ssim(r, tr))
        return total


# ----------------------------------------------------------------------------- optimisation


def optimise(material: G.ProceduralMaterial, target: Any, config: RecomposeConfig | None = None,
             **overrides: Any) -> RecomposeResult:
    """Fit the filter parameters of ``material`` to ``target`` (Material or maps dict); returns a new material.

    The graph is evaluated at the target's size with ``scale = target width / material working width``.
    ``overrides`` replace config fields (e.g. ``iterations=50``).
    """
    cfg = dataclasses.replace(config or RecomposeConfig(), **overrides)
    if cfg.optimizer not in ("adam", "lbfgs"):
        raise InputError(f"recompose optimizer must be 'adam' or 'lbfgs', got {cfg.optimizer!r}")
    flush = torch.set_flush_denormal(True)  # tiny FFT / kernel values as denormals slow CPU steps ~10x
    try:
        return _optimise(material, target, cfg)
    finally:
        if flush:
            torch.set_flush_denormal(False)


def _setup(material: G.ProceduralMaterial, target: Any, cfg: RecomposeConfig,
           device: torch.device) -> tuple[TorchGraph, RecomposeLoss]:
    """The torch graph of ``material`` at the target's size and the loss against the target's maps."""
    tmaps = _target_maps(target)
    h, w = tmaps["albedo"].shape[:2]
    tg = TorchGraph(material, w, h, w / float(material.working_size[0]), device, cfg)
    produced = tg.forward(tg.params)
    tgt = {k: torch.as_tensor(v, device=device) for k, v in tmaps.items() if k in produced}
    if "normal" in produced and "normal" in tmaps:
        tgt["normal"] = torch.as_tensor(tmaps["normal"], device=device)
    return tg, RecomposeLoss(tgt, cfg, device)


def _initial_values(tg: TorchGraph, device: torch.device) -> dict[str, torch.Tensor]:
    """The graph's own parameter values (a blend's per-mask sigmas as one, their largest)."""
    init_vals = {}
    for key, t in tg.params.items():
        v0 = tg.initial[key]
        if tg.kinds[key] == "sigma":
            v0 = float(np.max(np.atleast_1d(np.asarray(v0, dtype=np.float64))))
            init_vals[key] = torch.tensor([v0], dtype=torch.float32, device=device)
        else:
            init_vals[key] = t.detach().clone()
    return init_vals


def evaluation_loss(material: G.ProceduralMaterial, target: Any, config: RecomposeConfig | None = None) -> float:
    """The fixed evaluation loss (the paper's 16 lights) of ``material`` as it stands: ``loss_before`` of
    :func:`optimise`."""
    cfg = config or RecomposeConfig()
    device = pick_device(cfg.device)
    tg, loss_fn = _setup(material, target, cfg, device)
    with torch.no_grad():
        return float(loss_fn(tg.forward(_initial_values(tg, device)), None))


def _keeps_layout(material: G.ProceduralMaterial, node: str, fit: Mapping, mask: np.ndarray | None = None) -> bool:
    """Whether the mask of tree node ``node`` in ``material`` (its ``pptbf`` node at the working size) shows the
    lattice its fit was made for (``meta["lattice"]``, at the fit's size): crisp cells that lose the layout are
    no choice, whatever the material's loss says. ``mask``: that mask when the caller rendered it already."""
    meta = fit.get("meta", {})
    if not meta.get("lattice"):
        return True
    w = material.working_size[0]
    lat = Lattice.from_dict(meta["lattice"]).scaled(w / float(fit["fit_size"][0]))
    nid = graph_id("mask", node)
    return mask_shows_lattice(_node_mask(material, node) if mask is None else mask, lat,
                              np.asarray(material.node(nid)["params"]["params"], dtype=np.float64))


def _node_mask(material: G.ProceduralMaterial, node: str) -> np.ndarray:
    """The mask of tree node ``node`` in ``material`` (its ``pptbf`` node) at the working size, as bool."""
    w, h = material.working_size
    ctx = G.EvalContext(width=w, height=h, seed=material.seed, working_size=tuple(material.working_size))
    return G.evaluate_node(material, graph_id("mask", node), ctx)[..., 0] > 0.5


def _trial(build: Callable[[Mapping[str, Mapping]], G.ProceduralMaterial], fits: Mapping[str, Mapping], node: str,
           change: Mapping, target: Any, config: RecomposeConfig | None,
           network_white: bool | None = None) -> tuple[Mapping, G.ProceduralMaterial, float]:
    """``fits`` with ``node``'s fit updated by ``change``, its material and its evaluation loss: inf where the
    mask loses the lattice its fit was made for, or (``network_white``: which side of the mask is the network)
    where the network falls apart (its largest piece under NETWORK_PIECE_SHARE)."""
    fit = fits[node]["fit"]
    trial = {**fits, node: {**fits[node], "fit": {**fit, **change}}}
    material = build(trial)
    mask = None
    ok = True
    if network_white is not None:
        mask = _node_mask(material, node)
        ok = largest_piece_share(mask if network_white else ~mask) >= NETWORK_PIECE_SHARE
    ok = ok and _keeps_layout(material, node, fit, mask)
    return trial, material, evaluation_loss(material, target, config) if ok else math.inf


#: how much lower the evaluation loss of the straight cells must be for the material to take them: the loss is
#: the assembled graph's, before the optimisation adapts the filters to either; smaller gains did not survive it
#: (the README roof: 6.481 against 6.501 before, then VGG-19 Gram / floor albedo 3.87 -> 4.21, normal
#: 5.16 -> 5.88 after, the picture unchanged; the README metal's plates: 1.389 against 1.427, normal 5.93 -> 5.52)
CELLS_MARGIN = 0.01


def choose_cells(build: Callable[[Mapping[str, Mapping]], G.ProceduralMaterial], fits: Mapping[str, Mapping],
                 target: Any, config: RecomposeConfig | None = None,
                 thinner: Collection[str] = ()) -> tuple[G.ProceduralMaterial, dict]:
    """The assembled material (``build(fits)``) with, for each mask fitted on a lattice whose cells the fit shaped
    (window, features, jitter, distortion) or left rounded (the fit's starting template), crisp cells with straight
    borders (``lattice.template_cells`` with ``STRAIGHT_CELLS``: same layout and threshold) where they keep the
    fit's lattice and the material's evaluation loss prefers them; and a report of the losses compared.

    A mask fit judges cells against the decomposition's mask, which is ragged where a threshold cut the relief's
    bevels and grain; cells shaped to copy that raggedness score better on the mask and worse on the material:
    metal_plate_02 at 256 px came back as barrel-shaped plates in wavy courses (mask loss 0.22 against 0.36 for
    the 16-sector crisp cells), while with those every map but the roughness is nearer the input (VGG-19 Gram
    over the input's halves: normal 6.62 -> 6.08, height 4.07 -> 3.86, albedo 1.45 -> 1.39, render 1.70 -> 1.64),
    and with the straight ones the normal nearer still (5.93 -> 5.52).
    Not for a network fitted widened (``masks``: under 10 % of the pixels): the template's field cut at such a
    share does not make even lines: with 16 border sectors it gathered the white into wedges at the junctions
    (metal_plate_02 at 512 px, 10 % seams, though the material's loss preferred them, 1.26 -> 1.21), with 64 the
    seams across the cells' short sides are hairlines (the field is the cell scaled about its point, so a seam's
    width follows the side's distance from it).
    Then the masks named in ``thinner`` (networks cut from a band wider than the input's lines) are offered a
    thinner cut (:func:`_thinner_network`), every lattice mask a cut on its cells' border distance
    (:func:`_even_network`), and the ``thinner`` ones a thinner cut of that distance.
    Greedy, one fit at a time in node order; ``fits`` maps node id -> {"fit": MaskFit dict, ...}."""
    material = build(fits)
    best = evaluation_loss(material, target, config)
    compared: dict[str, dict] = {}
    for node in sorted(fits):
        fit = fits[node].get("fit", {})
        if fit.get("meta", {}).get("method") != "lattice" or fit["meta"].get("widened"):
            continue
        crisp = template_cells(fit["params"], STRAIGHT_CELLS)
        if np.allclose(crisp, np.asarray(fit["params"], dtype=np.float64)):
            continue
        trial, trial_material, loss = _trial(build, fits, node, {"params": crisp.tolist()}, target, config)
        layout = math.isfinite(loss)
        chosen = "template" if loss < (1.0 - CELLS_MARGIN) * best else "fitted"
        compared[node] = {"fitted": best, "template": loss if layout else None, "keeps_lattice": layout,
                          "chosen": chosen}
        logger.info("recompose: mask %s, fitted cells %.4f, template cells %s: %s", node, best,
                    f"{loss:.4f}" if layout else "lose the lattice", chosen)
        if chosen == "template":
            fits, material, best = trial, trial_material, loss
    for node in sorted(set(fits) & set(thinner)):
        fits, material, best = _thinner_network(build, fits, node, material, best, target, config, compared)
    for node in sorted(fits):
        fits, material, best = _even_network(build, fits, node, material, best, target, config, compared)
    for node in sorted(set(fits) & set(thinner)):
        fits, material, best = _thinner_network(build, fits, node, material, best, target, config, compared,
                                                field="border")
    return material, {"loss": best, "fits": compared}


def _even_network(build: Callable[[Mapping[str, Mapping]], G.ProceduralMaterial], fits: Mapping[str, Mapping],
                  node: str, material: G.ProceduralMaterial, best: float, target: Any,
                  config: RecomposeConfig | None, compared: dict) -> tuple[Mapping, G.ProceduralMaterial, float]:
    """The lattice mask ``node`` cut on the distance to its cells' border (``pptbf`` field ``border``: a network
    of one width along every side) instead of the PPTBF value, on its cells and on the straight template's,
    where that keeps the lattice and the material's evaluation loss is CELLS_MARGIN lower; else unchanged.

    Cut on the value, the cellular window leaves along each side a band as wide as that side's distance from the
    cell's point: bricks twice as long as high got head joints twice as wide as their bed joints, the README
    metal's plates horizontal seams twice as wide as the vertical ones; and a thin network fitted widened
    (``masks``) could not take the straight template, whose value cut at a few % of the pixels left hairlines
    across the cells' short sides (see ``choose_cells``)."""
    fit = fits[node].get("fit", {})
    if fit.get("meta", {}).get("method") != "lattice" or fit.get("field", "value") != "value":
        return fits, material, best
    params = np.asarray(fit["params"], dtype=np.float64)
    offers = {"border": params}
    straight = template_cells(params, STRAIGHT_CELLS)
    if not np.allclose(straight, params):
        offers["straight_border"] = straight
    report = compared.setdefault(node, {})
    report["border"] = {"value": best}
    for name, p in offers.items():
        if not pp.uses_cellular(pp.decode(p)):
            continue
        trial, trial_material, loss = _trial(build, fits, node, {"params": p.tolist(), "field": "border"}, target,
                                             config)
        layout = math.isfinite(loss)
        report["border"][name] = loss if layout else None
        if loss < (1.0 - CELLS_MARGIN) * best:
            fits, material, best = trial, trial_material, loss
            report["border"]["chosen"] = name
    logger.info("recompose: mask %s, cut on the border distance: %s", node, report["border"])
    return fits, material, best


#: the network shares offered to a lattice mask, as fractions of its fitted share (see _thinner_network)
THINNER_SHARES = (0.6, 0.35)


def _thinner_network(build: Callable[[Mapping[str, Mapping]], G.ProceduralMaterial], fits: Mapping[str, Mapping],
                     node: str, material: G.ProceduralMaterial, best: float, target: Any,
                     config: RecomposeConfig | None, compared: dict,
                     field: str = "value") -> tuple[Mapping, G.ProceduralMaterial, float]:
    """The lattice mask ``node`` cut thinner (its network at THINNER_SHARES of the fitted share: the same cells,
    the PPTBF's threshold moved; cut on ``field``) where that keeps the lattice and the material's evaluation loss
    is CELLS_MARGIN lower; else unchanged. Offered on the value, then (after :func:`_even_network`) on the border
    distance: an even network keeps the share the value cut spent on its widest sides, so the input's thin
    lines can be thinner still (the README metal: 1-2 px seams, the value cut's 15 % as 2 px vertical and 4 px
    horizontal seams).

    The structural split takes the cut whose lattice is clearest, and at a small working size that is a band
    wider than the input's lines: metal_plate_02's seams are 1-2 px at 256 px, its split's network 25 % of the
    pixels (the normals' tilt, which takes both bevels of a seam); the mask fit copies that width, so the plates
    came back with seams about three times the input's. The fit judges the mask, the material judges the width.
    Only for such bands (``choose_cells``' ``thinner``): where the cut is the network's own width the evaluation
    loss still prefers a thinner one, and the maps move away from the input (the castle's 31 % mortar at 512 px,
    a fine groove's cut: loss 2.60 -> 2.28 at 19 %, VGG-19 Gram over the input's halves albedo 2.22 -> 2.92,
    normal 2.35 -> 2.76, roughness 2.43 -> 2.98, height 3.52 -> 2.42).
    A thinner cut must keep the network in one piece (NETWORK_PIECE_SHARE): the cells' short sides thin out
    first; offered a thinner cut (before the offer was kept for bands: the roof's is a one-sided slope's), the
    README roof's slates at 60 % of their network's share lost their joints (537 pieces, the largest 1.5 % of
    the network) where the evaluation loss still preferred them (the albedo's VGG-19 Gram over the input's halves
    3.87 -> 6.41)."""
    fit = fits[node].get("fit", {})
    meta = fit.get("meta", {})
    if meta.get("method") != "lattice" or meta.get("widened"):
        return fits, material, best
    params = np.asarray(fit["params"], dtype=np.float64)
    compl = bool(fit.get("complement"))
    white = 1.0 - params[0] if compl else params[0]        # the PPTBF's threshold is the share it cuts
    net_white = white <= 0.5                               # the network is the smaller phase
    share = white if net_white else 1.0 - white
    if field != "value" and not pp.uses_cellular(pp.decode(params)):
        return fits, material, best
    key = "network" if field == "value" else f"network_{field}"
    report = compared.setdefault(node, {})
    report[key] = {"fitted": [round(float(share), 4), best]}
    for k in THINNER_SHARES:
        p = params.copy()
        new_white = k * share if net_white else 1.0 - k * share
        p[0] = 1.0 - new_white if compl else new_white
        trial, trial_material, loss = _trial(build, fits, node, {"params": p.tolist(), "field": field}, target,
                                             config, network_white=net_white)
        layout = math.isfinite(loss)
        report[key][f"x{k}"] = [round(float(k * share), 4), loss if layout else None]
        if loss < (1.0 - CELLS_MARGIN) * best:
            fits, material, best = trial, trial_material, loss
            report[key]["chosen"] = f"x{k}"
    logger.info("recompose: mask %s, network share %.3f cut on the %s: %s", node, share, field, report[key])
    return fits, material, best


def _optimise(material: G.ProceduralMaterial, target: Any, cfg: RecomposeConfig) -> RecomposeResult:
    """Body of :func:`optimise`."""
    t0 = time.perf_counter()
    device = pick_device(cfg.device)
    tg, loss_fn = _setup(material, target, cfg, device)
    w, h = tg.ctx.width, tg.ctx.height
    init_vals = _initial_values(tg, device)
    with torch.no_grad():
        loss_before = float(loss_fn(tg.forward(init_vals), None))
    params_before = tg.json_values(init_vals)
    history: list[float] = []
    rng = torch.Generator().manual_seed(cfg.seed + 1)
    plist = list(tg.params.values())
    if not plist:
        logger.warning("recompose: the graph has no optimisable parameters")
    elif cfg.optimizer == "adam":
        groups = []
        for kind, scale in (("value", 1.0), ("sigma", cfg.sigma_lr_scale), ("offset", cfg.offset_lr_scale)):
            ps = [t for k, t in tg.params.items() if tg.kinds[k] == kind]
            if ps:
                groups.append({"params": ps, "lr": cfg.lr * scale})
        opt = torch.optim.Adam(groups)
        n_it = max(cfg.iterations, 1)
        sched = torch.optim.lr_scheduler.LambdaLR(
            opt, lambda i: cfg.lr_final + (1.0 - cfg.lr_final) * 0.5 * (1.0 + math.cos(math.pi * min(i, n_it) / n_it)))
        for _ in tqdm(range(cfg.iterations), disable=not cfg.progress, desc="recompose"):
            idx = torch.randperm(cfg.light_pool, generator=rng)[: cfg.lights_per_step].to(device)
            opt.zero_grad(set_to_none=True)
            loss = loss_fn(tg.forward(), idx)
            loss.backward()
            opt.step()
            sched.step()
            _project(tg, cfg)
            history.append(float(loss.detach()))
    else:
        opt = torch.optim.LBFGS(plist, lr=cfg.lbfgs_lr, max_iter=1, max_eval=10, history_size=20,
                                line_search_fn="strong_wolfe")
        idx = torch.randperm(cfg.light_pool, generator=rng)[: cfg.lights_per_step].to(device)

        def closure() -> torch.Tensor:
            opt.zero_grad(set_to_none=True)
            loss = loss_fn(tg.forward(), idx)
            loss.backward()
            return loss

        for _ in tqdm(range(cfg.iterations), disable=not cfg.progress, desc="recompose"):
            loss = opt.step(closure)
            _project(tg, cfg)
            history.append(float(loss.detach()))
    with torch.no_grad():
        loss_after = float(loss_fn(tg.forward(), None))
    kept = not loss_after < loss_before
    values = params_before if kept else tg.json_values()
    if kept:
        loss_after = loss_before
    out = copy.deepcopy(material)
    tg.write_back(out, values)
    out.meta["recompose"] = {"loss_before": loss_before, "loss_after": loss_after, "optimizer": cfg.optimizer,
                             "iterations": cfg.iterations, "kept_original": kept}
    secs = time.perf_counter() - t0
    logger.info("recompose %dx%d on %s: %s x%d, loss %.4f -> %.4f in %.1f s", w, h, device, cfg.optimizer,
                cfg.iterations, loss_before, loss_after, secs)
    return RecomposeResult(material=out, loss_before=loss_before, loss_after=loss_after, history=history,
                           seconds=secs, device=str(device), iterations=cfg.iterations,
                           params_before=params_before, params_after=values, kept_original=kept)


def _project(tg: TorchGraph, cfg: RecomposeConfig) -> None:
    """Keep sigmas inside [0, sigma_max] after a step."""
    with torch.no_grad():
        for k, t in tg.params.items():
            if tg.kinds[k] == "sigma":
                t.clamp_(0.0, cfg.sigma_max)


def torch_maps(material: G.ProceduralMaterial, width: int, height: int, scale: float = 1.0,
               device: str = "cpu") -> dict[str, np.ndarray]:
    """The material's maps through the torch graph (parity check with graph.evaluate)."""
    tg = TorchGraph(material, width, height, scale, pick_device(device), RecomposeConfig(sigma_init=0.0))
    with torch.no_grad():
        return {k: v.cpu().numpy() for k, v in tg.forward().items()}
