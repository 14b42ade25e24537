"""Pointwise and blur filters of the material graph: constant, level, blur, blend, channel, add, clamp.

These are the operations of the paper's material graph (section 5.3) that join generators and masks into maps;
level, blur and blend carry the parameters the recomposition optimises (gains, offsets, blur widths).
"""
from __future__ import annotations

import numpy as np

from ..errors import GraphError
from .base import NodeType, Param, Slot, as3, gaussian_blur, numbers, register_node

#: the largest blur sigma (working-size pixels) a file may hold
MAX_SIGMA = 1e4
#: floor of the mask sum a normalised blend divides by
NORMALISE_EPS = 1e-6


@register_node
class ConstantNode(NodeType):
    """A constant value (scalar or per channel) over the whole map."""

    name = "constant"
    params = (Param("value", "numbers", required=True, doc="a number or one per channel"),)

    def evaluate(self, params, inputs, ctx, node_id):
        v = np.atleast_1d(np.asarray(params["value"], dtype=np.float32))
        return np.broadcast_to(v, (ctx.height, ctx.width, v.size)).copy()

    def materialx(self, b, node, node_id, offset):
        return [b.const(float(x), node_id) for x in np.atleast_1d(np.asarray(node["params"]["value"], np.float32))]


@register_node
class LevelNode(NodeType):
    """Affine level filter ``x * a + d`` (per channel or scalar a, d), optional clamp to [0,1]."""

    name = "level"
    inputs = ("input",)
    params = (Param("a", "numbers", 1.0, optimise="value", doc="gain"),
              Param("d", "numbers", 0.0, optimise="offset", doc="offset"),
              Param("clamp", "bool", False, doc="clamp the result to [0, 1]"))
    group = "level"
    differentiable = True

    def evaluate(self, params, inputs, ctx, node_id):
        x = inputs["input"]
        a = np.asarray(self.get(params, "a"), dtype=np.float32)
        d = np.asarray(self.get(params, "d"), dtype=np.float32)
        y = x * a + d
        if self.get(params, "clamp"):
            y = np.clip(y, 0.0, 1.0)
        return y.astype(np.float32)

    def forward(self, params, ins, t):
        out = ins["input"] * t.value("a", self.get(params, "a")) + t.value("d", self.get(params, "d"))
        return out.clamp(0.0, 1.0) if self.get(params, "clamp") else out

    def materialx(self, b, node, node_id, offset):
        p = node["params"]
        x = b.value(node["inputs"]["input"], offset)
        a = [float(v) for v in numbers(self.get(p, "a"), f"{node_id}.a").astype(np.float32)]
        d = [float(v) for v in numbers(self.get(p, "d"), f"{node_id}.d").astype(np.float32)]
        x, a, d = (list(v) for v in _broadcast_lists(x, a, d))
        out = [b.op("add", node_id, b.op("multiply", node_id, xi, ai), di) for xi, ai, di in zip(x, a, d)]
        if self.get(p, "clamp"):
            out = [b.op("clamp", node_id, o) for o in out]
        return out


@register_node
class BlurNode(NodeType):
    """Gaussian blur; sigma is in working-size pixels and follows the pattern scale."""

    name = "blur"
    inputs = ("input",)
    params = (Param("sigma", "number", 0.0, 0.0, MAX_SIGMA, optimise="sigma", doc="working-size px"),)
    group = "blur"
    differentiable = True

    def evaluate(self, params, inputs, ctx, node_id):
        return gaussian_blur(inputs["input"], float(self.get(params, "sigma")) * ctx.px_scale)

    def forward(self, params, ins, t):
        return t.blur(ins["input"], t.sigma("sigma", self.get(params, "sigma")) * t.px)


def _mix(masks: list, children: list, normalise: bool, floor):
    """``sum_i m_i c_i``, divided by ``floor(sum_i m_i)`` when normalised (numpy arrays or torch tensors alike);
    None without masks."""
    out = total = None
    for m, c in zip(masks, children):
        term = m * c
        out = term if out is None else out + term
        total = m if total is None else total + m
    if out is None or not normalise:
        return out
    return out / floor(total)


@register_node
class BlendNode(NodeType):
    """Mask blend. Inputs ``mask0, child0, mask1, child1, ...`` give ``sum_i blur(mask_i; sigma_i) * child_i``
    (params ``sigmas``: per-mask blur in working-size pixels, default 0); with ``normalise: true`` that sum is
    divided by ``sum_i blur(mask_i; sigma_i)``, so the blurred masks of a partition keep summing to 1 whatever
    their sigmas (every pixel is one child's value, or a convex mix across a blurred edge). Inputs
    ``mask, fg, bg`` give ``m*fg + (1-m)*bg`` with ``m = blur(mask; sigma)``."""

    name = "blend"
    inputs = ("*",)
    params = (Param("sigma", "number", 0.0, 0.0, MAX_SIGMA, optimise="sigma", doc="mask blur (mask/fg/bg form)"),
              Param("sigmas", "list", [], 0.0, MAX_SIGMA, optimise="sigma", doc="blur of mask0, mask1, ..."),
              Param("normalise", "bool", False, doc="divide by the sum of the blurred masks"))
    group = "blend"
    differentiable = True

    def evaluate(self, params, inputs, ctx, node_id):
        sig = list(self.get(params, "sigmas"))
        if "mask" in inputs:
            m = gaussian_blur(as3(inputs["mask"])[..., :1], float(self.get(params, "sigma")) * ctx.px_scale)
            return (m * inputs["fg"] + (1.0 - m) * inputs["bg"]).astype(np.float32)
        masks, children = [], []
        while f"mask{len(masks)}" in inputs:
            i = len(masks)
            masks.append(gaussian_blur(as3(inputs[f"mask{i}"])[..., :1], (float(sig[i]) if i < len(sig) else 0.0)
                                       * ctx.px_scale))
            children.append(inputs[f"child{i}"])
        out = _mix(masks, children, self.get(params, "normalise"), lambda t: np.maximum(t, NORMALISE_EPS))
        if out is None:
            raise GraphError(f"blend node {node_id} has no inputs (need mask/fg/bg or mask0/child0...)")
        return out.astype(np.float32)

    def slots(self, node, t):
        p = node["params"]
        if "mask" in node["inputs"]:
            return [Slot("sigma", self.get(p, "sigma"), "sigma")]
        n = sum(1 for k in node["inputs"] if k.startswith("mask"))
        sig = list(self.get(p, "sigmas")) + [0.0] * (n - len(self.get(p, "sigmas")))
        return [Slot(f"sigmas.{i}", sig[i], "sigma") for i in range(n)]

    def forward(self, params, ins, t):
        if "mask" in ins:
            m = t.blur_mask("mask", t.sigma("sigma", self.get(params, "sigma")) * t.px)
            return m * ins["fg"] + (1.0 - m) * ins["bg"]
        stored = list(self.get(params, "sigmas"))
        masks, children = [], []
        while f"mask{len(masks)}" in ins:
            i = len(masks)
            masks.append(t.blur_mask(f"mask{i}", t.sigma(f"sigmas.{i}", float(stored[i]) if i < len(stored) else 0.0)
                                     * t.px))
            children.append(ins[f"child{i}"])
        out = _mix(masks, children, self.get(params, "normalise"), lambda x: x.clamp_min(NORMALISE_EPS))
        if out is None:
            raise GraphError(f"blend node {t.node_id} has no inputs")
        return out

    def materialx(self, b, node, node_id, offset):
        p, ins = node["params"], b.inputs(node, offset)
        px = b.ctx.px_scale
        if "mask" in ins:
            if not blur_is_identity(float(self.get(p, "sigma")) * px):
                return None                  # a blurred mask is not pointwise: baked
            m = ins["mask"][0]
            fg, bg = _broadcast_lists(ins["fg"], ins["bg"])
            return [b.op("mix", node_id, fg=f, bg=g, mix=m) for f, g in zip(fg, bg)]
        n = sum(1 for k in ins if k.startswith("mask"))
        if not all(blur_is_identity(float(s) * px) for s in self.get(p, "sigmas")[:n]):
            return None
        masks = [ins[f"mask{i}"][0] for i in range(n)]
        children = list(_broadcast_lists(*(ins[f"child{i}"] for i in range(n))))

        def add(x, y):
            return b.op("add", node_id, x, y)

        out = [None] * len(children[0])
        total = None
        for m, child in zip(masks, children):
            out = [b.op("multiply", node_id, c, m) if o is None else add(o, b.op("multiply", node_id, c, m))
                   for o, c in zip(out, child)]
            total = m if total is None else add(total, m)
        if self.get(p, "normalise"):
            den = b.op("max", node_id, total, NORMALISE_EPS)
            out = [b.op("divide", node_id, o, den) for o in out]
        return out


#: the most a blur may change a mask value and still be left out of a pointwise export (half the check's 2/255)
BLUR_NEGLIGIBLE = 1.0 / 255.0


def blur_is_identity(sigma: float) -> bool:
    """Whether :func:`gaussian_blur` at ``sigma`` (output pixels) changes no value of a binary mask by more than
    BLUR_NEGLIGIBLE: its kernel (scipy's, radius int(4 sigma + 0.5)) keeps at least 1 - BLUR_NEGLIGIBLE at the
    centre (a pixel unlike all its neighbours moves by 1 - the centre weight; sigma < 0.125 is scipy's identity,
    the bound holds to sigma ~ 0.27)."""
    if sigma <= 1e-3:
        return True
    r = int(4.0 * sigma + 0.5)
    w = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    centre = (w[r] / w.sum()) ** 2
    return bool(1.0 - centre <= BLUR_NEGLIGIBLE)


@register_node
class ChannelNode(NodeType):
    """Pick channels ``channels`` (list of indices) of the input (e.g. one cluster of an instance map)."""

    name = "channel"
    inputs = ("input",)
    params = (Param("channels", "data", required=True, doc="list of channel indices"),)
    differentiable = True

    def check(self, params: dict) -> None:
        ch = params.get("channels")
        if not isinstance(ch, list) or not ch or not all(isinstance(c, int) and c >= 0 for c in ch):
            raise GraphError("channel.channels must be a non-empty list of channel indices")

    def evaluate(self, params, inputs, ctx, node_id):
        x = inputs["input"]
        if max(params["channels"]) >= x.shape[2]:
            raise GraphError(f"channel node {node_id}: input has {x.shape[2]} channels")
        return x[..., params["channels"]].astype(np.float32)

    def forward(self, params, ins, t):
        return ins["input"][..., list(params["channels"])]

    def materialx(self, b, node, node_id, offset):
        x = b.value(node["inputs"]["input"], offset)
        if max(node["params"]["channels"]) >= len(x):
            raise GraphError(f"channel node {node_id}: input has {len(x)} channels")
        return [x[c] for c in node["params"]["channels"]]


@register_node
class AddNode(NodeType):
    """Sum of all inputs (e.g. noise layers plus base colour)."""

    name = "add"
    inputs = ("*",)
    differentiable = True

    def evaluate(self, params, inputs, ctx, node_id):
        if not inputs:
            raise GraphError(f"add node {node_id} has no inputs")
        vals = [inputs[k] for k in sorted(inputs)]
        out = vals[0].astype(np.float32).copy()
        for v in vals[1:]:
            out = out + v
        return out

    def forward(self, params, ins, t):
        keys = sorted(ins)
        out = ins[keys[0]]
        for k in keys[1:]:
            out = out + ins[k]
        return out

    def materialx(self, b, node, node_id, offset):
        ins = b.inputs(node, offset)
        if not ins:
            raise GraphError(f"add node {node_id} has no inputs")
        vals = list(_broadcast_lists(*(ins[k] for k in sorted(ins))))
        out = vals[0]
        for v in vals[1:]:
            out = [b.op("add", node_id, o, x) for o, x in zip(out, v)]
        return out


@register_node
class ClampNode(NodeType):
    """Clamp to [lo, hi] (default [0, 1])."""

    name = "clamp"
    inputs = ("input",)
    params = (Param("lo", "number", 0.0), Param("hi", "number", 1.0))
    differentiable = True

    def evaluate(self, params, inputs, ctx, node_id):
        return np.clip(inputs["input"], self.get(params, "lo"), self.get(params, "hi")).astype(np.float32)

    def forward(self, params, ins, t):
        return ins["input"].clamp(float(self.get(params, "lo")), float(self.get(params, "hi")))

    def materialx(self, b, node, node_id, offset):
        lo, hi = float(self.get(node["params"], "lo")), float(self.get(node["params"], "hi"))
        return [b.op("clamp", node_id, **{"in": x, "low": lo, "high": hi})
                for x in b.value(node["inputs"]["input"], offset)]


def _broadcast_lists(*values: list) -> list[list]:
    """Per-channel lists broadcast like numpy's HxWx1 against HxWxC (a single entry repeats)."""
    n = max(len(v) for v in values)
    if any(len(v) not in (1, n) for v in values):
        raise GraphError(f"cannot broadcast channel counts {[len(v) for v in values]}")
    return [list(v) * n if len(v) == 1 else list(v) for v in values]
