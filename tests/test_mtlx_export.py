"""The procedural MaterialX export: the node library, the graph mapping, and its GLSL run on the CPU (llvmpipe)
against proceduralize's own render of the same material."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pptbf_db import pptbf as pp
from workers import graph as G
from workers.mtlx import glsl, library
from workers.noise import fit_noise, noise_params

SIZE = 128
#: a running bond like the fitted bricks: cellular window only, crisp cells, bricks about 2:1
BOND = {"threshold": 0.7, "tiling": 4, "jitter": 0.0, "resolution": 18, "rotation": 0.0, "aspect_ratio": 2.2,
        "window_shape": 1, "window_arity": 4, "window_larp": 1.0, "window_norm": 2.0, "window_smoothness": 0.0,
        "window_blend": 1.0, "window_sigma": 4.0, "feature_mixture": 0}


def bond_params(**edit) -> list[float]:
    v = pp.clip_params(np.zeros(pp.N_PARAMS) + [0.5 * (s.lo + s.hi) if s.kind == "cont" else s.lo
                                                for s in pp.PARAM_SPECS])
    for k, x in {**BOND, **edit}.items():
        v[pp.PARAM_INDEX[k]] = x
    v[pp.PARAM_INDEX["distortion_base"]] = 0.0
    v[pp.PARAM_INDEX["distortion_amplitude"]] = 0.0
    return [float(x) for x in v]


needs_gl = pytest.mark.skipif(not glsl.available(), reason="no headless OpenGL 4 context here (moderngl with EGL: "
                                                         "Debian libegl1 libegl-mesa0 libgl1-mesa-dri)")


@pytest.fixture(scope="module")
def noise_model():
    rng = np.random.default_rng(0)
    img = np.clip(0.5 + 0.1 * rng.standard_normal((64, 64, 3)), 0, 1).astype(np.float32)
    return fit_noise(img, None)


def bricks(noise_model, sigma: float = 0.0, input_size=(256, 256), field: str = "value") -> G.ProceduralMaterial:
    """Mortar (a PPTBF running bond, cut on ``field``) and bricks (its complement): noise albedo, level-filtered
    roughness, a height step (optionally blurred by the blend), normals from the height."""
    mat = G.new_material(seed=5, working_size=(SIZE, SIZE))
    mat.input_size = input_size
    mat.add("mortar", "pptbf", {"params": bond_params(), "ref_width": SIZE, "complement": True, "field": field})
    mat.add("bricks", "level", {"a": -1.0, "d": 1.0, "clamp": True}, input="mortar")
    mat.add("n_mortar", "noise", noise_params(noise_model, seed=1))
    mat.add("n_brick", "noise", noise_params(noise_model, seed=2))
    mat.add("r_mortar", "constant", {"value": 0.9})
    mat.add("r_brick", "level", {"a": 0.5, "d": 0.1}, input="n_brick")
    mat.add("r_brick1", "channel", {"channels": [1]}, input="r_brick")
    mat.add("h_mortar", "constant", {"value": 0.2})
    mat.add("h_brick", "constant", {"value": 0.8})
    for m, (a, b) in {"albedo": ("n_mortar", "n_brick"), "roughness": ("r_mortar", "r_brick1"),
                      "height": ("h_mortar", "h_brick")}.items():
        mat.add(f"{m}_out", "blend", {"sigmas": [sigma if m == "height" else 0.0] * 2, "normalise": True},
                mask0="mortar", child0=a, mask1="bricks", child1=b)
    mat.maps = [{"name": "albedo", "node": "albedo_out"}, {"name": "roughness", "node": "roughness_out"},
                {"name": "height", "node": "height_out"},
                {"name": "normal", "from_height": "height", "strength": 3.0, "tilt": [0.01, -0.02]}]
    return mat


def test_library_files_are_current_and_validate():
    import MaterialX as mx

    for path, make in library.GENERATED.items():
        assert path.read_text(encoding="utf-8") == make(), f"{path} is stale: run python -m workers.mtlx.library"
    doc = mx.createDocument()
    mx.readFromXmlFile(doc, str(library.DEFS_FILE))
    ours = [impl.getFile() for impl in doc.getImplementations()]
    assert sorted(ours) == sorted([nd.file for nd in library.NODEDEFS] + [nd.osl_file for nd in library.NODEDEFS])
    assert all((library.LIBRARY / f).is_file() for f in ours), ours
    std = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), std)
    doc.importLibrary(std)
    ok, msg = doc.validate()
    assert ok, msg
    nd = doc.getNodeDef("ND_pptbf_float")
    names = [i.getName() for i in nd.getInputs()]
    assert names[-pp.N_PARAMS:] == list(pp.PARAM_NAMES)


def export(mat, folder: Path, name="bricks", **kw):
    import MaterialX as mx

    from workers.export import write_document
    from workers.mtlx.procedural import add_material

    doc = mx.createDocument()
    g = add_material(doc, mat, name, SIZE, SIZE, folder, **kw)
    write_document(doc, folder / f"{name}.mtlx", name)       # validates, with the XIncluded library
    return doc, g


@needs_gl
@pytest.mark.parametrize("field", pp.FIELDS)
def test_procedural_graph_renders_like_proceduralize(noise_model, tmp_path, field):
    from workers.mtlx.check import compare

    mat = bricks(noise_model, field=field)
    doc, g = export(mat, tmp_path)
    assert sorted(g.baked) == ["n_brick", "n_mortar"] and g.fixed == [] and g.pinned == []
    maps = G.evaluate(mat, SIZE, SIZE)
    res = compare(doc, g, maps, SIZE, SIZE)
    print(json.dumps(res, indent=1))
    assert set(res) == {"albedo", "roughness", "height", "normal"}
    # the height is the mask's step: its share of equal pixels is the mask's (float32 vs float64 at the borders)
    assert res["height"]["within_2_255"] > 0.995
    for k in ("albedo", "roughness", "height"):
        assert res[k]["mad"] < 0.5 / 255, (k, res[k])
    # a flipped mask pixel changes the Sobel normal of its 8 neighbours
    assert res["normal"]["mad"] < 2 / 255 and res["normal"]["within_2_255"] > 1 - 9 * (
        1 - res["height"]["within_2_255"]) - 1e-3, res["normal"]
    # the normal's 8 reads of the mask come from one pptbf_ring node (one PPTBF in the shader, not eight)
    assert len(g.nodegraph.getNodes("pptbf_ring")) == 1


@needs_gl
def test_blurred_blend_is_baked_and_pins_its_pptbf(noise_model, tmp_path):
    from workers.mtlx.check import compare

    mat = bricks(noise_model, sigma=1.5)
    doc, g = export(mat, tmp_path)
    assert g.fixed == ["height_out"] and g.pinned == ["mortar"]
    seeds = [nd.getInput("seed") for nd in g.nodegraph.getNodes("pptbf")]
    assert seeds and all(i.getInterfaceName() == "" and i.getValue() == 0 for i in seeds)
    res = compare(doc, g, G.evaluate(mat, SIZE, SIZE), SIZE, SIZE)
    for k, r in res.items():
        assert r["mad"] < 0.5 / 255, (k, r)


@needs_gl
def test_negligible_blur_stays_pointwise(noise_model, tmp_path):
    """A blend blur too small to change a mask value by 1/255 is exported as unblurred (fitted sigmas can be
    ~0.0005 px): nothing is baked but the noise, and the maps still match."""
    from workers.mtlx.check import compare
    from workers.nodes.filters import blur_is_identity

    assert blur_is_identity(0.2) and not blur_is_identity(0.3)
    mat = bricks(noise_model, sigma=0.1)              # 0.2 output pixels: the export is at twice the working size
    doc, g = export(mat, tmp_path)
    assert g.fixed == [] and g.pinned == []
    res = compare(doc, g, G.evaluate(mat, SIZE, SIZE), SIZE, SIZE)
    assert res["height"]["mad"] < 1 / 255, res["height"]


def test_cli_export_procedural_check(noise_model, tmp_path):
    from service.cli import main

    path = G.save(bricks(noise_model), tmp_path / "m" / "material.json")
    out = tmp_path / "out"
    args = ["export", str(path), "--size", f"{SIZE}x{SIZE}", "--out", str(out), "--procedural"]
    rc = main(args + (["--check"] if glsl.available() else []))
    assert rc == 0
    info = json.loads((out / "export.json").read_text())
    proc = info["procedural"]
    assert proc["material"] == "M_m_procedural" and sorted(proc["noise_tiles"]) == ["n_brick", "n_mortar"]
    text = (out / "m.mtlx").read_text()
    assert 'href="proceduralize_library/proceduralize_defs.mtlx"' in text and "M_m_procedural" in text
    assert (out / "proceduralize_library" / "genglsl" / "mx_pptbf_float.glsl").is_file()
    assert len(list((out / "m_tiles").glob("*.exr"))) == 2
    if glsl.available():
        assert all(r["mad"] < 2 / 255 for r in proc["check"].values())


def test_glsl_entry_points_take_the_nodedef_inputs_in_order():
    """MaterialX calls an implementation's function with the nodedef's inputs in declaration order."""
    import re

    types = {"vector2": "vec2", "float": "float", "integer": "int", "boolean": "bool"}
    for nd in library.NODEDEFS:
        text = (library.LIBRARY / nd.file).read_text(encoding="utf-8")
        m = re.search(rf"void\s+{nd.function}\s*\(([^)]*)\)", text)
        assert m, nd.file
        args = [a.split() for a in m.group(1).replace("\n", " ").split(",")]
        glsl_type = {**types, "vector4": "vec4"}[nd.type]
        outs = [["out", glsl_type, "result"]] if nd.outputs == ("out",) else [["out", glsl_type, o]
                                                                            for o in nd.outputs]
        want = [[types[t], n] for n, t, _, _ in nd.inputs] + outs
        assert args == want, (nd.file, args)
