"""The differentiable material graph: a material's maps as torch tensors, with the recomposition's free
parameters as leaf tensors (paper section 5.3).

Each node type gives its own torch form (:meth:`workers.nodes.NodeType.forward`, with :class:`NodeTorch` as its
view of the graph); a node whose type has none, or whose ``prepare`` declines, is evaluated once with numpy and
enters as a constant image (PPTBF and instance masks, ``constant``, a generator whose filters are not optimised).
Blurs multiply FFTs (of the fixed layers and masks, computed once) by the transfer function of scipy's periodic
Gaussian (sampled, truncate 4) rebuilt from sigma each step, so an optimised graph renders identically with
:func:`workers.nodes.gaussian_blur` (max difference about 3e-7).
"""
from __future__ import annotations

import copy
import logging
from typing import TYPE_CHECKING, Any, Mapping

import numpy as np
import torch

from . import graph as G
from .nodes import NODE_TYPES, NodeType, as3
from .nodes.stack import IDENTITY_FILTER

if TYPE_CHECKING:
    from .recompose import RecomposeConfig

logger = logging.getLogger(__name__)


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


# ----------------------------------------------------------------------------- one node's view


class NodeTorch:
    """What a node type's ``prepare``/``slots``/``forward`` see of the torch graph: the node's free parameters
    (:meth:`leaf`), its stored values as tensors, the blur and FFT operations, and the evaluation context."""

    def __init__(self, graph: "TorchGraph", node_id: str, vals: Mapping[str, torch.Tensor], ins: Mapping | None = None,
                 state: Any = None):
        self.graph, self.node_id, self.vals, self.ins, self.state = graph, node_id, vals, ins or {}, state
        self.ctx = graph.ctx
        self.torch = torch              # the module, for node types' own tensor operations
        self.px = graph.ctx.px_scale
        self.check_tol = graph.cfg.check_tol
        self.collinear_offsets = graph.cfg.collinear_offsets

    def with_state(self, state: Any) -> "NodeTorch":
        return NodeTorch(self.graph, self.node_id, self.vals, self.ins, state)

    def optimises(self, group: str | None) -> bool:
        """The recomposition frees this group's parameters (``RecomposeConfig.optimise``)."""
        return group is not None and group in self.graph.cfg.optimise

    def leaf(self, path: str) -> torch.Tensor | None:
        """The free tensor of parameter ``path`` of this node, None when it is not optimised."""
        return self.vals.get(f"{self.node_id}.{path}")

    def value(self, path: str, stored: Any) -> torch.Tensor:
        """Parameter ``path``: its free tensor, else the stored value as a 1-D tensor (scalar or per channel)."""
        leaf = self.leaf(path)
        return self.tensor(np.atleast_1d(stored)) if leaf is None else leaf

    def sigma(self, path: str, stored: float) -> torch.Tensor:
        """A blur width: its free tensor kept in [0, sigma_max], else the stored value."""
        leaf = self.leaf(path)
        return torch.tensor(float(stored), device=self.graph.device) if leaf is None else self.clamp_sigma(leaf)

    def clamp_sigma(self, t: torch.Tensor) -> torch.Tensor:
        return t.clamp(0.0, self.graph.cfg.sigma_max).reshape(())

    def tensor(self, a: Any) -> torch.Tensor:
        return torch.as_tensor(np.asarray(a, dtype=np.float32), device=self.graph.device)

    def detached(self, t: torch.Tensor) -> np.ndarray:
        return t.detach().cpu().numpy()

    def rfft(self, x: torch.Tensor) -> torch.Tensor:
        return rfft_hw(x)

    def irfft(self, f: torch.Tensor) -> torch.Tensor:
        return irfft_hw(f, self.ctx.height, self.ctx.width)

    def gauss_transfer(self, sigma: torch.Tensor) -> torch.Tensor | None:
        return gauss_transfer(sigma, self.ctx.height, self.ctx.width, self.graph.device)

    def blur(self, x: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
        return blur_t(x, sigma)

    def blur_mask(self, port: str, sigma: torch.Tensor) -> torch.Tensor:
        """Blur of input ``port``'s first channel; a constant input's spectrum is computed once."""
        src = self.graph.mat.node(self.node_id)["inputs"][port]
        m = self.ins[port][..., :1]
        spec = None
        if src in self.graph.fixed:
            if src not in self.graph.spectra:
                self.graph.spectra[src] = rfft_hw(m)
            spec = self.graph.spectra[src]
        return blur_t(m, sigma, spec)

    def numpy_value(self) -> np.ndarray:
        """The node's output by the numpy evaluation (the reference its torch form must reproduce)."""
        return G.evaluate_node(self.graph.mat, self.node_id, self.ctx)

    def warn(self, message: str) -> None:
        node = self.graph.mat.node(self.node_id)
        logger.warning("node %s (%s): %s", self.node_id, node["type"], message)


# ----------------------------------------------------------------------------- torch graph


class TorchGraph:
    """Differentiable re-evaluation of a material's filter parameters over fixed, pre-evaluated generators.

    ``config``: a :class:`workers.recompose.RecomposeConfig` (optimise, sigma_init, sigma_max, check_tol,
    collinear_offsets)."""

    def __init__(self, mat: G.ProceduralMaterial, width: int, height: int, scale: float, device: torch.device,
                 config: "RecomposeConfig"):
        self.mat, self.device, self.cfg = mat, device, config
        self.ctx = G.EvalContext(width=width, height=height, scale=scale, seed=mat.seed,
                                 working_size=tuple(mat.working_size))
        self.params: dict[str, torch.Tensor] = {}     # "node.path" -> leaf tensor
        self.kinds: dict[str, str] = {}               # "node.path" -> "sigma" | "value" | "offset"
        self.initial: dict[str, Any] = {}             # "node.path" -> original JSON value
        self.fixed: dict[str, torch.Tensor] = {}      # node id -> HxWxC constant
        self.states: dict[str, Any] = {}              # node id -> what its type's forward needs
        self.spectra: dict[str, torch.Tensor] = {}    # node id of a fixed mask -> its rfft (first channel)
        self.order = self._needed_nodes()
        for nid in self.order:
            self._prepare(nid)
        logger.info("torch graph: %d nodes, %d fixed, %d parameters", len(self.order), len(self.fixed),
                    len(self.params))

    def _type(self, nid: str) -> NodeType:
        return NODE_TYPES[self.mat.node(nid)["type"]]

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

    def _prepare(self, nid: str) -> None:
        """The node's torch state and free parameters, or its numpy output as a constant."""
        node, typ = self.mat.node(nid), self._type(nid)
        view = NodeTorch(self, nid, {})
        state = typ.prepare(node, view)
        if state is None:
            self.fixed[nid] = view.tensor(as3(np.asarray(G.evaluate_node(self.mat, nid, self.ctx))))
            return
        self.states[nid] = state
        if view.optimises(typ.group):
            for s in typ.slots(node, view.with_state(state)):
                self._param(f"{nid}.{s.path}", s.value, s.kind, s.channels)

    def _param(self, key: str, value: Any, kind: str, c: int | None) -> None:
        """Register an optimisable leaf tensor (sigma: scalar, a stored 0 starts at sigma_init; value / offset:
        (C,) when the slot has C channels, else as stored)."""
        self.initial[key] = copy.deepcopy(value)
        if kind == "sigma":
            v = float(np.max(np.atleast_1d(np.asarray(value, dtype=np.float64))))
            init = self.cfg.sigma_init
            t = torch.tensor([v if init is None or v > 1e-3 else init], dtype=torch.float32, device=self.device)
        else:
            arr = np.atleast_1d(np.asarray(value, dtype=np.float64))
            if c is not None:
                arr = np.broadcast_to(arr, (c,)).copy()
            t = torch.as_tensor(arr.astype(np.float32), device=self.device).clone()
        self.params[key] = t.requires_grad_(True)
        self.kinds[key] = kind

    # -------------------------------------------------------------- forward
    def node_value(self, nid: str, cache: dict[str, torch.Tensor], vals: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """Torch value (HxWxC) of node ``nid``."""
        if nid in cache:
            return cache[nid]
        if nid in self.fixed:
            cache[nid] = self.fixed[nid]
            return cache[nid]
        node = self.mat.node(nid)
        ins = {k: self.node_value(s, cache, vals) for k, s in node["inputs"].items()}
        cache[nid] = self._type(nid).forward(node["params"], ins, NodeTorch(self, nid, vals, ins, self.states[nid]))
        return cache[nid]

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
                    filters.append(dict(IDENTITY_FILTER))
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
