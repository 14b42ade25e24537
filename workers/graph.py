"""The procedural material: a versioned JSON graph of generator and filter nodes.

File layout (``material.json``)::

    {"format": "proceduralize/1.1",
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

Nodes are evaluated lazily from the map outputs. Arrays inside params are stored compactly with
:func:`encode_array` (base64 float16/float32/uint8), never pickled, and never hold input pixels.
Stages register new node types with :func:`register_node`.
"""
from __future__ import annotations

import base64
import copy
import json
import re
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol

import numpy as np
from scipy import ndimage

from .errors import GraphError

FORMAT = "proceduralize/1.1"   # 1.1 adds "input_size" (scale 1 = the input's pattern size)
NORMALISE_EPS = 1e-6   # floor of the mask sum a normalised blend divides by
SUPPORTED_FORMATS = ("proceduralize/1", FORMAT)
#: the most bytes one encoded array of a material file may inflate to (real ones are a few KB)
MAX_ARRAY_BYTES = 16 * 2**20
#: pattern scales ``evaluate`` accepts (1/64 .. 64): the scale multiplies every spatial size in the graph
MIN_SCALE, MAX_SCALE = 1.0 / 64.0, 64.0
#: the largest blur sigma (working-size pixels) a file may hold
MAX_SIGMA = 1e4
#: a map output's name (it becomes ``<name>.png``): albedo, normal, roughness, height, metallic, ...
MAP_NAME = re.compile(r"^[a-z][a-z0-9_]{0,31}$")
#: channel counts the known maps may have (renderers, exporters and PNG writers rely on them); other names any
MAP_CHANNELS: dict[str, tuple[int, ...]] = {"albedo": (1, 3), "normal": (3,), "roughness": (1,), "height": (1,),
                                            "metallic": (1,)}


# ----------------------------------------------------------------------------- arrays


def encode_array(a: np.ndarray, dtype: str = "float16") -> dict:
    """Encode an array as a small JSON object (zlib-compressed base64 of a fixed dtype)."""
    arr = np.ascontiguousarray(np.asarray(a), dtype=np.dtype(dtype))
    return {
        "__array__": True,
        "dtype": str(arr.dtype),
        "shape": list(arr.shape),
        "data": base64.b64encode(zlib.compress(arr.tobytes(), 6)).decode("ascii"),
    }


def decode_array(obj: Any) -> np.ndarray:
    """Decode an object written by :func:`encode_array` (plain lists are accepted too) to float32/int. The
    declared size is checked against MAX_ARRAY_BYTES before anything is inflated, and inflation stops there."""
    if isinstance(obj, dict) and obj.get("__array__"):
        try:
            dtype = np.dtype(obj["dtype"])
            shape = [int(n) for n in obj["shape"]]
            if dtype.kind not in "fiub" or any(n < 0 for n in shape) or len(shape) > 8:
                raise ValueError(f"dtype {dtype} / shape {shape} not allowed")
            nbytes = int(np.prod(shape, dtype=np.float64)) * dtype.itemsize
            if nbytes > MAX_ARRAY_BYTES:
                raise ValueError(f"declares {nbytes / 2**20:.0f} MiB, more than the {MAX_ARRAY_BYTES >> 20} MiB "
                                 "an array of a material file may hold")
            z = zlib.decompressobj()
            raw = z.decompress(base64.b64decode(obj["data"]), nbytes + 1)
            if len(raw) != nbytes or z.unconsumed_tail:
                raise ValueError(f"data does not match its declared shape {shape} ({dtype})")
            arr = np.frombuffer(raw, dtype=dtype).reshape(shape)
        except Exception as exc:  # noqa: BLE001 - any corruption is a GraphError
            raise GraphError(f"corrupt array in material file: {exc}") from None
        return arr.astype(np.float32) if arr.dtype.kind == "f" else arr.copy()
    return np.asarray(obj, dtype=np.float32)


# ----------------------------------------------------------------------------- evaluation context


@dataclass
class EvalContext:
    """What every node needs to render itself: output extent, pattern scale and randomness."""

    width: int
    height: int
    scale: float = 1.0
    seed: int = 0
    working_size: tuple[int, int] = (512, 512)
    cache: dict = field(default_factory=dict)

    def rng(self, node_id: str, stream: int = 0) -> np.random.Generator:
        """A generator that depends only on (seed, node id, stream): deterministic, independent per node."""
        key = zlib.crc32(node_id.encode("utf-8"))
        return np.random.default_rng(np.random.SeedSequence([int(self.seed) & 0xFFFFFFFF, key, stream]))

    def node_seed(self, node_id: str) -> int:
        """An integer seed for node ``node_id`` derived from the material seed."""
        return int(self.rng(node_id, 99).integers(0, 2**31 - 1))

    @property
    def px_scale(self) -> float:
        """Output pixels per working-size pixel of pattern (scale=2 -> features twice as many pixels)."""
        return float(self.scale)


class NodeType(Protocol):
    """A node type: validates its params and renders an HxWxC float32 array."""

    name: str
    inputs: tuple[str, ...]

    def validate(self, params: dict) -> None: ...

    def evaluate(self, params: dict, inputs: dict[str, np.ndarray], ctx: EvalContext, node_id: str) -> np.ndarray: ...


NODE_TYPES: dict[str, NodeType] = {}


def register_node(cls: type) -> type:
    """Class decorator: register a node type (instantiated once) under ``cls.name``."""
    inst = cls()
    if not getattr(inst, "name", None):
        raise TypeError(f"node type {cls.__name__} has no name")
    NODE_TYPES[inst.name] = inst
    return cls


def _ensure_builtin_types_loaded() -> None:
    """Import stage modules that register node types (kept lazy to avoid import cycles)."""
    import importlib

    for mod in ("workers.noise", "workers.masks", "workers.pieces"):
        try:
            importlib.import_module(mod)
        except ModuleNotFoundError as exc:
            if exc.name != mod:
                raise


def _numbers(value: Any, field: str) -> np.ndarray:
    """A parameter as a 1-D float array; GraphError naming `field` when it is not numbers (a string, a dict)."""
    try:
        return np.atleast_1d(np.asarray(value, dtype=np.float64))
    except (TypeError, ValueError, OverflowError):
        raise GraphError(f"{field} must be a number or a list of numbers, got {value!r}") from None


def _as3(a: np.ndarray) -> np.ndarray:
    """View a 2-D array as HxWx1."""
    return a[..., None] if a.ndim == 2 else a


# ----------------------------------------------------------------------------- built-in nodes


@register_node
class ConstantNode:
    """A constant value (scalar or per channel) over the whole map."""

    name = "constant"
    inputs: tuple[str, ...] = ()

    def validate(self, params: dict) -> None:
        v = _numbers(params.get("value"), "constant.value")
        if v.ndim != 1 or v.size == 0 or not np.all(np.isfinite(v)):
            raise GraphError("constant.value must be a finite number or list of numbers")

    def evaluate(self, params, inputs, ctx, node_id):
        v = np.atleast_1d(np.asarray(params["value"], dtype=np.float32))
        return np.broadcast_to(v, (ctx.height, ctx.width, v.size)).copy()


@register_node
class LevelNode:
    """Affine level filter ``x * a + d`` (per channel or scalar a, d), optional clamp to [0,1]."""

    name = "level"
    inputs = ("input",)

    def validate(self, params: dict) -> None:
        for k in ("a", "d"):
            v = _numbers(params.get(k, 1.0 if k == "a" else 0.0), f"level.{k}")
            if not np.all(np.isfinite(v)):
                raise GraphError(f"level.{k} must be finite")

    def evaluate(self, params, inputs, ctx, node_id):
        x = inputs["input"]
        a = np.asarray(params.get("a", 1.0), dtype=np.float32)
        d = np.asarray(params.get("d", 0.0), dtype=np.float32)
        y = x * a + d
        if params.get("clamp", False):
            y = np.clip(y, 0.0, 1.0)
        return y.astype(np.float32)


def gaussian_blur(x: np.ndarray, sigma: float) -> np.ndarray:
    """Periodic (wrap) Gaussian blur over the two spatial axes; sigma in output pixels."""
    if sigma <= 1e-3:
        return x
    if sigma >= max(x.shape[0], x.shape[1]):  # the periodic blur is the mean to within exp(-2 pi^2) ~ 3e-9
        return np.broadcast_to(x.mean(axis=(0, 1), keepdims=True), x.shape).astype(np.float32)
    s = (sigma, sigma, 0) if x.ndim == 3 else (sigma, sigma)
    return ndimage.gaussian_filter(x, s, mode="wrap").astype(np.float32)


@register_node
class BlurNode:
    """Gaussian blur; sigma is in working-size pixels and follows the pattern scale."""

    name = "blur"
    inputs = ("input",)

    def validate(self, params: dict) -> None:
        s = params.get("sigma", 0.0)
        if not isinstance(s, (int, float)) or isinstance(s, bool) or not np.isfinite(s) or not 0 <= s <= MAX_SIGMA:
            raise GraphError(f"blur.sigma must be a number from 0 to {MAX_SIGMA:g}")

    def evaluate(self, params, inputs, ctx, node_id):
        return gaussian_blur(inputs["input"], float(params.get("sigma", 0.0)) * ctx.px_scale)


@register_node
class BlendNode:
    """Mask blend. Inputs ``mask0, child0, mask1, child1, ...`` give ``sum_i blur(mask_i; sigma_i) * child_i``
    (params ``sigmas``: per-mask blur in working-size pixels, default 0); with ``normalise: true`` that sum is
    divided by ``sum_i blur(mask_i; sigma_i)``, so the blurred masks of a partition keep summing to 1 whatever
    their sigmas (every pixel is one child's value, or a convex mix across a blurred edge). Inputs
    ``mask, fg, bg`` give ``m*fg + (1-m)*bg`` with ``m = blur(mask; sigma)``."""

    name = "blend"
    inputs = ("*",)

    def validate(self, params: dict) -> None:
        sig = params.get("sigmas", [])
        if not isinstance(sig, list) or any(not isinstance(s, (int, float)) or s < 0 for s in sig):
            raise GraphError("blend.sigmas must be a list of numbers >= 0")
        if not isinstance(params.get("normalise", False), bool):
            raise GraphError("blend.normalise must be true or false")

    def evaluate(self, params, inputs, ctx, node_id):
        sig = list(params.get("sigmas", []))
        if "mask" in inputs:
            m = gaussian_blur(_as3(inputs["mask"])[..., :1], float(params.get("sigma", 0.0)) * ctx.px_scale)
            return (m * inputs["fg"] + (1.0 - m) * inputs["bg"]).astype(np.float32)
        i, out, total = 0, None, None
        while f"mask{i}" in inputs:
            s = float(sig[i]) if i < len(sig) else 0.0
            m = gaussian_blur(_as3(inputs[f"mask{i}"])[..., :1], s * ctx.px_scale)
            term = m * inputs[f"child{i}"]
            out = term if out is None else out + term
            total = m if total is None else total + m
            i += 1
        if out is None:
            raise GraphError(f"blend node {node_id} has no inputs (need mask/fg/bg or mask0/child0...)")
        if params.get("normalise", False):
            out = out / np.maximum(total, NORMALISE_EPS)
        return out.astype(np.float32)


@register_node
class ChannelNode:
    """Pick channels ``channels`` (list of indices) of the input (e.g. one cluster of an instance map)."""

    name = "channel"
    inputs = ("input",)

    def validate(self, params: dict) -> None:
        ch = params.get("channels")
        if not isinstance(ch, list) or not ch or not all(isinstance(c, int) and c >= 0 for c in ch):
            raise GraphError("channel.channels must be a non-empty list of channel indices")

    def evaluate(self, params, inputs, ctx, node_id):
        x = inputs["input"]
        if max(params["channels"]) >= x.shape[2]:
            raise GraphError(f"channel node {node_id}: input has {x.shape[2]} channels")
        return x[..., params["channels"]].astype(np.float32)


@register_node
class AddNode:
    """Sum of all inputs (e.g. noise layers plus base colour)."""

    name = "add"
    inputs = ("*",)

    def validate(self, params: dict) -> None:
        pass

    def evaluate(self, params, inputs, ctx, node_id):
        if not inputs:
            raise GraphError(f"add node {node_id} has no inputs")
        vals = [inputs[k] for k in sorted(inputs)]
        out = vals[0].astype(np.float32).copy()
        for v in vals[1:]:
            out = out + v
        return out


@register_node
class ClampNode:
    """Clamp to [lo, hi] (default [0, 1])."""

    name = "clamp"
    inputs = ("input",)

    def validate(self, params: dict) -> None:
        pass

    def evaluate(self, params, inputs, ctx, node_id):
        return np.clip(inputs["input"], params.get("lo", 0.0), params.get("hi", 1.0)).astype(np.float32)


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


def from_json(doc: Any, source: str = "<material>") -> ProceduralMaterial:
    """Validate a parsed JSON document and build a :class:`ProceduralMaterial`."""
    _ensure_builtin_types_loaded()
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
    if fmt == "proceduralize/1" and "input_size" in doc:
        raise GraphError(f"{source}: 'input_size' needs format {FORMAT!r} (format {fmt!r} draws scale 1 at the "
                         f"working size's pattern)")
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
    tmp = p.with_suffix(p.suffix + ".tmp")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_text(json.dumps(doc, indent=1), encoding="utf-8")
        tmp.replace(p)
    except OSError as exc:
        tmp.unlink(missing_ok=True) if tmp.parent.is_dir() else None
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
    out = _as3(np.asarray(t.evaluate(n["params"], inputs, ctx, node_id), dtype=np.float32))
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
            from .height import height_to_normal

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
    cur: Any = node["params"]
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
        if last not in cur and not last.startswith("_"):
            raise GraphError(f"parameter path {path!r}: node {parts[0]!r} has no parameter {last!r} "
                             f"(has: {sorted(cur)})")
        cur[last] = value
    t = NODE_TYPES[node["type"]]
    try:
        t.validate(node["params"])
    except (TypeError, ValueError, OverflowError) as exc:
        raise GraphError(f"node {parts[0]!r}: {exc}") from None


Evaluator = Callable[[dict, dict, EvalContext, str], np.ndarray]
