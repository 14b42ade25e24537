"""Run a decomposition tree described by a manifest-style dict and return the tree of masks (MaskNode).

Spec (JSON/TOML dict), every key optional except inside ``children``::

    {"method": "matting",            # "matting" | "instances" | "leaf"
     "layers": 2,                    # matting: int 2..8 or "auto" (silhouette over k = 2..5)
     "scribbles": None,              # matting: scribble image array (see workers.matting) or None = automatic
     "scribbles_source": "s.png",    # optional file name used in error messages
     "spectral_weight": 0.5,         # matting: weight of the spectral PCA-3 features
     "structure": True,              # root, automatic matting: split the layout's network first (see below)
     "children": {"0": {...}, "1": {"method": "instances"}}}

Matting keys also accepted: k, k_nonlocal, lambda, confidence, seed_smooth. Instance keys: open_close,
min_side, distance_threshold, outlier_z, crop_size. ``spec=None`` means ``{"method": "matting", "layers": 2}``
(an automatic two-layer split of the whole material; its leaves are then sub-materials).

Structure first: an automatic (scribble-free) matting split of the root first looks for a layout in the relief
(height from normals, normal tilt) and then the albedo (workers.structure). When one is found and its cut shows
the layout about as strongly as the colour split's layers or more (workers.structure.layout_rank: a 2-D
lattice, then regularity; at a small working size a 1-2 px mortar cut turns to speckle while the colours still
show the bricks), the root's split is that layout: "root.0" = the network (mortar, grout, seams, edges),
"root.1" = the cells; with more than 2 layers (or "auto"), the cells are split again by colour matting
(layers - 1, or "auto") as "root.1.*", so stains and colour variation become nested splits. With 2 layers,
the cells are cut at their necks (``AUTO_SEPARATE`` of the period between markers; pieces shorter than
``AUTO_MIN_SIDE`` of it are fragments); when that gives at least
``AUTO_INSTANCE_MIN`` pieces in two or more kinds (at most ``AUTO_MAX_KINDS``) by appearance, they
become an instance split "root.1.*" (each brick one kind's colour, as in the input); otherwise the cells stay
one leaf and their variation stays in its noise. The network is split by colour when it holds two distinct
shades (``_network_shades``: light mortar and the dark shadowed brick edges in the same grooves), else it stays one
leaf. Children specs apply to root.0 / root.1 as usual (``children = {"1" = {method = "leaf"}}`` keeps the cells
one leaf, ``children = {"0" = {method = "leaf"}}`` the network). Scribbles override it;
``structure = false`` turns it off.

Node ids: "root", "root.0", "root.1", "root.0.1", ... (layer / kind index). A split solves only over its parent's
pixels. Matting layers that come out empty are dropped (a warning; the other ids keep their index).
Children specs for an index that a split did not produce ("auto" layers, instance kinds) are ignored with a
warning.
"""
from __future__ import annotations

import logging
import numbers
from dataclasses import replace
from typing import Any, Mapping

import numpy as np

from .errors import InputError, ManifestError
from .instances import InstanceConfig, InstanceSplit, split_instances
from .lattice import analyse_lattice
from .matting import MAX_LAYERS, FeatureMaps, MattingConfig, feature_maps, matte
from .structure import find_structure, layout_rank
from .tree import MaskNode, root_node

logger = logging.getLogger(__name__)

#: an automatic split needs at least this many pixels (a smaller region stays one leaf)
MIN_AUTO_SPLIT_PIXELS = 64

METHODS = ("matting", "instances", "leaf")
DEFAULT_SPEC: dict = {"method": "matting", "layers": 2}
_MATTING_KEYS = {"layers": "layers", "scribbles": None, "scribbles_source": None, "structure": None,
                 "spectral_weight": "spectral_weight",
                 "k": "k", "k_nonlocal": "k_nonlocal", "lambda": "lam", "confidence": "confidence",
                 "seed_smooth": "seed_smooth"}
_INSTANCE_KEYS = {"open_close": "open_close", "min_side": "min_side", "distance_threshold": "distance_threshold",
                  "outlier_z": "outlier_z", "crop_size": "crop_size"}


# ----------------------------------------------------------------------------- validation

def _is_num(v: Any) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and np.isfinite(v)


def _is_int(v: Any) -> bool:
    return isinstance(v, numbers.Integral) and not isinstance(v, bool)


def _check_node(spec: Any, where: str, problems: list[str]) -> None:
    """Append every problem of one spec node (and its children) to problems."""
    if not isinstance(spec, Mapping):
        problems.append(f"{where}: must be a table/dict, got {type(spec).__name__}")
        return
    method = spec.get("method", "matting")
    if method not in METHODS:
        problems.append(f"{where}.method: must be one of {', '.join(METHODS)}, got {method!r}")
        return
    allowed = {"method", "children"} | (set(_MATTING_KEYS) if method == "matting" else set()) \
        | (set(_INSTANCE_KEYS) if method == "instances" else set())
    for key in spec:
        if key not in allowed:
            problems.append(f"{where}.{key}: unknown key for method {method!r} (allowed: {', '.join(sorted(allowed))})")
    layers = spec.get("layers", 2)
    if method == "matting":
        if not (layers == "auto" or (_is_int(layers) and 2 <= layers <= MAX_LAYERS)):
            problems.append(f"{where}.layers: must be an integer 2..{MAX_LAYERS} or \"auto\", got {layers!r}")
        sc = spec.get("scribbles")
        if sc is not None and not (isinstance(sc, np.ndarray) and sc.ndim in (2, 3)):
            problems.append(f"{where}.scribbles: must be an image array (HxW or HxWxC) or None; the service reads "
                            f"the file, got {type(sc).__name__}")
        if not isinstance(spec.get("structure", True), bool):
            problems.append(f"{where}.structure: must be true or false, got {spec['structure']!r}")
        src = spec.get("scribbles_source")
        if src is not None and not isinstance(src, str):
            problems.append(f"{where}.scribbles_source: must be a file name string")
        for key, lo, integer in (("spectral_weight", 0.0, False), ("k", 1, True), ("k_nonlocal", 0, True),
                                 ("lambda", 1e-9, False), ("confidence", 1e-9, False), ("seed_smooth", 0.0, False)):
            if key in spec and not ((_is_int if integer else _is_num)(spec[key]) and spec[key] >= lo):
                problems.append(f"{where}.{key}: must be {'an integer' if integer else 'a number'} >= {lo}, "
                                f"got {spec[key]!r}")
        if "confidence" in spec and _is_num(spec["confidence"]) and spec["confidence"] > 1:
            problems.append(f"{where}.confidence: must be <= 1, got {spec['confidence']!r}")
    if method == "instances":
        if "open_close" in spec and not isinstance(spec["open_close"], bool):
            problems.append(f"{where}.open_close: must be true or false, got {spec['open_close']!r}")
        for key, lo, integer in (("min_side", 1, True), ("crop_size", 4, True), ("distance_threshold", 1e-9, False),
                                 ("outlier_z", 1e-9, False)):
            if key in spec and not ((_is_int if integer else _is_num)(spec[key]) and spec[key] >= lo):
                problems.append(f"{where}.{key}: must be {'an integer' if integer else 'a number'} >= {lo}, "
                                f"got {spec[key]!r}")
    children = spec.get("children")
    if children is None:
        return
    if method == "leaf":
        problems.append(f"{where}.children: a leaf has no children; set method to matting or instances")
        return
    if not isinstance(children, Mapping):
        problems.append(f"{where}.children: must be a table/dict keyed by child index (\"0\", \"1\", ...)")
        return
    for key, child in children.items():
        k = str(key)
        if not k.isdigit():
            problems.append(f"{where}.children.{k}: child keys must be layer/kind indices \"0\", \"1\", ...")
            continue
        if method == "matting" and _is_int(layers) and int(k) >= layers:
            problems.append(f"{where}.children.{k}: this split has only {layers} layers (indices 0..{layers - 1})")
        _check_node(child, f"{where}.children.{k}", problems)


def validate_spec(spec: Mapping | None, where: str = "decompose") -> dict:
    """Check a decomposition spec; returns it (DEFAULT_SPEC for None) or raises ManifestError listing every problem."""
    if spec is None:
        return dict(DEFAULT_SPEC)
    problems: list[str] = []
    _check_node(spec, where, problems)
    if problems:
        raise ManifestError(problems)
    return dict(spec)


# ----------------------------------------------------------------------------- inputs

def _arrays(maps: Any) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(albedo HxWx3, height HxW | None, roughness HxW | None) from a Material or a dict of arrays."""
    if hasattr(maps, "maps") and callable(maps.maps):
        maps = maps.maps()
    if not isinstance(maps, Mapping):
        raise InputError(f"decompose needs a Material or a dict of arrays, got {type(maps).__name__}")
    if maps.get("albedo") is None:
        raise InputError("decompose: the maps have no 'albedo'")
    albedo = np.asarray(maps["albedo"], np.float32)
    if albedo.ndim == 2:
        albedo = albedo[..., None]
    if albedo.ndim != 3 or albedo.shape[2] not in (1, 3, 4):
        raise InputError(f"decompose: albedo must be HxWx3, got shape {albedo.shape}")
    albedo = np.repeat(albedo, 3, axis=2) if albedo.shape[2] == 1 else albedo[..., :3]
    out = []
    for name in ("height", "roughness"):
        m = maps.get(name)
        if m is not None:
            m = np.asarray(m, np.float32)
            m = m[..., 0] if m.ndim == 3 else m
            if m.shape != albedo.shape[:2]:
                raise InputError(f"decompose: {name} is {m.shape[1]}x{m.shape[0]} but the albedo is "
                                 f"{albedo.shape[1]}x{albedo.shape[0]}")
        out.append(m)
    height, rough = out
    if height is None and maps.get("normal") is not None:
        from .height import normal_to_height

        height, _ = normal_to_height(np.asarray(maps["normal"], np.float32))
    return albedo, height, rough


def _uses_spectrum(spec: Mapping) -> bool:
    if spec.get("method", "matting") == "matting" and spec.get("spectral_weight", 0.5) > 0:
        return True
    return any(_uses_spectrum(c) for c in (spec.get("children") or {}).values())


# ----------------------------------------------------------------------------- running

def _matting_config(spec: Mapping) -> MattingConfig:
    return MattingConfig(**{attr: spec[key] for key, attr in _MATTING_KEYS.items()
                            if attr and attr != "layers" and key in spec})


def _split(node: MaskNode, spec: Mapping, fm: FeatureMaps, seed: int) -> None:
    """Split node in place according to spec (recursively)."""
    method = spec.get("method", "matting")
    if method == "leaf":
        return
    children_spec = {str(k): v for k, v in (spec.get("children") or {}).items()}
    if method == "matting":
        if spec.get("scribbles") is None and int(np.count_nonzero(node.mask)) < MIN_AUTO_SPLIT_PIXELS:
            logger.warning("%s: %d pixel(s) are too few to split automatically; kept as one leaf", node.id,
                           int(np.count_nonzero(node.mask)))
            return
        res = matte(fm, node.mask, spec.get("layers", 2), spec.get("scribbles"), _matting_config(spec), seed,
                    source=spec.get("scribbles_source"))
        node.method, node.meta = "matting", {**node.meta, **res.meta}
        for i, m in enumerate(res.masks()):
            if not m.any():
                logger.warning("%s: matting layer %d is empty; dropped", node.id, i)
                continue
            node.children.append(MaskNode(id=f"{node.id}.{i}", mask=m, alpha=res.alphas[i]))
        if len(node.children) < 2:  # a uniform region: one layer is no split (and no mask to fit)
            logger.warning("%s: the split found a single layer (a uniform region); kept as one leaf", node.id)
            node.children, node.method = [], "leaf"
            return
    else:
        cfg = InstanceConfig(**{attr: spec[key] for key, attr in _INSTANCE_KEYS.items() if key in spec})
        _set_instances(node, split_instances(node.mask, fm.colour, cfg, seed))
    made = {c.id.rsplit(".", 1)[1] for c in node.children}
    for key in sorted(set(children_spec) - made):
        logger.warning("%s: spec has children.%s but the split made no such child; ignored", node.id, key)
    for child in node.children:
        sub = children_spec.get(child.id.rsplit(".", 1)[1])
        if sub is not None:
            _split(child, sub, fm, seed)


def _set_instances(node: MaskNode, res: InstanceSplit) -> None:
    """Make ``node`` an instance split with one child per kind of ``res``."""
    node.method, node.shares = "instances", list(res.shares)
    node.meta = {**node.meta, **res.meta, "instance_labels": res.labels, "instance_kinds": res.kinds.tolist()}
    node.children = [MaskNode(id=f"{node.id}.{i}", mask=m) for i, m in enumerate(res.masks)]


#: the layout's network is split by colour when its two matting layers are at least this far apart in shade
#: (shade_separation) and each holds at least AUTO_NETWORK_MIN_SHARE of it. 2.0: an even mixture of two equal
#: normal distributions has two modes only when their means are more than 2 standard deviations apart. At 512 px:
#: castle_brick_broken_06 2.94 (split: light mortar 30 %, dark edges 70 %), metal_plate_02 1.92 (one leaf; split
#: by hand its maps came nearer, albedo 1.68 -> 1.31 and roughness 1.47 -> 1.12 x floor, normal 6.96 -> 7.29, but
#: the seams showed light grey stretches the input has not), roof_slates_02 0.03
AUTO_NETWORK_SEPARATION = 2.0
AUTO_NETWORK_MIN_SHARE = 0.15
#: an automatic instance split of the layout's cells needs at least this many separate cells
AUTO_INSTANCE_MIN = 16
#: the automatic split keeps at most this many kinds (a palette of cell appearances; each kind is a leaf whose
#: noise is fitted on its own pixels, so more kinds cost fits and thin each kind's sample)
AUTO_MAX_KINDS = 4
#: markers of the cut at the cells' necks lie at least this fraction of the layout's period apart
AUTO_SEPARATE = 1.0 / 3.0
#: pieces whose bounding box is shorter than this fraction of the layout's period are dropped as fragments (at
#: most ``InstanceConfig.min_side``, at least 3 px): a fixed 10 px bar dropped every slate of a roof at 256 px
AUTO_MIN_SIDE = 0.5


def _cell_kinds(cells: MaskNode, fm: FeatureMaps, period: float | None, seed: int) -> None:
    """Split the layout's cells (bricks, tiles, plates) into instance kinds when they are separate pieces that fall
    into two or more kinds by appearance (paper 4.2): each brick then takes one kind's colour and texture, as in
    the input, instead of a noise that mixes every brick's colour inside each brick. The cells are cut at their
    necks first (markers a third of the layout's period apart): a worn mortar line or a faded slate edge leaves
    gaps in the network, and without the cut the cells join into a few large pieces. Few cells, or a single
    kind, leave the cells one leaf."""
    base = InstanceConfig()
    min_side = int(np.clip(round(AUTO_MIN_SIDE * period), 3, base.min_side)) if period else base.min_side
    cfg = replace(base, separate=max(3.0, AUTO_SEPARATE * period) if period else 0.0, max_kinds=AUTO_MAX_KINDS,
                  min_side=min_side)
    res = split_instances(cells.mask, fm.colour, cfg, seed)
    kept = int(res.meta.get("kept", 0))
    if kept < AUTO_INSTANCE_MIN or len(res.masks) < 2:
        logger.info("%s: %d separate cell(s), %d kind(s): the cells stay one leaf", cells.id, kept, len(res.masks))
        return
    _set_instances(cells, res)
    cells.meta["auto"] = True
    cells.meta["separate"] = cfg.separate
    cells.meta["min_side"] = cfg.min_side


def shade_separation(colour: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """How far apart two pixel sets are in luma (Rec. 709 weights of the sRGB albedo, ``colour``'s first 3
    channels): the difference of the means over the pooled standard deviation (a Fisher-like d'; 0 = the same
    shade)."""
    luma = colour[..., :3] @ np.array([0.2126, 0.7152, 0.0722], dtype=colour.dtype)
    la, lb = luma[a], luma[b]
    pooled = np.sqrt(0.5 * (la.var() + lb.var())) + 1e-6
    return float(abs(la.mean() - lb.mean()) / pooled)


def _network_shades(network: MaskNode, fm: FeatureMaps, seed: int) -> None:
    """Split the layout's network (mortar, grout, seams) by colour when it holds two distinct shades: the relief's
    grooves of castle_brick_broken_06 hold the light mortar (30 % of them) and the dark shadows and broken edges of
    the bricks (70 %); as one leaf their noise mixes both into a muddy red-brown in every joint, and the light
    mortar lines, the first thing one sees in the input, are gone. A split whose two layers are less than
    ``AUTO_NETWORK_SEPARATION`` apart (``shade_separation``) or one of which is under ``AUTO_NETWORK_MIN_SHARE`` of
    the network stays one leaf (roof_slates_02's slate edges at 512 px split into two layers of the same shade,
    0.03 apart)."""
    if int(np.count_nonzero(network.mask)) < MIN_AUTO_SPLIT_PIXELS:
        return
    res = matte(fm, network.mask, 2, None, MattingConfig(), seed)
    masks = res.masks()
    shares = [float(m.sum()) / max(1, int(network.mask.sum())) for m in masks]
    sep = shade_separation(fm.colour, masks[0], masks[1]) if min(shares) > 0 else 0.0
    network.meta["shade_separation"] = round(sep, 3)
    if sep < AUTO_NETWORK_SEPARATION or min(shares) < AUTO_NETWORK_MIN_SHARE:
        logger.info("%s: shades %.2f apart (shares %s): the network stays one leaf", network.id, sep,
                    [round(s, 3) for s in shares])
        return
    logger.info("%s: two shades %.2f apart (shares %s): split", network.id, sep, [round(s, 3) for s in shares])
    network.method, network.meta = "matting", {**network.meta, **res.meta, "auto": True}
    network.children = [MaskNode(id=f"{network.id}.{i}", mask=m, alpha=res.alphas[i]) for i, m in enumerate(masks)]


def _structure_first(root: MaskNode, spec: Mapping, split: Any, fm: FeatureMaps, seed: int) -> None:
    """Root split = the layout's network (root.0) and its cells (root.1); the cells split by colour when more
    than 2 layers are asked for, else into instance kinds where they have some; children specs apply as usual."""
    root.method = "matting"
    root.meta["structure"] = split.describe()
    root.children = [MaskNode(id="root.0", mask=split.mask.copy()), MaskNode(id="root.1", mask=~split.mask)]
    layers = spec.get("layers", 2)
    children = {str(k): v for k, v in (spec.get("children") or {}).items()}
    if "1" not in children and (layers == "auto" or layers > 2):
        rest = "auto" if layers == "auto" else int(layers) - 1
        if rest == "auto" or rest >= 2:
            children["1"] = {"method": "matting", "layers": rest,
                             **{k: spec[k] for k in _MATTING_KEYS if k in spec and k not in
                                ("layers", "scribbles", "scribbles_source", "structure")}}
    for key in sorted(set(children) - {"0", "1"}):
        logger.warning("root: spec has children.%s but the structural split made only 0 and 1; ignored", key)
    for child in root.children:
        sub = children.get(child.id.rsplit(".", 1)[1])
        if sub is not None:
            _split(child, sub, fm, seed)
    if "0" not in children:
        _network_shades(root.children[0], fm, seed)
    if "1" not in children:
        _cell_kinds(root.children[1], fm, split.lattice.period, seed)


def structure_cell_length(root: MaskNode, node: MaskNode) -> float | None:
    """The cells' length along the rows (px) that the structural first split measured in the relief
    (workers.structure.cells_along_rows), for that split's network (root.0, see _structure_first); else None."""
    if not root.children or root.children[0].id != node.id:
        return None
    length = (root.meta.get("structure") or {}).get("cell_length")
    return float(length) if length else None


def decompose(maps: Any, spec: Mapping | None = None, seed: int = 0) -> MaskNode:
    """Decompose a material into a mask tree.

    maps: a Material, or a dict of arrays (linear albedo HxWx3; optional height, roughness, normal).
    spec: see the module docstring (None = automatic two-layer matting at the root, structure first).
    Deterministic from seed.
    """
    spec = validate_spec(spec)
    albedo, height, rough = _arrays(maps)
    fm = feature_maps(albedo, height, rough, spectrum_dims=16 if _uses_spectrum(spec) else 0, seed=seed)
    root = _root(albedo, fm)
    if spec.get("method", "matting") == "matting" and spec.get("scribbles") is None and spec.get("structure", True):
        d = maps.maps() if hasattr(maps, "maps") and callable(maps.maps) else maps
        normal = d.get("normal")
        split = find_structure(albedo, height, None if normal is None else np.asarray(normal, np.float32))
        if split is not None:
            _split(root, spec, fm, seed)
            colour = _colour_layout(root)
            if not _colour_shows_more(colour[0], layout_rank(split.lattice)):
                root = _root(albedo, fm)
                _structure_first(root, spec, split, fm, seed)
            else:
                logger.info("structure: the colour split shows the layout more (%s vs %s); kept", colour[1],
                            layout_rank(split.lattice))
                root.meta["structure_rejected"] = {**split.describe(), "colour_rank": colour[0]}
            return root
    _split(root, spec, fm, seed)
    return root


def _root(albedo: np.ndarray, fm: FeatureMaps) -> MaskNode:
    """An unsplit root over the whole material, naming the matting features."""
    root = root_node(*albedo.shape[:2])
    root.meta["features"] = fm.names
    return root


#: the colour split replaces a found structural split only when its layout is this much more regular: the relief
#: cut is preferred (stains and colour variation stay out of it) unless it has clearly lost the layout
COLOUR_MARGIN = 1.15


def _colour_shows_more(colour: float, structure: float) -> bool:
    return colour > COLOUR_MARGIN * structure


def _colour_layout(root: MaskNode) -> tuple[float, str]:
    """The strongest layout among the root's colour-split layers: (rank, layer id). A relief cut too fine for the
    working size (1-2 px mortar) loses its lattice to speckle while the colours still show the bricks; the first
    split is the one that shows the layout most."""
    best: tuple[float, str] = (-1.0, "")
    for child in root.children:
        rank = layout_rank(analyse_lattice(np.asarray(child.mask) > 0.5))
        if rank > best[0]:
            best = (rank, child.id)
    return best
