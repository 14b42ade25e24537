"""The decomposition tree: nested binary masks, each child inside its parent."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterator

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


def root_node(height: int, width: int) -> MaskNode:
    """A root covering the whole image."""
    return MaskNode(id="root", mask=np.ones((height, width), dtype=bool))
