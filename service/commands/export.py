"""``proceduralize export MATERIAL.json --size WxH``: glTF-ready maps and a MaterialX document."""
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
)
from service.folder import safe_name
from workers.export import export_maps


def register(sub) -> None:
    p = sub.add_parser("export", parents=[common_parser()], help="export glTF-ready maps and a MaterialX document",
                       description="Evaluate a material at SIZE and write NAME_basecolor.png (sRGB), "
                                   "NAME_normal_gl.png (OpenGL), NAME_orm.png (R occlusion = 1, G roughness, "
                                   "B metallic), NAME_roughness.png, NAME_height.png (normalised, 16-bit; range "
                                   "in export.json) and NAME.mtlx binding them to a standard_surface and a "
                                   "UsdPreviewSurface material (validated against the MaterialX libraries).")
    p.add_argument("material", type=Path, metavar="MATERIAL.json")
    p.add_argument("--size", type=parse_size, required=True, metavar="WxH", help="output size, e.g. 2048x2048")
    p.add_argument("--scale", type=parse_scale, default=1.0,
                   help="pattern scale: 1 = the input maps' pattern size, 2 = features twice as big; 1/64 to 64")
    p.add_argument("--seed", type=parse_seed, default=None, help="realisation seed (default: the material's own)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    add_budget_option(p)
    p.add_argument("--name", default=None, help="file name prefix (default: the material file's folder name)")
    p.add_argument("--bits", type=int, choices=(8, 16), default=8, help="bit depth of the colour/ORM PNGs")
    p.add_argument("--no-materialx", action="store_true", help="skip the .mtlx document")
    p.add_argument("--procedural", action="store_true",
                   help="add M_NAME_procedural to the .mtlx: the material as a node graph that renderers evaluate "
                        "(our PPTBF node with GLSL code, the filters as standard nodes, noise read from periodic "
                        "tiles baked at SIZE in NAME_tiles/); the node library is copied beside it "
                        "(proceduralize_library/) and included; the graph's inputs size, scale and seed are editable")
    p.add_argument("--check", action="store_true",
                   help="with --procedural: render the procedural graph's generated GLSL on the CPU (OpenGL through "
                        "EGL, e.g. Mesa llvmpipe) and compare each map with this export's maps; exit code 1 when a "
                        "map's mean absolute difference exceeds 2/255")
    p.set_defaults(handler=handle)


def export_name(material: Path) -> str:
    """Default export prefix: the material file's stem, or its folder's name for ``material.json``."""
    stem = material.stem if material.stem != "material" else material.resolve().parent.name
    return safe_name(stem or "material")


def handle(args) -> int:
    from workers import graph
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
    procedural, built = None, {}
    if args.procedural:
        from workers.mtlx.procedural import add_material

        def procedural(doc):
            built["graph"] = add_material(doc, mat, name, w, h, Path(args.out), seed=args.seed, scale=args.scale)
            built["doc"] = doc
    files = export_maps(maps, args.out, name=name, materialx=not args.no_materialx, bits=args.bits,
                        procedural=procedural)
    hmap = maps.get("height")
    info = {"material": str(args.material), "size": [w, h], "scale": args.scale,
            "seed": mat.seed if args.seed is None else args.seed, "seconds_evaluate": round(t_eval, 3),
            "files": {k: Path(v).name for k, v in vars(files).items() if k != "folder" and v is not None},
            "height_range": [float(hmap.min()), float(hmap.max())] if hmap is not None else None,
            "normal_convention": "opengl", "orm_channels": "R occlusion (1), G roughness, B metallic"}
    rc = 0
    if built:
        g = built["graph"]
        info["procedural"] = {"material": f"M_{name}_procedural", "noise_tiles": g.baked, "baked_nodes": g.fixed,
                              "pinned": g.pinned}
        if args.check:
            from workers.mtlx.check import TOLERANCE, compare

            info["procedural"]["check"] = res = compare(built["doc"], g, maps, w, h)
            for k, r in res.items():
                print(f"check {k}: mean |difference| {r['mad'] * 255:.3f}/255, max {r['max'] * 255:.1f}/255, "
                      f"{r['within_2_255']:.2%} of pixels within 2/255, GLSL render {r['seconds']:.2f} s")
            rc = 1 if any(r["mad"] > TOLERANCE for r in res.values()) else 0
    (files.folder / "export.json").write_text(json.dumps(info, indent=1), encoding="utf-8")
    print(f"exported {name} at {w}x{h} (scale {args.scale}): "
          f"{', '.join(info['files'].values())} -> {files.folder}")
    return rc
