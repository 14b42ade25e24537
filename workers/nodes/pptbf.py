"""The ``pptbf`` generator: a binary PPTBF mask (paper section 5.2) at any size, pattern scale and realisation."""
from __future__ import annotations

import math

import numpy as np

from pptbf_db import pptbf as pp

from ..errors import GraphError
from .base import EvalContext, NodeType, Param, register_node
from .instances import CELL_SCALE

#: what a pptbf node outputs: its binary mask, or the cell each pixel is in (``CELL_SCALE`` keys in [0, 1))
OUTPUTS = ("mask", "cells")


def node_shift(params: dict, ctx: EvalContext, node_id: str) -> tuple[float, float]:
    """The realisation: params["shift"] when given, else derived from the material seed and the node id (that of
    params["stream"] when given: a node that shares another's realisation)."""
    s = params.get("shift")
    if s is not None:
        return float(s[0]), float(s[1])
    r = np.random.default_rng(ctx.node_seed(params.get("stream") or node_id))
    return tuple(float(x) for x in r.uniform(0.0, 8.0, size=2))


@register_node
class PPTBFNode(NodeType):
    """Binary PPTBF mask (HxWx1 in {0,1}); params: `params` (29 numbers, period in `ref_width` pixels),
    `complement`, `ref_width` (working width the params are defined at), optional `shift`; optional input
    `parent` multiplies the mask (sub-layer masks stay inside their parent). With `output: cells` the node gives
    instead the key of the cell each pixel is in (HxWx1 in [0, 1), one value per PPTBF cell), for per-cell
    draws (``instances``, ``piece_offsets``); `stream` names the node whose realisation it shares. With
    `field: border` the cut is made on the distance to the cell's border instead of the PPTBF value (cells with
    the cellular window): a network of one width along every side of the cells (``pptbf.border_distance``)."""

    name = "pptbf"
    inputs = ("parent",)
    params = (Param("params", "data", required=True, doc=f"{pp.N_PARAMS} numbers: {', '.join(pp.PARAM_NAMES)}"),
              Param("ref_width", "number", lo=1e-9, required=True, doc="the working width the params are defined at"),
              Param("complement", "bool", False, doc="swap the mask's two sides"),
              Param("shift", "data", None, doc="the realisation: null or [x, y]"),
              Param("output", "data", "mask", doc="mask | cells"),
              Param("stream", "data", None, doc="node id whose realisation this node shares (default: its own)"),
              Param("field", "data", "value", doc=f"what is cut: {' | '.join(pp.FIELDS)}"))

    def check(self, params: dict) -> None:
        p = params.get("params")
        if not isinstance(p, list) or len(p) != pp.N_PARAMS or not all(
                isinstance(x, (int, float)) and math.isfinite(x) for x in p):
            raise GraphError(f"pptbf.params must be a list of {pp.N_PARAMS} finite numbers "
                             f"({', '.join(pp.PARAM_NAMES)})")
        s = params.get("shift")
        if s is not None and (not isinstance(s, list) or len(s) != 2 or not all(
                isinstance(x, (int, float)) and math.isfinite(x) for x in s)):
            raise GraphError("pptbf.shift must be null or a list of 2 finite numbers")
        if self.get(params, "output") not in OUTPUTS:
            raise GraphError(f"pptbf.output must be one of {', '.join(OUTPUTS)}")
        st = params.get("stream")
        if st is not None and not (isinstance(st, str) and st):
            raise GraphError("pptbf.stream must be null or a node id")
        f = self.get(params, "field")
        if f not in pp.FIELDS:
            raise GraphError(f"pptbf.field must be one of {', '.join(pp.FIELDS)}")
        if f == "border" and not pp.uses_cellular(pp.decode(p)):
            raise GraphError("pptbf.field 'border' needs cells with the cellular window (window_blend > 0 and "
                             "feature_mixture other than 3 or 4)")

    def field(self, params, ctx: EvalContext, node_id: str, cells: bool = False):
        """The raw PPTBF values (HxW) of this node's realisation, before the cut (and the cell keys)."""
        rw = float(params["ref_width"])
        # scale 1 = the pattern size it had at the working size, whatever width the params are defined at
        pixel_scale = ctx.px_scale * float(ctx.working_size[0]) / rw
        return pp.evaluate(np.asarray(params["params"], dtype=np.float64), ctx.width, ctx.height,
                           shift=node_shift(params, ctx, node_id), pixel_scale=pixel_scale, ref_width=int(round(rw)),
                           cells=cells, field=self.get(params, "field"))

    def evaluate(self, params, inputs, ctx, node_id):
        if self.get(params, "output") == "cells":
            _, keys = self.field(params, ctx, node_id, cells=True)
            return (keys.astype(np.float64) / CELL_SCALE).astype(np.float32)[..., None]
        m = pp.binarize(self.field(params, ctx, node_id), float(params["params"][0]),
                        pp.field_gap(self.get(params, "field")))
        if self.get(params, "complement"):
            m = ~m
        out = m.astype(np.float32)[..., None]
        if "parent" in inputs:
            out = out * (inputs["parent"][..., :1] > 0.5)
        return out.astype(np.float32)

    def materialx(self, b, node, node_id, offset):
        """Our ``pptbf`` MaterialX node with the cut of the exported realisation (the quantile ``binarize`` takes
        over the whole image, of the value or, with ``field: border``, of the border distance), so that the
        shader's mask equals the numpy mask at the exported size and seed; or, for ``output: cells``, our
        ``pptbf_cells`` node. Read at one of the 8 neighbouring pixels (``RING``), it is
        an output of the node's single ``pptbf_ring`` (one PPTBF in the shader for all 8 reads)."""
        from ..mtlx.library import RING, RING_OUTPUTS

        p = node["params"]
        cells = self.get(p, "output") == "cells"
        vec = pp.clip_params(np.asarray(p["params"], np.float64))
        inputs = {s.name: (("integer", str(int(vec[i]))) if s.kind == "disc" else float(vec[i]))
                  for i, s in enumerate(pp.PARAM_SPECS)}
        if not cells:
            key = ("pptbf_cut", node_id)
            if key not in b.ctx.cache:
                b.ctx.cache[key] = pp.cut_level(self.field(p, b.ctx, node_id), float(p["params"][0]),
                                                pp.field_gap(self.get(p, "field")))
            inputs.update(cut=b.ctx.cache[key], complement=bool(self.get(p, "complement")),
                          border=self.get(p, "field") == "border")
        shift = node_shift(p, b.ctx, node_id)
        inputs.update(texcoord=("vector2", b.texcoord), size=("interface", b.size_in),
                      unit=float(b.mat.pattern_unit * b.mat.working_size[0]), scale=("interface", b.scale_in),
                      seed=("interface", b.seed_in), stream=("integer", str(b.seed_stream(p.get("stream") or node_id))),
                      shift=("vector2", f"{shift[0]!r}, {shift[1]!r}"),
                      ref_width=float(int(round(float(p["ref_width"])))))
        if offset in RING:
            # a neighbouring pixel (the Sobel normal reads all 8): one pptbf_ring node evaluates the 8 in a loop
            ring = b.once(("pptbf_ring", node_id), lambda: b.multi(
                "pptbf_ring", f"{node_id}_ring", offset=("vector2", "0.0, 0.0"), cells=cells, **inputs))
            k = RING.index(offset)
            out = b.pick(ring, RING_OUTPUTS[k // 4], k % 4, f"{node_id}_ring{k}")
        else:
            out = b.op("pptbf_cells" if cells else "pptbf", node_id,
                       offset=("vector2", f"{offset[0]}, {offset[1]}"), **inputs)
        if "parent" in node["inputs"] and not cells:
            parent = b.value(node["inputs"]["parent"], offset)[0]
            out = b.op("ifgreater", node_id, value1=parent, value2=0.5, in1=out, in2=0.0)
        return [out]
