"""Run a procedural MaterialX graph's generated GLSL on the CPU and compare it with proceduralize's own render.

MaterialX's GLSL generator writes the shader of one node graph output; :mod:`workers.mtlx.glsl` draws it over the
exported size on llvmpipe with the baked tiles bound; the result is compared with ``graph.evaluate`` of the same
material at the same size, seed and scale.
"""
from __future__ import annotations

import logging
import re
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from . import glsl
from .library import LIBRARY

logger = logging.getLogger(__name__)

_SAMPLER = re.compile(r"uniform\s+sampler2D\s+(\w+)\s*;")


@dataclass
class Shader:
    """The generated GLSL of one output: vertex and pixel stages, and the image nodes' sampler uniforms."""

    vertex: str
    pixel: str
    samplers: list[str]


def with_libraries(doc):
    """A copy of ``doc`` with the standard node definitions and ours imported (what code generation needs)."""
    import MaterialX as mx

    from .library import DEFS_FILE

    out = mx.createDocument()
    out.copyContentFrom(doc)
    std = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), std)
    ours = mx.createDocument()
    mx.readFromXmlFile(ours, str(DEFS_FILE))
    out.importLibrary(std)
    out.importLibrary(ours)
    return out


def generate_glsl(doc, output) -> Shader:
    """GLSL (MaterialX's genglsl) of a node graph output of ``doc`` (a document with its libraries imported:
    :func:`with_libraries`)."""
    import MaterialX as mx
    import MaterialX.PyMaterialXGenGlsl as mx_glsl
    import MaterialX.PyMaterialXGenShader as mx_gen

    gen = mx_glsl.GlslShaderGenerator.create()
    ctx = mx_gen.GenContext(gen)
    ctx.registerSourceCodeSearchPath(mx.getDefaultDataSearchPath())
    ctx.registerSourceCodeSearchPath(mx.FilePath(str(LIBRARY)))
    shader = gen.generate(mx.createValidName(output.getNamePath()), output, ctx)
    pixel = shader.getSourceCode(mx_gen.PIXEL_STAGE)
    return Shader(shader.getSourceCode(mx_gen.VERTEX_STAGE), pixel, _SAMPLER.findall(pixel))


def read_tile(path: Path) -> np.ndarray:
    """A baked tile (float RGBA EXR) as HxWx4 float32."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(f"{path}: cannot read the baked tile ({oiio.geterror()})")
    try:
        a = inp.read_image(0, 0, 0, 4, "float")
    finally:
        inp.close()
    return np.asarray(a, dtype=np.float32).reshape(inp.spec().height, inp.spec().width, 4)


def render_output(doc, output, tiles: dict[str, Path], width: int, height: int,
                  uniforms: dict | None = None) -> tuple[np.ndarray, float]:
    """Render one node graph output at width x height: (HxWxC float32 with C = the output's channels, seconds)."""
    sh = generate_glsl(doc, output)
    textures, nearest = {}, set()
    graph = output.getParent()
    for s in sh.samplers:
        node = s[:-len("_file")] if s.endswith("_file") else s
        if node not in tiles:
            raise InputError(f"generated shader samples {s!r}, which names no baked tile")
        textures[s] = read_tile(tiles[node])
        filt = graph.getNode(node).getInput("filtertype")
        if filt is not None and filt.getValueString() == "closest":
            nearest.add(s)
    t0 = time.perf_counter()
    rgba = glsl.render(sh.pixel, width, height, vertex=sh.vertex, uniforms=uniforms, textures=textures,
                       nearest=frozenset(nearest))
    seconds = time.perf_counter() - t0
    n = {"float": 1, "vector2": 2, "color3": 3, "vector3": 3}.get(output.getType(), 4)
    return rgba[..., :n], seconds


#: the agreement the procedural document must reach with proceduralize's render (mean absolute difference)
TOLERANCE = 2.0 / 255.0
#: below this two values are the same (masks are 0 or 1, cell keys multiples of 2^-24: exact in float32)
EQUAL = 0.5 / 2 ** 24


def _channels(ng, output, hint: str) -> list:
    """Float nodes of each channel of a node graph output (its connected node), for packing."""
    node = output.getConnectedNode()
    n = {"float": 1, "vector2": 2, "color3": 3, "vector3": 3}.get(output.getType(), 4)
    if n == 1:
        return [node]
    chans = []
    for c in range(n):
        ex = ng.addNode("extract", ng.createValidChildName(f"{hint}_c{c}"), "float")
        ex.addInput("in", output.getType()).setConnectedNode(node)
        ex.addInput("index", "integer").setValue(c)
        chans.append(ex)
    return chans


def packed_outputs(doc, graph, names: list[str]) -> list[tuple[object, list[tuple[str, int]]]]:
    """Vector4 outputs added to ``doc``'s copy of the procedural node graph, each packing 4 channels of the maps
    ``names``: [(output, [(map, channel), ...])]. One shader then computes several maps, and a PPTBF that several
    maps read is compiled once per pack, not once per map (compiling is what takes time on llvmpipe)."""
    ng = doc.getDescendant(graph.nodegraph.getNamePath())
    chans = []
    for name in names:
        out = doc.getDescendant(graph.outputs[name].getNamePath())
        chans += [(name, c, node) for c, node in enumerate(_channels(ng, out, f"pz_check_{name}"))]
    packs = []
    for k in range(0, len(chans), 4):
        part = chans[k:k + 4]
        comb = ng.addNode("combine4", ng.createValidChildName(f"pz_check_pack{k // 4}"), "vector4")
        for i in range(4):
            inp = comb.addInput(f"in{i + 1}", "float")
            if i < len(part):
                inp.setConnectedNode(part[i][2])
            else:
                inp.setValue(0.0)
        out = ng.addOutput(ng.createValidChildName(f"pz_check_out{k // 4}"), "vector4")
        out.setConnectedNode(comb)
        packs.append((out, [(name, c) for name, c, _ in part]))
    return packs


def compare(doc, graph, maps: dict[str, np.ndarray], width: int, height: int) -> dict[str, dict]:
    """Render every map output of a :class:`~workers.mtlx.procedural.ProceduralGraph` and compare it with
    ``maps`` (proceduralize's render at the same size, seed and scale): mean and max absolute difference, share
    of pixels within 2/255 and of equal pixels (for masks and cell keys), render seconds (of the packs the map
    was rendered in: maps are rendered 4 channels at a time, :func:`packed_outputs`). Normals (``graph.sobel``)
    leave out the image's outer pixels: numpy's Sobel wraps around the image, the shader reads the pattern on
    beyond it (a procedural material has no edge)."""
    full = with_libraries(doc)
    names = [name for name in graph.outputs if name in maps]
    got: dict[str, list] = {name: [] for name in names}
    seconds: dict[str, float] = {name: 0.0 for name in names}
    for out, layout in packed_outputs(full, graph, names):
        rgba, sec = render_output(full, out, graph.tiles, width, height)
        for i, (name, _c) in enumerate(layout):
            got[name].append(rgba[..., i])
        for name in {name for name, _c in layout}:
            seconds[name] += sec
    res = {}
    for name in names:
        img = np.stack(got[name], axis=-1)
        ref = np.asarray(maps[name], dtype=np.float32).reshape(img.shape)
        d = np.abs(img - ref)
        if name in graph.sobel and min(d.shape[:2]) > 2:
            d = d[1:-1, 1:-1]
        res[name] = {"mad": float(d.mean()), "max": float(d.max()),
                     "within_2_255": float((d.max(axis=-1) <= TOLERANCE).mean()),
                     "equal": float((d.max(axis=-1) < EQUAL).mean()), "seconds": round(seconds[name], 3)}
    return res


# ---------------------------------------------------------------------------------------------- the PPTBF core

_INCLUDE = re.compile(r'^\s*#include\s+"([^"]+)"\s*$', re.M)


def expand_includes(path: Path, seen: set | None = None) -> str:
    """A GLSL file with its ``#include``s (relative to the including file, as MaterialX resolves nested ones)
    written in, each file once."""
    seen = set() if seen is None else seen

    def sub(m: re.Match) -> str:
        p = (path.parent / m.group(1)).resolve()
        if p in seen:
            return ""
        seen.add(p)
        return expand_includes(p, seen)

    return _INCLUDE.sub(sub, Path(path).read_text(encoding="utf-8"))


def pptbf_shader(function: str = "pptbf_value") -> str:
    """A fragment shader writing the PPTBF core's ``function`` (pptbf_value: V; pptbf_cell: the cell key;
    pptbf_border: the distance to the cell's border) at
    base coordinates pixel / unit + shift, parameters from the uniform ``prm_u``."""
    core = expand_includes(LIBRARY / "genglsl" / "lib" / "pptbf_core.glsl")
    return f"""#version 400
in vec2 texcoord;
out vec4 color;
uniform float prm_u[29];
uniform vec2 size;
uniform float unit;
uniform vec2 shift;
uniform float ref_width;
{core}
void main()
{{
    float i = texcoord.x * size.x - 0.5;
    float j = (1.0 - texcoord.y) * size.y - 0.5;
    float prm[29];
    for (int k = 0; k < 29; ++k)
        prm[k] = prm_u[k];
    color = vec4({function}(i / unit + shift.x, j / unit + shift.y, ref_width, prm), 0.0, 0.0, 1.0);
}}
"""


def render_pptbf(params, width: int, height: int | None = None, *, shift=(0.0, 0.0), ref_width: int | None = None,
                 function: str = "pptbf_value") -> tuple[np.ndarray, float]:
    """The GLSL PPTBF over an image as ``pptbf_db.pptbf.evaluate`` lays it out (pixel_scale 1): (HxW float32,
    seconds). ``function="pptbf_cell"`` gives the cell keys / 2^24, ``"pptbf_border"`` the border distance."""
    height = width if height is None else height
    ref = float(ref_width or width)
    t0 = time.perf_counter()
    out = glsl.render(pptbf_shader(function), width, height, uniforms={
        "prm_u": [float(x) for x in params], "size": (float(width), float(height)), "unit": ref,
        "shift": (float(shift[0]), float(shift[1])), "ref_width": ref})
    return out[..., 0].copy(), time.perf_counter() - t0
