"""What a node type of the material graph is: its declared parameters, its numpy evaluation, its torch form.

A node type is one class registered under its ``name``: its input ports, its parameters declared once with
:class:`Param` (name, kind, default, range, and how the recomposition optimises it), a numpy ``evaluate`` and,
where the recomposition passes gradients through it, a torch ``forward``. Validation, the editable parameter
list and the recomposition's free parameters all read the declarations.

Torch is never imported here or in the node modules: ``forward`` receives a per-node view of the differentiable
graph (``workers.torch_graph.NodeTorch``) that holds the tensors and the operations a node needs, so evaluating a
material needs neither torch nor any fitting code.
"""
from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import ndimage

from ..errors import GraphError

if TYPE_CHECKING:  # the torch view of a node and the MaterialX builder, only for annotations
    from ..mtlx.procedural import Builder
    from ..torch_graph import NodeTorch

#: kinds of declared parameters: a number, a number or a list of numbers (per channel), a list of numbers (one
#: per input or item), an integer, true/false, or structured data that the type's ``check`` validates
PARAM_KINDS = ("number", "numbers", "list", "int", "bool", "data")
#: how the recomposition optimises a parameter: a blur width (>= 0), a gain, or an additive offset
OPTIMISE_KINDS = ("sigma", "value", "offset")


# ----------------------------------------------------------------------------- evaluation context


@dataclass
class EvalContext:
    """What every node needs to render itself: output extent, pattern scale and randomness."""

    width: int
    height: int
    scale: float = 1.0
    seed: int = 0
    working_size: tuple[int, int] = (512, 512)
    cache: dict = field(default_factory=dict)

    def rng(self, node_id: str, stream: int = 0) -> np.random.Generator:
        """A generator that depends only on (seed, node id, stream): deterministic, independent per node."""
        key = zlib.crc32(node_id.encode("utf-8"))
        return np.random.default_rng(np.random.SeedSequence([int(self.seed) & 0xFFFFFFFF, key, stream]))

    def node_seed(self, node_id: str) -> int:
        """An integer seed for node ``node_id`` derived from the material seed."""
        return int(self.rng(node_id, 99).integers(0, 2**31 - 1))

    @property
    def px_scale(self) -> float:
        """Output pixels per working-size pixel of pattern (scale=2 -> features twice as many pixels)."""
        return float(self.scale)


# ----------------------------------------------------------------------------- parameters


@dataclass(frozen=True)
class Param:
    """One declared parameter of a node type.

    ``kind``: one of :data:`PARAM_KINDS`; ``default``: the value when the parameter is absent (``required``:
    absence is an error); ``lo``/``hi``: the closed range of every number; ``optimise``: one of
    :data:`OPTIMISE_KINDS` when the recomposition may change it, else None."""

    name: str
    kind: str
    default: Any = None
    lo: float = -math.inf
    hi: float = math.inf
    optimise: str | None = None
    required: bool = False
    doc: str = ""

    def check(self, type_name: str, params: dict) -> None:
        """GraphError naming ``type.param`` when the value present in ``params`` breaks the declaration."""
        if self.name not in params:
            if self.required:
                raise GraphError(f"{type_name}.{self.name} is required ({self.doc or self.kind})")
            return
        v = params[self.name]
        where = f"{type_name}.{self.name}"
        if self.kind == "bool":
            if not isinstance(v, bool):
                raise GraphError(f"{where} must be true or false")
        elif self.kind == "int":
            if not isinstance(v, int) or isinstance(v, bool) or not self.lo <= v <= self.hi:
                raise GraphError(f"{where} must be an integer{self._range()}")
        elif self.kind in ("number", "numbers", "list"):
            self._check_numbers(where, v)

    def _check_numbers(self, where: str, v: Any) -> None:
        scalar = isinstance(v, (int, float)) and not isinstance(v, bool)
        items = v if isinstance(v, list) else None
        ok = (scalar and self.kind != "list") or (
            items is not None and self.kind != "number" and (items or self.kind == "list")
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in items))
        if ok:
            vals = [v] if scalar else items
            ok = all(math.isfinite(x) and self.lo <= x <= self.hi for x in vals)
        if not ok:
            what = {"number": "a number", "numbers": "a number or a list of numbers",
                    "list": "a list of numbers"}[self.kind]
            raise GraphError(f"{where} must be {what}{self._range()} (finite), got {v!r}")

    def _range(self) -> str:
        if math.isinf(self.lo) and math.isinf(self.hi):
            return ""
        if math.isinf(self.hi):
            return f" >= {self.lo:g}"
        if math.isinf(self.lo):
            return f" <= {self.hi:g}"
        return f" from {self.lo:g} to {self.hi:g}"


@dataclass(frozen=True)
class Slot:
    """One parameter the recomposition frees: its path under the node's params (``a``, ``sigmas.1``,
    ``filters.0.sigma``), the stored value, how it is optimised, and its channel count (None: as stored)."""

    path: str
    value: Any
    kind: str
    channels: int | None = None


# ----------------------------------------------------------------------------- node types


class NodeType:
    """Base of every node type: declared parameters, numpy evaluation, optional torch form.

    ``inputs``: the port names (``("*",)``: any ports, e.g. ``in0, in1, ...``). ``group``: the recomposition's name
    for this type's optimisable parameters (``RecomposeConfig.optimise``); ``differentiable``: ``forward`` exists,
    so the node's output carries gradients (a type without it enters the torch graph as a constant image)."""

    name: str = ""
    inputs: tuple[str, ...] = ()
    params: tuple[Param, ...] = ()
    group: str | None = None
    differentiable: bool = False

    def validate(self, params: dict) -> None:
        """GraphError when ``params`` break a declaration or the type's own rules (:meth:`check`)."""
        for p in self.params:
            p.check(self.name, params)
        self.check(params)

    def check(self, params: dict) -> None:
        """Rules beyond the declarations (structured data, relations between parameters)."""

    def get(self, params: dict, name: str) -> Any:
        """A parameter's value, or its declared default."""
        if name in params:
            return params[name]
        for p in self.params:
            if p.name == name:
                return p.default
        raise KeyError(f"node type {self.name!r} declares no parameter {name!r}")

    def evaluate(self, params: dict, inputs: dict[str, np.ndarray], ctx: EvalContext, node_id: str) -> np.ndarray:
        """The node's output, HxWxC float32 (or HxW)."""
        raise NotImplementedError

    # -------------------------------------------------------------- torch form
    def prepare(self, node: dict, t: "NodeTorch") -> Any:
        """What ``forward`` needs beyond the params (None: the node is a constant in the torch graph)."""
        return {} if self.differentiable else None

    def slots(self, node: dict, t: "NodeTorch") -> list[Slot]:
        """The parameters the recomposition frees: by default each declared ``optimise`` parameter."""
        return [Slot(p.name, node["params"].get(p.name, p.default), p.optimise)
                for p in self.params if p.optimise is not None]

    def forward(self, params: dict, ins: dict, t: "NodeTorch"):
        """The node's output as a torch tensor (HxWxC) from its inputs' tensors."""
        raise NotImplementedError(f"node type {self.name!r} has no torch form")

    # -------------------------------------------------------------- MaterialX form
    def materialx(self, b: "Builder", node: dict, node_id: str, offset: tuple[int, int]) -> list | None:
        """The node in a procedural MaterialX graph: one float value per channel, built with ``b``
        (``workers.mtlx.procedural.Builder``) for the pixel ``offset`` pixels away; None: no pointwise form, the
        exporter bakes the node's output at the exported size and seed."""
        return None


NODE_TYPES: dict[str, NodeType] = {}


def register_node(cls: type) -> type:
    """Class decorator: register a node type (instantiated once) under ``cls.name``."""
    inst = cls()
    if not getattr(inst, "name", None):
        raise TypeError(f"node type {cls.__name__} has no name")
    if not isinstance(inst, NodeType):
        raise TypeError(f"node type {cls.__name__} must derive from workers.nodes.NodeType")
    for p in inst.params:
        if p.kind not in PARAM_KINDS or (p.optimise is not None and p.optimise not in OPTIMISE_KINDS):
            raise TypeError(f"node type {inst.name}: parameter {p.name} has kind {p.kind!r} / optimise "
                            f"{p.optimise!r}")
    NODE_TYPES[inst.name] = inst
    return cls


# ----------------------------------------------------------------------------- shared helpers


def numbers(value: Any, field: str) -> np.ndarray:
    """A parameter as a 1-D float array; GraphError naming `field` when it is not numbers (a string, a dict)."""
    try:
        return np.atleast_1d(np.asarray(value, dtype=np.float64))
    except (TypeError, ValueError, OverflowError):
        raise GraphError(f"{field} must be a number or a list of numbers, got {value!r}") from None


def as3(a: np.ndarray) -> np.ndarray:
    """View a 2-D array as HxWx1."""
    return a[..., None] if a.ndim == 2 else a


def gaussian_blur(x: np.ndarray, sigma: float) -> np.ndarray:
    """Periodic (wrap) Gaussian blur over the two spatial axes; sigma in output pixels."""
    if sigma <= 1e-3:
        return x
    if sigma >= max(x.shape[0], x.shape[1]):  # the periodic blur is the mean to within exp(-2 pi^2) ~ 3e-9
        return np.broadcast_to(x.mean(axis=(0, 1), keepdims=True), x.shape).astype(np.float32)
    s = (sigma, sigma, 0) if x.ndim == 3 else (sigma, sigma)
    return ndimage.gaussian_filter(x, s, mode="wrap").astype(np.float32)
