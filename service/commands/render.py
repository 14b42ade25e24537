"""``proceduralize render MATERIAL.json --size WxH``: evaluate a procedural material to map files."""
from __future__ import annotations

import json
import time
from pathlib import Path

from service.commands.common import (
    add_budget_option,
    check_render_memory,
    common_parser,
    output_folder,
    parse_scale,
    parse_seed,
    parse_size,
    write_maps,
    write_preview,
)


def register(sub) -> None:
    p = sub.add_parser("render", parents=[common_parser()], help="evaluate a procedural material.json to maps",
                       description="Evaluate a procedural material at any size, pattern scale and seed and "
                                   "write each map as PNG (albedo sRGB, normal encoded, grey maps 16-bit) "
                                   "plus preview.png (top light | side light).")
    p.add_argument("material", type=Path, metavar="MATERIAL.json")
    p.add_argument("--size", type=parse_size, required=True, metavar="WxH", help="output size, e.g. 2048x2048")
    p.add_argument("--scale", type=parse_scale, default=1.0,
                   help="pattern scale: 1 = the input maps' pattern size (files without input_size: the working "
                        "size's), 2 = features twice as big; 1/64 to 64")
    p.add_argument("--seed", type=parse_seed, default=None, help="realisation seed (default: the material's own)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    p.add_argument("--bits", type=int, choices=(8, 16), default=8, help="bit depth of albedo and normal PNGs")
    p.add_argument("--no-preview", action="store_true", help="skip the preview render")
    add_budget_option(p)
    p.set_defaults(handler=handle)


def handle(args) -> int:
    from workers import graph

    mat = graph.load(args.material)
    w, h = args.size
    check_render_memory(mat, w, h, args.memory_budget)     # a refused render leaves no folder behind
    output_folder(args.out)
    t0 = time.perf_counter()
    maps = graph.evaluate(mat, w, h, scale=args.scale, seed=args.seed)
    seconds = time.perf_counter() - t0
    files = write_maps(maps, args.out, bits=args.bits)
    preview = None if args.no_preview else write_preview(maps, args.out / "preview.png")
    info = {"material": str(args.material), "size": [w, h], "scale": args.scale,
            "seed": mat.seed if args.seed is None else args.seed, "seconds": round(seconds, 3),
            "files": {k: v.name for k, v in files.items()}, "preview": preview.name if preview else None}
    (args.out / "render.json").write_text(json.dumps(info, indent=1), encoding="utf-8")
    print(f"rendered {', '.join(files)} at {w}x{h} (scale {args.scale}) in {seconds:.2f} s -> {args.out}")
    return 0
