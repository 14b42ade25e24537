"""A material graph as a procedural MaterialX node graph (``M_<name>_procedural``).

Every node of the graph becomes MaterialX nodes, one float value per channel (so any channel count maps):
the pointwise filters become standard nodes (multiply, add, clamp, divide, ifgreater, ...), the PPTBF masks our
``pptbf`` node (the node library of :mod:`workers.mtlx.library`), and what a shader cannot compute per pixel is
*baked*: evaluated by proceduralize at the exported size and seed and read back as a periodic tile through our
``tile_coords`` node. The noise generators are baked by design (they are FFT syntheses); other node types that
have no pointwise form (blurred blends, instance kinds, per-piece offsets, blurs, warps) are baked too and listed
in :attr:`ProceduralGraph.fixed`: those keep the exported realisation when the document's seed changes.

The node graph has three interface inputs: ``size`` (pixels the texture coordinates span; rendering that many
pixels reproduces proceduralize's render pixel for pixel), ``scale`` (pattern scale, as ``render --scale``) and
``seed`` (0 = the exported realisation; other values move the PPTBF masks and the tiles to other realisations).
A node type declares its MaterialX form in its module (``NodeType.materialx``); this module holds the builder
they call and the assembly of the maps and the material.
"""
from __future__ import annotations

import logging
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import GraphError
from ..graph import ProceduralMaterial, evaluate_node
from ..nodes import NODE_TYPES
from ..nodes.base import EvalContext

logger = logging.getLogger(__name__)

#: the float values of one node's channels in the document: (node, output name or "") per channel
Value = list


@dataclass(frozen=True)
class Chan:
    """One float-typed value in the node graph: a node's (named) output."""

    node: object
    output: str = ""


Offset = tuple[int, int]
NO_OFFSET: Offset = (0, 0)


@dataclass
class ProceduralGraph:
    """What :func:`build` made: the node graph, its outputs by map name, the tiles written, the baked nodes."""

    nodegraph: object
    outputs: dict[str, object]
    tiles: dict[str, Path]                  # image node name -> file
    baked: list[str] = field(default_factory=list)      # noise nodes (by design)
    fixed: list[str] = field(default_factory=list)      # other baked nodes: no pointwise form
    pinned: list[str] = field(default_factory=list)     # nodes kept at the exported realisation
    sobel: list[str] = field(default_factory=list)      # maps computed from a height's 8 neighbours (normals)


class Builder:
    """Builds one material's node graph: memoised per (graph node, pixel offset); the node types' ``materialx``
    hooks call back into it for their inputs, standard operations, constants and tiles."""

    def __init__(self, mat: ProceduralMaterial, doc, name: str, width: int, height: int, scale: float,
                 seed: int, tile_folder: Path, tile_prefix: str, force_bake: frozenset = frozenset()):
        self.mat, self.doc, self.name = mat, doc, name
        self.width, self.height = int(width), int(height)
        self.ctx = EvalContext(width=self.width, height=self.height, scale=float(scale) * mat.pattern_unit,
                               seed=int(seed), working_size=tuple(mat.working_size))
        self.tile_folder, self.tile_prefix = Path(tile_folder), tile_prefix
        self.force_bake = force_bake
        self.ng = doc.addNodeGraph(f"NG_{name}_procedural")
        self.size_in = self.ng.addInput("size", "vector2")
        self.size_in.setValueString(f"{self.width:.1f}, {self.height:.1f}")
        self.scale_in = self.ng.addInput("scale", "float")
        self.scale_in.setValue(1.0)
        self.seed_in = self.ng.addInput("seed", "integer")
        self.seed_in.setValue(0)
        self.memo: dict[tuple[str, Offset], Value] = {}
        self.shared: dict[tuple, object] = {}        # document nodes that several reads share (pptbf_ring)
        self.result = ProceduralGraph(self.ng, {}, {})
        self.tile_nodes: dict[str, list] = {}          # graph node id -> [image node, ...]
        self.seeded: list[tuple[str, object]] = []     # (graph node id, document node whose seed is the graph's)
        self._emitting: list[str] = []
        self.texcoord = self.ng.addNode("texcoord", "texcoord", "vector2")

    # ------------------------------------------------------------------ values
    def value(self, node_id: str, offset: Offset = NO_OFFSET) -> Value:
        """The channels of graph node ``node_id`` read ``offset`` pixels away (x right, y down)."""
        key = (node_id, offset)
        if key not in self.memo:
            n = self.mat.node(node_id)
            t = NODE_TYPES.get(n["type"])
            if t is None:
                raise GraphError(f"node {node_id!r} has unknown type {n['type']!r}")
            self._emitting.append(node_id)
            try:
                out = None if n["type"] in self.force_bake else t.materialx(self, n, node_id, offset)
                if out is None:
                    out = self.tile(node_id, offset, reason="fixed")
            finally:
                self._emitting.pop()
            self.memo[key] = list(out)
        return self.memo[key]

    def inputs(self, node: dict, offset: Offset) -> dict[str, Value]:
        """The node's inputs, each as its channels."""
        return {port: self.value(src, offset) for port, src in node["inputs"].items()}

    def numpy(self, node_id: str) -> np.ndarray:
        """The node's numpy output at the exported size and seed (HxWxC)."""
        return evaluate_node(self.mat, node_id, self.ctx)

    # ------------------------------------------------------------------ document nodes
    def node(self, category: str, typ: str, hint: str, **inputs) -> object:
        """A new node; inputs are numbers, strings, Chans (connected) or (type, value) pairs."""
        nd = self.ng.addNode(category, self.ng.createValidChildName(hint), typ)
        for name, v in inputs.items():
            self.set_input(nd, name, v)
            if isinstance(v, tuple) and v[0] == "interface" and v[1] is self.seed_in and self._emitting:
                self.seeded.append((self._emitting[-1], nd))
        return nd

    def set_input(self, nd, name: str, v) -> None:
        """Set or connect input ``name`` of ``nd``."""
        if isinstance(v, Chan):
            inp = nd.addInput(name, "float")
            inp.setConnectedNode(v.node)
            if v.output:
                inp.setOutputString(v.output)
        elif isinstance(v, tuple) and len(v) == 2 and isinstance(v[0], str):
            typ, val = v
            inp = nd.addInput(name, typ)
            if typ == "interface":
                inp.setType(val.getType())
                inp.setInterfaceName(val.getName())
            elif hasattr(val, "getCategory"):       # a node of that type
                inp.setConnectedNode(val)
            else:
                inp.setValueString(val if isinstance(val, str) else _value_string(val))
        elif isinstance(v, bool):
            nd.addInput(name, "boolean").setValue(v)
        elif isinstance(v, (int, float, np.floating, np.integer)):
            nd.addInput(name, "float").setValueString(_value_string(v))   # 9 digits: float32 exact
        else:
            raise GraphError(f"MaterialX export: cannot set input {name} to {v!r}")

    def op(self, category: str, hint: str, *args, **named) -> Chan:
        """A float node of a standard operation: inputs ``in`` (one argument), ``in1``, ``in2`` (two), or named."""
        if named:
            return Chan(self.node(category, "float", hint, **named))
        if len(args) == 1:
            return Chan(self.node(category, "float", hint, **{"in": args[0]}))
        return Chan(self.node(category, "float", hint, in1=args[0], in2=args[1]))

    def const(self, x: float, hint: str = "const") -> Chan:
        """A float constant."""
        return Chan(self.node("constant", "float", hint, value=float(x)))

    def once(self, key: tuple, make) -> object:
        """The document node ``make()`` built the first time ``key`` is asked for (one node for several reads)."""
        if key not in self.shared:
            self.shared[key] = make()
        return self.shared[key]

    def multi(self, category: str, hint: str, **inputs) -> object:
        """A new multi-output node (its outputs are read with :meth:`pick`)."""
        return self.node(category, "multioutput", hint, **inputs)

    def pick(self, nd, output: str, index: int, hint: str) -> Chan:
        """Channel ``index`` of the vector4 output ``output`` of a multi-output node."""
        ex = self.ng.addNode("extract", self.ng.createValidChildName(hint), "float")
        inp = ex.addInput("in", "vector4")
        inp.setConnectedNode(nd)
        inp.setOutputString(output)
        ex.addInput("index", "integer").setValue(int(index))
        return Chan(ex)

    def seed_stream(self, node_id: str) -> int:
        """The seed stream of a graph node (independent realisations per node)."""
        return int(zlib.crc32(node_id.encode("utf-8")) & 0x7FFFFFFF)

    # ------------------------------------------------------------------ tiles
    def tile(self, node_id: str, offset: Offset, reason: str) -> Value:
        """The node's numpy output baked into periodic RGBA float tiles (4 channels a file) and read back: noise
        (``reason="noise"``) with linear filtering, other nodes (``"fixed"``: masks, cell keys, kinds) with the
        closest texel (exact, never a blend of two keys)."""
        if node_id not in self.tile_nodes:
            arr = self.numpy(node_id)
            images = []
            for k in range(0, arr.shape[2], 4):
                part = arr[..., k:k + 4]
                if part.shape[2] < 4:
                    part = np.concatenate([part, np.zeros(part.shape[:2] + (4 - part.shape[2],), np.float32)], -1)
                images.append((self._write_tile(node_id, k // 4, part), min(4, arr.shape[2] - k)))
            self.tile_nodes[node_id] = images
            (self.result.baked if reason == "noise" else self.result.fixed).append(node_id)
        coords = self.node("tile_coords", "vector2", f"{node_id}_uv", texcoord=("vector2", self.texcoord),
                           offset=("vector2", f"{offset[0]:.1f}, {offset[1]:.1f}"),
                           size=("interface", self.size_in),
                           tile_size=("vector2", f"{self.width:.1f}, {self.height:.1f}"),
                           scale=("interface", self.scale_in), seed=("interface", self.seed_in),
                           stream=("integer", str(self.seed_stream(node_id))))
        chans: Value = []
        for path, n in self.tile_nodes[node_id]:
            img = self.node("image", "vector4", f"{node_id}_tile", texcoord=("vector2", coords),
                            uaddressmode=("string", "periodic"), vaddressmode=("string", "periodic"),
                            filtertype=("string", "linear" if reason == "noise" else "closest"))
            img.addInput("file", "filename").setValueString(path.relative_to(self.tile_folder.parent).as_posix())
            self.result.tiles[img.getName()] = path
            for c in range(n):
                chans.append(Chan(self.node("extract", "float", f"{node_id}_c{c}", **{
                    "in": ("vector4", img), "index": ("integer", str(c))})))
        return chans

    def _write_tile(self, node_id: str, part: int, rgba: np.ndarray) -> Path:
        from ..maps import output_file, write_image

        self.tile_folder.mkdir(parents=True, exist_ok=True)
        path = output_file(self.tile_folder, f"{self.tile_prefix}{node_id}_{part}", ".exr")
        write_image(path, rgba, bits="float")
        return path


def _value_string(v) -> str:
    if isinstance(v, (list, tuple, np.ndarray)):
        return ", ".join(f"{float(x):.9g}" for x in v)
    return f"{float(v):.9g}"



# ---------------------------------------------------------------------------------------------- assembly

#: MaterialX type of a map by channel count
MAP_TYPES = {1: "float", 3: "color3", 4: "color4"}


def _sobel(b: Builder, node_id: str, strength: Chan, tilt: tuple[float, float], sign: float) -> list:
    """(nx, ny, nz) of ``workers.height.height_to_normal`` from the height read at the 8 neighbouring pixels."""
    def h(dx: int, dy: int) -> Chan:
        return b.value(node_id, (dx, dy))[0]

    def diff(p, q, w):
        return b.op("multiply", "sobel", b.op("subtract", "sobel", h(*p), h(*q)), w)

    def total(*terms):
        out = terms[0]
        for t in terms[1:]:
            out = b.op("add", "sobel", out, t)
        return out

    gx = total(diff((1, -1), (-1, -1), 0.125), diff((1, 0), (-1, 0), 0.25), diff((1, 1), (-1, 1), 0.125))
    gy = total(diff((-1, 1), (-1, -1), 0.125), diff((0, 1), (0, -1), 0.25), diff((1, 1), (1, -1), 0.125))
    nx = b.op("multiply", "normal_x", b.op("add", "sobel", b.op("multiply", "sobel", gx, strength), tilt[0]), -1.0)
    ny = b.op("multiply", "normal_y", b.op("add", "sobel", b.op("multiply", "sobel", gy, strength), tilt[1]), sign)
    vec = b.node("combine3", "vector3", "normal_raw", in1=nx, in2=ny, in3=1.0)
    return b.node("normalize", "vector3", "normal", **{"in": ("vector3", vec)})


def build(mat: ProceduralMaterial, doc, name: str, width: int, height: int, *, tile_folder: Path,
          tile_prefix: str = "", scale: float = 1.0, seed: int | None = None,
          force_bake: frozenset = frozenset()) -> ProceduralGraph:
    """Add ``NG_<name>_procedural`` (the material's maps as node graph outputs) to ``doc``; tiles go to
    ``tile_folder``. The realisation is the material's at ``seed`` (default its own) and ``scale``; ``size`` =
    width x height. ``force_bake``: node types to bake even where they have a pointwise form (checks)."""
    from ..height import _check_convention

    b = Builder(mat, doc, name, width, height, scale, mat.seed if seed is None else seed, tile_folder, tile_prefix,
                force_bake)
    outs = b.result.outputs
    values = {}
    for m in mat.maps:
        if "node" not in m:
            continue
        chans = b.value(m["node"])
        if m.get("clamp", True) and m["name"] != "height":
            chans = [b.op("clamp", f"{m['name']}_clamp", c) for c in chans]
        values[m["name"]] = chans
        typ = MAP_TYPES.get(len(chans))
        if typ is None:
            raise GraphError(f"map {m['name']!r} has {len(chans)} channels: no MaterialX type")
        node = chans[0].node if typ == "float" else b.node(
            f"combine{len(chans)}", typ, m["name"], **{f"in{i + 1}": c for i, c in enumerate(chans)})
        outs[m["name"]] = _output(b, m["name"], typ, node)
    for m in mat.maps:
        if "from_height" not in m:
            continue
        src = next(mm for mm in mat.maps if mm["name"] == m["from_height"])
        strength = b.op("multiply", "normal_strength", float(m.get("strength", 1.0)) * mat.pattern_unit,
                        ("interface", b.scale_in))
        sign = _check_convention(m.get("convention", "opengl"))
        nrm = _sobel(b, src["node"], strength, tuple(float(t) for t in m.get("tilt", (0.0, 0.0))), sign)
        b.result.sobel.append(m["name"])
        outs[m["name"]] = _output(b, m["name"], "vector3", nrm)
        enc = b.node("add", "vector3", "normal_encoded", in1=("vector3", b.node(
            "multiply", "vector3", "normal_half", in1=("vector3", nrm), in2=0.5)), in2=0.5)
        outs[f"{m['name']}_encoded"] = _output(b, f"{m['name']}_encoded", "vector3", enc)
        if m["name"] == "normal":
            shading = b.node("normalmap", "vector3", "normalmap", **{"in": ("vector3", enc)})
            outs["shading_normal"] = _output(b, "shading_normal", "vector3", shading)
    _pin(b)
    return b.result


def _output(b: Builder, name: str, typ: str, node) -> object:
    out = b.ng.addOutput(b.ng.createValidChildName(f"out_{name}"), typ)
    out.setConnectedNode(node)
    return out


def _upstream(mat: ProceduralMaterial, node_id: str) -> set[str]:
    seen, todo = set(), [node_id]
    while todo:
        n = todo.pop()
        for src in mat.node(n)["inputs"].values():
            if src not in seen:
                seen.add(src)
                todo.append(src)
    return seen


def _pin(b: Builder) -> None:
    """Nodes that a baked node reads keep the exported realisation: their ``seed`` input becomes 0, so that the
    document's seed cannot move them away from what the tiles hold (a PPTBF mask under a baked blurred blend,
    the kinds of its cells)."""
    used = set().union(*(_upstream(b.mat, n) for n in b.result.fixed)) if b.result.fixed else set()
    for node_id, nd in b.seeded:
        if node_id in used:
            inp = nd.getInput("seed")
            inp.removeAttribute("interfacename")
            inp.setValue(0)
            if node_id not in b.result.pinned:
                b.result.pinned.append(node_id)


#: the node library's folder name beside an exported document (the document XIncludes it relatively)
LIBRARY_DIRNAME = "proceduralize_library"


def copy_library(folder: Path) -> Path:
    """Copy the node library (nodedefs, GLSL and OSL) to ``folder / LIBRARY_DIRNAME``; returns that folder."""
    import shutil

    from .library import LIBRARY

    dst = Path(folder) / LIBRARY_DIRNAME
    shutil.copytree(LIBRARY, dst, dirs_exist_ok=True, ignore=shutil.ignore_patterns("__pycache__"))
    return dst


def add_material(doc, mat: ProceduralMaterial, name: str, width: int, height: int, folder: Path, *,
                 seed: int | None = None, scale: float = 1.0) -> ProceduralGraph:
    """Add ``M_<name>_procedural`` (a standard_surface over the procedural node graph) to ``doc``, which will be
    written in ``folder``: the node library is copied beside it and XIncluded, the tiles go to ``<name>_tiles/``."""
    import MaterialX as mx

    from .library import DEFS_NAME

    copy_library(folder)
    mx.prependXInclude(doc, f"{LIBRARY_DIRNAME}/{DEFS_NAME}")
    r = build(mat, doc, name, width, height, tile_folder=Path(folder) / f"{name}_tiles", tile_prefix=f"{name}_",
              seed=seed, scale=scale)
    ss = doc.addNode("standard_surface", f"SR_{name}_procedural", "surfaceshader")
    ss.addInput("base", "float").setValue(1.0)
    for port, key, typ in (("base_color", "albedo", "color3"), ("specular_roughness", "roughness", "float"),
                           ("normal", "shading_normal", "vector3"), ("metalness", "metallic", "float")):
        out = r.outputs.get(key)
        if out is not None and out.getType() == typ:
            i = ss.addInput(port, typ)
            i.setNodeGraphString(r.nodegraph.getName())
            i.setOutputString(out.getName())
    doc.addMaterialNode(f"M_{name}_procedural", ss)
    logger.info("procedural MaterialX %s: %d tiles (noise: %d, baked other nodes: %s; pinned PPTBF: %s)", name,
                len(r.tiles), len(r.baked), ", ".join(r.fixed) or "none", ", ".join(r.pinned) or "none")
    return r
