"""Exports of regenerated maps to artists' tools: MaterialX (standard_surface + UsdPreviewSurface) and glTF maps."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import InputError

logger = logging.getLogger(__name__)


@dataclass
class ExportedFiles:
    """Paths written by :func:`export_maps`."""

    folder: Path
    base_color: Path
    normal: Path
    orm: Path
    roughness: Path
    height: Path | None
    materialx: Path | None


def pack_orm(roughness: np.ndarray, metallic: np.ndarray | None = None,
             occlusion: np.ndarray | None = None) -> np.ndarray:
    """glTF occlusion-roughness-metallic texture: R = occlusion (1), G = roughness, B = metallic (0)."""
    r = np.asarray(roughness, dtype=np.float32)
    r = r[..., 0] if r.ndim == 3 else r
    m = np.zeros_like(r) if metallic is None else np.asarray(metallic, dtype=np.float32).reshape(r.shape)
    o = np.ones_like(r) if occlusion is None else np.asarray(occlusion, dtype=np.float32).reshape(r.shape)
    return np.clip(np.stack([o, r, m], axis=-1), 0.0, 1.0)


def encode_normal(normal: np.ndarray) -> np.ndarray:
    """Unit OpenGL normal in [-1,1] -> the usual [0,1] texture encoding."""
    return np.clip(np.asarray(normal, dtype=np.float32) * 0.5 + 0.5, 0.0, 1.0)


def export_maps(maps: dict[str, np.ndarray], folder: str | Path, name: str = "material",
                materialx: bool = True, bits: int = 8, procedural=None) -> ExportedFiles:
    """Write glTF-ready maps (sRGB base colour, OpenGL normal, packed ORM) and, optionally, a MaterialX document
    (``procedural``: see :func:`write_materialx`)."""
    from .maps import linear_to_srgb, write_image

    for req in ("albedo", "normal", "roughness"):
        if req not in maps:
            raise InputError(f"export of {name!r}: map {req!r} missing (have {sorted(maps)})")
    from .maps import output_file

    out = Path(folder)
    base, nrm, orm, rough = (output_file(out, name, f"_{k}.png") for k in ("basecolor", "normal_gl", "orm",
                                                                          "roughness"))
    out.mkdir(parents=True, exist_ok=True)
    write_image(base, linear_to_srgb(np.clip(maps["albedo"], 0, 1)), bits=bits)
    write_image(nrm, encode_normal(maps["normal"]), bits=bits)
    write_image(orm, pack_orm(maps["roughness"], maps.get("metallic")), bits=bits)
    write_image(rough, np.clip(maps["roughness"], 0, 1), bits=bits)
    height = None
    if "height" in maps:
        height = output_file(out, name, "_height.png")
        h = maps["height"]
        write_image(height, (h - h.min()) / max(float(h.max() - h.min()), 1e-8), bits=16)
    mtlx = write_materialx(output_file(out, name, ".mtlx"), name, base.name, nrm.name, rough.name,
                           "metallic" in maps and orm.name or None, procedural=procedural) if materialx else None
    return ExportedFiles(out, base, nrm, orm, rough, height, mtlx)


def write_materialx(path: str | Path, name: str, base_color: str, normal: str, roughness: str,
                    orm: str | None = None, procedural=None) -> Path:
    """A MaterialX 1.38+ document: image nodes -> standard_surface and UsdPreviewSurface, both as materials.

    ``procedural``: a callable given the document (before validation) that adds a procedural material to it
    (``workers.mtlx.procedural.add_material``); the document is then validated against our node library too."""
    doc = materialx_document(name, base_color, normal, roughness, orm)
    if procedural is not None:
        procedural(doc)
    return write_document(doc, path, name)


def materialx_document(name: str, base_color: str, normal: str, roughness: str, orm: str | None = None):
    """The baked-maps MaterialX document (``M_<name>``: standard_surface; ``M_<name>_usd``: UsdPreviewSurface)."""
    import MaterialX as mx

    doc = mx.createDocument()
    ng = doc.addNodeGraph(f"NG_{name}")

    def image(node_name: str, file: str, typ: str, colorspace: str | None = None) -> mx.Node:
        node = ng.addNode("image", node_name, typ)
        inp = node.addInput("file", "filename")
        inp.setValueString(file)
        if colorspace:
            inp.setColorSpace(colorspace)
        return node

    base = image("base_color", base_color, "color3", "srgb_texture")
    rough = image("roughness", roughness, "float")
    nimg = image("normal_image", normal, "vector3")
    nmap = ng.addNode("normalmap", "normalmap", "vector3")
    nmap.addInput("in", "vector3").setConnectedNode(nimg)
    outs = {}
    for nm, node, typ in (("out_base", base, "color3"), ("out_rough", rough, "float"), ("out_normal", nmap, "vector3")):
        o = ng.addOutput(nm, typ)
        o.setConnectedNode(node)
        outs[nm] = o
    metal_out = None
    if orm:
        orm_img = image("orm", orm, "vector3")
        sep = ng.addNode("extract", "metallic_extract", "float")
        sep.addInput("in", "vector3").setConnectedNode(orm_img)
        sep.addInput("index", "integer").setValue(2)
        metal_out = ng.addOutput("out_metal", "float")
        metal_out.setConnectedNode(sep)

    def bind(shader: mx.Node, inp: str, typ: str, out: mx.Output) -> None:
        i = shader.addInput(inp, typ)
        i.setNodeGraphString(ng.getName())
        i.setOutputString(out.getName())

    ss = doc.addNode("standard_surface", f"SR_{name}", "surfaceshader")
    bind(ss, "base_color", "color3", outs["out_base"])
    ss.addInput("base", "float").setValue(1.0)
    bind(ss, "specular_roughness", "float", outs["out_rough"])
    bind(ss, "normal", "vector3", outs["out_normal"])
    if metal_out is not None:
        bind(ss, "metalness", "float", metal_out)
    mat = doc.addMaterialNode(f"M_{name}", ss)

    # UsdPreviewSurface takes the tangent-space normal in [-1, 1] (it applies its own normalmap node)
    n2 = ng.addNode("multiply", "normal_x2", "vector3")
    n2.addInput("in1", "vector3").setConnectedNode(nimg)
    n2.addInput("in2", "float").setValue(2.0)
    nts = ng.addNode("subtract", "normal_tangent", "vector3")
    nts.addInput("in1", "vector3").setConnectedNode(n2)
    nts.addInput("in2", "float").setValue(1.0)
    out_ts = ng.addOutput("out_normal_ts", "vector3")
    out_ts.setConnectedNode(nts)

    usd = doc.addNode("UsdPreviewSurface", f"SR_{name}_usd", "surfaceshader")
    bind(usd, "diffuseColor", "color3", outs["out_base"])
    bind(usd, "roughness", "float", outs["out_rough"])
    bind(usd, "normal", "vector3", out_ts)
    if metal_out is not None:
        bind(usd, "metallic", "float", metal_out)
    doc.addMaterialNode(f"M_{name}_usd", usd)
    logger.debug("MaterialX material %s", mat.getName())
    return doc


def write_document(doc, path: str | Path, name: str) -> Path:
    """Validate ``doc`` against the standard node definitions (and the XIncluded libraries), then write it."""
    import MaterialX as mx

    check = mx.createDocument()
    search = mx.FileSearchPath(str(Path(path).resolve().parent))
    mx.readFromXmlString(check, mx.writeToXmlString(doc), search)
    lib = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), lib)
    check.importLibrary(lib)  # validate against the standard node definitions, not just the syntax
    ok, msg = check.validate()
    if not ok:
        raise InputError(f"MaterialX document for {name!r} does not validate: {msg}")
    p = Path(path)
    mx.writeToXmlFile(doc, str(p))
    logger.info("wrote MaterialX %s", p)
    return p
