"""The ``warp`` filter: a directional warp, each pixel read from a point displaced along one direction by an amount
that a second input drives (as the directional warp of node-based material editors).

``out(p) = input(p - amount * (by(p) - 0.5) * (cos angle, sin angle))``: sampled bilinearly and periodically, so
a warped map still tiles. ``amount`` is in working-size pixels and follows the pattern scale; ``by`` is any map
(its first channel), e.g. a leaf's noise: warping a PPTBF mask by it roughens straight cell edges, warping an
albedo by a stripe mask shears it. The torch form is differentiable in ``amount`` and in both inputs.
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import GraphError
from .base import NodeType, Param, as3, register_node

MAX_AMOUNT = 1e3


def _displacement(params: dict, px_scale: float) -> tuple[float, float]:
    """Pixels of displacement per unit of ``by - 0.5`` along x and y."""
    amount = float(params.get("amount", 0.0)) * px_scale
    angle = math.radians(float(params.get("angle", 0.0)))
    return amount * math.cos(angle), amount * math.sin(angle)


def _corners(h: int, w: int, dx, dy, floor, arange):
    """Periodic bilinear sampling plan: the four source indices and weights for a displaced grid."""
    ys = arange(h)[:, None] - dy
    xs = arange(w)[None, :] - dx
    y0, x0 = floor(ys), floor(xs)
    fy, fx = ys - y0, xs - x0
    return y0, x0, fy, fx


@register_node
class WarpNode(NodeType):
    """Directional warp of input ``input`` driven by input ``by``; params ``amount`` (working-size px at
    ``by = 1``, half of it each way), ``angle`` (degrees, 0 = along x)."""

    name = "warp"
    inputs = ("input", "by")
    params = (Param("amount", "number", 0.0, -MAX_AMOUNT, MAX_AMOUNT, optimise="value",
                    doc="working-size px of displacement per unit of 'by' (follows the scale)"),
              Param("angle", "number", 0.0, -360.0, 360.0, doc="direction, degrees from the x axis"))
    group = "warp"
    differentiable = True

    def evaluate(self, params, inputs, ctx, node_id):
        if "input" not in inputs or "by" not in inputs:
            raise GraphError(f"warp node {node_id} needs inputs 'input' and 'by'")
        x = as3(inputs["input"]).astype(np.float32)
        h, w = x.shape[:2]
        ux, uy = _displacement(params, ctx.px_scale)
        b = as3(inputs["by"])[..., 0].astype(np.float64) - 0.5
        y0, x0, fy, fx = _corners(h, w, ux * b, uy * b, np.floor, np.arange)
        y0, x0 = y0.astype(np.int64) % h, x0.astype(np.int64) % w
        y1, x1 = (y0 + 1) % h, (x0 + 1) % w
        fy, fx = fy[..., None].astype(np.float32), fx[..., None].astype(np.float32)
        top = x[y0, x0] * (1 - fx) + x[y0, x1] * fx
        bottom = x[y1, x0] * (1 - fx) + x[y1, x1] * fx
        return (top * (1 - fy) + bottom * fy).astype(np.float32)

    def forward(self, params, ins, t):
        torch = t.torch
        x = ins["input"]
        h, w = x.shape[:2]
        amount = t.value("amount", self.get(params, "amount")).reshape(()) * t.px
        angle = math.radians(float(self.get(params, "angle")))
        b = ins["by"][..., 0] - 0.5
        dx, dy = amount * math.cos(angle) * b, amount * math.sin(angle) * b
        y0, x0, fy, fx = _corners(h, w, dx, dy, torch.floor,
                                  lambda n: torch.arange(n, device=x.device, dtype=x.dtype))
        y0, x0 = y0.long() % h, x0.long() % w
        y1, x1 = (y0 + 1) % h, (x0 + 1) % w
        fy, fx = fy[..., None], fx[..., None]
        top = x[y0, x0] * (1 - fx) + x[y0, x1] * fx
        bottom = x[y1, x0] * (1 - fx) + x[y1, x1] * fx
        return top * (1 - fy) + bottom * fy
