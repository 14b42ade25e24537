"""Parameter edits of a procedural material (a :class:`workers.graph.ProceduralMaterial`).

:func:`editable_params` lists the scalar (or short per-channel list) parameters a user can change,
:func:`parse_assignment` reads one ``PATH=VALUE`` text, :func:`apply_edits` applies such pairs with
``graph.set_param``, :func:`insert_node` puts a new filter node after an existing one (``warp`` a mask, ``blur``
a height, ...) and :func:`suggest_edit` picks one visible edit of the albedo path (the report shows it).
Pure functions over the material: no files, no printing.
"""
from __future__ import annotations

import copy
import json
import re
from dataclasses import dataclass
from typing import Any, Iterator

from pptbf_db import pptbf as pp
from workers import graph
from workers.errors import GraphError, InputError

# noise-node fields that are fitted data, not knobs (changing them alone does nothing sensible)
_DATA_KEYS = {"kind", "layers", "info", "quantiles", "pca_basis", "pca_mean", "base", "fit_size", "meta", "spectrum",
              "transport"}
_SHORT_LIST = 4  # number lists up to this length are one parameter (a per-channel value)


@dataclass
class Edit:
    """One parameter change: ``path`` (``node.param[.i]``), the value before and after, and what it does."""

    path: str
    before: Any
    after: Any
    label: str


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _walk(value: Any, path: str) -> Iterator[tuple[str, Any]]:
    """(path, value) of the editable leaves below ``value``."""
    if isinstance(value, dict):
        if value.get("__array__"):
            return
        for k, v in value.items():
            if k not in _DATA_KEYS:
                yield from _walk(v, f"{path}.{k}")
    elif isinstance(value, list):
        if value and all(_is_number(v) for v in value) and len(value) <= _SHORT_LIST:
            yield path, value
        else:
            for i, v in enumerate(value):
                yield from _walk(v, f"{path}.{i}")
    elif _is_number(value) or isinstance(value, bool):
        yield path, value


def _param_label(node_type: str, path: str) -> str:
    """A readable name for a parameter path: the type's declared description, PPTBF vector entries by name."""
    parts = path.split(".")
    if node_type == "pptbf" and len(parts) == 3 and parts[1] == "params":
        try:
            return pp.PARAM_NAMES[int(parts[2])]
        except (IndexError, ValueError):
            return ""
    t = graph.NODE_TYPES.get(node_type)
    if t is not None and len(parts) >= 2:
        return next((p.doc for p in t.params if p.name == parts[1] and p.kind != "data"), "")
    return ""


def editable_params(mat: graph.ProceduralMaterial) -> list[dict]:
    """Every scalar (or short per-channel list) parameter: node id, type, path, current value, label."""
    rows = [{"node": "", "type": "material", "path": "seed", "value": mat.seed, "label": "realisation"}]
    for nid, node in mat.nodes.items():
        for path, value in _walk(node.get("params", {}), nid):
            rows.append({"node": nid, "type": node["type"], "path": path, "value": value,
                         "label": _param_label(node["type"], path)})
    return rows


def upstream(mat: graph.ProceduralMaterial, node_id: str) -> list[str]:
    """Node ids feeding ``node_id`` (itself first, breadth first)."""
    order, todo = [], [node_id]
    while todo:
        nid = todo.pop(0)
        if nid in order or nid not in mat.nodes:
            continue
        order.append(nid)
        todo.extend(mat.nodes[nid].get("inputs", {}).values())
    return order


def suggest_edit(mat: graph.ProceduralMaterial, delta: float = 0.1) -> Edit | None:
    """A visible edit of the albedo: raise the offset ``d`` of one of its noise or level nodes by ``delta``, the
    one that brightens the albedo most (a layer's noise only shows where its mask is, so the first one found
    may cover little of the surface); measured on a small render."""
    out = next((m["node"] for m in mat.maps if m.get("name") == "albedo" and "node" in m), None)
    if out is None:
        return None
    edits = []
    for nid in upstream(mat, out):
        node = mat.nodes[nid]
        if node["type"] in ("noise", "level"):
            before = node["params"].get("d", 0.0)
            after = [round(float(v) + delta, 6) for v in before] if isinstance(before, list) else \
                round(float(before) + delta, 6)
            edits.append(Edit(f"{nid}.d", before, after, f"albedo offset +{delta:g} ({node['type']} node {nid})"))
    if len(edits) <= 1:
        return edits[0] if edits else None
    base = float(graph.evaluate(mat, 32, 32)["albedo"].mean())

    def gain(e: Edit) -> float:
        m = copy.deepcopy(mat)
        graph.set_param(m, e.path, e.after)
        return float(graph.evaluate(m, 32, 32)["albedo"].mean()) - base

    return max(edits, key=gain)


def parse_assignment(text: str) -> tuple[str, Any]:
    """``path=value`` -> (path, value): the value parsed as JSON, else kept as a string."""
    path, sep, raw = text.partition("=")
    if not sep or not path.strip():
        raise InputError(f"--set {text!r}: expected PATH=VALUE, e.g. noise_root_0_albedo.d=0.1")
    try:
        value = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    return path.strip(), value


def apply_edits(mat: graph.ProceduralMaterial, assignments: list[tuple[str, Any]],
                source: str = "<material>") -> list[Edit]:
    """Apply ``(path, value)`` pairs with ``graph.set_param``; GraphError naming ``source`` and the path."""
    current = {r["path"]: r["value"] for r in editable_params(mat)}
    done = []
    for path, value in assignments:
        before = current.get(path)
        try:
            graph.set_param(mat, path, value)
        except GraphError as exc:
            raise GraphError(f"{source}: --set {path}: {exc} (see 'proceduralize edit {source} --list')") from None
        except (IndexError, ValueError, TypeError, KeyError) as exc:
            raise GraphError(f"{source}: --set {path}={json.dumps(value)}: invalid ({exc}); "
                             f"see 'proceduralize edit {source} --list'") from None
        done.append(Edit(path, before, value, ""))
    return done


_INSERT = re.compile(r"^\s*([A-Za-z0-9_]+)\s*=\s*([a-z_][a-z0-9_]*)\s*\((.*)\)\s*$", re.S)


def parse_insertion(text: str) -> tuple[str, str, dict[str, Any]]:
    """``AFTER=TYPE(key=value, ...)`` -> (after node id, node type, arguments): values as JSON, else strings
    (node ids for input ports); e.g. ``mask_root_0=warp(by=noise_root_0_height, amount=3)``."""
    m = _INSERT.match(text)
    if not m:
        raise InputError(f"--insert {text!r}: expected NODE=TYPE(key=value, ...), e.g. "
                         "mask_root_0=warp(by=noise_root_0_height, amount=3)")
    args: dict[str, Any] = {}
    for part in filter(None, (p.strip() for p in _split_args(m.group(3)))):
        key, value = parse_assignment(part)
        args[key] = value
    return m.group(1), m.group(2), args


def _split_args(text: str) -> list[str]:
    """Split on the commas outside brackets (values may be lists)."""
    parts, depth, cur = [], 0, ""
    for ch in text:
        depth += ch in "[{"
        depth -= ch in "]}"
        if ch == "," and depth == 0:
            parts.append(cur)
            cur = ""
        else:
            cur += ch
    return parts + [cur]


def insert_node(mat: graph.ProceduralMaterial, after: str, type_name: str, args: dict[str, Any]) -> str:
    """Insert a node of ``type_name`` right after node ``after``: its first input port takes ``after``, every
    node input and map output that read ``after`` reads the new node instead. ``args`` give the type's other
    input ports (node ids) and its parameters (validated by the type's declarations). Returns the new id."""
    t = graph.NODE_TYPES.get(type_name)
    if t is None:
        raise GraphError(f"--insert: unknown node type {type_name!r} (known: {sorted(graph.NODE_TYPES)})")
    mat.node(after)
    ports = [p for p in t.inputs if p != "*"]
    if not ports:
        raise GraphError(f"--insert: a {type_name!r} node has no input to put {after!r} into")
    inputs = {ports[0]: after}
    params = {}
    for key, value in args.items():
        if key in ports[1:]:
            if not isinstance(value, str):
                raise GraphError(f"--insert: input {type_name}.{key} must name a node, got {value!r}")
            mat.node(value)
            inputs[key] = value
        elif any(p.name == key for p in t.params):
            params[key] = value
        else:
            raise GraphError(f"--insert: a {type_name!r} node has no input or parameter {key!r} (inputs: "
                             f"{', '.join(ports)}; parameters: {', '.join(p.name for p in t.params) or 'none'})")
    missing = [p for p in ports[1:] if p not in inputs]
    if missing:
        raise GraphError(f"--insert: a {type_name!r} node needs input(s) {', '.join(missing)} (name a node)")
    t.validate(params)
    n = 0
    while f"{after}_{type_name}{n or ''}" in mat.nodes:
        n += 1
    new = f"{after}_{type_name}{n or ''}"
    for node in mat.nodes.values():
        node["inputs"] = {port: (new if src == after else src) for port, src in node["inputs"].items()}
    for m in mat.maps:
        if m.get("node") == after:
            m["node"] = new
    mat.add(new, type_name, params, **inputs)
    return new
