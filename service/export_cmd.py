"""Commands on one material file: ``export`` (glTF-ready maps + MaterialX) and ``edit`` (change parameters).

Also the graph helpers they share with the report: :func:`editable_params` lists the scalar parameters a
user can change, :func:`suggest_edit` picks one visible edit of the albedo path.
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

logger = logging.getLogger(__name__)

# noise-node fields that are fitted data, not knobs (changing them alone does nothing sensible)
_DATA_KEYS = {"kind", "layers", "info", "quantiles", "pca_basis", "pca_mean", "base", "fit_size", "meta", "spectrum"}
_SHORT_LIST = 4  # number lists up to this length are one parameter (a per-channel value)


@dataclass
class Edit:
    """One parameter change: ``path`` (``node.param[.i]``), the value before and after, and what it does."""

    path: str
    before: Any
    after: Any
    label: str


# ----------------------------------------------------------------------------- graph helpers


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
    """A readable name for a parameter path (PPTBF vector entries get their names)."""
    parts = path.split(".")
    if node_type == "pptbf" and len(parts) == 3 and parts[1] == "params":
        try:
            from pptbf_db import pptbf as pp

            return pp.PARAM_NAMES[int(parts[2])]
        except (ImportError, IndexError, ValueError, AttributeError):
            return ""
    return ""


def editable_params(mat) -> list[dict]:
    """Every scalar (or short per-channel list) parameter: node id, type, path, current value, label."""
    rows = [{"node": "", "type": "material", "path": "seed", "value": mat.seed, "label": "realisation"}]
    for nid, node in mat.nodes.items():
        for path, value in _walk(node.get("params", {}), nid):
            rows.append({"node": nid, "type": node["type"], "path": path, "value": value,
                         "label": _param_label(node["type"], path)})
    return rows


def upstream(mat, node_id: str) -> list[str]:
    """Node ids feeding ``node_id`` (itself first, breadth first)."""
    order, todo = [], [node_id]
    while todo:
        nid = todo.pop(0)
        if nid in order or nid not in mat.nodes:
            continue
        order.append(nid)
        todo.extend(mat.nodes[nid].get("inputs", {}).values())
    return order


def suggest_edit(mat, delta: float = 0.1) -> Edit | None:
    """A visible edit of the albedo: raise the offset ``d`` of one of its noise or level nodes by ``delta``, the
    one that brightens the albedo most (a layer's noise only shows where its mask is, so the first one found
    may cover little of the surface); measured on a small render."""
    import copy

    from workers import graph

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
    from workers.errors import InputError

    path, sep, raw = text.partition("=")
    if not sep or not path.strip():
        raise InputError(f"--set {text!r}: expected PATH=VALUE, e.g. noise_root_0_albedo.d=0.1")
    try:
        value = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    return path.strip(), value


def apply_edits(mat, assignments: list[tuple[str, Any]], source: str = "<material>") -> list[Edit]:
    """Apply ``(path, value)`` pairs with ``graph.set_param``; GraphError naming ``source`` and the path."""
    from workers import graph
    from workers.errors import GraphError

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


# ----------------------------------------------------------------------------- edit


def _add_edit(sub) -> None:
    from service.cli import _common

    p = sub.add_parser("edit", parents=[_common()], help="change parameters of a procedural material.json",
                       description="Set parameters of a material graph, e.g. --set noise_root_0_albedo.d=0.1 "
                                   "(values are JSON: numbers, lists like [0.1,0,0], true/false; anything else "
                                   "is a string). Each edit is validated; an unknown node or parameter exits 2. "
                                   "--list prints the editable parameters.")
    p.add_argument("material", type=Path, metavar="MATERIAL.json")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="PATH=VALUE",
                   help="node_id.param[.index]=value, or seed=N (repeatable)")
    p.add_argument("--out", type=Path, default=None, metavar="NEW.json",
                   help="write the edited material here (default: overwrite MATERIAL.json)")
    p.add_argument("--list", action="store_true", help="print the editable parameters and their values")
    p.set_defaults(handler=_cmd_edit)


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    return json.dumps(v) if not isinstance(v, str) else v


#: the edited material is evaluated at this size before it is written
EDIT_CHECK_SIZE = 8


def _cmd_edit(args) -> int:
    from service.cli import _print_table
    from workers import graph
    from workers.errors import GraphError, InputError

    mat = graph.load(args.material)
    if args.list:
        _print_table([(r["path"], r["type"], _fmt(r["value"]), r["label"]) for r in editable_params(mat)],
                     header=("parameter", "node type", "value", "name"))
        if not args.sets:
            return 0
    if not args.sets:
        raise InputError("edit: nothing to do (give --set PATH=VALUE or --list)")
    edits = apply_edits(mat, [parse_assignment(s) for s in args.sets], str(args.material))
    try:    # an edit that breaks evaluation (a map with the wrong channel count) is refused before writing
        graph.evaluate(mat, EDIT_CHECK_SIZE, EDIT_CHECK_SIZE)
    except GraphError as exc:
        raise InputError(f"the edit does not evaluate: {exc}") from None
    out = graph.save(mat, args.out or args.material)
    for e in edits:
        print(f"{e.path}: {_fmt(e.before)} -> {_fmt(e.after)}")
    print(f"wrote {out}")
    return 0


# ----------------------------------------------------------------------------- export


def _add_export(sub) -> None:
    from service.cli import _add_budget_option, _common, _scale, _seed, _size

    p = sub.add_parser("export", parents=[_common()], help="export glTF-ready maps and a MaterialX document",
                       description="Evaluate a material at SIZE and write NAME_basecolor.png (sRGB), "
                                   "NAME_normal_gl.png (OpenGL), NAME_orm.png (R occlusion = 1, G roughness, "
                                   "B metallic), NAME_roughness.png, NAME_height.png (normalised, 16-bit; range "
                                   "in export.json) and NAME.mtlx binding them to a standard_surface and a "
                                   "UsdPreviewSurface material (validated against the MaterialX libraries).")
    p.add_argument("material", type=Path, metavar="MATERIAL.json")
    p.add_argument("--size", type=_size, required=True, metavar="WxH", help="output size, e.g. 2048x2048")
    p.add_argument("--scale", type=_scale, default=1.0,
                   help="pattern scale: 1 = the input maps' pattern size, 2 = features twice as big; 1/64 to 64")
    p.add_argument("--seed", type=_seed, default=None, help="realisation seed (default: the material's own)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    _add_budget_option(p)
    p.add_argument("--name", default=None, help="file name prefix (default: the material file's folder name)")
    p.add_argument("--bits", type=int, choices=(8, 16), default=8, help="bit depth of the colour/ORM PNGs")
    p.add_argument("--no-materialx", action="store_true", help="skip the .mtlx document")
    p.set_defaults(handler=_cmd_export)


def export_name(material: Path) -> str:
    """Default export prefix: the material file's stem, or its folder's name for ``material.json``."""
    from service.pipeline import safe_name

    stem = material.stem if material.stem != "material" else material.resolve().parent.name
    return safe_name(stem or "material")


def _cmd_export(args) -> int:
    from workers import graph
    from workers.export import export_maps

    from service.cli import check_render_memory, output_folder
    from workers.maps import output_file

    mat = graph.load(args.material)
    w, h = args.size
    name = args.name or export_name(args.material)
    output_file(args.out, name, "")  # a bad --name is refused before anything is computed or created
    check_render_memory(mat, w, h, args.memory_budget)     # a refused export leaves no folder behind
    output_folder(args.out)
    t0 = time.perf_counter()
    maps = graph.evaluate(mat, w, h, scale=args.scale, seed=args.seed)
    t_eval = time.perf_counter() - t0
    files = export_maps(maps, args.out, name=name, materialx=not args.no_materialx, bits=args.bits)
    hmap = maps.get("height")
    info = {"material": str(args.material), "size": [w, h], "scale": args.scale,
            "seed": mat.seed if args.seed is None else args.seed, "seconds_evaluate": round(t_eval, 3),
            "files": {k: Path(v).name for k, v in vars(files).items() if k != "folder" and v is not None},
            "height_range": [float(hmap.min()), float(hmap.max())] if hmap is not None else None,
            "normal_convention": "opengl", "orm_channels": "R occlusion (1), G roughness, B metallic"}
    (files.folder / "export.json").write_text(json.dumps(info, indent=1), encoding="utf-8")
    print(f"exported {name} at {w}x{h} (scale {args.scale}): "
          f"{', '.join(info['files'].values())} -> {files.folder}")
    return 0


COMMANDS = [_add_edit, _add_export]
