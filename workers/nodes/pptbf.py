"""The ``pptbf`` generator: a binary PPTBF mask (paper section 5.2) at any size, pattern scale and realisation."""
from __future__ import annotations

import math

import numpy as np

from pptbf_db import pptbf as pp

from ..errors import GraphError
from .base import EvalContext, NodeType, Param, register_node


def node_shift(params: dict, ctx: EvalContext, node_id: str) -> tuple[float, float]:
    """The realisation: params["shift"] when given, else derived from the material seed and node id."""
    s = params.get("shift")
    if s is not None:
        return float(s[0]), float(s[1])
    r = np.random.default_rng(ctx.node_seed(node_id))
    return tuple(float(x) for x in r.uniform(0.0, 8.0, size=2))


@register_node
class PPTBFNode(NodeType):
    """Binary PPTBF mask (HxWx1 in {0,1}); params: `params` (29 numbers, period in `ref_width` pixels),
    `complement`, `ref_width` (working width the params are defined at), optional `shift`; optional input
    `parent` multiplies the mask (sub-layer masks stay inside their parent)."""

    name = "pptbf"
    inputs = ("parent",)
    params = (Param("params", "data", required=True, doc=f"{pp.N_PARAMS} numbers: {', '.join(pp.PARAM_NAMES)}"),
              Param("ref_width", "number", lo=1e-9, required=True, doc="the working width the params are defined at"),
              Param("complement", "bool", False, doc="swap the mask's two sides"),
              Param("shift", "data", None, doc="the realisation: null or [x, y]"))

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

    def evaluate(self, params, inputs, ctx, node_id):
        rw = float(params["ref_width"])
        # scale 1 = the pattern size it had at the working size, whatever width the params are defined at
        pixel_scale = ctx.px_scale * float(ctx.working_size[0]) / rw
        v = pp.evaluate(np.asarray(params["params"], dtype=np.float64), ctx.width, ctx.height,
                        shift=node_shift(params, ctx, node_id), pixel_scale=pixel_scale, ref_width=int(round(rw)))
        m = pp.binarize(v, float(params["params"][0]))
        if self.get(params, "complement"):
            m = ~m
        out = m.astype(np.float32)[..., None]
        if "parent" in inputs:
            out = out * (inputs["parent"][..., :1] > 0.5)
        return out.astype(np.float32)
