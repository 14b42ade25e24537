"""Per-piece variation nodes: ``piece_labels`` numbers the pieces of a procedural cell mask, ``piece_offsets``
draws one offset per piece (the between-piece spread of an instance kind), ``piece_ramps`` tilts every piece
about its centroid (overlapping slates), see :mod:`workers.pieces`."""
from __future__ import annotations

import numpy as np

from ..errors import GraphError
from .base import EvalContext, NodeType, Param, register_node
from .instances import SEPARATE, cell_normal, cell_pieces, cell_stream


def psd_root(cov: np.ndarray) -> np.ndarray:
    """F with F @ F.T the nearest positive semi-definite matrix to ``cov`` (negative eigenvalues set to zero)."""
    w, v = np.linalg.eigh((cov + cov.T) / 2)
    return v * np.sqrt(np.clip(w, 0.0, None))


@register_node
class PieceLabelsNode(NodeType):
    """Piece numbers (HxWx1 float, 0 outside, 1..n) of input ``parent`` (a cell mask), cut at its necks with
    ``separate`` working-size px (follows the scale), as the ``instances`` node over the same parent."""

    name = "piece_labels"
    inputs = ("parent",)
    params = (SEPARATE,)

    def evaluate(self, params, inputs, ctx: EvalContext, node_id):
        if "parent" not in inputs:
            raise GraphError(f"piece_labels node {node_id} needs input 'parent'")
        sep = float(self.get(params, "separate")) * ctx.px_scale
        return cell_pieces(ctx, inputs["parent"], sep).astype(np.float32)[..., None]


@register_node
class PieceOffsetsNode(NodeType):
    """One offset per piece drawn from N(0, ``cov``) with the node's seed, HxWxC (C = the size of cov): per piece
    of input ``labels`` (a ``piece_labels`` node; zero outside the pieces), or per cell of input ``cells`` (a
    ``pptbf`` node with ``output: cells``; pointwise, as a shader draws it)."""

    name = "piece_offsets"
    inputs = ("labels", "cells")
    params = (Param("cov", "data", required=True, doc="C x C covariance of the pieces' offsets"),)

    def check(self, params: dict) -> None:
        cov = params.get("cov")
        try:
            a = np.asarray(cov, np.float64)
        except (TypeError, ValueError):
            a = None
        if a is None or a.ndim != 2 or a.shape[0] != a.shape[1] or not 1 <= a.shape[0] <= 4 or \
                not np.all(np.isfinite(a)) or np.any(np.diag(a) < 0):
            raise GraphError("piece_offsets.cov must be a square list of lists (1x1 to 4x4) of finite numbers with "
                             "a non-negative diagonal")

    def evaluate(self, params, inputs, ctx: EvalContext, node_id):
        f = psd_root(np.asarray(params["cov"], np.float64))
        if "cells" in inputs:
            stream = cell_stream(ctx, node_id)
            z = np.stack([cell_normal(inputs["cells"][..., 0], stream, k) for k in range(f.shape[0])], axis=-1)
            return (z @ f.T).astype(np.float32)
        if "labels" not in inputs:
            raise GraphError(f"piece_offsets node {node_id} needs input 'labels' or 'cells'")
        lab = np.rint(inputs["labels"][..., 0]).astype(np.int64)
        n = int(lab.max()) if lab.size else 0
        table = ctx.rng(node_id).standard_normal((n + 1, f.shape[0])) @ f.T
        table[0] = 0.0
        return table[lab].astype(np.float32)

    def materialx(self, b, node, node_id, offset):
        """Per-cell offsets: ``cell_normal`` draws mixed by the covariance's root (per-label offsets: baked)."""
        if "cells" not in node["inputs"]:
            return None
        cells = b.value(node["inputs"]["cells"], offset)[0]
        f = psd_root(np.asarray(node["params"]["cov"], np.float64))
        stream = ("integer", str(cell_stream(b.ctx, node_id)))
        z = [b.op("cell_normal", node_id, cells=cells, stream=stream, seed=("interface", b.seed_in),
                  k=("integer", str(k))) for k in range(f.shape[0])]
        out = []
        for row in f:
            acc = b.op("multiply", node_id, z[0], float(row[0]))
            for zk, w in zip(z[1:], row[1:]):
                acc = b.op("add", node_id, acc, b.op("multiply", node_id, zk, float(w)))
            out.append(acc)
        return out


def same_key_regions(keys: np.ndarray) -> np.ndarray:
    """HxW int: the 4-connected regions of equal value of ``keys`` (HxW), numbered from 0. A ``pptbf`` node's
    cell keys are hashes, equal for some distant cells (at 2048x1024 px about one cell in twenty shares its key
    with another), so a cell is a connected region of one key, not a key."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    h, w = keys.shape
    idx = np.arange(h * w, dtype=np.int32 if h * w < 2**31 else np.int64).reshape(h, w)
    right, down = keys[:, 1:] == keys[:, :-1], keys[1:] == keys[:-1]
    a = np.concatenate([idx[:, :-1][right], idx[:-1][down]])
    b = np.concatenate([idx[:, 1:][right], idx[1:][down]])
    graph = coo_matrix((np.ones(a.size, np.int8), (a, b)), shape=(h * w, h * w))
    return connected_components(graph, directed=False)[1].reshape(h, w)


def _piece_ids(inputs: dict, ctx: EvalContext, node_id: str) -> tuple[np.ndarray, bool]:
    """(HxW int piece ids, whether id 0 is "no piece"): the labels of a ``piece_labels`` node, or the cells of a
    ``pptbf`` node (:func:`same_key_regions`, once per evaluation: every kind's ramps read the same cells)."""
    if "cells" in inputs:
        key = ("same_key_regions", id(inputs["cells"]))
        if key not in ctx.cache:
            ctx.cache[key] = same_key_regions(inputs["cells"][..., 0])
        return ctx.cache[key], False
    if "labels" not in inputs:
        raise GraphError(f"piece_ramps node {node_id} needs input 'labels' or 'cells'")
    return np.rint(inputs["labels"][..., 0]).astype(np.int64), True


@register_node
class PieceRampsNode(NodeType):
    """Every piece tilted about its centroid, HxWxC: ``ramp`` (C x 2) is each channel's slope along x and y per
    working-size px (follows the scale), per piece of input ``labels`` (zero outside the pieces) or per cell of
    input ``cells``; the distance from the centroid is clipped to ``reach`` (x, y working-size px; the input's
    pieces' extent), so a piece larger than any the input had (cells joined by the cut) does not ramp past the
    input's heights. A piece cut by the image's edge is tilted about the centroid of what the image shows of it."""

    name = "piece_ramps"
    inputs = ("labels", "cells")
    params = (Param("ramp", "data", required=True, doc="C x 2 slopes (x, y) per working-size px"),
              Param("reach", "data", doc="[x, y]: largest distance from a piece's centroid ramped (working px)"))

    def check(self, params: dict) -> None:
        a, r = (_floats(params.get(k)) for k in ("ramp", "reach"))
        if a is None or a.ndim != 2 or a.shape[1] != 2 or not 1 <= a.shape[0] <= 4 or not np.all(np.isfinite(a)):
            raise GraphError("piece_ramps.ramp must be a list of 1 to 4 [x, y] pairs of finite numbers")
        if "reach" in params and (r is None or r.shape != (2,) or not np.all(np.isfinite(r)) or np.any(r <= 0)):
            raise GraphError("piece_ramps.reach must be [x, y], two positive numbers")

    def evaluate(self, params, inputs, ctx: EvalContext, node_id):
        ramp = np.asarray(params["ramp"], np.float64)
        lab, zero_is_gap = _piece_ids(inputs, ctx, node_id)
        inside = lab > 0 if zero_is_gap else np.ones(lab.shape, bool)
        xy = np.zeros(lab.shape + (2,))
        xy[inside] = piece_coordinates(lab, inside, periodic=False) / ctx.px_scale       # working px
        if "reach" in params:
            r = np.asarray(params["reach"], np.float64)
            xy = np.clip(xy, -r, r)
        return (xy @ ramp.T).astype(np.float32)


def piece_coordinates(labels: np.ndarray, mask: np.ndarray, periodic: bool = True) -> np.ndarray:
    """(N, 2) x and y of the ``mask`` pixels (row-major, as ``image[mask]``) about their piece's centroid.
    ``periodic``: the image is a tile and a piece that wraps around its edge (the decomposition's labels join
    across it) is measured as one (circular means); else plain means, as for a render of any size."""
    ys, xs = np.nonzero(mask)
    lab = np.asarray(labels)[mask].astype(np.int64)
    n = np.maximum(np.bincount(lab), 1)
    out = np.empty((lab.size, 2))
    for k, (pos, period) in enumerate(((xs, mask.shape[1]), (ys, mask.shape[0]))):
        if not periodic:
            out[:, k] = pos - (np.bincount(lab, pos) / n)[lab]
            continue
        a = 2.0 * np.pi * pos / period
        centre = np.arctan2(np.bincount(lab, np.sin(a)), np.bincount(lab, np.cos(a))) * period / (2.0 * np.pi)
        out[:, k] = (pos - centre[lab] + period / 2.0) % period - period / 2.0
    return out


def _floats(v) -> np.ndarray | None:
    try:
        return np.asarray(v, np.float64)
    except (TypeError, ValueError):
        return None
