"""Per-stage glue the scheduler runs on workers: read the previous stages' files, call the pure stage, write results.

Every stage call is a plain dict (``StageCall.to_dict``) and returns a plain dict::

    {"artefacts": [{"path": <relative to the job output>, "kind", "checksum", "bytes"}],
     "info": {...}, "worker": "host:pid", "started", "finished", "duration"}

Results are files (npz without pickles, JSON, PNG), each written atomically (tmp + rename) before the call
returns, so the driver can record them and a rerun can skip them. No Ray and no SQLite here.
"""
from __future__ import annotations

import contextlib
import importlib.util
import json
import logging
import os
import signal
import socket
import threading
import time
from dataclasses import asdict, dataclass, field, is_dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from workers.errors import InputError

logger = logging.getLogger(__name__)

STAGES = ("load", "decompose", "noise", "masks", "recompose", "output")
DEPENDS = {"load": (), "decompose": ("load",), "noise": ("decompose",), "masks": ("decompose",),
           "recompose": ("noise", "masks"), "output": ("recompose",)}
NOISE_MAPS = ("albedo", "height", "roughness", "metallic")


class StageUnavailable(RuntimeError):
    """A stage's module is not installed / not written yet."""


class StageTimeout(RuntimeError):
    """A stage item ran longer than the job's ``stage_timeout`` (not retried: it would time out again)."""


@contextlib.contextmanager
def time_limit(seconds: float | None, what: str) -> Iterator[None]:
    """Raise StageTimeout in this thread after ``seconds`` of wall time (SIGALRM; main thread only, which is
    where Ray runs tasks and single-threaded actor calls). A C call that never returns to Python is not
    interrupted; the timer fires as soon as it does."""
    if not seconds or threading.current_thread() is not threading.main_thread() or not hasattr(signal, "SIGALRM"):
        yield
        return

    def expire(signum, frame):
        raise StageTimeout(f"{what} ran longer than {seconds:g} s (job.stage_timeout); cancelled")

    old = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, float(seconds))
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


@dataclass
class StageCall:
    """Everything a worker needs for one stage item (JSON-able)."""

    job: str
    root: str
    material: dict
    stage: str
    item: str = ""
    debug: dict = field(default_factory=dict)
    timeout: float | None = None
    memory_budget: int | None = None   # bytes; None: the worker's default (half its machine's memory)

    def to_dict(self) -> dict:
        return asdict(self)


def required_modules(stage: str, material: dict) -> list[str]:
    """Modules a stage needs for this material (decompose mode 'none' needs only workers.tree)."""
    if stage == "decompose":
        return ["workers.tree"] if material.get("decompose", {}).get("mode", "auto") == "none" else [
            "workers.decompose"]
    return {"load": ["workers.maps"], "noise": ["workers.noise"], "masks": ["workers.masks", "pptbf_db.index"],
            "recompose": ["workers.recompose"], "output": ["workers.graph"]}[stage]


def missing_modules(stage: str, material: dict) -> list[str]:
    """Required modules of a stage that cannot be found (checked without importing them)."""
    out = []
    for mod in required_modules(stage, material):
        try:
            found = importlib.util.find_spec(mod) is not None
        except (ImportError, ValueError):
            found = False
        if not found:
            out.append(mod)
    return out


# ----------------------------------------------------------------------------- files


def material_dir(call: dict) -> Path:
    """The material's folder inside the job output."""
    return Path(call["root"]) / call["material"]["output"]


def _tmp(path: Path) -> Path:
    return path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")


def write_json(path: Path, doc: Any) -> Path:
    """Atomic JSON write."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp(path)
    tmp.write_text(json.dumps(doc, indent=1, default=_json_default), encoding="utf-8")
    tmp.replace(path)
    return path


def write_npz(path: Path, arrays: dict[str, np.ndarray]) -> Path:
    """Atomic npz write (plain arrays, never object arrays)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp(path)
    with open(tmp, "wb") as f:
        np.savez_compressed(f, **{k: np.ascontiguousarray(v) for k, v in arrays.items()})
    tmp.replace(path)
    return path


def read_npz(path: Path) -> dict[str, np.ndarray]:
    """Read an npz written by :func:`write_npz` (pickles refused)."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing stage result (was the previous stage run?)")
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, Path):
        return str(o)
    if is_dataclass(o):
        return asdict(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def artefact(root: str | Path, path: Path, kind: str) -> dict:
    """Artefact record of a written file: path relative to the job output, checksum, size."""
    from service.store import file_checksum

    return {"path": str(Path(path).resolve().relative_to(Path(root).resolve())), "kind": kind,
            "checksum": file_checksum(path), "bytes": Path(path).stat().st_size}


def safe_name(text: str) -> str:
    """A file-name-safe version of an item id."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in text)


# ----------------------------------------------------------------------------- reading previous stages


def load_working_material(mdir: Path):
    """The working-size Material written by the load stage."""
    from workers.maps import Material

    arrays = read_npz(mdir / "load" / "maps.npz")
    meta = json.loads((mdir / "load" / "material.json").read_text(encoding="utf-8"))
    return Material(albedo=arrays["albedo"], normal=arrays.get("normal"), roughness=arrays.get("roughness"),
                    height=arrays.get("height"), metallic=arrays.get("metallic"), name=meta["name"],
                    sources=meta.get("sources", {}), height_scale=float(meta.get("height_scale", 1.0)),
                    meta=meta.get("meta", {}), normal_tilt=tuple(meta.get("normal_tilt", (0.0, 0.0))))


def load_tree(mdir: Path):
    """The decomposition tree (MaskNode) written by the decompose stage."""
    from workers.tree import MaskNode

    arrays = read_npz(mdir / "decompose" / "masks.npz")
    doc = json.loads((mdir / "decompose" / "tree.json").read_text(encoding="utf-8"))

    def build(d: dict) -> MaskNode:
        key = safe_name(d["id"])
        meta = {k: arrays[v["npz"]] if isinstance(v, dict) and set(v) == {"npz"} else v
                for k, v in d.get("meta", {}).items()}
        return MaskNode(id=d["id"], mask=arrays[f"mask_{key}"].astype(bool), method=d.get("method", "leaf"),
                        children=[build(c) for c in d.get("children", [])], shares=d.get("shares"),
                        alpha=arrays.get(f"alpha_{key}"), meta=meta)

    return build(doc["tree"])


def tree_info(tree) -> dict:
    """What the driver needs to plan the next stages: node ids, leaves, parents, split methods."""
    parents = {c.id: n.id for n in tree.walk() for c in n.children}
    # masks to fit: every child of a matting split but the last (the last is 1 - the others); instance splits
    # need no fit (their clusters are drawn from the recorded shares)
    fit = [c.id for n in tree.walk() if n.children and n.method != "instances" for c in n.children[:-1]]
    return {"nodes": [n.id for n in tree.walk()], "leaves": [n.id for n in tree.leaves()], "parents": parents,
            "fit_masks": fit,
            "methods": {n.id: n.method for n in tree.walk()},
            "coverage": {n.id: round(float(np.mean(n.mask)), 4) for n in tree.walk()}}


def _find(tree, node_id: str):
    for n in tree.walk():
        if n.id == node_id:
            return n
    raise KeyError(f"no node {node_id!r} in the decomposition tree")


def _config(cls: Any, options: dict, where: str) -> Any:
    """Build a stage config dataclass from manifest options, naming unknown keys."""
    if cls is None:
        return None
    try:
        return cls(**options)
    except TypeError as exc:
        raise InputError(f"manifest {where}: {exc}") from None


def _to_jsonable(x: Any) -> Any:
    """Stage results (dataclasses, arrays) -> JSON-able dicts."""
    for meth in ("to_params", "to_json", "to_dict"):
        if hasattr(x, meth):
            return json.loads(json.dumps(getattr(x, meth)(), default=_json_default))
    return json.loads(json.dumps(x, default=_json_default))


# ----------------------------------------------------------------------------- stages


def stage_load(call: dict, resources: Any = None) -> dict:
    """Read and validate the maps, write them at working size (npz for the next stages, PNG for people)."""
    from workers.maps import load_material, save_material

    from workers import budget
    from workers.maps import image_header, working_size_for

    m = call["material"]
    maps = m["maps"]
    ch = {k: maps[k].get("channel") for k in maps}
    ws = m.get("working_size")
    ws = tuple(ws) if isinstance(ws, list) else ws
    sizes = [image_header(maps[k]["file"]) for k in maps]  # headers only: refuse before decoding anything
    w0, h0 = sizes[0][:2]
    try:
        tw, th = working_size_for(ws, w0, h0)
    except InputError as exc:
        raise InputError(f"{maps['albedo']['file']}: {exc}") from None
    limit = budget.budget(call.get("memory_budget"))
    budget.check(f"loading {maps['albedo']['file']} ({w0}x{h0}) at working size {tw}x{th}",
                 budget.load_bytes(sizes, (tw, th)), limit)
    budget.check(f"fitting material {m['name']!r} at working size {tw}x{th}", budget.fit_bytes(tw, th), limit)
    mat = load_material(
        maps["albedo"]["file"], *(maps[k]["file"] if k in maps else None for k in
                                  ("normal", "roughness", "height", "metallic")),
        roughness_channel=ch.get("roughness"), metallic_channel=ch.get("metallic"),
        albedo_colorspace=m.get("albedo_colorspace", "srgb"), normal_convention=m.get("normal_convention", "opengl"),
        working_size=ws, name=m["name"])
    out = material_dir(call) / "load"
    arrays = {k: v.astype(np.float32) for k, v in mat.maps().items()}
    files = [write_npz(out / "maps.npz", arrays)]
    meta = {"name": mat.name, "size": list(mat.size), "height_scale": mat.height_scale,
            "normal_tilt": list(mat.normal_tilt), "sources": mat.sources, "meta": mat.meta,
            "maps": sorted(arrays)}
    files.append(write_json(out / "material.json", meta))
    pngs = save_material(mat, out / "maps")
    files += [p for p in pngs.values()]
    return {"files": files, "info": {"size": list(mat.size), "maps": sorted(arrays),
                                     "height_scale": mat.height_scale,
                                     "original_size": mat.meta.get("original_size")}}


def _with_scribble_images(spec: dict, shape: tuple[int, int]) -> dict:
    """Copy of a decomposition spec with every scribble file read and resized (nearest) to the working size."""
    from workers.maps import read_image

    out = dict(spec)
    if isinstance(out.get("scribbles"), str):
        img = read_image(out["scribbles"])
        h0, w0 = img.shape[:2]
        if (h0, w0) != tuple(shape):  # nearest neighbour keeps the flat scribble colours
            rows = (np.arange(shape[0]) * h0) // shape[0]
            cols = (np.arange(shape[1]) * w0) // shape[1]
            img = img[rows][:, cols]
        out["scribbles"] = img
    if isinstance(out.get("children"), dict):
        out["children"] = {k: _with_scribble_images(c, shape) if isinstance(c, dict) else c
                           for k, c in out["children"].items()}
    return out


def stage_decompose(call: dict, resources: Any = None) -> dict:
    """Build the decomposition tree (root only for mode 'none'); write masks (npz + PNG) and tree.json."""
    from workers.maps import write_image
    from workers.tree import root_node

    m = call["material"]
    mdir = material_dir(call)
    mat = load_working_material(mdir)
    spec = dict(m.get("decompose", {"mode": "auto"}))
    mode = spec.pop("mode", "auto")
    w, h = mat.size
    if mode == "none":
        tree = root_node(h, w)
    else:
        from workers.decompose import decompose

        tree = decompose(mat, _with_scribble_images(spec, (h, w)), seed=int(m.get("seed", 0)))
    out = mdir / "decompose"
    arrays: dict[str, np.ndarray] = {}

    def doc(n) -> dict:
        key = safe_name(n.id)
        arrays[f"mask_{key}"] = np.asarray(n.mask, dtype=np.uint8)
        if n.alpha is not None:
            arrays[f"alpha_{key}"] = np.asarray(n.alpha, dtype=np.float32)
        meta = {}
        for k, v in n.meta.items():  # large arrays (instance labels...) go to the npz, not the JSON
            if isinstance(v, np.ndarray) and v.size > 64:
                arrays[f"meta_{key}__{safe_name(k)}"] = v
                meta[k] = {"npz": f"meta_{key}__{safe_name(k)}"}
            else:
                meta[k] = v
        return {"id": n.id, "method": n.method, "shares": n.shares, "meta": _to_jsonable(meta),
                "children": [doc(c) for c in n.children]}

    tree_doc = {"tree": doc(tree), "summary": tree.describe()}
    files = [write_npz(out / "masks.npz", arrays), write_json(out / "tree.json", tree_doc)]
    for n in tree.walk():
        files.append(write_image(out / "masks" / f"{safe_name(n.id)}.png", n.mask.astype(np.float32)))
    return {"files": files, "info": tree_info(tree)}


def stage_noise(call: dict, resources: Any = None) -> dict:
    """Fit the multi-layer noise model of one (leaf, map) item; write its parameters as JSON. A kind of an
    instance split is fitted on its within-piece residual, and the spread of its pieces' means is written beside
    (``pieces``, workers.pieces)."""
    from workers import noise
    from workers.pieces import kind_piece_labels, piece_residual

    leaf_id, map_name = call["item"].rsplit("/", 1)
    mdir = material_dir(call)
    mat = load_working_material(mdir)
    tree = load_tree(mdir)
    leaf = _find(tree, leaf_id)
    image = mat.maps()[map_name]
    cfg = _config(noise.NoiseConfig, call["material"].get("noise", {}), "noise")
    parent = _find(tree, tree_info(tree)["parents"][leaf_id]) if leaf_id != tree.id else None
    doc: dict = {"leaf": leaf_id, "map": map_name}
    if map_name in cfg.per_piece and parent is not None and parent.method == "instances" and \
            "instance_labels" in parent.meta:
        lab = kind_piece_labels(parent.meta["instance_labels"], parent.meta["instance_kinds"],
                                [c.id for c in parent.children].index(leaf_id))
        image, stats = piece_residual(image, lab, leaf.mask)
        doc["pieces"] = stats.to_dict()
    doc["params"] = _to_jsonable(noise.fit_noise(image, leaf.mask, config=cfg))
    path = write_json(mdir / "noise" / f"{safe_name(leaf_id)}__{map_name}.json", doc)
    return {"files": [path], "info": {"leaf": leaf_id, "map": map_name}}


def _inpainted_target(mdir: Path, parent, node) -> tuple[np.ndarray, dict]:
    """The inpainting variant for a sub-layer (workers.inpaint.complete_child_mask over the working maps)."""
    from workers.inpaint import complete_child_mask

    mat = load_working_material(mdir)
    maps = {k: v for k, v in (("albedo", mat.albedo), ("height", mat.height), ("roughness", mat.roughness))
            if v is not None}
    target, info = complete_child_mask(maps, parent.mask, [c.mask for c in parent.children],
                                       [c.id for c in parent.children].index(node.id))
    return target, {"inpaint": info}


def fit_region(tree, parent, node) -> np.ndarray | None:
    """Where child ``node``'s mask is fitted: inside its parent and outside its earlier siblings (the split is
    fitted as a binary tree: child i inside what children 0..i-1 left; the graph multiplies child i's PPTBF by
    that remainder). None when that is the whole image."""
    region = np.ones_like(node.mask, dtype=bool) if parent.id == tree.id else parent.mask.astype(bool).copy()
    for sib in parent.children[:parent.children.index(node)]:
        region &= ~sib.mask.astype(bool)
    return None if region.all() else region


def stage_masks(call: dict, resources: Any = None) -> dict:
    """Proceduralise one matting child's mask by a PPTBF fit (query + optimise) inside what its parent and its
    earlier siblings left (:func:`fit_region`); write JSON."""
    from workers import masks

    node_id = call["item"]
    mdir = material_dir(call)
    tree = load_tree(mdir)
    node = _find(tree, node_id)
    parent = _find(tree, tree_info(tree)["parents"][node_id])
    if parent.method == "instances":
        raise InputError(f"tree node {node_id!r} is an instance cluster: it has no PPTBF mask to fit")
    valid = fit_region(tree, parent, node)
    fitter = resources
    if fitter is None:  # run outside an actor (tests, single machine)
        from workers.actors import MaskFitter

        fitter = MaskFitter()
    cfg = _config(getattr(masks, "MaskFitConfig", None), call["material"].get("masks", {}), "masks")
    target, extra = node.mask, {}
    if parent.id != tree.id and cfg.incomplete == "inpaint":
        target, extra = _inpainted_target(mdir, parent, node)
        valid = None
    fit = fitter.fit(target, valid=valid, config=cfg, seed=int(call["material"].get("seed", 0)))
    doc = {"node": node_id, "parent": parent.id, "kind": "pptbf", "fit": _to_jsonable(fit),
           "node_params": fit.node_params(int(node.mask.shape[1])), **extra}
    path = write_json(mdir / "masks" / f"{safe_name(node_id)}.json", doc)
    return {"files": [path], "info": {"node": node_id, "loss_query": float(fit.loss_query),
                                      "loss_final": float(fit.loss_final), "evaluations": int(fit.evaluations),
                                      "holder_fits": fitter.fits, "holder_index_loads": fitter.loads,
                                      "index_load_s": round(fitter.load_seconds, 3)}}


def stage_recompose(call: dict, resources: Any = None) -> dict:
    """Assemble the procedural graph from the tree, noise models and mask fits, optimise it, write material.json."""
    from workers import graph

    mdir = material_dir(call)
    mat = load_working_material(mdir)
    tree = load_tree(mdir)
    noises, pieces = {}, {}
    for f in sorted((mdir / "noise").glob("*.json")) if (mdir / "noise").is_dir() else []:
        d = json.loads(f.read_text(encoding="utf-8"))
        noises[(d["leaf"], d["map"])] = d["params"]
        if d.get("pieces"):
            pieces[(d["leaf"], d["map"])] = d["pieces"]
    fits = {}
    for f in sorted((mdir / "masks").glob("*.json")) if (mdir / "masks").is_dir() else []:
        d = json.loads(f.read_text(encoding="utf-8"))
        fits[d["node"]] = d
    recomposer = resources
    if recomposer is None:  # run outside an actor (tests, single machine)
        from workers.actors import Recomposer

        recomposer = Recomposer()
    proc, info = recomposer.run(mat, tree, noises, fits, options=call["material"].get("recompose", {}),
                                seed=int(call["material"].get("seed", 0)), pieces=pieces)
    path = graph.save(proc, mdir / "recompose" / "material.json")
    rep = write_json(mdir / "recompose" / "report.json", info)
    return {"files": [path, rep], "info": _to_jsonable(info)}


def _write_maps(maps: dict[str, np.ndarray], out: Path, bits: int) -> list[Path]:
    """Evaluated maps as PNG: albedo sRGB, normal encoded, grey maps 16-bit."""
    from workers.maps import linear_to_srgb, output_file, write_image

    files = []
    for name, arr in maps.items():
        if name == "albedo":
            data, b = linear_to_srgb(arr), bits
        elif name == "normal":
            data, b = np.clip(arr * 0.5 + 0.5, 0.0, 1.0), bits
        else:
            data, b = np.clip(arr, 0.0, 1.0), 16
        files.append(write_image(output_file(out, name, ".png"), data[..., :3] if data.ndim == 3 else data, bits=b))
    return files


def _write_materialx(maps: dict[str, np.ndarray], folder: Path, name: str, bits: int) -> list[Path]:
    """A MaterialX document over the written maps (albedo.png is sRGB, normal.png OpenGL-encoded), plus a
    glTF ORM texture when the material has a metallic map."""
    from workers.export import pack_orm, write_materialx
    from workers.maps import write_image

    files = []
    orm = None
    if "metallic" in maps:
        orm = write_image(folder / "orm.png", pack_orm(maps["roughness"], maps["metallic"]), bits=bits)
        files.append(orm)
    files.append(write_materialx(folder / "material.mtlx", safe_name(name), "albedo.png", "normal.png",
                                 "roughness.png", orm.name if orm else None))
    return files


def output_renders(material: dict) -> list[str]:
    """Render tags of the output stage, one work item each: ``WxH_seedS[_scaleX]`` for sizes x seeds x scales."""
    outs = material.get("outputs", {})
    return [f"{w}x{h}_seed{seed}" + ("" if float(scale) == 1.0 else f"_scale{float(scale):g}")
            for w, h in outs.get("sizes", [[1024, 1024]]) for seed in outs.get("seeds", [0])
            for scale in outs.get("scales", [1.0])]


def _parse_render(tag: str) -> tuple[int, int, int, float]:
    size, seed, *rest = tag.split("_")
    w, h = (int(v) for v in size.split("x"))
    return w, h, int(seed[len("seed"):]), float(rest[0][len("scale"):]) if rest else 1.0


def stage_output(call: dict, resources: Any = None) -> dict:
    """Regenerate the maps for one render item (size, seed, scale) + preview; the first item also publishes
    material.json next to the map folders."""
    from workers import graph

    m = call["material"]
    mdir = material_dir(call)
    tag = call["item"] or output_renders(m)[0]
    proc = graph.load(mdir / "recompose" / "material.json")
    files = [graph.save(proc, mdir / "material.json")] if tag == output_renders(m)[0] else []
    outs = m.get("outputs", {})
    w, h, seed, scale = _parse_render(tag)
    from workers import budget

    budget.check(f"rendering {m['name']!r} at {w}x{h}", budget.render_bytes(len(proc.nodes), w, h),
                 budget.budget(call.get("memory_budget")))
    t0 = time.perf_counter()
    maps = graph.evaluate(proc, w, h, scale=scale, seed=seed)
    folder = mdir / "maps" / tag
    files += _write_maps(maps, folder, int(outs.get("bits", 8)))
    if outs.get("preview", True) and importlib.util.find_spec("workers.render") is not None:
        from workers.maps import write_image
        from workers.render import preview_image

        files.append(write_image(folder / "preview.png", preview_image(maps), bits=8))
    if outs.get("materialx", True):
        files += _write_materialx(maps, folder, m["name"], int(outs.get("bits", 8)))
    return {"files": files, "info": {"render": tag, "seconds": round(time.perf_counter() - t0, 3)}}


STAGE_FUNCS: dict[str, Callable[[dict, Any], dict]] = {
    "load": stage_load, "decompose": stage_decompose, "noise": stage_noise, "masks": stage_masks,
    "recompose": stage_recompose, "output": stage_output}


def _debug_hooks(call: dict) -> None:
    """Test hooks from the manifest's [debug] table: sleep in a stage; crash the worker once (marker file)."""
    dbg = call.get("debug") or {}
    name = call["material"]["name"]
    s = dbg.get("sleep")
    if s and s["stage"] == call["stage"] and s.get("material") in (None, name):
        time.sleep(float(s["seconds"]))
    c = dbg.get("crash_once")
    if c and c["stage"] == call["stage"] and c.get("material") in (None, name):
        marker = Path(c["marker"])
        try:
            fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            return
        os.write(fd, f"{name} {call['stage']} {call['item']} pid {os.getpid()}\n".encode())
        os.close(fd)
        logger.warning("debug.crash_once: exiting worker pid %d in %s/%s", os.getpid(), name, call["stage"])
        os._exit(17)


def run_stage(call: dict, resources: Any = None) -> dict:
    """Run one stage item and return its result record (artefacts with checksums, info, timing, worker)."""
    stage = call["stage"]
    missing = missing_modules(stage, call["material"])
    if missing:
        raise StageUnavailable(f"stage {stage!r} needs module(s) {', '.join(missing)}, which are not installed")
    started = time.time()
    t0, c0 = time.perf_counter(), time.process_time()
    what = f"stage {stage}" + (f"[{call['item']}]" if call.get("item") else "")
    with time_limit(call.get("timeout"), what):
        _debug_hooks(call)
        res = STAGE_FUNCS[stage](call, resources)
    root = call["root"]
    arts = [artefact(root, Path(p), kind=f"{stage}:{Path(p).suffix.lstrip('.')}") for p in res["files"]]
    info = dict(res.get("info", {}))
    # CPU seconds of this process (all its threads) and its thread count: a stage busier than its reservation
    # (cpu_s > duration) or starved by its neighbours (cpu_s well under duration) shows here
    info.update(cpu_s=round(time.process_time() - c0, 3), threads=_thread_count())
    return {"artefacts": arts, "info": info, "worker": f"{socket.gethostname()}:{os.getpid()}",
            "started": started, "finished": time.time(), "duration": time.perf_counter() - t0}


def _thread_count() -> int | None:
    """OS threads of this process (Linux /proc), None where that is not readable."""
    try:
        return len(os.listdir("/proc/self/task"))
    except OSError:
        return None
