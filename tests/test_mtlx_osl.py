"""The OSL implementations (MaterialX genosl) of the node library: current generated files and entry points in the
nodedefs' order (always); with an OSL compiler (Cycles' oslc from the PyPI bpy wheel, in a separate environment
named by PROCEDURALIZE_BPY_PYTHON): every file compiles, MaterialX's OSL of a procedural material compiles, and
Cycles renders of the OSL PPTBF and per-cell draws match numpy."""
from __future__ import annotations

import functools
import re
from pathlib import Path

import numpy as np
import pytest

from pptbf_db import pptbf as pp
from workers.errors import InputError
from workers.mtlx import library, osl

W = 64


@functools.lru_cache(maxsize=1)
def _bpy_python() -> str | None:
    try:
        return osl.bpy_python()
    except osl.OslUnavailable:
        return None


needs_oslc = pytest.mark.skipif(_bpy_python() is None, reason=f"no OSL compiler: {osl.BPY_HINT}")


def test_osl_generated_files_are_current():
    for path, make in osl.GENERATED.items():
        assert path.read_text(encoding="utf-8") == make(), f"{path} is stale: run python -m workers.mtlx.osl"
    assert [i[0] for i in osl.IMPLEMENTATIONS] == [nd.name for nd in library.NODEDEFS]
    assert all((library.LIBRARY / f).is_file() for _, f, _ in osl.IMPLEMENTATIONS)


def test_osl_entry_points_take_the_nodedef_inputs_in_order():
    """MaterialX's OSL generator calls the function with the nodedef's inputs in order, then the outputs (a
    boolean is an int in its OSL)."""
    types = {"vector2": "vector2", "float": "float", "integer": "int", "boolean": "int"}
    for nd in library.NODEDEFS:
        text = (library.LIBRARY / osl.osl_file(nd)).read_text(encoding="utf-8")
        m = re.search(rf"void\s+{nd.function}\s*\(([^)]*)\)", text)
        assert m, nd.function
        args = [a.split() for a in m.group(1).replace("\n", " ").split(",")]
        typ = {**types, "vector4": "vector4"}[nd.type]
        outs = [["output", typ, "result"]] if nd.outputs == ("out",) else [["output", typ, o] for o in nd.outputs]
        assert args == [[types[t], n] for n, t, _, _ in nd.inputs] + outs, nd.function


def test_osl_tables_keep_the_glsl_tables():
    """The OSL tables hold the GLSL tables' values (uint multiplier powers as int bits)."""
    from workers.mtlx import tables

    glsl, text = tables.glsl_tables(), tables.osl_tables()
    for name in ("pptbf_perm", "pptbf_noise", "pptbf_code", "pptbf_ex_rho"):
        g = re.search(rf"{name}\[\d+\] = \w+\[\d+\]\((.*?)\);", glsl, re.S).group(1)
        o = re.search(rf"\b{name}\(int i\)\n{{\n    \w+ t\[\d+\] = {{(.*?)}};", text, re.S).group(1)
        assert re.findall(r"-?[\d.e+-]+", g.replace("ivec3", "")) == re.findall(r"-?[\d.e+-]+", o), name
    mpow = re.search(r"pptbf_mpow\(int i\)\n{\n    int t\[\d+\] = {(.*?)};", text, re.S).group(1)
    assert [int(v, 0) % 2 ** 32 for v in mpow.replace("\n", " ").split(",")] == [int(v) for v in pp.MPOW]


def _call(nd) -> list[str]:
    args = [{"vector2": "tc", "float": "0.5", "integer": "1", "boolean": "0"}[t] for _, t, _, _ in nd.inputs]
    outs = [f"o_{nd.node}"] if nd.outputs == ("out",) else [f"{o}_{nd.node}" for o in nd.outputs]
    return [f"    {nd.type} {o};" for o in outs] + [f"    {nd.function}({', '.join(args + outs)});"]


@needs_oslc
def test_every_osl_file_compiles(tmp_path):
    """One shader that includes every implementation file (and so the lib/ files) and calls every function."""
    inc = "\n".join(f'#include "{library.LIBRARY / f}"' for _, f, _ in osl.IMPLEMENTATIONS)
    calls = "\n".join(line for nd in library.NODEDEFS for line in _call(nd))
    src = f"""#include "mx_funcs.h"
{inc}
shader all_nodes(output color Out = 0)
{{
    vector2 tc = vector2(u, v);
{calls}
    Out = color(o_pptbf + o_pptbf_cells + ring0_pptbf_ring.x + ring1_pptbf_ring.w, o_tile_coords.x + o_cell_kind,
                o_cell_normal);
}}
"""
    oso = osl.compile_osl_with(_bpy_python(), src, tmp_path, osl.materialx_osl_include())
    assert oso.stat().st_size > 0
    with pytest.raises(InputError, match="does not compile"):
        osl.compile_osl_with(_bpy_python(), src.replace("o_cell_normal);", "undeclared);"), tmp_path / "bad",
                             osl.materialx_osl_include())


def _with_osl_implementations(defs: Path) -> None:
    """Add the genosl implementations to a (copied) nodedef document where it has none yet."""
    import MaterialX as mx

    doc = mx.createDocument()
    mx.readFromXmlFile(doc, str(defs))
    for nd_name, file, function in osl.IMPLEMENTATIONS:
        if not any(i.getTarget() == "genosl" for i in doc.getImplementations() if i.getNodeDefString() == nd_name):
            impl = doc.addImplementation(f"IM_{nd_name[3:]}_genosl")
            impl.setNodeDefString(nd_name)
            impl.setFile(file)
            impl.setFunction(function)
            impl.setTarget("genosl")
    mx.writeToXmlFile(doc, str(defs))


def _procedural_doc(tmp_path: Path, noise_model):
    """The bricks material of test_mtlx_export as a procedural MaterialX document in tmp_path, with the libraries
    imported (the standard ones and a copy of ours with the genosl implementations)."""
    import MaterialX as mx

    from tests.test_mtlx_export import bricks
    from workers.mtlx.procedural import LIBRARY_DIRNAME, add_material

    doc = mx.createDocument()
    g = add_material(doc, bricks(noise_model), "bricks", 128, 128, tmp_path)
    lib = tmp_path / LIBRARY_DIRNAME
    _with_osl_implementations(lib / library.DEFS_NAME)
    full = mx.createDocument()
    full.copyContentFrom(doc)
    std = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), std)
    ours = mx.createDocument()
    mx.readFromXmlFile(ours, str(lib / library.DEFS_NAME))
    full.importLibrary(std)
    full.importLibrary(ours)
    ok, msg = full.validate()
    assert ok, msg
    return doc, full, g, lib        # (doc: g's elements live in it)


@pytest.fixture(scope="module")
def noise_model():
    from workers.noise import fit_noise

    rng = np.random.default_rng(0)
    img = np.clip(0.5 + 0.1 * rng.standard_normal((64, 64, 3)), 0, 1).astype(np.float32)
    return fit_noise(img, None)


@needs_oslc
def test_materialx_osl_of_a_procedural_material_compiles(tmp_path, noise_model):
    """MaterialX's OSL generator writes a shader per map output of a material that uses the PPTBF (mask and
    ring), per-cell-free nodes and baked tiles; every one compiles."""
    doc, full, g, lib = _procedural_doc(tmp_path, noise_model)
    assert {"albedo", "roughness", "height", "normal"} <= set(g.outputs)
    for name, output in g.outputs.items():
        src = osl.generate_osl(full, full.getDescendant(output.getNamePath()), lib)
        if name in ("height", "normal"):
            assert "mx_pptbf_" in src and "pptbf_eval" in src, name
        osl.compile_osl_with(_bpy_python(), src, tmp_path / "osl" / name, osl.materialx_osl_include())


def _probe(function: str) -> str:
    """A shader that writes the PPTBF core's V and cell key at base coordinates pixel / unit + shift (the OSL
    twin of workers.mtlx.check.pptbf_shader)."""
    params = "\n".join(f"    float prm{k} = 0.0," for k in range(pp.N_PARAMS))
    core = library.LIBRARY / "genosl" / "lib" / "pptbf_core.osl"
    return f"""#include "{core}"
shader pptbf_probe(
{params}
    float unit = 64.0, float shiftx = 0.0, float shifty = 0.0, float ref_width = 64.0, float size = 64.0,
    output color Out = 0)
{{
    float i = (P[0] + 1.0) * 0.5 * size - 0.5;
    float j = (1.0 - (P[1] + 1.0) * 0.5) * size - 0.5;
    float prm[{pp.N_PARAMS}] = {{{", ".join(f"prm{k}" for k in range(pp.N_PARAMS))}}};
    float key;
    float V = {function}(i / unit + shiftx, j / unit + shifty, ref_width, prm, key);
    Out = color(V, key, 0.0);
}}
"""


@pytest.mark.slow
@needs_oslc
def test_osl_pptbf_matches_numpy(tmp_path):
    """The OSL PPTBF rendered by Cycles (CPU) against numpy on the GLSL test's cases (every tiling, window,
    mixture, cellular setting, 20 random vectors): masks at the database thresholds and cell keys."""
    from tests.test_pptbf_glsl import AGREEMENT, CASES, SHIFT

    names = sorted(CASES)
    cases = [{**{f"prm{k}": float(v) for k, v in enumerate(CASES[n])}, "shiftx": SHIFT[0], "shifty": SHIFT[1]}
             for n in names]
    out = osl.render_osl(_bpy_python(), _probe("pptbf_eval"), W, W, cases, tmp_path)
    low = {}
    for n, img in zip(names, out):
        ref, keys = pp.evaluate(CASES[n], W, W, shift=SHIFT, ref_width=W, cells=True)
        for q in pp.DATABASE_THRESHOLDS:
            cut = float(np.quantile(ref, 1.0 - q))
            share = float(np.mean((img[..., 0] > cut) == (ref > cut)))
            if share < AGREEMENT:
                low[(n, q)] = share
        gk = np.rint(img[..., 1].astype(np.float64) * 2 ** 24).astype(np.int64)
        if np.mean(gk == keys) < AGREEMENT:
            low[(n, "keys")] = float(np.mean(gk == keys))
    assert not low, low


@pytest.mark.slow
@needs_oslc
def test_osl_cell_draws_and_tile_coords_match_numpy(tmp_path):
    """cell_kind, cell_normal and tile_coords (pz_seed's integer hashes in OSL's int) draw what numpy draws."""
    from workers.nodes.instances import _mix, cell_normal, cell_uniform

    inc = "\n".join(f'#include "{library.LIBRARY / "genosl" / f"mx_{n}.osl"}"'
                    for n in ("cell_kind_float", "cell_normal_float", "tile_coords_vector2"))
    src = f"""#include "mx_funcs.h"
{inc}
shader draws(int seed = 0, int stream = 7, int k = 0, output color Out = 0)
{{
    vector2 tc = vector2((P[0] + 1.0) * 0.5, (P[1] + 1.0) * 0.5);
    float cells = (floor(tc.x * {W}.0) + {W}.0 * floor((1.0 - tc.y) * {W}.0)) * 977.0 / 16777216.0;
    float kind, nrm;
    mx_cell_kind_float(cells, 1.0, seed, stream, 0.25, 0.75, kind);
    mx_cell_normal_float(cells, seed, stream, k, nrm);
    vector2 t;
    mx_tile_coords_vector2(tc, vector2(0.0, 0.0), vector2({W}.0, {W}.0), vector2(32.0, 48.0), 2.0, seed, stream, t);
    Out = color(kind, nrm, t.x);
}}
"""
    settings = [(0, 7, 0), (5, 7, 1), (123456, 2 ** 31 - 5, 3)]
    out = osl.render_osl(_bpy_python(), src, W, W, [{"seed": s, "stream": st, "k": k} for s, st, k in settings],
                         tmp_path, osl.materialx_osl_include())
    cells = (np.arange(W * W).reshape(W, W) * 977 / 2 ** 24)
    for (seed, stream, k), img in zip(settings, out):
        st = stream if seed == 0 else int(np.uint32(stream) ^ _mix(np.uint32(seed)))
        u = cell_uniform(cells, st, 0)
        kind = ((u >= 0.25) & (u < 0.75)).astype(np.float32)
        assert np.mean(img[..., 0] == kind) == 1.0, seed
        assert np.abs(img[..., 1] - cell_normal(cells, st, k)).max() < 1e-4, seed
        # tile_coords: x of the tile at texcoord u (scale 2, tile 32 px, seed offset), against the GLSL formula
        i = ((np.arange(W) + 0.5) - 0.5) / 2.0 + 0.5
        with np.errstate(over="ignore"):
            h = _mix(np.uint32(seed) * np.uint32(0x9E3779B9) + _mix(np.uint32(stream)))
        ox = float(h >> np.uint32(8)) / 2 ** 24 if seed else 0.0
        assert np.abs(img[0, :, 2] - (i / 32.0 + ox)).max() < 1e-3, seed


@pytest.mark.slow
@needs_oslc
def test_materialx_osl_renders_like_proceduralize(tmp_path, noise_model):
    """MaterialX's OSL of the bricks' height (a pptbf node) and normal (a pptbf_ring node) rendered by Cycles
    against proceduralize's own maps, with the GLSL test's bounds (texture coordinates from P: Cycles' u, v are
    not the plane's UVs)."""
    from tests.test_mtlx_export import SIZE, bricks
    from workers import graph as G

    doc, full, g, lib = _procedural_doc(tmp_path, noise_model)
    maps = G.evaluate(bricks(noise_model), SIZE, SIZE)
    within = {}
    for name in ("height", "normal"):
        src = osl.generate_osl(full, full.getDescendant(g.outputs[name].getNamePath()), lib)
        assert src.count("vector2(u,v)") == 1, name
        src = src.replace("vector2(u,v)", "vector2((P[0] + 1.0) * 0.5, (P[1] + 1.0) * 0.5)")
        out = osl.render_osl(_bpy_python(), src, SIZE, SIZE, [{}], tmp_path / name, osl.materialx_osl_include())
        ref = np.asarray(maps[name], dtype=np.float32)
        ref = ref.reshape(SIZE, SIZE, -1)
        d = np.abs(out[0, ..., :ref.shape[-1]] - ref)
        if name == "normal":
            d = d[1:-1, 1:-1]        # numpy's Sobel wraps around the image, the shader reads the pattern on
        within[name] = float((d.max(axis=-1) <= 2 / 255).mean())
        assert d.mean() < 2 / 255, (name, float(d.mean()))
    assert within["height"] > 0.995, within
    assert within["normal"] > 1 - 9 * (1 - within["height"]) - 1e-3, within
