"""The proceduralize MaterialX node library: nodedefs of our procedural nodes and their GLSL implementations.

Shipped with the package in ``workers/mtlx/library/`` (``proceduralize_defs.mtlx``, ``genglsl/``, ``genosl/``: the
OSL ports, :mod:`workers.mtlx.osl`). The nodedefs
with many inputs (the PPTBF's 29 parameters) and their GLSL entry points are written from the parameter tables
here (``python -m workers.mtlx.library`` rewrites them; a test checks that the shipped files are current); the
algorithms are hand-written GLSL in ``genglsl/lib/``.

Nodes (:data:`NODEDEFS`):
- ``pptbf`` (float): the binary PPTBF mask of :mod:`workers.nodes.pptbf` at a texture coordinate, with the
  binarisation cut stored (the numpy node thresholds at a quantile of the whole image, which a shader cannot see);
  ``pptbf_cells``: the key of the cell a pixel is in (``output: cells``).
- ``cell_kind``, ``cell_normal``: the per-cell draws of the ``instances`` and ``piece_offsets`` nodes.
- ``tile_coords`` (vector2): the texture coordinates at which a baked periodic tile is read, following the
  document's size, scale and seed as the procedural nodes do.
The texture nodes take ``offset`` (pixels), so that the exporter can read a node at a neighbouring pixel (the
Sobel normal).
"""
from __future__ import annotations

import argparse
import logging
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

from pptbf_db import pptbf as pp

logger = logging.getLogger(__name__)

#: the folder to put on a renderer's library search path (MaterialXView: --library, or the document's include)
LIBRARY = Path(__file__).resolve().parent / "library"
DEFS_NAME = "proceduralize_defs.mtlx"
DEFS_FILE = LIBRARY / DEFS_NAME

#: inputs every texture node of ours starts with: (name, MaterialX type, default, doc)
FRAME = (
    ("texcoord", "vector2", None, "texture coordinate (0..1 over the document's size)"),
    ("offset", "vector2", "0.0, 0.0", "read the pixel this many pixels away (x right, y down)"),
    ("size", "vector2", "1024.0, 1024.0", "pixels the texture coordinates span (the exported size)"),
)
SEEDED = (
    ("seed", "integer", "0", "realisation: 0 = the exported one"),
    ("stream", "integer", "0", "this node's stream of the seed"),
)
#: the PPTBF's placement inputs (before its 29 parameters); the mask adds cut and complement
PPTBF_PLACE = FRAME + (
    ("unit", "float", "1024.0", "pixels per reference width at scale 1"),
    ("scale", "float", "1.0", "pattern scale: 2 = features twice as big"),
) + SEEDED + (
    ("shift", "vector2", "0.0, 0.0", "the exported realisation, in reference widths"),
    ("ref_width", "float", "256.0", "the width the parameters are defined at"),
)
PPTBF_CUT = (
    ("cut", "float", "0.5", "white where the PPTBF value is above this"),
    ("complement", "boolean", "false", "swap white and black"),
    ("border", "boolean", "false", "cut the distance to the cell's border instead of the value (cut in its units)"),
)
#: the 8 neighbouring pixels (dx right, dy down) a ``pptbf_ring`` node evaluates: ring0 holds the first 4, ring1
#: the last 4 (the Sobel normal reads exactly these)
RING = ((-1, -1), (0, -1), (1, -1), (-1, 0), (1, 0), (-1, 1), (0, 1), (1, 1))
RING_OUTPUTS = ("ring0", "ring1")


def _param_type(spec: pp.ParamSpec) -> str:
    return "integer" if spec.kind == "disc" else "float"


def _param_default(spec: pp.ParamSpec) -> str:
    v = min(max(0.5 * (spec.lo + spec.hi), spec.lo), spec.hi)
    return str(int(spec.lo)) if spec.kind == "disc" else f"{v:g}"


PPTBF_PARAMS = tuple((s.name, _param_type(s), _param_default(s), f"PPTBF parameter ({s.kind}: {s.lo:g} to {s.hi:g})")
                     for s in pp.PARAM_SPECS)


@dataclass(frozen=True)
class NodeDef:
    """One node of the library: its nodedef and its GLSL implementation (``genglsl/<file>``, function
    ``mx_<node>_<type>``); ``generated``: the GLSL entry point is written by this module."""

    node: str
    type: str
    inputs: tuple
    doc: str
    generated: bool = False
    outputs: tuple = ("out",)       # several: a multi-output node, every output of ``type``

    @property
    def name(self) -> str:
        return f"ND_{self.node}_{self.type}"

    @property
    def function(self) -> str:
        return f"mx_{self.node}_{self.type}"

    @property
    def file(self) -> str:
        return f"genglsl/{self.function}.glsl"

    @property
    def osl_file(self) -> str:
        """The OSL implementation (``genosl/``: :mod:`workers.mtlx.osl`)."""
        return f"genosl/{self.function}.osl"


NODEDEFS = (
    NodeDef("pptbf", "float", PPTBF_PLACE + PPTBF_CUT + PPTBF_PARAMS,
            "Binary PPTBF mask (Guehl et al. 2020) of a proceduralize material", generated=True),
    NodeDef("pptbf_cells", "float", PPTBF_PLACE + PPTBF_PARAMS,
            "The PPTBF cell each pixel is in, as a key in [0, 1) (per-cell draws: cell_kind, cell_normal)",
            generated=True),
    NodeDef("pptbf_ring", "vector4", PPTBF_PLACE + PPTBF_CUT + (
        ("cells", "boolean", "false", "the cell keys instead of the mask"),) + PPTBF_PARAMS,
        "The pptbf (or pptbf_cells) node at the 8 neighbouring pixels of RING order, in one call: a shader that "
        "reads a mask around a pixel (normals from a height) compiles one PPTBF, not eight",
        generated=True, outputs=RING_OUTPUTS),
    NodeDef("tile_coords", "vector2", FRAME + (
        ("tile_size", "vector2", "1024.0, 1024.0", "pixels of the baked tile"),
        ("scale", "float", "1.0", "pattern scale: 2 = features twice as big")) + SEEDED,
        "Texture coordinates of a baked periodic tile, following size, scale and seed"),
    NodeDef("cell_kind", "float", (
        ("cells", "float", "0.0", "cell key (pptbf_cells)"), ("parent", "float", "1.0", "the area the kinds share"),
    ) + SEEDED + (("lo", "float", "0.0", "this kind's draws: from"), ("hi", "float", "1.0", "to (excluded)")),
        "1 where the pixel's cell drew this kind (an instance split), else 0"),
    NodeDef("cell_normal", "float", (("cells", "float", "0.0", "cell key (pptbf_cells)"),) + SEEDED + (
        ("k", "integer", "0", "which draw"),), "A standard normal draw per cell (per-piece offsets)"),
)


def _input_xml(name: str, typ: str, value: str | None, doc: str) -> str:
    val = ' defaultgeomprop="UV0"' if value is None else f" value={quoteattr(value)}"
    return f'    <input name="{name}" type="{typ}"{val} doc={quoteattr(doc)}/>'


def defs_text() -> str:
    """The nodedef document of the library (``proceduralize_defs.mtlx``)."""
    lines = ['<?xml version="1.0"?>',
             "<!-- proceduralize node library: generated by `python -m workers.mtlx.library`; do not edit -->",
             '<materialx version="1.39">']
    for nd in NODEDEFS:
        lines.append(f'  <nodedef name="{nd.name}" node="{nd.node}" nodegroup="texture2d" doc={quoteattr(nd.doc)}>')
        lines += [_input_xml(*i) for i in nd.inputs]
        lines += [f'    <output name="{o}" type="{nd.type}"/>' for o in nd.outputs] + ["  </nodedef>"]
    for nd in NODEDEFS:
        lines.append(f'  <implementation name="IM_{nd.node}_{nd.type}_genglsl" nodedef="{nd.name}" '
                     f'file="{nd.file}" function="{nd.function}" target="genglsl"/>')
        lines.append(f'  <implementation name="IM_{nd.node}_{nd.type}_genosl" nodedef="{nd.name}" '
                     f'file="{nd.osl_file}" function="{nd.function}" target="genosl"/>')
    lines += ["</materialx>", ""]
    return "\n".join(lines)


def _glsl_type(typ: str) -> str:
    return {"vector2": "vec2", "float": "float", "integer": "int", "boolean": "bool"}[typ]


def _pptbf_glsl(nd: NodeDef, body: str) -> str:
    """A PPTBF entry point: pixel -> base coordinates (x0, y0) and the parameter array prm, then ``body``."""
    outs = ["out float result"] if nd.outputs == ("out",) else [f"out vec4 {o}" for o in nd.outputs]
    sig = ",\n    ".join([f"{_glsl_type(t)} {n}" for n, t, _, _ in nd.inputs] + outs)
    prm = ", ".join(f"float({s.name})" if s.kind == "disc" else s.name for s in pp.PARAM_SPECS)
    return f"""// proceduralize: generated by `python -m workers.mtlx.library`; do not edit
// (the algorithm: lib/pptbf_core.glsl)
#include "lib/pptbf_core.glsl"
#include "lib/pz_seed.glsl"

void {nd.function}(
    {sig})
{{
    // the pixel (i, j) counted from the top-left as in proceduralize's maps, moved by offset pixels
    float i = texcoord.x * size.x - 0.5 + offset.x;
    float j = (1.0 - texcoord.y) * size.y - 0.5 + offset.y;
    vec2 s = shift + 8.0 * pz_seed_offset(seed, stream);
    float u = unit * scale;
    float x0 = i / u + s.x;
    float y0 = j / u + s.y;
    float prm[{pp.N_PARAMS}] = float[{pp.N_PARAMS}]({prm});
{body}
}}
"""


def pptbf_glsl_text() -> str:
    """The GLSL entry point of the ``pptbf`` node: the PPTBF value (or the border distance) against the stored
    cut."""
    return _pptbf_glsl(NODEDEFS[0], "    float key;\n"
                                    "    float v = pptbf_eval_field(x0, y0, ref_width, prm, border, key);\n"
                                    "    result = ((v > cut) != complement) ? 1.0 : 0.0;")


def pptbf_cells_glsl_text() -> str:
    """The GLSL entry point of the ``pptbf_cells`` node: the key of the closest point's cell."""
    return _pptbf_glsl(NODEDEFS[1], "    result = pptbf_cell(x0, y0, ref_width, prm);")


def pptbf_ring_glsl_text() -> str:
    """The GLSL entry point of the ``pptbf_ring`` node: one PPTBF evaluation in a loop over the RING pixels (a
    loop, not eight calls: the shader compiler inlines every call, and a PPTBF is a large function)."""
    dx = ", ".join(f"{d[0]:.1f}" for d in RING)
    dy = ", ".join(f"{d[1]:.1f}" for d in RING)
    return _pptbf_glsl(NODEDEFS[2], f"""    const float dx[8] = float[8]({dx});
    const float dy[8] = float[8]({dy});
    float r[8];
    int n = 8 + min(tiling, 0);          // 8, not known to the compiler: the loop stays one loop
    for (int k = 0; k < n; ++k) {{
        float key;
        float v = pptbf_eval_field((i + dx[k]) / u + s.x, (j + dy[k]) / u + s.y, ref_width, prm, border && !cells,
                                   key);
        r[k] = cells ? key : (((v > cut) != complement) ? 1.0 : 0.0);
    }}
    ring0 = vec4(r[0], r[1], r[2], r[3]);
    ring1 = vec4(r[4], r[5], r[6], r[7]);""")


def pptbf_tables_text() -> str:
    """The PPTBF's tables (``genglsl/lib/pptbf_tables.glsl``, see :mod:`workers.mtlx.tables`)."""
    from .tables import glsl_tables

    return glsl_tables()


GENERATED = {DEFS_FILE: defs_text, LIBRARY / NODEDEFS[0].file: pptbf_glsl_text,
             LIBRARY / NODEDEFS[1].file: pptbf_cells_glsl_text, LIBRARY / NODEDEFS[2].file: pptbf_ring_glsl_text,
             LIBRARY / "genglsl" / "lib" / "pptbf_tables.glsl": pptbf_tables_text}


def write_library() -> list[Path]:
    """Rewrite the generated library files (the OSL ones too: :func:`workers.mtlx.osl.write_osl_library`); returns
    those that changed."""
    from .osl import write_osl_library

    return write_osl_library() + write_generated(GENERATED)


def write_generated(files: dict) -> list[Path]:
    """Write each path of ``files`` (path -> function giving its text) whose text changed; returns those."""
    changed = []
    for path, make in files.items():
        text = make()
        if not path.exists() or path.read_text(encoding="utf-8") != text:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text, encoding="utf-8")
            changed.append(path)
    return changed


def main(argv: list[str] | None = None) -> int:
    """Command line: rewrite the generated files of the node library."""
    argparse.ArgumentParser(description="Rewrite the generated files of the proceduralize MaterialX node library "
                                        f"({DEFS_NAME}, the PPTBF nodes' GLSL and OSL entry points and the "
                                        "PPTBF's tables).").parse_args(argv)
    for p in write_library():
        print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
