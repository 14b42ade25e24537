"""The material graph of a decomposed material (paper section 5.3): the whole tree-to-graph mapping in one place.

:func:`build_material` turns the decomposition tree, the fitted noise models of its leaves and the fitted masks
of its splits into a :class:`workers.graph.ProceduralMaterial`:

* a ``noise`` node per leaf and map;
* per split, ``pptbf`` masks for all children but the last (child i fitted inside what children 0..i-1 left, as a
  binary tree of splits): child i's mask is its PPTBF times the remainder ``1 - sum(masks 0..i-1)`` and the last
  child takes the final remainder, so the masks of a split partition the plane at any size, scale and seed;
* per instance split, an ``instances`` node over the split's absolute mask and one ``channel`` per kind, and for
  kinds with per-piece variation a ``piece_labels`` numbering and one ``piece_offsets`` draw per map;
* :func:`assemble_material`: one normalised ``blend`` per split and map, bottom-up, and the map outputs (normal
  derived from height).

The recomposition (:mod:`workers.recompose`) then optimises the graph's filter parameters.
"""
from __future__ import annotations

import logging
from typing import Any, Mapping

from .errors import GraphError
from .graph import ProceduralMaterial, new_material
from .masks import MaskFit
from .nodes.instances import check_shares
from .noise import NoiseModel, noise_params
from .pieces import PieceStats
from .tree import MaskNode

logger = logging.getLogger(__name__)

#: the maps a leaf may generate, in output order (normal is derived from height)
MAP_ORDER = ("albedo", "roughness", "height", "metallic")


def graph_id(prefix: str, tree_id: str, suffix: str = "") -> str:
    """Graph node id from a tree id: no dots (edit paths are ``node.param``)."""
    return f"{prefix}_{tree_id.replace('.', '_')}" + (f"_{suffix}" if suffix else "")


def add_mask_node(mat: ProceduralMaterial, node_id: str, fit: MaskFit, working_width: int | None = None,
                  parent: str | None = None, pin_shift: bool = False) -> str:
    """Add a "pptbf" node for `fit` to `mat` (optionally inside node `parent`); returns its id."""
    ww = int(working_width or mat.working_size[0])
    ins = {"parent": parent} if parent else {}
    return mat.add(node_id, "pptbf", fit.node_params(ww, pin_shift), **ins)


def add_instances_node(mat: ProceduralMaterial, node_id: str, parent: str, shares, separate: float = 0.0,
                       cells: str | None = None) -> str:
    """Add an "instances" node (HxWxK one-hot) over mask node `parent`; pick cluster i with a "channel" node.
    With ``cells`` (a cells node, :func:`add_cells_node`) each PPTBF cell draws its kind; else each piece of the
    parent, cut at its necks (``separate``)."""
    params: dict = {"shares": [float(x) for x in check_shares(shares)]}
    if cells is not None:
        return mat.add(node_id, "instances", params, parent=parent, cells=cells)
    if separate > 0:
        params["separate"] = round(float(separate), 3)
    return mat.add(node_id, "instances", params, parent=parent)


def pptbf_source(mat: ProceduralMaterial, node_id: str) -> str | None:
    """The ``pptbf`` mask node whose cells make up mask node ``node_id`` (the node itself, or the complement
    ``level`` of one), else None."""
    n = mat.node(node_id)
    p = n["params"]
    if n["type"] == "pptbf" and p.get("output", "mask") == "mask" and "parent" not in n["inputs"]:
        return node_id
    if n["type"] == "level" and p.get("a") == -1.0 and p.get("d") == 1.0 and "input" in n["inputs"]:
        return pptbf_source(mat, n["inputs"]["input"])
    return None


def add_cells_node(mat: ProceduralMaterial, node_id: str, source: str) -> str:
    """A ``pptbf`` node giving the cells of ``pptbf`` node ``source`` (same parameters and realisation)."""
    p = mat.node(source)["params"]
    params = {k: p[k] for k in ("params", "ref_width", "shift") if k in p}
    return mat.add(node_id, "pptbf", {**params, "output": "cells", "stream": p.get("stream") or source})


def add_piece_offsets(mat: ProceduralMaterial, node_id: str, leaf: str, pieces: dict[str, str],
                      stats: PieceStats) -> str:
    """Add ``piece_offsets`` over ``pieces`` (``{"cells": node}`` or ``{"labels": node}``), and ``piece_ramps`` when
    the kind's pieces are ramps, and an ``add`` of them to node ``leaf``; returns the add node's id."""
    d = stats.to_dict()
    terms = {"in0": leaf, "in1": mat.add(f"{node_id}_offsets", "piece_offsets", {"cov": d["cov"]}, **pieces)}
    if "ramp" in d:
        ramp = {k: d[k] for k in ("ramp", "reach") if k in d}
        terms["in2"] = mat.add(f"{node_id}_ramps", "piece_ramps", ramp, **pieces)
    return mat.add(node_id, "add", {}, **terms)


def build_material(material: Any, tree: MaskNode, noises: Mapping, fits: Mapping, seed: int = 0,
                   pieces: Mapping | None = None) -> ProceduralMaterial:
    """The assembled (not yet optimised) graph of ``material`` (a :class:`workers.maps.Material`): ``noises``
    ((leaf id, map) -> noise model params), ``fits`` (child id -> {"fit": MaskFit dict}), ``pieces`` ((leaf id,
    map) -> PieceStats dict) for the leaves of instance splits that vary per piece."""
    pieces = pieces or {}
    w, h = material.size
    orig = material.meta.get("original_size")
    proc = new_material(seed=seed, working_size=(w, h), input_size=tuple(orig) if orig else None)
    leaf_nodes: dict[str, dict[str, str]] = {}
    for leaf in tree.leaves():
        leaf_nodes[leaf.id] = {}
        for m in MAP_ORDER:
            if (leaf.id, m) in noises:
                model = NoiseModel.from_params(noises[(leaf.id, m)])
                leaf_nodes[leaf.id][m] = proc.add(graph_id("noise", leaf.id, m), "noise", noise_params(model))
    mask_nodes: dict[str, str] = {}
    absolute: dict[str, str] = {}

    def abs_mask(node: MaskNode, parent: MaskNode | None) -> str:
        """Graph node holding ``node``'s mask in image space (product of its ancestors' masks)."""
        if node.id in absolute:
            return absolute[node.id]
        if parent is None:
            nid = proc.add(graph_id("one", node.id), "constant", {"value": [1.0]})
        elif parent.id == tree.id:
            nid = mask_nodes[node.id]
        else:
            grand = next(n for n in tree.walk() if parent in n.children)
            nid = proc.add(graph_id("abs", node.id), "blend", {"sigmas": [0.0]}, mask0=abs_mask(parent, grand),
                           child0=mask_nodes[node.id])
        absolute[node.id] = nid
        return nid

    def visit(node: MaskNode, parent: MaskNode | None) -> None:
        if node.is_leaf:
            return
        if node.method == "instances":
            area, sep = abs_mask(node, parent), float(node.meta.get("separate", 0.0))
            src = pptbf_source(proc, area)
            cells = add_cells_node(proc, graph_id("cells", node.id), src) if src else None
            inst = add_instances_node(proc, graph_id("inst", node.id), area,
                                      node.shares or [1.0 / len(node.children)] * len(node.children), sep, cells)
            for i, c in enumerate(node.children):
                mask_nodes[c.id] = proc.add(graph_id("mask", c.id), "channel", {"channels": [i]}, input=inst)
            varied = [(c.id, m) for c in node.children for m in leaf_nodes.get(c.id, {}) if (c.id, m) in pieces]
            if varied:   # one numbering of the pieces (the PPTBF's cells when it has them), one draw per (kind, map)
                by = {"cells": cells} if cells else {"labels": proc.add(
                    graph_id("pieces", node.id), "piece_labels", {"separate": round(sep, 3)}, parent=area)}
                for cid, m in varied:
                    leaf_nodes[cid][m] = add_piece_offsets(proc, graph_id("leaf", cid, m), leaf_nodes[cid][m],
                                                           by, PieceStats.from_dict(pieces[(cid, m)]))
        else:
            fitted: list[str] = []
            remainder: str | None = None
            for i, c in enumerate(node.children[:-1]):
                if c.id not in fits:
                    raise KeyError(f"no mask fit for tree node {c.id!r} (masks stage missing?)")
                fitted.append(add_mask_node(proc, graph_id("mask", c.id), MaskFit.from_dict(fits[c.id]["fit"]),
                                            working_width=w, parent=remainder))
                mask_nodes[c.id] = fitted[-1]
                src = fitted[0] if len(fitted) == 1 else proc.add(
                    graph_id("sum", node.id, str(i)), "add", {}, **{f"in{j}": f for j, f in enumerate(fitted)})
                remainder = proc.add(graph_id("rest", node.id, str(i)), "level", {"a": -1.0, "d": 1.0, "clamp": True},
                                     input=src)
            mask_nodes[node.children[-1].id] = remainder
        for c in node.children:
            visit(c, node)

    visit(tree, None)
    return assemble_material(tree, leaf_nodes, mask_nodes, proc, height_strength=material.height_scale,
                             tilt=tuple(material.normal_tilt))


def assemble_material(tree: MaskNode, leaf_nodes: Mapping[str, Mapping[str, str]], mask_nodes: Mapping[str, str],
                      material: ProceduralMaterial, height_strength: float = 1.0, *,
                      maps: tuple[str, ...] | None = None, blend_sigma: float = 0.0,
                      tilt: tuple[float, float] = (0.0, 0.0), convention: str = "opengl",
                      prefix: str = "blend") -> ProceduralMaterial:
    """Add one ``blend`` node per internal tree node and map, bottom-up, and the map outputs; returns ``material``.

    ``leaf_nodes[leaf.id][map_name]`` is the graph node generating that map inside the leaf (e.g. a ``noise``
    node); ``mask_nodes[child.id]`` the graph node (1-channel mask, e.g. ``pptbf`` or ``channel`` of
    ``instances``) giving that child's mask inside its parent; the masks of a split should partition it (the
    blends are normalised by the sum of the blurred masks). ``maps`` defaults to the maps every leaf provides
    (order albedo, roughness, height, metallic). With a height map, a ``normal`` output ``from_height`` with
    ``height_strength`` (and ``tilt``) is declared. Internal node ``n`` and map ``m`` get id ``{prefix}_{n}_{m}``
    (dots of tree ids become underscores: graph ids cannot hold dots).
    """
    leaves = tree.leaves()
    for leaf in leaves:
        if leaf.id not in leaf_nodes:
            raise GraphError(f"assemble_material: no generator nodes given for leaf {leaf.id!r}")
        for nid in leaf_nodes[leaf.id].values():
            material.node(nid)
    if maps is None:
        common = set.intersection(*(set(leaf_nodes[leaf.id]) for leaf in leaves))
        maps = tuple(m for m in MAP_ORDER if m in common)
    if not maps:
        raise GraphError("assemble_material: the leaves share no map (need albedo/roughness/height/metallic)")
    for node in tree.walk():
        for child in node.children:
            if child.id not in mask_nodes:
                raise GraphError(f"assemble_material: no mask node given for tree node {child.id!r} "
                                 f"(child of {node.id!r})")
            material.node(mask_nodes[child.id])

    def build(node: MaskNode, m: str) -> str:
        if node.is_leaf:
            if m not in leaf_nodes[node.id]:
                raise GraphError(f"assemble_material: leaf {node.id!r} has no {m!r} generator")
            return leaf_nodes[node.id][m]
        ins: dict[str, str] = {}
        for i, child in enumerate(node.children):
            ins[f"mask{i}"] = mask_nodes[child.id]
            ins[f"child{i}"] = build(child, m)
        return material.add(f"{prefix}_{node.id.replace('.', '_')}_{m}", "blend",
                            {"sigmas": [float(blend_sigma)] * len(node.children), "normalise": True}, **ins)

    existing = {e["name"] for e in material.maps}
    for m in maps:
        out = build(tree, m)
        if m in existing:
            raise GraphError(f"assemble_material: map {m!r} is already declared")
        entry = {"name": m, "node": out}
        if m == "albedo":
            entry["colorspace"] = "linear"
        material.maps.append(entry)
    if "height" in maps and "normal" not in existing:
        material.maps.append({"name": "normal", "from_height": "height", "strength": float(height_strength),
                              "convention": convention, "tilt": [float(tilt[0]), float(tilt[1])]})
    material.meta.setdefault("tree", tree.describe())
    logger.info("assembled %d maps over %d leaves (%d nodes)", len(maps), len(leaves), len(material.nodes))
    return material
