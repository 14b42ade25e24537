"""Benchmark the procedural MaterialX export's node library: per node type, GLSL and OSL lines, and the render time
of the node's GLSL at SIZE^2 on this machine's OpenGL (Mesa llvmpipe on a CPU-only machine) against our numpy.

Run: python bench/mtlx.py [--size 1024] [--materials out/example/*/material.json]
Table 1, one row per node type of the library: lines of its implementation (with the files it includes), the
first render (compile + draw; Mesa's shader cache makes later runs of the same source skip the compile) and a
warm render (draw only), and numpy over the same pixels. With --materials, table 2: each material's procedural
document (`proceduralize export --procedural`) rendered map by map against proceduralize's maps at SIZE, seeds
0 and 2.
"""
from __future__ import annotations

import argparse
import re
import tempfile
import time
from pathlib import Path

import numpy as np

from pptbf_db import pptbf as pp
from workers.mtlx import check, glsl, library
from workers.nodes import instances

BOND = {"threshold": 0.7, "tiling": 4, "jitter": 0.0, "resolution": 18, "rotation": 0.0, "aspect_ratio": 2.2,
        "window_shape": 1, "window_arity": 4, "window_larp": 1.0, "window_norm": 2.0, "window_smoothness": 0.0,
        "window_blend": 1.0, "window_sigma": 4.0, "feature_mixture": 0, "distortion_amplitude": 0.0}


def _bond() -> np.ndarray:
    v = pp.sample_params(np.random.default_rng(0), 1, ref_width=256)[0]
    for k, x in BOND.items():
        v[pp.PARAM_INDEX[k]] = x
    return pp.clip_params(v)


def _lines(path: Path, seen: set | None = None) -> int:
    """Lines of a shader file and of the files it includes (each once)."""
    seen = set() if seen is None else seen
    if not path.is_file() or path in seen:
        return 0
    seen.add(path)
    text = path.read_text(encoding="utf-8")
    inc = re.findall(r'^\s*#include\s+"([^"]+)"', text, re.M)
    return len(text.splitlines()) + sum(_lines((path.parent / i).resolve(), seen) for i in inc)


def _osl_lines(nd: library.NodeDef) -> int:
    return _lines(library.LIBRARY / "genosl" / f"{nd.function}.osl")


def _timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def _cell_shader(call: str) -> str:
    """A fragment shader that calls a per-cell node on synthetic cell keys (the pixel index mod 4093)."""
    src = check.expand_includes(library.LIBRARY / "genglsl" / "lib" / "pz_seed.glsl")
    return f"""#version 400
in vec2 texcoord;
out vec4 color;
uniform vec2 size;
{src}
void main()
{{
    float i = floor(texcoord.x * size.x);
    float j = floor((1.0 - texcoord.y) * size.y);
    float cells = mod(i + 37.0 * j, 4093.0) / 16777216.0;
    color = vec4({call}, 0.0, 0.0, 1.0);
}}
"""


def node_rows(size: int) -> list[tuple]:
    """(node, GLSL lines, OSL lines, first render s, warm render s, numpy s, note) per library node."""
    nds = {nd.node: nd for nd in library.NODEDEFS}
    glsl_dir = library.LIBRARY
    bond = _bond()
    rows = []
    for name, fn, np_fn, note in (
            ("pptbf", "pptbf_value", lambda: pp.evaluate(bond, size, size, ref_width=256), "running bond"),
            ("pptbf_cells", "pptbf_cell", lambda: pp.evaluate(bond, size, size, ref_width=256, cells=True),
             "running bond")):
        first = _timed(lambda fn=fn: check.render_pptbf(bond, size, ref_width=256, function=fn))
        warm = _timed(lambda fn=fn: check.render_pptbf(bond, size, ref_width=256, function=fn))
        rows.append((name, _lines(glsl_dir / nds[name].file), _osl_lines(nds[name]), first, warm, _timed(np_fn),
                     note))
    rows.append(("pptbf_ring", _lines(glsl_dir / nds["pptbf_ring"].file), _osl_lines(nds["pptbf_ring"]),
                 None, None, None, "8 x pptbf per pixel (normals)"))
    i = np.arange(size, dtype=np.float64)
    keys = np.mod(i[None, :] + 37.0 * i[:, None], 4093.0) / instances.CELL_SCALE
    for name, call, np_fn in (
            ("cell_kind", "pz_cell_uniform(cells, pz_stream(1234, 0), 0u)",
             lambda: instances.cell_kinds(keys, [0.3, 0.7], 1234)),
            ("cell_normal", "pz_cell_normal(cells, pz_stream(1234, 0), 0u)",
             lambda: instances.cell_normal(keys, 1234, 0))):
        src = _cell_shader(call)
        first = _timed(lambda src=src: glsl.render(src, size, size, uniforms={"size": (float(size), float(size))}))
        warm = _timed(lambda src=src: glsl.render(src, size, size, uniforms={"size": (float(size), float(size))}))
        rows.append((name, _lines(glsl_dir / nds[name].file), _osl_lines(nds[name]), first, warm, _timed(np_fn),
                     "synthetic keys"))
    rows.append(("tile_coords", _lines(glsl_dir / nds["tile_coords"].file), _osl_lines(nds["tile_coords"]),
                 None, None, None, "+ stdlib image: noise tiles (in table 2)"))
    for stdlib in ("constant", "level", "blend (sigma 0)", "channel", "add", "clamp"):
        rows.append((stdlib, "stdlib", "stdlib", None, None, None, "MaterialX standard nodes (in table 2)"))
    return rows


def material_rows(paths: list[Path], size: int) -> list[tuple]:
    """(material, seed, map, MAD, within 2/255, render s, numpy s) per map of each material's procedural
    document."""
    import MaterialX as mx

    from workers import graph as G
    from workers.mtlx.procedural import add_material

    rows = []
    for path in paths:
        mat = G.load(path)
        name = path.parent.name
        for seed in (0, 2):
            with tempfile.TemporaryDirectory() as tmp:
                doc = mx.createDocument()
                g = add_material(doc, mat, name, size, size, Path(tmp), seed=seed)
                t0 = time.perf_counter()
                maps = G.evaluate(mat, size, size, seed=seed)
                t_np = time.perf_counter() - t0
                res = check.compare(doc, g, maps, size, size)
            for k, r in res.items():
                rows.append((name, seed, k, r["mad"] * 255, r["within_2_255"], r["seconds"], t_np))
    return rows


def _f(x) -> str:
    return f"{x:.2f}" if isinstance(x, float) else "-"


def mask_rows(paths: list[Path], size: int) -> list[tuple]:
    """(material, seed, node, output, share of equal pixels, GLSL s) per PPTBF node of each material: the node
    alone as the document's only map, rendered against its numpy output."""
    import dataclasses

    import MaterialX as mx

    from workers import graph as G
    from workers.mtlx.procedural import add_material

    rows = []
    for path in paths:
        mat = G.load(path)
        ids = [i for i, n in mat.nodes.items() if n["type"] == "pptbf"]
        one = dataclasses.replace(mat, maps=[{"name": f"m_{i}", "node": i, "clamp": False} for i in ids])
        for seed in (0, 2):
            with tempfile.TemporaryDirectory() as tmp:
                doc = mx.createDocument()
                g = add_material(doc, one, "masks", size, size, Path(tmp), seed=seed)
                res = check.compare(doc, g, G.evaluate(one, size, size, seed=seed), size, size)
            for i in ids:
                r = res[f"m_{i}"]
                kind = mat.node(i)["params"].get("output", "mask")
                rows.append((path.parent.name, seed, i, kind, r["equal"], r["seconds"]))
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024, help="image side in pixels")
    ap.add_argument("--materials", type=Path, nargs="*", default=[], help="material.json files for table 2")
    args = ap.parse_args(argv)
    print(f"renderer: {glsl.renderer()}")
    print(f"\n{'node':<16} {'GLSL lines':>10} {'OSL lines':>9} {'GLSL first':>10} {'GLSL warm':>9} "
          f"{'numpy':>7}  ({args.size}^2, seconds)")
    for name, gl, osl, first, warm, t_np, note in node_rows(args.size):
        print(f"{name:<16} {gl!s:>10} {osl!s:>9} {_f(first):>10} {_f(warm):>9} {_f(t_np):>7}  {note}")
    if args.materials:
        print(f"\n{'material':<24} {'seed':>4} {'PPTBF node':<16} {'output':<6} {'equal':>7} {'GLSL s':>7}  "
              f"(each PPTBF node alone, {args.size}^2)")
        for name, seed, node, kind, equal, t_gl in mask_rows(args.materials, args.size):
            print(f"{name:<24} {seed:>4} {node:<16} {kind:<6} {equal:>7.4f} {t_gl:>7.1f}")
        print(f"\n{'material':<24} {'seed':>4} {'map':<10} {'MAD*255':>8} {'<=2/255':>8} {'GLSL s':>7} "
              f"{'numpy s':>8}  (all maps, {args.size}^2)")
        for name, seed, k, mad, within, t_gl, t_np in material_rows(args.materials, args.size):
            print(f"{name:<24} {seed:>4} {k:<10} {mad:>8.3f} {within:>8.4f} {t_gl:>7.1f} {t_np:>8.1f}")


if __name__ == "__main__":
    main()
