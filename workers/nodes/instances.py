"""The ``instances`` node: random kinds for the pieces of a procedural cell mask (paper section 5.2, instance
masks are sampled, not fitted): each piece draws a kind from the stored shares."""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from ..errors import GraphError, InputError
from ..instances import check_mask, piece_labels
from .base import EvalContext, NodeType, Param, register_node

#: the widest neck cut a file may ask for (working-size px)
MAX_SEPARATE = 1e4
#: cell keys (24-bit integers, ``pptbf_db.pptbf.cell_keys``) travel in float maps as key / CELL_SCALE (exact)
CELL_SCALE = float(2 ** 24)


# ----------------------------------------------------------------------------- per-cell draws
# The same integer arithmetic as the GLSL of the MaterialX node library (genglsl/lib/pz_seed.glsl), so that a
# shader draws what numpy draws: murmur3's finaliser on uint32, wrapping.

def _mix(h: np.ndarray) -> np.ndarray:
    h = np.asarray(h, dtype=np.uint32)
    with np.errstate(over="ignore"):
        h = h ^ (h >> np.uint32(16))
        h = h * np.uint32(0x85EBCA6B)
        h = h ^ (h >> np.uint32(13))
        h = h * np.uint32(0xC2B2AE35)
        return h ^ (h >> np.uint32(16))


def cell_hash(cells: np.ndarray, stream: int, k: int) -> np.ndarray:
    """uint32 hash of (cell key, stream, k) for a cell map (floats key / CELL_SCALE)."""
    key = np.rint(np.asarray(cells, dtype=np.float64) * CELL_SCALE).astype(np.int64).astype(np.uint32)
    with np.errstate(over="ignore"):
        salt = _mix(np.uint32((int(stream) + 0x632BE5AB * int(k)) & 0xFFFFFFFF))
        return _mix(key * np.uint32(0x9E3779B9) + salt)


def cell_uniform(cells: np.ndarray, stream: int, k: int = 0) -> np.ndarray:
    """One uniform draw in [0, 1) per cell (24 bits: exact in float32)."""
    return (cell_hash(cells, stream, k) >> np.uint32(8)).astype(np.float64) / CELL_SCALE


def cell_normal(cells: np.ndarray, stream: int, k: int = 0) -> np.ndarray:
    """One standard normal draw per cell (Box-Muller on two :func:`cell_uniform` draws)."""
    u1 = ((cell_hash(cells, stream, 2 * k) >> np.uint32(8)).astype(np.float64) + 0.5) / CELL_SCALE
    u2 = cell_uniform(cells, stream, 2 * k + 1)
    return np.sqrt(-2.0 * np.log(u1)) * np.cos(2.0 * np.pi * u2)


def cell_stream(ctx: EvalContext, node_id: str) -> int:
    """The node's stream of per-cell draws at the material seed (a shader adds the document's seed to it)."""
    return int(ctx.node_seed(node_id)) & 0x7FFFFFFF


def cell_kinds(cells: np.ndarray, shares, stream: int) -> np.ndarray:
    """Kind index per pixel: each cell draws one kind with probabilities ``shares``."""
    edges = np.cumsum(check_shares(shares))[:-1]
    return np.searchsorted(edges, cell_uniform(cells, stream), side="right")


def check_shares(shares) -> np.ndarray:
    """Non-negative finite shares with a positive sum, normalised to 1."""
    s = np.asarray(shares, dtype=np.float64).ravel()
    if s.size == 0 or not np.all(np.isfinite(s)) or (s < 0).any() or s.sum() <= 0:
        raise InputError(f"shares: need a non-empty list of non-negative numbers with a positive sum, got {shares!r}")
    return s / s.sum()


def sample_instances(parent_mask, shares, rng: np.random.Generator, separate: float = 0.0,
                     labels: np.ndarray | None = None) -> np.ndarray:
    """Cluster labels (HxW int, -1 outside the parent): each connected component draws a cluster from `shares`.
    ``separate`` > 0 first cuts the parent at its necks (``workers.instances.separate_cells``, markers that many
    px apart), as the decomposition cut the input's cells before it measured their kinds: an outline network
    with gaps then still gives one piece per cell; the cut lines take the kind of the nearest piece. ``labels``:
    those pieces when already numbered (:func:`cell_pieces`)."""
    m = check_mask(parent_mask, "parent_mask")
    p = check_shares(shares)
    lab = piece_labels(m, separate) if labels is None else labels
    n = int(lab.max())
    draws = rng.choice(p.size, size=n, p=p) if n else np.zeros(0, dtype=np.int64)
    return np.concatenate([[-1], draws]).astype(np.int64)[lab]


def instance_shares(labels: np.ndarray, n_clusters: int) -> np.ndarray:
    """Measured share of components per cluster in a label map from `sample_instances` (for checks)."""
    lab, n = ndimage.label(labels >= 0)
    if n == 0:
        return np.zeros(n_clusters)
    first = ndimage.labeled_comprehension(labels, lab, np.arange(1, n + 1), lambda v: v[0], np.int64, -1)
    return np.bincount(first, minlength=n_clusters)[:n_clusters] / float(n)


def cell_pieces(ctx: EvalContext, parent: np.ndarray, separate: float) -> np.ndarray:
    """``piece_labels`` of a parent mask node's output (HxWx1), computed once per evaluation: the ``instances``
    node and the ``piece_labels`` node over the same parent share it (the neck cut is the costly part at
    output sizes: about 10 s at 2048 x 1024)."""
    key = ("cell_pieces", id(parent), float(separate))
    if key not in ctx.cache:
        ctx.cache[key] = piece_labels(parent[..., 0] > 0.5, separate)
    return ctx.cache[key]


SEPARATE = Param("separate", "number", 0.0, 0.0, MAX_SEPARATE,
                 doc="neck cut, working-size px (follows the scale; 0 = connected components only)")


@register_node
class InstancesNode(NodeType):
    """One-hot cluster masks (HxWxK) of the pieces of input `parent`, drawn with `shares`. With input `cells` (a
    ``pptbf`` node with ``output: cells``) each PPTBF cell draws its kind (pointwise: a shader does the same);
    without, each connected component of `parent` does, after an optional neck cut `separate` (working-size px,
    follows the scale)."""

    name = "instances"
    inputs = ("parent", "cells")
    params = (Param("shares", "data", required=True, doc="share of pieces per kind"), SEPARATE)

    def check(self, params: dict) -> None:
        s = params.get("shares")
        if not isinstance(s, list) or not s:
            raise GraphError("instances.shares must be a non-empty list of numbers")
        try:
            check_shares(s)
        except InputError as exc:
            raise GraphError(f"instances.{exc}") from None

    def evaluate(self, params, inputs, ctx, node_id):
        if "parent" not in inputs:
            raise GraphError(f"instances node {node_id} needs input 'parent'")
        k = len(params["shares"])
        if "cells" in inputs:
            kinds = cell_kinds(inputs["cells"][..., 0], params["shares"], cell_stream(ctx, node_id))
            labels = np.where(inputs["parent"][..., 0] > 0.5, kinds, -1)
        else:
            sep = float(self.get(params, "separate")) * ctx.px_scale
            labels = sample_instances(inputs["parent"][..., 0] > 0.5, params["shares"], ctx.rng(node_id), sep,
                                      labels=cell_pieces(ctx, inputs["parent"], sep))
        out = np.zeros((ctx.height, ctx.width, k), dtype=np.float32)
        hh, ww = np.nonzero(labels >= 0)
        out[hh, ww, labels[hh, ww]] = 1.0
        return out

    def materialx(self, b, node, node_id, offset):
        """Per-cell kinds: one ``cell_kind`` node per kind (connected components are not pointwise: baked)."""
        if "cells" not in node["inputs"]:
            return None
        cells = b.value(node["inputs"]["cells"], offset)[0]
        parent = b.value(node["inputs"]["parent"], offset)[0]
        edges = [float(e) for e in np.cumsum(check_shares(node["params"]["shares"]))[:-1]]
        lo, hi = [-1.0] + edges, edges + [2.0]
        stream = ("integer", str(cell_stream(b.ctx, node_id)))
        return [b.op("cell_kind", node_id, cells=cells, parent=parent, stream=stream, seed=("interface", b.seed_in),
                     lo=a, hi=z) for a, z in zip(lo, hi)]
