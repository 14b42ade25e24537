"""Long-lived stage holders that the scheduler wraps as Ray actors (no Ray here).

``MaskFitter`` loads the PPTBF index once and fits many masks with it; ``Recomposer`` keeps a torch device
(GPU when the scheduler places it on one) for the recomposition optimisation.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

logger = logging.getLogger(__name__)


class MaskFitter:
    """Holds one PPTBF index (loaded on first use) and fits binary masks against it."""

    def __init__(self, database: str | Path | None = None):
        self.database = database
        self._index = None
        self.load_seconds = 0.0
        self.loads = 0
        self.fits = 0

    @property
    def index(self) -> Any:
        """The loaded PPTBFIndex (loaded once per holder)."""
        if self._index is None:
            from pptbf_db.index import PPTBFIndex, default_database_path

            t0 = time.perf_counter()
            self._index = PPTBFIndex.load(self.database or default_database_path())
            self.load_seconds = time.perf_counter() - t0
            self.loads += 1
            logger.info("PPTBF index loaded in %.2f s", self.load_seconds)
        return self._index

    def fit(self, mask: np.ndarray, valid: np.ndarray | None = None, config: Any = None, seed: int = 0) -> Any:
        """``workers.masks.fit_pptbf_mask`` with the held index."""
        from workers.masks import fit_pptbf_mask

        self.fits += 1
        if config is None:
            return fit_pptbf_mask(mask, self.index, valid=valid, seed=seed)
        return fit_pptbf_mask(mask, self.index, valid=valid, config=config, seed=seed)


def mask_fit_from_json(d: dict) -> Any:
    """Rebuild a ``workers.masks.MaskFit`` from its JSON form (lists back to arrays/tuples)."""
    from workers.masks import MaskFit

    d = dict(d)
    d["params"] = np.asarray(d["params"], dtype=np.float64)
    d["fit_size"] = tuple(int(v) for v in d["fit_size"])
    d["shift"] = tuple(float(v) for v in d.get("shift", (0.0, 0.0)))
    known = set(MaskFit.__dataclass_fields__)
    return MaskFit(**{k: v for k, v in d.items() if k in known})


class Recomposer:
    """Builds the procedural graph of one material and optimises it on a fixed torch device.

    Graph: a ``noise`` node per leaf and map; per internal tree node, ``pptbf`` masks for all children but the
    last (fitted by the masks stage, child i inside what children 0..i-1 left, as a binary tree of splits):
    child i's mask is its PPTBF times the remainder ``1 - sum(masks 0..i-1)`` and the last child takes the
    final remainder, so the masks of a split partition the plane at any size, scale and seed; instance splits
    get an ``instances`` node over the node's absolute mask and one ``channel`` per cluster.
    ``workers.recompose.assemble_material`` adds the blends; ``optimise`` fits the filters.
    """

    def __init__(self, device: str = "cpu"):
        self.device = device

    def build(self, material: Any, tree: Any, noises: dict, fits: dict, seed: int = 0,
              pieces: dict | None = None) -> Any:
        """The assembled (not yet optimised) ProceduralMaterial; ``pieces`` ((leaf, map) -> workers.pieces
        PieceStats dict) adds one offset per piece to those leaves of instance splits."""
        from workers import graph as G
        from workers import masks as MK
        from workers import noise as N
        from workers.pieces import PieceStats, add_piece_offsets
        from workers.recompose import MAP_ORDER, assemble_material

        pieces = pieces or {}
        w, h = material.size
        orig = material.meta.get("original_size")
        proc = G.new_material(seed=seed, working_size=(w, h), input_size=tuple(orig) if orig else None)

        def gid(prefix: str, tree_id: str, suffix: str = "") -> str:
            """Graph node id from a tree id: no dots (edit paths are ``node.param``)."""
            return f"{prefix}_{tree_id.replace('.', '_')}" + (f"_{suffix}" if suffix else "")

        leaf_nodes: dict[str, dict[str, str]] = {}
        for leaf in tree.leaves():
            leaf_nodes[leaf.id] = {}
            for m in MAP_ORDER:
                if (leaf.id, m) in noises:
                    model = N.NoiseModel.from_params(noises[(leaf.id, m)])
                    leaf_nodes[leaf.id][m] = proc.add(gid("noise", leaf.id, m), "noise", N.noise_params(model))
        mask_nodes: dict[str, str] = {}
        absolute: dict[str, str] = {}

        def abs_mask(node: Any, parent: Any | None) -> str:
            """Graph node holding ``node``'s mask in image space (product of its ancestors' masks)."""
            if node.id in absolute:
                return absolute[node.id]
            if parent is None:
                nid = proc.add(gid("one", node.id), "constant", {"value": [1.0]})
            elif parent.id == tree.id:
                nid = mask_nodes[node.id]
            else:
                grand = next(n for n in tree.walk() if parent in n.children)
                nid = proc.add(gid("abs", node.id), "blend", {"sigmas": [0.0]}, mask0=abs_mask(parent, grand),
                               child0=mask_nodes[node.id])
            absolute[node.id] = nid
            return nid

        def visit(node: Any, parent: Any | None) -> None:
            if node.is_leaf:
                return
            if node.method == "instances":
                cells, sep = abs_mask(node, parent), float(node.meta.get("separate", 0.0))
                inst = MK.add_instances_node(proc, gid("inst", node.id), cells,
                                             node.shares or [1.0 / len(node.children)] * len(node.children), sep)
                for i, c in enumerate(node.children):
                    mask_nodes[c.id] = proc.add(gid("mask", c.id), "channel", {"channels": [i]}, input=inst)
                varied = [(c.id, m) for c in node.children for m in leaf_nodes.get(c.id, {}) if (c.id, m) in pieces]
                if varied:   # one numbering of the pieces, one offset draw per (kind, map)
                    labels = proc.add(gid("pieces", node.id), "piece_labels", {"separate": round(sep, 3)},
                                      parent=cells)
                    for cid, m in varied:
                        leaf_nodes[cid][m] = add_piece_offsets(proc, gid("leaf", cid, m), leaf_nodes[cid][m], labels,
                                                               PieceStats.from_dict(pieces[(cid, m)]))
            else:
                fitted: list[str] = []
                remainder: str | None = None
                for i, c in enumerate(node.children[:-1]):
                    if c.id not in fits:
                        raise KeyError(f"no mask fit for tree node {c.id!r} (masks stage missing?)")
                    fitted.append(MK.add_mask_node(proc, gid("mask", c.id), mask_fit_from_json(fits[c.id]["fit"]),
                                                   working_width=w, parent=remainder))
                    mask_nodes[c.id] = fitted[-1]
                    src = fitted[0] if len(fitted) == 1 else proc.add(
                        gid("sum", node.id, str(i)), "add", {}, **{f"in{j}": f for j, f in enumerate(fitted)})
                    remainder = proc.add(gid("rest", node.id, str(i)), "level", {"a": -1.0, "d": 1.0, "clamp": True},
                                         input=src)
                mask_nodes[node.children[-1].id] = remainder
            for c in node.children:
                visit(c, node)

        visit(tree, None)
        return assemble_material(tree, leaf_nodes, mask_nodes, proc, height_strength=material.height_scale,
                                 tilt=tuple(material.normal_tilt))

    def run(self, material: Any, tree: Any, noises: dict, fits: dict, options: dict | None = None,
            seed: int = 0, pieces: dict | None = None) -> tuple[Any, dict]:
        """(optimised ProceduralMaterial, report with loss before/after) via ``workers.recompose``."""
        from workers.recompose import RecomposeConfig, optimise

        t0 = time.perf_counter()
        proc = self.build(material, tree, noises, fits, seed, pieces)
        opts = dict(options or {})
        if int(opts.get("iterations", 1)) == 0:
            return proc, {"device": self.device, "iterations": 0, "seconds": time.perf_counter() - t0}
        cfg = RecomposeConfig.from_dict({"seed": seed, "device": self.device, **opts})
        res = optimise(proc, material, cfg)
        report = res.report()
        report["seconds_total"] = round(time.perf_counter() - t0, 3)
        return res.material, report
