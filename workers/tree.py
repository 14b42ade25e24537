"""The decomposition tree: nested binary masks, each child inside its parent.

A tree stores itself as a JSON-able document plus named arrays (:meth:`MaskNode.to_arrays`, read back by
:meth:`MaskNode.from_arrays`): masks, soft mattes and large meta arrays (instance labels) go to the arrays, the
rest to the document; the caller decides where both are written.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Iterator

import numpy as np


@dataclass
class MaskNode:
    """One node of the decomposition tree.

    ``mask`` is an HxW bool array (already multiplied by the parent's mask); the root's mask is all True.
    ``method`` says how this node's *children* were made: "leaf" (none), "matting" or "instances".
    ``shares`` (instance splits only) is each child's share of the parent's instances, summing to 1.
    ``alpha`` optionally keeps the soft matte (HxW float32) this node's mask was cut from.
    """

    id: str
    mask: np.ndarray
    method: str = "leaf"
    children: list["MaskNode"] = field(default_factory=list)
    shares: list[float] | None = None
    alpha: np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    @property
    def is_leaf(self) -> bool:
        """True when this node has no children (a sub-material)."""
        return not self.children

    def walk(self) -> Iterator["MaskNode"]:
        """Pre-order traversal (self first)."""
        yield self
        for c in self.children:
            yield from c.walk()

    def leaves(self) -> list["MaskNode"]:
        """All leaves, in pre-order."""
        return [n for n in self.walk() if n.is_leaf]

    def describe(self) -> dict:
        """A JSON-able summary (ids, methods, pixel shares) without pixel data."""
        return {
            "id": self.id,
            "method": self.method,
            "coverage": float(np.mean(self.mask)),
            "shares": self.shares,
            "children": [c.describe() for c in self.children],
        }


    def to_arrays(self) -> tuple[dict, dict[str, np.ndarray]]:
        """(document, arrays): the tree's ids, methods, shares and meta as JSON-able data (with a ``summary``),
        its masks (uint8), mattes (float32) and meta arrays of more than 64 values as named arrays."""
        arrays: dict[str, np.ndarray] = {}

        def doc(n: MaskNode) -> dict:
            key = array_key(n.id)
            arrays[f"mask_{key}"] = np.asarray(n.mask, dtype=np.uint8)
            if n.alpha is not None:
                arrays[f"alpha_{key}"] = np.asarray(n.alpha, dtype=np.float32)
            meta = {}
            for k, v in n.meta.items():
                if isinstance(v, np.ndarray) and v.size > 64:
                    arrays[f"meta_{key}__{array_key(k)}"] = v
                    meta[k] = {"npz": f"meta_{key}__{array_key(k)}"}
                else:
                    meta[k] = _plain(v)
            return {"id": n.id, "method": n.method, "shares": _plain(n.shares), "meta": meta,
                    "children": [doc(c) for c in n.children]}

        return {"tree": doc(self), "summary": self.describe()}, arrays

    @classmethod
    def from_arrays(cls, document: dict, arrays: dict[str, np.ndarray]) -> "MaskNode":
        """The tree :meth:`to_arrays` stored."""

        def build(d: dict) -> MaskNode:
            key = array_key(d["id"])
            meta = {k: arrays[v["npz"]] if isinstance(v, dict) and set(v) == {"npz"} else v
                    for k, v in d.get("meta", {}).items()}
            return cls(id=d["id"], mask=arrays[f"mask_{key}"].astype(bool), method=d.get("method", "leaf"),
                       children=[build(c) for c in d.get("children", [])], shares=d.get("shares"),
                       alpha=arrays.get(f"alpha_{key}"), meta=meta)

        return build(document["tree"])


def array_key(text: str) -> str:
    """A node id (or meta key) as part of an array name: letters, digits, '-', '_' and '.' kept, the rest '_'."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in text)


def _plain(v: Any) -> Any:
    """JSON-able form of a meta value: numpy scalars and small arrays as numbers and lists."""
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, np.ndarray):
        return _plain(v.tolist())
    if isinstance(v, np.bool_):
        return bool(v)
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.floating):
        return float(v)
    return v


def root_node(height: int, width: int) -> MaskNode:
    """A root covering the whole image."""
    return MaskNode(id="root", mask=np.ones((height, width), dtype=bool))
