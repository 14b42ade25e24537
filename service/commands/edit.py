"""``proceduralize edit MATERIAL.json --set PATH=VALUE``: change parameters of a procedural material
(the edits themselves: :mod:`workers.edit`)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from service.commands.common import common_parser, print_table
from workers.errors import GraphError, InputError

#: the edited material is evaluated at this size before it is written
EDIT_CHECK_SIZE = 8


def register(sub) -> None:
    p = sub.add_parser("edit", parents=[common_parser()], help="change parameters of a procedural material.json",
                       description="Set parameters of a material graph, e.g. --set noise_root_0_albedo.d=0.1 "
                                   "(values are JSON: numbers, lists like [0.1,0,0], true/false; anything else "
                                   "is a string), or insert a filter node after one, e.g. --insert "
                                   "'mask_root_0=warp(by=noise_root_0_height, amount=3)'. Each edit is validated; "
                                   "an unknown node or parameter exits 2. --list prints the editable parameters.")
    p.add_argument("material", type=Path, metavar="MATERIAL.json")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="PATH=VALUE",
                   help="node_id.param[.index]=value, or seed=N (repeatable)")
    p.add_argument("--insert", dest="inserts", action="append", default=[], metavar="NODE=TYPE(key=value,...)",
                   help="insert a node of TYPE after NODE (its consumers read the new node); key=value sets the "
                        "type's other inputs (node ids) and parameters (repeatable, applied before --set)")
    p.add_argument("--out", type=Path, default=None, metavar="NEW.json",
                   help="write the edited material here (default: overwrite MATERIAL.json)")
    p.add_argument("--list", action="store_true", help="print the editable parameters and their values")
    p.set_defaults(handler=handle)


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    return json.dumps(v) if not isinstance(v, str) else v


def handle(args) -> int:
    from workers import graph
    from workers.edit import apply_edits, editable_params, insert_node, parse_assignment, parse_insertion

    mat = graph.load(args.material)
    if args.list:
        print_table([(r["path"], r["type"], _fmt(r["value"]), r["label"]) for r in editable_params(mat)],
                    header=("parameter", "node type", "value", "name"))
        if not args.sets:
            return 0
    if not args.sets and not args.inserts:
        raise InputError("edit: nothing to do (give --set PATH=VALUE, --insert NODE=TYPE(...) or --list)")
    inserted = []
    for text in args.inserts:
        after, type_name, node_args = parse_insertion(text)
        try:
            inserted.append((insert_node(mat, after, type_name, node_args), type_name, after))
        except GraphError as exc:
            raise GraphError(f"{args.material}: {exc}") from None
    edits = apply_edits(mat, [parse_assignment(s) for s in args.sets], str(args.material))
    try:    # an edit that breaks evaluation (a map with the wrong channel count) is refused before writing
        graph.evaluate(mat, EDIT_CHECK_SIZE, EDIT_CHECK_SIZE)
    except GraphError as exc:
        raise InputError(f"the edit does not evaluate: {exc}") from None
    out = graph.save(mat, args.out or args.material)
    for new, type_name, after in inserted:
        print(f"inserted {type_name} node {new} after {after}")
    for e in edits:
        print(f"{e.path}: {_fmt(e.before)} -> {_fmt(e.after)}")
    print(f"wrote {out}")
    return 0
