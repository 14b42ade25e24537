"""The procedural material: a versioned JSON graph of generator and filter nodes.

File layout (``material.json``)::

    {"format": "proceduralize/1.3",
     "seed": 1234,                      # default realisation
     "working_size": [512, 512],        # size (px) the graph was fitted at (node params are in these pixels)
     "input_size": [2048, 2048],        # size (px) of the input maps; scale 1 = the input's pattern size
     "maps": [{"name": "albedo", "node": "albedo_out", "colorspace": "srgb"},
              {"name": "roughness", "node": "rough_out"},
              {"name": "height", "node": "height_out"},
              {"name": "normal", "from_height": "height", "strength": 4.0, "convention": "opengl"}],
     "nodes": [{"id": "c0", "type": "constant", "params": {"value": [0.5, 0.4, 0.3]}, "inputs": {}}, ...],
     "meta": {...}}

Scale semantics: ``evaluate(mat, W, H, scale=1)`` draws the pattern at the input's size, so W x H equal to
``input_size`` reproduces the input's look and any other size extends the surface at that pattern size;
``scale`` zooms from there. Files without ``input_size`` (format ``proceduralize/1``) keep their meaning:
scale 1 = the working size's pattern. Inside the graph, nodes see ``EvalContext.px_scale``: output pixels
per working-size pixel of pattern.

Nodes are evaluated lazily from the map outputs. Node types (their parameters, numpy and torch forms) live in
:mod:`workers.nodes`, one module per family. Arrays inside params are stored compactly
(:mod:`workers.arrays`: base64 float16/float32/uint8), never pickled, and never hold input pixels.
"""
from __future__ import annotations

import copy
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pptbf_db.files import write_text

from .errors import GraphError
from .height import height_to_normal
from .nodes import NODE_TYPES, EvalContext, as3

#: 1.1 adds "input_size" (scale 1 = the input's pattern size); 1.2 the pptbf node's "field" (a reader of 1.1
#: would ignore it and cut a border-distance mask on the PPTBF value); 1.3 the piece_ramps node (a reader of 1.2
#: stops at the unknown node type)
FORMAT = "proceduralize/1.3"
SUPPORTED_FORMATS = ("proceduralize/1", "proceduralize/1.1", "proceduralize/1.2", FORMAT)
#: pattern scales ``evaluate`` accepts (1/64 .. 64): the scale multiplies every spatial size in the graph
MIN_SCALE, MAX_SCALE = 1.0 / 64.0, 64.0
#: a map output's name (it becomes ``<name>.png``): albedo, normal, roughness, height, metallic, ...
MAP_NAME = re.compile(r"^[a-z][a-z0-9_]{0,31}$")
#: channel counts the known maps may have (renderers, exporters and PNG writers rely on them); other names any
MAP_CHANNELS: dict[str, tuple[int, ...]] = {"albedo": (1, 3), "normal": (3,), "roughness": (1,), "height": (1,),
                                            "metallic": (1,)}


# ----------------------------------------------------------------------------- material


@dataclass
class ProceduralMaterial:
    """In-memory form of ``material.json``."""

    nodes: dict[str, dict]
    maps: list[dict]
    seed: int = 0
    working_size: tuple[int, int] = (512, 512)
    meta: dict = field(default_factory=dict)
    input_size: tuple[int, int] | None = None
    source: str = field(default="<material>", compare=False)    # where it was read from (for messages)

    @property
    def pattern_unit(self) -> float:
        """Output pixels per working-size pixel of pattern at scale 1: input width / working width (1 when the
        input size is unknown: files of format proceduralize/1)."""
        if self.input_size is None:
            return 1.0
        return float(self.input_size[0]) / float(self.working_size[0])

    @property
    def working_scale(self) -> float:
        """The ``scale`` that draws the pattern as it was at the working size (to compare with working maps)."""
        return 1.0 / self.pattern_unit

    def to_json(self) -> dict:
        """The JSON document (plain dicts/lists, arrays already encoded)."""
        doc = {
            "format": FORMAT,
            "seed": int(self.seed),
            "working_size": [int(self.working_size[0]), int(self.working_size[1])],
        }
        if self.input_size is not None:
            doc["input_size"] = [int(self.input_size[0]), int(self.input_size[1])]
        doc.update({
            "maps": copy.deepcopy(self.maps),
            "nodes": [copy.deepcopy(n) for n in self.nodes.values()],
            "meta": copy.deepcopy(self.meta),
        })
        return doc

    def node(self, node_id: str) -> dict:
        """The node dict with id ``node_id`` (GraphError if absent)."""
        try:
            return self.nodes[node_id]
        except KeyError:
            raise GraphError(f"no node with id {node_id!r}") from None

    def add(self, node_id: str, type_name: str, params: dict | None = None, **inputs: str) -> str:
        """Add a node and return its id (no dots: parameter paths are ``node.param.index``)."""
        if node_id in self.nodes:
            raise GraphError(f"duplicate node id {node_id!r}")
        if not node_id or "." in node_id:
            raise GraphError(f"node id {node_id!r}: must be non-empty and contain no '.' (paths use it)")
        self.nodes[node_id] = {"id": node_id, "type": type_name, "params": params or {}, "inputs": dict(inputs)}
        return node_id


def new_material(seed: int = 0, working_size: tuple[int, int] = (512, 512),
                 input_size: tuple[int, int] | None = None) -> ProceduralMaterial:
    """An empty material to which stages add nodes and map outputs (``input_size``: the input maps' size, which
    scale 1 reproduces; None = the working size's pattern)."""
    return ProceduralMaterial(nodes={}, maps=[], seed=seed, working_size=tuple(working_size),
                              input_size=None if input_size is None else (int(input_size[0]), int(input_size[1])))


def _size_field(doc: dict, key: str, source: str) -> tuple[int, int] | None:
    """An optional [width, height] field of positive integers."""
    v = doc.get(key)
    if v is None:
        return None
    if not (isinstance(v, list) and len(v) == 2 and all(isinstance(x, int) and not isinstance(x, bool) and x > 0
                                                         for x in v)):
        raise GraphError(f"{source}: '{key}' must be [width, height] in positive whole pixels, got {v!r}")
    return int(v[0]), int(v[1])


def _needs_format(fmt: str, first: str, what: str, source: str, why: str = "") -> None:
    """Raise GraphError when document format ``fmt`` is older than ``first``, the format that introduced ``what``."""
    if SUPPORTED_FORMATS.index(fmt) < SUPPORTED_FORMATS.index(first):
        raise GraphError(f"{source}: {what} needs format {first!r} or later (got {fmt!r}){why}")


def from_json(doc: Any, source: str = "<material>") -> ProceduralMaterial:
    """Validate a parsed JSON document and build a :class:`ProceduralMaterial`."""
    if not isinstance(doc, dict):
        raise GraphError(f"{source}: top level must be a JSON object")
    fmt = doc.get("format")
    if fmt not in SUPPORTED_FORMATS:
        raise GraphError(f"{source}: unsupported format {fmt!r}; this version reads {', '.join(SUPPORTED_FORMATS)}")
    nodes_list = doc.get("nodes")
    maps = doc.get("maps")
    if not isinstance(nodes_list, list) or not isinstance(maps, list):
        raise GraphError(f"{source}: 'nodes' and 'maps' must be lists")
    nodes: dict[str, dict] = {}
    for i, n in enumerate(nodes_list):
        if not isinstance(n, dict) or not isinstance(n.get("id"), str) or not isinstance(n.get("type"), str):
            raise GraphError(f"{source}: nodes[{i}] needs string 'id' and 'type'")
        if n["id"] in nodes:
            raise GraphError(f"{source}: duplicate node id {n['id']!r}")
        if not n["id"] or "." in n["id"]:
            raise GraphError(f"{source}: node id {n['id']!r} must be non-empty and contain no '.'")
        t = NODE_TYPES.get(n["type"])
        if t is None:
            raise GraphError(f"{source}: node {n['id']!r} has unknown type {n['type']!r} (known: {sorted(NODE_TYPES)})")
        params = n.get("params", {})
        ins = n.get("inputs", {})
        if not isinstance(params, dict) or not isinstance(ins, dict):
            raise GraphError(f"{source}: node {n['id']!r}: 'params' and 'inputs' must be objects")
        try:
            t.validate(params)
        except (GraphError, TypeError, ValueError, OverflowError) as exc:
            raise GraphError(f"{source}: node {n['id']!r}: {exc}") from None
        nodes[n["id"]] = {"id": n["id"], "type": n["type"], "params": params, "inputs": ins}
    for nid, n in nodes.items():
        for port, src in n["inputs"].items():
            if src not in nodes:
                raise GraphError(f"{source}: node {nid!r} input {port!r} refers to missing node {src!r}")
    if "input_size" in doc:
        _needs_format(fmt, "proceduralize/1.1", "'input_size'", source,
                      f" (format {fmt!r} draws scale 1 at the working size's pattern)")
    if any(n["type"] == "pptbf" and "field" in n["params"] for n in nodes.values()):
        _needs_format(fmt, "proceduralize/1.2", "a pptbf node's 'field'", source)
    if any(n["type"] == "piece_ramps" for n in nodes.values()):
        _needs_format(fmt, "proceduralize/1.3", "a piece_ramps node", source)
    seed = doc.get("seed", 0)
    if not (isinstance(seed, int) and not isinstance(seed, bool) and 0 <= seed < 2**63):
        raise GraphError(f"{source}: seed must be an integer from 0 to 2**63-1, got {seed!r}")
    ws = doc.get("working_size", [512, 512])
    if not (isinstance(ws, list) and len(ws) == 2 and all(isinstance(v, int) and not isinstance(v, bool)
                                                          and 1 <= v <= 32768 for v in ws)):
        raise GraphError(f"{source}: working_size must be [W, H] with 1 <= W, H <= 32768, got {ws!r}")
    meta = doc.get("meta", {})
    if not isinstance(meta, dict):
        raise GraphError(f"{source}: meta must be an object")
    mat = ProceduralMaterial(nodes=nodes, maps=maps, seed=seed, working_size=(ws[0], ws[1]), meta=meta,
                             input_size=_size_field(doc, "input_size", source), source=source)
    names = set()
    for i, m in enumerate(maps):
        if not isinstance(m, dict) or not isinstance(m.get("name"), str):
            raise GraphError(f"{source}: maps[{i}] needs a string 'name'")
        if not MAP_NAME.match(m["name"]):  # map names become file names: never a path
            raise GraphError(f"{source}: maps[{i}].name {m['name']!r} must be 1-32 lower-case letters, digits "
                             "or '_' starting with a letter (e.g. albedo, normal, roughness, height, metallic)")
        if m["name"] in names:
            raise GraphError(f"{source}: maps[{i}].name {m['name']!r} appears twice")
        _check_map_entry(m, f"{source}: maps[{i}]")
        if "node" in m:
            if m["node"] not in nodes:
                raise GraphError(f"{source}: map {m['name']!r} refers to missing node {m['node']!r}")
        elif "from_height" not in m:
            raise GraphError(f"{source}: map {m['name']!r} needs 'node' or 'from_height'")
        names.add(m["name"])
    for m in maps:
        if "from_height" in m and m["from_height"] not in names:
            raise GraphError(f"{source}: map {m['name']!r} derives from missing map {m['from_height']!r}")
    _check_acyclic(mat, source)
    return mat


def _check_map_entry(m: dict, where: str) -> None:
    """The optional fields of a map output: strength, tilt, convention, clamp."""
    st = m.get("strength", 1.0)
    if not isinstance(st, (int, float)) or isinstance(st, bool) or not np.isfinite(st) or abs(st) > 1e6:
        raise GraphError(f"{where}.strength must be a finite number (|strength| <= 1e6), got {st!r}")
    tilt = m.get("tilt", [0.0, 0.0])
    if not (isinstance(tilt, (list, tuple)) and len(tilt) == 2 and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) for v in tilt)):
        raise GraphError(f"{where}.tilt must be two finite numbers, got {tilt!r}")
    if m.get("convention", "opengl") not in ("opengl", "directx"):
        raise GraphError(f"{where}.convention must be 'opengl' or 'directx', got {m.get('convention')!r}")
    if not isinstance(m.get("clamp", True), bool):
        raise GraphError(f"{where}.clamp must be true or false")


def _check_acyclic(mat: ProceduralMaterial, source: str) -> None:
    """Reject graphs with cycles (they cannot be evaluated)."""
    state: dict[str, int] = {}

    def visit(nid: str) -> None:
        s = state.get(nid, 0)
        if s == 1:
            raise GraphError(f"{source}: cycle through node {nid!r}")
        if s == 2:
            return
        state[nid] = 1
        for src in mat.nodes[nid]["inputs"].values():
            visit(src)
        state[nid] = 2

    for nid in mat.nodes:
        visit(nid)


def load(path: str | Path) -> ProceduralMaterial:
    """Read and validate a ``material.json`` file."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise GraphError(f"{p}: file not found") from None
    except OSError as exc:
        raise GraphError(f"{p}: cannot read ({exc})") from None
    except UnicodeDecodeError as exc:
        raise GraphError(f"{p}: not a UTF-8 text file ({exc.reason} at byte {exc.start}); is it a material.json?") \
            from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise GraphError(f"{p}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
    return from_json(doc, str(p))


def save(mat: ProceduralMaterial, path: str | Path) -> Path:
    """Write ``material.json`` (validated first, so a bad graph is never written)."""
    doc = mat.to_json()
    from_json(json.loads(json.dumps(doc)), str(path))
    p = Path(path)
    try:
        write_text(p, json.dumps(doc, indent=1))
    except OSError as exc:
        raise GraphError(f"{p}: cannot write the material file ({exc.strerror or exc})") from None
    return p


def evaluate_node(mat: ProceduralMaterial, node_id: str, ctx: EvalContext) -> np.ndarray:
    """Evaluate one node (memoised in ``ctx.cache``) and return HxWxC float32."""
    if node_id in ctx.cache:
        return ctx.cache[node_id]
    n = mat.node(node_id)
    t = NODE_TYPES.get(n["type"])
    if t is None:
        raise GraphError(f"node {node_id!r} has unknown type {n['type']!r}")
    inputs = {port: evaluate_node(mat, src, ctx) for port, src in n["inputs"].items()}
    out = as3(np.asarray(t.evaluate(n["params"], inputs, ctx, node_id), dtype=np.float32))
    if out.shape[:2] != (ctx.height, ctx.width):
        raise GraphError(f"node {node_id!r} ({n['type']}) returned {out.shape[:2]}, expected {(ctx.height, ctx.width)}")
    ctx.cache[node_id] = out
    return out


def evaluate(
    mat: ProceduralMaterial | dict | str | Path,
    width: int,
    height: int,
    scale: float = 1.0,
    seed: int | None = None,
    maps: list[str] | None = None,
) -> dict[str, np.ndarray]:
    """Render the material's maps at ``width x height``; ``scale`` scales the pattern (1 = the input's pattern
    size, or the working size's for files without ``input_size``), ``seed`` picks a realisation."""
    if isinstance(mat, (str, Path)):
        mat = load(mat)
    elif isinstance(mat, dict):
        mat = from_json(mat)
    if width < 1 or height < 1 or not MIN_SCALE <= scale <= MAX_SCALE:
        raise GraphError(f"bad evaluation size {width}x{height} or scale {scale} (scale must be from "
                         f"{MIN_SCALE:g} to {MAX_SCALE:g})")
    ctx = EvalContext(width=int(width), height=int(height), scale=float(scale) * mat.pattern_unit,
                      seed=mat.seed if seed is None else int(seed), working_size=tuple(mat.working_size))
    out: dict[str, np.ndarray] = {}
    wanted = None if maps is None else set(maps)
    for m in mat.maps:
        if "node" in m and (wanted is None or m["name"] in wanted or any(
                mm.get("from_height") == m["name"] and mm["name"] in wanted for mm in mat.maps)):
            v = evaluate_node(mat, m["node"], ctx)
            if m.get("clamp", True) and m["name"] != "height":
                v = np.clip(v, 0.0, 1.0)
            out[m["name"]] = v
    for m in mat.maps:
        if "from_height" in m and (wanted is None or m["name"] in wanted):
            h = out[m["from_height"]][..., 0]
            # scale zooms the relief with the pattern: slopes stay the same, so strength grows with px_scale
            out[m["name"]] = height_to_normal(h, strength=float(m.get("strength", 1.0)) * ctx.px_scale,
                                              convention=m.get("convention", "opengl"),
                                              tilt=tuple(m.get("tilt", (0.0, 0.0))))
    for name, v in out.items():
        allowed = MAP_CHANNELS.get(name)
        if allowed is not None and v.shape[-1] not in allowed:
            node = next((m.get("node") for m in mat.maps if m["name"] == name), None)
            raise GraphError(f"{mat.source}: map {name!r} (node {node!r}) has {v.shape[-1]} channels; a {name} "
                             f"map has {' or '.join(map(str, allowed))}")
    if wanted is not None:
        out = {k: v for k, v in out.items() if k in wanted}
    return out


def set_param(mat: ProceduralMaterial, path: str, value: Any) -> None:
    """Edit one parameter: ``path`` is ``node_id.param[.sub...]`` or ``seed``; numbers/lists as JSON values."""
    if path == "seed":
        if not (isinstance(value, int) and not isinstance(value, bool) and 0 <= value < 2**63):
            raise GraphError(f"seed must be an integer from 0 to 2**63-1, got {value!r}")
        mat.seed = value
        return
    parts = path.split(".")
    if len(parts) < 2:
        raise GraphError(f"parameter path {path!r} must be node_id.param")
    node = mat.node(parts[0])
    t = NODE_TYPES[node["type"]]
    params = copy.deepcopy(node["params"])   # edited and checked aside: a refused edit changes nothing
    cur: Any = params
    try:
        for p in parts[1:-1]:
            if isinstance(cur, list):
                cur = cur[int(p)]
            elif isinstance(cur, dict) and p in cur:
                cur = cur[p]
            else:
                raise GraphError(f"parameter path {path!r}: no {p!r} in node {parts[0]!r}")
        last = parts[-1]
        if isinstance(cur, list):
            cur[int(last)] = value
        elif isinstance(cur, dict):
            declared = len(parts) == 2 and any(p.name == last for p in t.params)
            if last not in cur and not declared and not last.startswith("_"):
                raise GraphError(f"parameter path {path!r}: node {parts[0]!r} has no parameter {last!r} "
                                 f"(has: {sorted(set(cur) | {p.name for p in t.params})})")
            cur[last] = value
        else:
            raise GraphError(f"parameter path {path!r}: {parts[-2]!r} of node {parts[0]!r} holds no parameters")
    except (ValueError, IndexError):
        raise GraphError(f"parameter path {path!r}: no such index in node {parts[0]!r}") from None
    try:
        t.validate(params)
    except (TypeError, ValueError, OverflowError) as exc:
        raise GraphError(f"node {parts[0]!r}: {exc}") from None
    node["params"] = params

