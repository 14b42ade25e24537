"""Filter stacks: generators built of layers that the recomposition filters one by one (paper section 5.3).

A filter-stack generator synthesises a histogram-matched map ``matched`` from K layers ``L_k`` and a base value;
its node carries one filter per layer (gain ``a_k``, offset ``b_k``, blur ``sigma_k``) and a global gain ``c`` on
the base and offset ``d``::

    O = matched + sum_k (blur(a_k L_k + b_k; sigma_k) - L_k) + (c - 1) base + d

Identity filters (a=1, b=0, sigma=0, c=1, d=0) give exactly the synthesis. The torch form holds the layers'
spectra, so the recomposition moves every a_k, sigma_k, c and d with gradients.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import GraphError
from .base import NodeType, Param, Slot, gaussian_blur

IDENTITY_FILTER = {"a": 1.0, "b": 0.0, "sigma": 0.0}
#: how the recomposition optimises each filter value
FILTER_KINDS = {"a": "value", "b": "offset", "sigma": "sigma"}


@dataclass
class Layers:
    """A synthesis split into its parts: ``matched`` (HxWxC, the generator's output with identity filters),
    ``base`` (C,) and the K layers (HxWxC each; empty when only ``matched`` was asked for)."""

    matched: np.ndarray
    base: np.ndarray
    layers: list


def filter_values(f: dict, key: str, default: float, c: int, where: str) -> np.ndarray:
    """A scalar or per-channel filter value as a (C,) float32 array (GraphError if malformed)."""
    v = np.atleast_1d(np.asarray(f.get(key, default), dtype=np.float64))
    if v.ndim != 1 or v.size not in (1, c) or not np.all(np.isfinite(v)):
        raise GraphError(f"{where}.{key} must be a finite number or a list of {c} numbers")
    return np.broadcast_to(v, (c,)).astype(np.float32)


def _vec(v, c: int) -> np.ndarray:
    """Scalar or per-channel value as (C,) float64."""
    return np.broadcast_to(np.atleast_1d(np.asarray(v, dtype=np.float64)), (c,)).copy()


class FilterStack(NodeType):
    """Base of filter-stack generators: subclasses give :meth:`parse`, :meth:`synthesize`, :meth:`channels` and
    :meth:`layer_count`."""

    params = (Param("filters", "data", [], doc="one {a, b, sigma} per layer"),
              Param("c", "numbers", 1.0, optimise="offset", doc="gain of the base value"),
              Param("d", "numbers", 0.0, optimise="offset", doc="offset"))
    group = "filters"
    differentiable = True

    def parse(self, params: dict):
        """The generator's model from its params (read once per evaluation; GraphError when malformed)."""
        raise NotImplementedError

    def synthesize(self, model, params: dict, ctx, node_id: str, with_layers: bool) -> Layers:
        """The synthesis with identity filters (layers only when ``with_layers``)."""
        raise NotImplementedError

    def layer_count(self, model) -> int:
        """K, the number of layers (the node may list fewer filters: the rest are identity)."""
        raise NotImplementedError

    def channels(self, model) -> int:
        """C, the channel count of the output."""
        raise NotImplementedError

    def check(self, params: dict) -> None:
        model = self.parse(params)
        c, k = self.channels(model), self.layer_count(model)
        filters = params.get("filters", [])
        if not isinstance(filters, list) or len(filters) > k:
            raise GraphError(f"{self.name}.filters must be a list of at most {k} objects (one per layer)")
        for i, f in enumerate(filters):
            if not isinstance(f, dict):
                raise GraphError(f"{self.name}.filters[{i}] must be an object with a, b, sigma")
            for key, dflt in IDENTITY_FILTER.items():
                v = filter_values(f, key, dflt, c, f"{self.name}.filters[{i}]")
                if key == "sigma" and np.any(v < 0):
                    raise GraphError(f"{self.name}.filters[{i}].sigma must be >= 0")
        for key, dflt in (("c", 1.0), ("d", 0.0)):
            filter_values(params, key, dflt, c, self.name)

    def evaluate(self, params, inputs, ctx, node_id):
        filt = []
        model = self.parse(params)
        c = self.channels(model)
        for f in params.get("filters", []):
            a = filter_values(f, "a", 1.0, c, "filters")
            b = filter_values(f, "b", 0.0, c, "filters")
            sig = filter_values(f, "sigma", 0.0, c, "filters") * np.float32(ctx.px_scale)
            filt.append(None if (np.all(a == 1) and np.all(b == 0) and np.all(sig <= 1e-3)) else (a, b, sig))
        res = self.synthesize(model, params, ctx, node_id, with_layers=any(v is not None for v in filt))
        out = res.matched
        for i, v in enumerate(filt):
            if v is None:
                continue
            a, b, sig = v
            lay = res.layers[i]
            x = a * lay + b
            if np.all(sig == sig[0]):
                y = gaussian_blur(x, float(sig[0]))
            else:
                y = np.stack([gaussian_blur(x[..., k], float(sig[k])) for k in range(c)], axis=-1)
            out = out + (y - lay)
        cg = filter_values(params, "c", 1.0, c, self.name)
        d = filter_values(params, "d", 0.0, c, self.name)
        out = out + (cg - 1.0) * res.base + d
        return out.astype(np.float32)

    # -------------------------------------------------------------- torch form
    def _keys(self, params: dict, k: int) -> list[tuple[str, object, str]]:
        """(path, stored value, optimise kind) of every filter value of K layers, missing filters as identity."""
        stored = list(params.get("filters", []))
        filters = stored + [{} for _ in range(k - len(stored))]
        keys = []
        for i, f in enumerate(filters):
            keys += [(f"filters.{i}.{k}", f.get(k, dflt), FILTER_KINDS[k]) for k, dflt in IDENTITY_FILTER.items()]
        return keys + [("c", params.get("c", 1.0), "offset"), ("d", params.get("d", 0.0), "offset")]

    def prepare(self, node, t):
        """The layers' spectra and the rest ``matched - sum L_k``; None (a constant) when the recomposition does
        not optimise filters, or when the split does not reproduce the node (then it is not of this form)."""
        if not t.optimises(self.group):
            return None
        p = node["params"]
        model = self.parse(p)
        res = self.synthesize(model, p, t.ctx, t.node_id, with_layers=True)
        c = res.matched.shape[2]
        lt = [t.tensor(a) for a in res.layers]
        rest = t.tensor(res.matched)
        for lay in lt:
            rest = rest - lay
        stored = {path: t.tensor(_vec(v, c)) if kind != "sigma" else t.tensor([float(np.max(np.atleast_1d(v)))])
                  for path, v, kind in self._keys(p, self.layer_count(model))}
        state = {"rest": rest, "base": t.tensor(np.asarray(res.base, dtype=np.float32)),
                 "spectra": [t.rfft(lay) for lay in lt], "c": c, "k": self.layer_count(model), "stored": stored}
        mine = t.detached(self.forward(p, {}, t.with_state(state)))
        ref = t.numpy_value()
        err = float(np.max(np.abs(mine - ref)))
        if err > t.check_tol * max(1.0, float(np.max(np.abs(ref)))):
            t.warn(f"filter split does not reproduce the node (max err {err:.3g}); kept fixed")
            return None
        return state

    def slots(self, node, t):
        c = t.state["c"]
        return [Slot(path, v, kind, c) for path, v, kind in self._keys(node["params"], t.state["k"])
                if t.collinear_offsets or not (path.endswith(".b") or path == "c")]

    def forward(self, params, ins, t):
        """O = (matched - sum L_k) + irfft(sum_k a_k T(sigma_k) FFT(L_k)) + sum_k b_k + (c - 1) base + d."""
        s = t.state

        def val(path: str):
            leaf = t.leaf(path)
            return s["stored"][path] if leaf is None else leaf

        acc = None
        offset = val("d") + (val("c") - 1.0) * s["base"]
        for i, fl in enumerate(s["spectra"]):
            a, b = val(f"filters.{i}.a"), val(f"filters.{i}.b")
            tf = t.gauss_transfer(t.clamp_sigma(val(f"filters.{i}.sigma")) * t.px)
            term = fl * a if tf is None else fl * (tf * a)
            acc = term if acc is None else acc + term
            offset = offset + b
        out = s["rest"] + offset
        return out if acc is None else out + t.irfft(acc)
