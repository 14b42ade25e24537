"""Recomposition (paper 5.3): assemble the material graph from the tree, then optimise its filter parameters.

:func:`assemble_material` turns the decomposition tree into ``blend`` nodes, one tree per map (albedo, roughness,
height, metallic), on top of the leaf generators and mask nodes the other stages added, and declares the map
outputs (normal derived from height).

:func:`optimise` fits the continuous filter parameters of that graph to the target maps by gradient descent:

* The fixed parts (PPTBF / instance masks, any node type without a torch form) are evaluated once with
  :mod:`workers.graph` at the target's size. ``noise`` nodes are split into ``matched``, ``base`` and layers
  ``L_k`` with :func:`workers.noise.synthesize_layers`; any other node whose params hold ``filters``
  [{a, b, sigma}], ``c``, ``d`` is split by probing the node itself (identity filters, one ``a_k = 0`` per layer,
  ``c = 2``). Either split is checked against the node's own output before it is trusted (else: kept fixed).
* A torch graph re-evaluates ``O = matched + sum_k (blur(a_k L_k + b_k; sigma_k) - L_k) + (c - 1) base + d`` and
  ``blend`` (``sum_i blur(mask_i; sigma_i) child_i``) (optionally ``level`` a/d and ``blur`` sigma) with those
  parameters as leaf tensors. Blurs multiply FFTs (of the fixed layers / masks, computed once) by the transfer
  function of scipy's periodic Gaussian (sampled, truncate 4) rebuilt from sigma each step, so the optimised
  graph renders identically with :func:`workers.graph.gaussian_blur` (max diff ~3e-7).
* ``b_k`` and ``c`` of a noise node shift the map exactly like ``d`` (its base is a constant colour): by default
  only ``d`` is optimised (``collinear_offsets=True`` adds them); all values are written back.
* Loss: Gram L1 (:class:`workers.features.GramExtractor`, normalised per layer by the target Gram) on albedo,
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
from typing import Any, Mapping

import numpy as np
import torch
from tqdm import tqdm

from . import graph as G
from .errors import GraphError, InputError
from .features import GramExtractor, ssim
from .render import paper_lights, random_lights, render, tonemap
from .tree import MaskNode

logger = logging.getLogger(__name__)

MAP_ORDER = ("albedo", "roughness", "height", "metallic")
FILTER_STACK_KEYS = ("filters", "c", "d")


# ----------------------------------------------------------------------------- assembly


def assemble_material(tree: MaskNode, leaf_nodes: Mapping[str, Mapping[str, str]], mask_nodes: Mapping[str, str],
                      material: G.ProceduralMaterial, height_strength: float = 1.0, *,
                      maps: tuple[str, ...] | None = None, blend_sigma: float = 0.0,
                      tilt: tuple[float, float] = (0.0, 0.0), convention: str = "opengl",
                      prefix: str = "blend") -> G.ProceduralMaterial:
    """Add one ``blend`` node per internal tree node and map, bottom-up, and the map outputs; returns ``material``.

    ``leaf_nodes[leaf.id][map_name]`` is the graph node generating that map inside the leaf (e.g. a ``noise``
    node); ``mask_nodes[child.id]`` the graph node (1-channel mask, e.g. ``pptbf`` or ``channel`` of
    ``instances``) giving that child's mask inside its parent; the masks of a split should partition it (the
    blends are normalised by the sum of the blurred masks). ``maps`` defaults to the maps every leaf provides
    (order albedo, roughness, height, metallic). With a height map, a ``normal`` output ``from_height`` with
    ``height_strength`` (and ``tilt``) is declared. Internal node ``n`` and map ``m`` get id ``{prefix}_{n}_{m}``
    (dots of tree ids become underscores: graph ids cannot hold dots).
    """
    leaves = tree.leaves()
    for leaf in leaves:
        if leaf.id not in leaf_nodes:
            raise GraphError(f"assemble_material: no generator nodes given for leaf {leaf.id!r}")
        for m, nid in leaf_nodes[leaf.id].items():
            material.node(nid)
    if maps is None:
        common = set.intersection(*(set(leaf_nodes[leaf.id]) for leaf in leaves))
        maps = tuple(m for m in MAP_ORDER if m in common)
    if not maps:
        raise GraphError("assemble_material: the leaves share no map (need albedo/roughness/height/metallic)")
    for node in tree.walk():
        for child in node.children:
            if child.id not in mask_nodes:
                raise GraphError(f"assemble_material: no mask node given for tree node {child.id!r} "
                                 f"(child of {node.id!r})")
            material.node(mask_nodes[child.id])

    def build(node: MaskNode, m: str) -> str:
        if node.is_leaf:
            if m not in leaf_nodes[node.id]:
                raise GraphError(f"assemble_material: leaf {node.id!r} has no {m!r} generator")
            return leaf_nodes[node.id][m]
        ins: dict[str, str] = {}
        for i, child in enumerate(node.children):
            ins[f"mask{i}"] = mask_nodes[child.id]
            ins[f"child{i}"] = build(child, m)
        return material.add(f"{prefix}_{node.id.replace('.', '_')}_{m}", "blend",
                            {"sigmas": [float(blend_sigma)] * len(node.children), "normalise": True}, **ins)

    existing = {e["name"] for e in material.maps}
    for m in maps:
        out = build(tree, m)
        if m in existing:
            raise GraphError(f"assemble_material: map {m!r} is already declared")
        entry = {"name": m, "node": out}
        if m == "albedo":
            entry["colorspace"] = "linear"
        material.maps.append(entry)
    if "height" in maps and "normal" not in existing:
        material.maps.append({"name": "normal", "from_height": "height", "strength": float(height_strength),
                              "convention": convention, "tilt": [float(tilt[0]), float(tilt[1])]})
    material.meta.setdefault("tree", tree.describe())
    logger.info("assembled %d maps over %d leaves (%d nodes)", len(maps), len(leaves), len(material.nodes))
    return material


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
    vgg_layers: int = 3                  # VGG-19 Gram layers used: relu1_1.. (3: up to relu3_1; 4: relu4_1)
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
    optimise: tuple[str, ...] = ("filters", "blend")  # also possible: "level" (a, d), "blur" (sigma)
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
        if cfg.features not in ("vgg19", "random"):
            raise InputError(f"recompose.features must be 'vgg19' or 'random', got {cfg.features!r}")
        if not 1 <= int(cfg.vgg_layers) <= 4:
            raise InputError(f"recompose.vgg_layers must be 1..4, got {cfg.vgg_layers!r}")
        if cfg.loss_size is not None and int(cfg.loss_size) != 0 and int(cfg.loss_size) < 32:
            raise InputError(f"recompose.loss_size must be null (half the maps' size), 0 (full size) or >= 32, "
                             f"got {cfg.loss_size!r}")
        return cfg


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


# ----------------------------------------------------------------------------- torch ops


def _wrapped_kernel(sigma: torch.Tensor, n: int, r: int) -> torch.Tensor:
    """Sampled, normalised Gaussian of radius ``r`` wrapped onto a circle of ``n`` samples (differentiable)."""
    t = torch.arange(-r, r + 1, device=sigma.device, dtype=sigma.dtype)
    k = torch.exp((-(t * t) / (2.0 * sigma * sigma)).clamp_min(-80.0))  # no denormals (100x slower on CPU)
    k = k / k.sum()
    idx = torch.remainder(torch.arange(-r, r + 1, device=sigma.device), n)
    return torch.zeros(n, device=sigma.device, dtype=sigma.dtype).index_add(0, idx, k)


def gauss_transfer(sigma: torch.Tensor | float, h: int, w: int, device=None) -> torch.Tensor | None:
    """Real transfer function (H, W//2+1, 1) of scipy's periodic Gaussian blur (truncate 4); None = identity."""
    if not torch.is_tensor(sigma):
        sigma = torch.tensor(float(sigma), device=device)
    sigma = sigma.reshape(()).to(torch.float32)
    s = float(sigma.detach())
    if s <= 1e-3:
        return None
    r = int(4.0 * s + 0.5)
    ky = torch.fft.fft(_wrapped_kernel(sigma, h, r)).real
    kx = torch.fft.rfft(_wrapped_kernel(sigma, w, r)).real
    return (ky[:, None] * kx[None, :])[..., None]


def rfft_hw(x: torch.Tensor) -> torch.Tensor:
    """2-D real FFT of HxWxC over the spatial axes -> (H, W//2+1, C) complex."""
    return torch.fft.rfft2(x, dim=(0, 1))


def irfft_hw(f: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """Inverse of :func:`rfft_hw`."""
    return torch.fft.irfft2(f, s=(h, w), dim=(0, 1))


def blur_t(x: torch.Tensor, sigma: torch.Tensor | float, spectrum: torch.Tensor | None = None) -> torch.Tensor:
    """Periodic Gaussian blur of HxWxC ``x`` with scipy's kernel (sampled, normalised, radius int(4 sigma + .5)),
    by FFT; differentiable w.r.t. ``x`` and ``sigma``. ``spectrum``: precomputed :func:`rfft_hw` of ``x``."""
    h, w = x.shape[:2]
    tf = gauss_transfer(sigma, h, w, x.device)
    if tf is None:
        return x
    return irfft_hw((rfft_hw(x) if spectrum is None else spectrum) * tf, h, w)


def sobel_t(h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(dh/dx, dh/drow) of HxW ``h``: the normalised wrap-around Sobel of workers.height.sobel_gradients."""
    cx = (torch.roll(h, -1, 1) - torch.roll(h, 1, 1)) * 0.5
    cy = (torch.roll(h, -1, 0) - torch.roll(h, 1, 0)) * 0.5
    dx = (torch.roll(cx, 1, 0) + 2.0 * cx + torch.roll(cx, -1, 0)) * 0.25
    dy = (torch.roll(cy, 1, 1) + 2.0 * cy + torch.roll(cy, -1, 1)) * 0.25
    return dx, dy


def height_to_normal_t(h: torch.Tensor, strength: float, convention: str = "opengl",
                       tilt: tuple[float, float] = (0.0, 0.0)) -> torch.Tensor:
    """Unit normals HxWx3 of an HxW(x1) height, as workers.height.height_to_normal (differentiable)."""
    if h.dim() == 3:
        h = h[..., 0]
    sign = 1.0 if convention == "opengl" else -1.0
    dx, dy = sobel_t(h)
    n = torch.stack([-(dx * strength + tilt[0]), sign * (dy * strength + tilt[1]), torch.ones_like(h)], dim=-1)
    return n / n.norm(dim=-1, keepdim=True)


# ----------------------------------------------------------------------------- torch graph


def _is_filter_stack(node: dict) -> bool:
    """Node params shaped like a noise node's recomposition filters."""
    p = node["params"]
    return isinstance(p.get("filters"), list) and all(isinstance(f, dict) for f in p["filters"])


def _n_layers(node: dict) -> int:
    """Number of noise layers a filter-stack node has (noise nodes may list fewer filters than layers)."""
    if node["type"] == "noise":
        from .noise import NoiseModel

        return len(NoiseModel.from_params(node["params"]).layers)
    return len(node["params"]["filters"])


def _vec(v: Any, c: int) -> np.ndarray:
    """Scalar or per-channel value as (C,) float64."""
    return np.broadcast_to(np.atleast_1d(np.asarray(v, dtype=np.float64)), (c,)).copy()


class TorchGraph:
    """Differentiable re-evaluation of a material's filter parameters over fixed, pre-evaluated generators."""

    def __init__(self, mat: G.ProceduralMaterial, width: int, height: int, scale: float, device: torch.device,
                 config: RecomposeConfig):
        self.mat, self.device, self.cfg = mat, device, config
        self.ctx = G.EvalContext(width=width, height=height, scale=scale, seed=mat.seed,
                                 working_size=tuple(mat.working_size))
        self.params: dict[str, torch.Tensor] = {}     # "node.path" -> leaf tensor
        self.kinds: dict[str, str] = {}               # "node.path" -> "sigma" | "value" | "offset"
        self.initial: dict[str, Any] = {}             # "node.path" -> original JSON value
        self.fixed: dict[str, torch.Tensor] = {}      # node id -> HxWxC constant
        self.stacks: dict[str, dict] = {}             # node id -> {"rest", "base", "spectra", "c", "k"}
        self.spectra: dict[str, torch.Tensor] = {}    # node id of a fixed mask -> its rfft (first channel)
        self.order = self._needed_nodes()
        for nid in self.order:
            self._prepare(nid)
        logger.info("torch graph: %d nodes, %d fixed, %d filter stacks, %d parameters", len(self.order),
                    len(self.fixed), len(self.stacks), len(self.params))

    # -------------------------------------------------------------- preparation
    def _needed_nodes(self) -> list[str]:
        """Nodes reachable from the map outputs, inputs first."""
        order: list[str] = []
        seen: set[str] = set()

        def visit(nid: str) -> None:
            if nid in seen:
                return
            seen.add(nid)
            for src in self.mat.node(nid)["inputs"].values():
                visit(src)
            order.append(nid)

        for m in self.mat.maps:
            if "node" in m:
                visit(m["node"])
        return order

    def _tensor(self, a: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.asarray(a, dtype=np.float32), device=self.device)

    def _param(self, key: str, value: Any, kind: str, c: int | None = None, init: float | None = None) -> None:
        """Register an optimisable leaf tensor (sigma: scalar; value / offset: (C,) or scalar)."""
        self.initial[key] = copy.deepcopy(value)
        if kind == "sigma":
            v = float(np.max(np.atleast_1d(np.asarray(value, dtype=np.float64))))
            t = torch.tensor([v if init is None or v > 1e-3 else init], dtype=torch.float32, device=self.device)
        else:
            arr = _vec(value, c) if c is not None else np.atleast_1d(np.asarray(value, dtype=np.float64))
            t = torch.as_tensor(arr.astype(np.float32), device=self.device).clone()
        self.params[key] = t.requires_grad_(True)
        self.kinds[key] = kind

    def _eval_graph(self, nid: str, params: dict | None = None) -> np.ndarray:
        """Evaluate node ``nid`` with workers.graph (optionally with replaced params), inputs memoised."""
        node = self.mat.node(nid)
        if params is None:
            return G.evaluate_node(self.mat, nid, self.ctx)
        t = G.NODE_TYPES[node["type"]]
        ins = {p: G.evaluate_node(self.mat, s, self.ctx) for p, s in node["inputs"].items()}
        return G._as3(np.asarray(t.evaluate(params, ins, self.ctx, nid), dtype=np.float32))

    def _prepare(self, nid: str) -> None:
        node = self.mat.node(nid)
        typ, p = node["type"], node["params"]
        opt = self.cfg.optimise
        if typ == "blend" and "blend" in opt:
            if "mask" in node["inputs"]:
                self._param(f"{nid}.sigma", p.get("sigma", 0.0), "sigma", init=self.cfg.sigma_init)
            else:
                n = sum(1 for k in node["inputs"] if k.startswith("mask"))
                sig = list(p.get("sigmas", [])) + [0.0] * (n - len(p.get("sigmas", [])))
                for i in range(n):
                    self._param(f"{nid}.sigmas.{i}", sig[i], "sigma", init=self.cfg.sigma_init)
        elif typ == "level" and "level" in opt:
            self._param(f"{nid}.a", p.get("a", 1.0), "value")
            self._param(f"{nid}.d", p.get("d", 0.0), "offset")
        elif typ == "blur" and "blur" in opt:
            self._param(f"{nid}.sigma", p.get("sigma", 0.0), "sigma", init=self.cfg.sigma_init)
        elif typ in ("blend", "level", "blur", "add", "clamp", "channel"):
            pass
        elif _is_filter_stack(node) and "filters" in opt and self._split_stack(nid):
            pass
        else:
            self.fixed[nid] = self._tensor(self._eval_graph(nid))

    def _split_stack(self, nid: str) -> bool:
        """Split a filter-stack node into matched / base / layers by probing it; False if it is not linear."""
        node = self.mat.node(nid)
        p = node["params"]
        k = _n_layers(node)
        if node["type"] == "noise":
            matched, base, layers = self._noise_layers(nid)
        else:
            matched, base, layers = self._probe_layers(nid, k)
        c = matched.shape[2]
        filters = list(p.get("filters", [])) + [{} for _ in range(k - len(p.get("filters", [])))]
        lt = [self._tensor(a) for a in layers]
        rest = self._tensor(matched)
        for lay in lt:
            rest = rest - lay
        stack = {"rest": rest, "base": self._tensor(base), "spectra": [rfft_hw(lay) for lay in lt], "c": c, "k": k}
        keys = []
        for i, f in enumerate(filters):
            keys.append((f"{nid}.filters.{i}.a", f.get("a", 1.0), "value"))
            keys.append((f"{nid}.filters.{i}.b", f.get("b", 0.0), "offset"))
            keys.append((f"{nid}.filters.{i}.sigma", f.get("sigma", 0.0), "sigma"))
        keys += [(f"{nid}.c", p.get("c", 1.0), "offset"), (f"{nid}.d", p.get("d", 0.0), "offset")]
        self.stacks[nid] = stack
        vals = {}
        for key, v, kind in keys:
            vals[key] = torch.as_tensor(_vec(v, c).astype(np.float32), device=self.device) if kind != "sigma" \
                else torch.tensor([float(np.max(np.atleast_1d(v)))], device=self.device)
        stack["stored"] = vals
        with torch.no_grad():
            mine = self._stack_forward(nid, vals).cpu().numpy()
        ref = self._eval_graph(nid)
        err = float(np.max(np.abs(mine - ref)))
        if err > self.cfg.check_tol * max(1.0, float(np.max(np.abs(ref)))):
            logger.warning("node %s (%s): filter split does not reproduce the node (max err %.3g); kept fixed",
                           nid, node["type"], err)
            del self.stacks[nid]
            return False
        for key, v, kind in keys:
            collinear = key.endswith(".b") or key == f"{nid}.c"
            if self.cfg.collinear_offsets or not collinear:
                self._param(key, v, kind, c=c, init=self.cfg.sigma_init)
        # a node listing fewer filters than layers gets the identity for the rest: record so write-back extends
        stack["n_filters_stored"] = len(p.get("filters", []))
        return True

    def _noise_layers(self, nid: str) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
        """matched, base, layers of a ``noise`` node straight from workers.noise.synthesize_layers."""
        from .noise import NoiseModel, synthesize_layers

        p = self.mat.node(nid)["params"]
        seed = int(p["seed"]) if "seed" in p else self.ctx.node_seed(nid)
        res = synthesize_layers(NoiseModel.from_params(p), self.ctx.width, self.ctx.height,
                                scale=self.ctx.px_scale, seed=seed)
        return res.matched, np.asarray(res.base, dtype=np.float32), list(res.layers)

    def _probe_layers(self, nid: str, k: int) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
        """matched, base, layers of any filter-stack node by evaluating it with probe filters (k + 2 runs)."""
        ident = copy.deepcopy(self.mat.node(nid)["params"])
        ident["filters"] = [{"a": 1.0, "b": 0.0, "sigma": 0.0} for _ in range(k)]
        ident["c"], ident["d"] = 1.0, 0.0
        matched = self._eval_graph(nid, ident)
        layers = []
        for i in range(k):
            q = copy.deepcopy(ident)
            q["filters"][i]["a"] = 0.0
            layers.append(matched - self._eval_graph(nid, q))
        q = copy.deepcopy(ident)
        q["c"] = 2.0
        base = (self._eval_graph(nid, q) - matched).mean(axis=(0, 1))
        return matched, base, layers

    # -------------------------------------------------------------- forward
    def _stack_forward(self, nid: str, vals: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """O = (matched - sum L_k) + irfft(sum_k a_k T(sigma_k) FFT(L_k)) + sum_k b_k + (c - 1) base + d."""
        s = self.stacks[nid]
        vals = {**s["stored"], **vals}
        h, w = self.ctx.height, self.ctx.width
        px = self.ctx.px_scale
        acc = None
        offset = vals[f"{nid}.d"] + (vals[f"{nid}.c"] - 1.0) * s["base"]
        for i, fl in enumerate(s["spectra"]):
            a, b = vals[f"{nid}.filters.{i}.a"], vals[f"{nid}.filters.{i}.b"]
            tf = gauss_transfer(self._sigma(vals[f"{nid}.filters.{i}.sigma"]) * px, h, w, self.device)
            term = fl * a if tf is None else fl * (tf * a)
            acc = term if acc is None else acc + term
            offset = offset + b
        out = s["rest"] + offset
        return out if acc is None else out + irfft_hw(acc, h, w)

    def _sigma(self, t: torch.Tensor) -> torch.Tensor:
        return t.clamp(0.0, self.cfg.sigma_max).reshape(())

    def node_value(self, nid: str, cache: dict[str, torch.Tensor], vals: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """Torch value (HxWxC) of node ``nid``."""
        if nid in cache:
            return cache[nid]
        if nid in self.fixed:
            cache[nid] = self.fixed[nid]
            return cache[nid]
        node = self.mat.node(nid)
        typ, p = node["type"], node["params"]
        ins = {k: self.node_value(s, cache, vals) for k, s in node["inputs"].items()}
        px = self.ctx.px_scale
        if nid in self.stacks:
            out = self._stack_forward(nid, vals)
        elif typ == "level":
            a = vals.get(f"{nid}.a", self._tensor(np.atleast_1d(p.get("a", 1.0))))
            d = vals.get(f"{nid}.d", self._tensor(np.atleast_1d(p.get("d", 0.0))))
            out = ins["input"] * a + d
            if p.get("clamp", False):
                out = out.clamp(0.0, 1.0)
        elif typ == "blur":
            s = vals.get(f"{nid}.sigma", torch.tensor(float(p.get("sigma", 0.0)), device=self.device))
            out = blur_t(ins["input"], self._sigma(s) * px)
        elif typ == "blend":
            out = self._blend(nid, node, ins, vals)
        elif typ == "add":
            keys = sorted(ins)
            out = ins[keys[0]]
            for kk in keys[1:]:
                out = out + ins[kk]
        elif typ == "clamp":
            out = ins["input"].clamp(float(p.get("lo", 0.0)), float(p.get("hi", 1.0)))
        elif typ == "channel":
            out = ins["input"][..., list(p["channels"])]
        else:  # pragma: no cover - every other type is fixed
            raise GraphError(f"torch graph: node {nid!r} of type {typ!r} has no torch form")
        cache[nid] = out
        return out

    def _blend(self, nid: str, node: dict, ins: dict, vals: Mapping[str, torch.Tensor]) -> torch.Tensor:
        p, px = node["params"], self.ctx.px_scale

        def sig(key: str, default: float) -> torch.Tensor:
            return self._sigma(vals[key]) if key in vals else torch.tensor(default, device=self.device)

        def mask(port: str, s: torch.Tensor) -> torch.Tensor:
            src = node["inputs"][port]
            m = ins[port][..., :1]
            spec = None
            if src in self.fixed:
                if src not in self.spectra:
                    self.spectra[src] = rfft_hw(m)
                spec = self.spectra[src]
            return blur_t(m, s * px, spec)

        if "mask" in ins:
            m = mask("mask", sig(f"{nid}.sigma", float(p.get("sigma", 0.0))))
            return m * ins["fg"] + (1.0 - m) * ins["bg"]
        stored = list(p.get("sigmas", []))
        out, total, i = None, None, 0
        while f"mask{i}" in ins:
            s = sig(f"{nid}.sigmas.{i}", float(stored[i]) if i < len(stored) else 0.0)
            m = mask(f"mask{i}", s)
            term = m * ins[f"child{i}"]
            out = term if out is None else out + term
            total = m if total is None else total + m
            i += 1
        if out is None:
            raise GraphError(f"blend node {nid} has no inputs")
        if p.get("normalise", False):
            out = out / total.clamp_min(G.NORMALISE_EPS)
        return out

    def forward(self, vals: Mapping[str, torch.Tensor] | None = None) -> dict[str, torch.Tensor]:
        """All maps (HxWxC tensors) as graph.evaluate gives them: clamped (except height), normal from height."""
        vals = self.params if vals is None else vals
        cache: dict[str, torch.Tensor] = {}
        out: dict[str, torch.Tensor] = {}
        for m in self.mat.maps:
            if "node" in m:
                v = self.node_value(m["node"], cache, vals)
                out[m["name"]] = v if m["name"] == "height" or not m.get("clamp", True) else v.clamp(0.0, 1.0)
        for m in self.mat.maps:
            if "from_height" in m:
                tilt = tuple(m.get("tilt", (0.0, 0.0)))
                out[m["name"]] = height_to_normal_t(out[m["from_height"]],
                                                    float(m.get("strength", 1.0)) * self.ctx.px_scale,
                                                    m.get("convention", "opengl"), (float(tilt[0]), float(tilt[1])))
        return out

    # -------------------------------------------------------------- parameters
    def json_values(self, vals: Mapping[str, torch.Tensor] | None = None) -> dict[str, Any]:
        """Parameter values as they are written to the material (sigma >= 0, per-channel lists or scalars)."""
        vals = self.params if vals is None else vals
        out = {}
        for key, t in vals.items():
            v = t.detach().cpu().double().numpy()
            if self.kinds[key] == "sigma":
                out[key] = round(float(np.clip(v[0], 0.0, self.cfg.sigma_max)), 6)
            elif isinstance(self.initial[key], (int, float)) and np.allclose(v, v[0]):
                out[key] = round(float(v[0]), 6)
            else:
                out[key] = [round(float(x), 6) for x in v]
        return out

    def write_back(self, mat: G.ProceduralMaterial, values: Mapping[str, Any]) -> None:
        """Store ``values`` ("node.path" -> JSON value) into ``mat``'s node params."""
        for key, v in values.items():
            nid, *path = key.split(".")
            node = mat.node(nid)
            if path[0] == "filters":
                filters = node["params"].setdefault("filters", [])
                i = int(path[1])
                while len(filters) <= i:
                    filters.append({"a": 1.0, "b": 0.0, "sigma": 0.0})
                filters[i][path[2]] = v
            elif path[0] == "sigmas":
                sig = node["params"].setdefault("sigmas", [])
                i = int(path[1])
                while len(sig) <= i:
                    sig.append(0.0)
                sig[i] = v
            else:
                node["params"][path[0]] = v
        for nid in {k.split(".")[0] for k in values}:
            node = mat.node(nid)
            G.NODE_TYPES[node["type"]].validate(node["params"])


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


def _optimise(material: G.ProceduralMaterial, target: Any, cfg: RecomposeConfig) -> RecomposeResult:
    """Body of :func:`optimise`."""
    t0 = time.perf_counter()
    device = pick_device(cfg.device)
    tmaps = _target_maps(target)
    h, w = tmaps["albedo"].shape[:2]
    scale = w / float(material.working_size[0])
    tg = TorchGraph(material, w, h, scale, device, cfg)
    produced = tg.forward(tg.params)
    tgt = {k: torch.as_tensor(v, device=device) for k, v in tmaps.items() if k in produced}
    if "normal" in produced and "normal" in tmaps:
        tgt["normal"] = torch.as_tensor(tmaps["normal"], device=device)
    loss_fn = RecomposeLoss(tgt, cfg, device)

    init_vals = {}
    for key, t in tg.params.items():
        v0 = tg.initial[key]
        if tg.kinds[key] == "sigma":
            v0 = float(np.max(np.atleast_1d(np.asarray(v0, dtype=np.float64))))
            init_vals[key] = torch.tensor([v0], dtype=torch.float32, device=device)
        else:
            init_vals[key] = t.detach().clone()
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
