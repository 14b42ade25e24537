"""The ``noise`` generator: the multi-layer random-phase noise model of a leaf (paper section 5.1) as a filter stack."""
from __future__ import annotations

from ..noise import NoiseLayers, NoiseModel, synthesize, synthesize_layers
from .base import Param, register_node
from .stack import FilterStack


@register_node
class NoiseNode(FilterStack):
    """Generator node: the noise model (params of :meth:`workers.noise.NoiseModel.to_params`) plus one recomposition
    filter per layer (see :mod:`workers.nodes.stack`); ``sigma`` is in working-size pixels (times
    ``ctx.px_scale``). Seed: ``params["seed"]`` or the node seed."""

    name = "noise"
    params = FilterStack.params + (Param("seed", "int", None, doc="realisation (default: from the material seed)"),)

    def parse(self, params: dict) -> NoiseModel:
        return NoiseModel.from_params(params)

    def channels(self, model: NoiseModel) -> int:
        return model.channels

    def layer_count(self, model: NoiseModel) -> int:
        return len(model.layers)

    def synthesize(self, model: NoiseModel, params: dict, ctx, node_id: str, with_layers: bool) -> NoiseLayers:
        seed = int(params["seed"]) if "seed" in params else ctx.node_seed(node_id)
        if with_layers:
            return synthesize_layers(model, ctx.width, ctx.height, scale=ctx.px_scale, seed=seed)
        matched = synthesize(model, ctx.width, ctx.height, scale=ctx.px_scale, seed=seed)
        return NoiseLayers(base=model.base, layers=[], matched=matched)

    def materialx(self, b, node, node_id, offset):
        """A random-phase synthesis is not pointwise: baked into a periodic tile at the exported size and seed."""
        return b.tile(node_id, offset, reason="noise")
