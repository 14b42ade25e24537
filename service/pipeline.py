"""The stage bodies: read the previous stages' files, call the pure stage of workers/, write the results.

Each body is declared as one stage in :mod:`service.stages` and takes a :class:`~service.stages.StageCall` (the
material's :class:`~service.manifest.MaterialSpec`, its :class:`~service.folder.MaterialFolder`, the item) and
the actor's holder (MaskFitter, Recomposer, or None in a task); it returns ``{"files": [...], "info": {...}}``.

Results are files (npz without pickles, JSON, PNG), each written atomically (tmp + rename) before the body
returns, so the driver can record them and a rerun can skip them. No Ray and no SQLite here.

The stage modules of workers/ (scipy, torch, OpenImageIO) are imported inside the bodies: this module is
imported by ``proceduralize --help`` (through service.report and service.stages), which stays light.
"""
from __future__ import annotations

import contextlib
import copy
import json
import logging
import os
import signal
import threading
import time
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator

import numpy as np

from pptbf_db.files import atomic_path, write_text
from service.folder import MaterialFolder, safe_name
from workers import budget
from workers.errors import InputError
from workers.export import pack_orm, write_materialx
from workers.tree import MaskNode, root_node

if TYPE_CHECKING:
    from service.manifest import MaterialSpec
    from service.stages import StageCall

logger = logging.getLogger(__name__)


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


# ----------------------------------------------------------------------------- files


def write_json(path: Path, doc: Any) -> Path:
    """Atomic JSON write."""
    return write_text(path, json.dumps(doc, indent=1, default=_json_default))


def write_npz(path: Path, arrays: dict[str, np.ndarray]) -> Path:
    """Atomic npz write (plain arrays, never object arrays)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, **{k: np.ascontiguousarray(v) for k, v in arrays.items()})
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


# ----------------------------------------------------------------------------- reading previous stages


def load_working_material(where: MaterialFolder | Path):
    """The working-size Material written by the load stage (of a MaterialFolder or a material folder path)."""
    from workers.maps import Material

    folder = MaterialFolder.of(where)
    return Material.from_arrays(read_npz(folder.working_maps),
                                json.loads(folder.working_meta.read_text(encoding="utf-8")))


def load_tree(folder: MaterialFolder) -> MaskNode:
    """The decomposition tree written by the decompose stage."""
    return MaskNode.from_arrays(json.loads(folder.tree.read_text(encoding="utf-8")), read_npz(folder.tree_masks))


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


def stage_load(call: StageCall, holder: Any = None) -> dict:
    """Read and validate the maps, write them at working size (npz for the next stages, PNG for people)."""
    from workers.maps import image_header, load_material, save_material, working_size_for

    spec, folder = call.spec, call.folder
    files = {k: str(m.file) for k, m in spec.maps.items()}
    ch = {k: m.channel for k, m in spec.maps.items()}
    ws = spec.working_size
    sizes = [image_header(files[k]) for k in files]  # headers only: refuse before decoding anything
    w0, h0 = sizes[0][:2]
    try:
        tw, th = working_size_for(ws, w0, h0)
    except InputError as exc:
        raise InputError(f"{files['albedo']}: {exc}") from None
    limit = budget.budget(call.memory_budget)
    budget.check(f"loading {files['albedo']} ({w0}x{h0}) at working size {tw}x{th}",
                 budget.load_bytes(sizes, (tw, th)), limit)
    budget.check(f"fitting material {spec.name!r} at working size {tw}x{th}", budget.fit_bytes(tw, th), limit)
    mat = load_material(
        files["albedo"], *(files.get(k) for k in ("normal", "roughness", "height", "metallic")),
        roughness_channel=ch.get("roughness"), metallic_channel=ch.get("metallic"),
        albedo_colorspace=spec.albedo_colorspace, normal_convention=spec.normal_convention,
        working_size=ws, name=spec.name)
    arrays, meta = mat.to_arrays()
    written = [write_npz(folder.working_maps, arrays), write_json(folder.working_meta, meta)]
    pngs = save_material(mat, folder.working_pngs)
    written += [p for p in pngs.values()]
    return {"files": written, "info": {"size": list(mat.size), "maps": sorted(arrays),
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


def stage_decompose(call: StageCall, holder: Any = None) -> dict:
    """Build the decomposition tree (root only for mode 'none'); write masks (npz + PNG) and tree.json."""
    from workers.maps import write_image

    folder = call.folder
    mat = load_working_material(folder)
    options = copy.deepcopy(call.spec.decompose)
    mode = options.pop("mode", "auto")
    w, h = mat.size
    if mode == "none":
        tree = root_node(h, w)
    else:
        from workers.decompose import decompose

        tree = decompose(mat, _with_scribble_images(options, (h, w)), seed=int(call.spec.seed))
    tree_doc, arrays = tree.to_arrays()
    files = [write_npz(folder.tree_masks, arrays), write_json(folder.tree, tree_doc)]
    for n in tree.walk():
        files.append(write_image(folder.mask_png(n.id), n.mask.astype(np.float32)))
    return {"files": files, "info": tree_info(tree)}


def stage_noise(call: StageCall, holder: Any = None) -> dict:
    """Fit the multi-layer noise model of one (leaf, map) item; write its parameters as JSON. A kind of an
    instance split is fitted on its within-piece residual, and the spread of its pieces' offsets from the split's
    smooth background is written beside (``pieces``, workers.pieces)."""
    from workers.noise import NoiseConfig, fit_noise
    from workers.pieces import kind_piece_labels, piece_residual, piece_trend

    leaf_id, map_name = call.item.rsplit("/", 1)
    folder = call.folder
    mat = load_working_material(folder)
    tree = load_tree(folder)
    leaf = _find(tree, leaf_id)
    image = mat.maps()[map_name]
    cfg = _config(NoiseConfig, call.options, "noise")
    parent = _find(tree, tree_info(tree)["parents"][leaf_id]) if leaf_id != tree.id else None
    doc: dict = {"leaf": leaf_id, "map": map_name}
    if map_name in cfg.per_piece and parent is not None and parent.method == "instances" and \
            "instance_labels" in parent.meta:
        split_labels, split_kinds = parent.meta["instance_labels"], parent.meta["instance_kinds"]
        lab = kind_piece_labels(split_labels, split_kinds, [c.id for c in parent.children].index(leaf_id))
        image, stats = piece_residual(image, lab, leaf.mask, piece_trend(image, split_labels, split_kinds))
        doc["pieces"] = stats.to_dict()
    doc["params"] = _to_jsonable(fit_noise(image, leaf.mask, config=cfg))
    path = write_json(folder.noise_model(leaf_id, map_name), doc)
    return {"files": [path], "info": {"leaf": leaf_id, "map": map_name}}


def _inpainted_target(folder: MaterialFolder, parent, node) -> tuple[np.ndarray, dict]:
    """The inpainting variant for a sub-layer (workers.inpaint.complete_child_mask over the working maps)."""
    from workers.inpaint import complete_child_mask

    mat = load_working_material(folder)
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


def stage_masks(call: StageCall, holder: Any = None) -> dict:
    """Proceduralise one matting child's mask by a PPTBF fit (query + optimise) inside what its parent and its
    earlier siblings left (:func:`fit_region`); write JSON."""
    from workers.decompose import structure_cell_length
    from workers.masks import MaskFitConfig

    node_id = call.item
    folder = call.folder
    tree = load_tree(folder)
    node = _find(tree, node_id)
    parent = _find(tree, tree_info(tree)["parents"][node_id])
    if parent.method == "instances":
        raise InputError(f"tree node {node_id!r} is an instance cluster: it has no PPTBF mask to fit")
    valid = fit_region(tree, parent, node)
    fitter = holder
    if fitter is None:  # run outside an actor (tests, single machine)
        from workers.actors import MaskFitter

        fitter = MaskFitter()
    cfg = _config(MaskFitConfig, call.options, "masks")
    target, extra = node.mask, {}
    if parent.id != tree.id and cfg.incomplete == "inpaint":
        target, extra = _inpainted_target(folder, parent, node)
        valid = None
    fit = fitter.fit(target, valid=valid, config=cfg, seed=int(call.spec.seed),
                     cell_length=structure_cell_length(tree, node))
    doc = {"node": node_id, "parent": parent.id, "kind": "pptbf", "fit": _to_jsonable(fit),
           "node_params": fit.node_params(int(node.mask.shape[1])), **extra}
    path = write_json(folder.mask_fit(node_id), doc)
    return {"files": [path], "info": {"node": node_id, "loss_query": float(fit.loss_query),
                                      "loss_final": float(fit.loss_final), "evaluations": int(fit.evaluations),
                                      "time_limited": bool(fit.meta.get("time_limited", False)),
                                      "holder_fits": fitter.fits, "holder_index_loads": fitter.loads,
                                      "index_load_s": round(fitter.load_seconds, 3)}}


def load_recompose_inputs(folder: MaterialFolder) -> tuple[Any, MaskNode, dict, dict, dict]:
    """What the recomposition assembles a graph from, as the earlier stages wrote it: the working-size Material,
    the decomposition tree, noise params and per-piece fits by (leaf, map), mask fits by node."""
    noises, pieces, fits = {}, {}, {}
    for f in folder.noise_models():
        d = json.loads(f.read_text(encoding="utf-8"))
        noises[(d["leaf"], d["map"])] = d["params"]
        if d.get("pieces"):
            pieces[(d["leaf"], d["map"])] = d["pieces"]
    for f in folder.mask_fits():
        d = json.loads(f.read_text(encoding="utf-8"))
        fits[d["node"]] = d
    return load_working_material(folder), load_tree(folder), noises, fits, pieces


def stage_recompose(call: StageCall, holder: Any = None) -> dict:
    """Assemble the procedural graph from the tree, noise models and mask fits, optimise it, write material.json."""
    from workers import graph

    folder = call.folder
    mat, tree, noises, fits, pieces = load_recompose_inputs(folder)
    recomposer = holder
    if recomposer is None:  # run outside an actor (tests, single machine)
        from workers.actors import Recomposer

        recomposer = Recomposer()
    proc, info = recomposer.run(mat, tree, noises, fits, options=call.options, seed=int(call.spec.seed),
                                pieces=pieces)
    path = graph.save(proc, folder.recomposed)
    rep = write_json(folder.recompose_report, info)
    return {"files": [path, rep], "info": _to_jsonable(info)}


def _write_materialx(maps: dict[str, np.ndarray], folder: MaterialFolder, tag: str, name: str,
                     bits: int, proc=None, render: tuple[int, int, int, float] | None = None) -> list[Path]:
    """A MaterialX document over the written maps (albedo.png is sRGB, normal.png OpenGL-encoded), plus a
    glTF ORM texture when the material has a metallic map; with ``proc`` (the material's graph) and ``render``
    (w, h, seed, scale) also the procedural material (``workers.mtlx.procedural``: node library and noise tiles
    beside the document)."""
    from workers.maps import write_image

    files = []
    orm = None
    if "metallic" in maps:
        orm = write_image(folder.orm(tag), pack_orm(maps["roughness"], maps["metallic"]), bits=bits)
        files.append(orm)
    procedural = None
    if proc is not None and render is not None:
        from workers.mtlx.procedural import add_material

        w, h, seed, scale = render
        out_dir = folder.materialx(tag).parent

        def procedural(doc):
            g = add_material(doc, proc, safe_name(name), w, h, out_dir, seed=seed, scale=scale)
            files.extend(g.tiles.values())
    files.append(write_materialx(folder.materialx(tag), safe_name(name), "albedo.png", "normal.png",
                                 "roughness.png", orm.name if orm else None, procedural=procedural))
    return files


def output_renders(spec: MaterialSpec) -> list[str]:
    """Render tags of the output stage, one work item each: ``WxH_seedS[_scaleX]`` for sizes x seeds x scales."""
    outs = spec.outputs
    return [f"{w}x{h}_seed{seed}" + ("" if float(scale) == 1.0 else f"_scale{float(scale):g}")
            for w, h in outs.sizes for seed in outs.seeds for scale in outs.scales]


def _parse_render(tag: str) -> tuple[int, int, int, float]:
    size, seed, *rest = tag.split("_")
    w, h = (int(v) for v in size.split("x"))
    return w, h, int(seed[len("seed"):]), float(rest[0][len("scale"):]) if rest else 1.0


def stage_output(call: StageCall, holder: Any = None) -> dict:
    """Regenerate the maps for one render item (size, seed, scale) + preview; the first item also publishes
    material.json next to the map folders."""
    from workers import graph
    from workers.maps import write_image, write_maps

    spec, folder = call.spec, call.folder
    first = output_renders(spec)[0]
    tag = call.item or first
    proc = graph.load(folder.recomposed)
    files = [graph.save(proc, folder.published)] if tag == first else []
    outs = spec.outputs
    w, h, seed, scale = _parse_render(tag)
    budget.check(f"rendering {spec.name!r} at {w}x{h}", budget.render_bytes(len(proc.nodes), w, h),
                 budget.budget(call.memory_budget))
    t0 = time.perf_counter()
    maps = graph.evaluate(proc, w, h, scale=scale, seed=seed)
    files += list(write_maps(maps, folder.render_dir(tag), int(outs.bits)).values())
    if outs.preview:
        from workers.render import preview_image

        files.append(write_image(folder.preview(tag), preview_image(maps), bits=8))
    if outs.materialx:
        files += _write_materialx(maps, folder, tag, spec.name, int(outs.bits),
                                  proc if outs.procedural else None, (w, h, seed, scale))
    return {"files": files, "info": {"render": tag, "seconds": round(time.perf_counter() - t0, 3)}}


def debug_hooks(call: StageCall) -> None:
    """Fault hooks for tests (PROCEDURALIZE_FAULTS): sleep in a stage; crash the worker once (marker file)."""
    dbg = call.debug or {}
    name = call.spec.name
    s = dbg.get("sleep")
    if s and s["stage"] == call.stage and s.get("material") in (None, name):
        time.sleep(float(s["seconds"]))
    c = dbg.get("crash_once")
    if c and c["stage"] == call.stage and c.get("material") in (None, name):
        marker = Path(c["marker"])
        try:
            fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            return
        os.write(fd, f"{name} {call.stage} {call.item} pid {os.getpid()}\n".encode())
        os.close(fd)
        logger.warning("debug.crash_once: exiting worker pid %d in %s/%s", os.getpid(), name, call.stage)
        os._exit(17)
