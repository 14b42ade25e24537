"""`proceduralize export`: glTF-ready maps that decode back to the evaluated maps, and a MaterialX document
that validates against the standard libraries and references files that exist."""
from __future__ import annotations

import json

import numpy as np
import pytest

from service.cli import main
from tests.test_edit import pattern_material
from workers import graph
from workers.maps import read_image, srgb_to_linear

mx = pytest.importorskip("MaterialX")
Q8 = 1.0 / 255.0


def _export(tmp_path, metallic=True, extra=()):
    src = pattern_material(tmp_path / "brick.json", metallic=metallic)
    out = tmp_path / "export"
    assert main(["export", str(src), "--size", "96x64", "--scale", "1.5", "--seed", "7", "--out", str(out),
                 *extra]) == 0
    maps = graph.evaluate(graph.load(src), 96, 64, scale=1.5, seed=7)
    return out, maps


def test_export_maps_decode_to_the_evaluated_maps(tmp_path):
    out, maps = _export(tmp_path)
    names = sorted(p.name for p in out.iterdir())
    assert names == ["brick.mtlx", "brick_basecolor.png", "brick_height.png", "brick_normal_gl.png", "brick_orm.png",
                     "brick_roughness.png", "export.json"]
    orm = read_image(out / "brick_orm.png")
    assert orm.shape == (64, 96, 3)
    assert np.all(orm[..., 0] == 1.0)  # no occlusion map: fully unoccluded
    assert np.abs(orm[..., 1] - maps["roughness"][..., 0]).max() <= Q8 / 2 + 1e-6
    assert np.abs(orm[..., 2] - maps["metallic"][..., 0]).max() <= Q8 / 2 + 1e-6
    assert maps["metallic"].std() > 0.3  # the check above compares a real pattern, not constants
    n = read_image(out / "brick_normal_gl.png") * 2.0 - 1.0
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip((n * maps["normal"]).sum(-1), -1.0, 1.0)))
    assert ang.mean() < 0.5 and ang.max() < 1.5, (ang.mean(), ang.max())
    assert np.abs(maps["normal"][..., :2]).max() > 0.2  # relief present (OpenGL: +y up, checked in test_height)
    base = srgb_to_linear(read_image(out / "brick_basecolor.png"))
    assert np.abs(base - maps["albedo"]).max() < 0.01
    info = json.loads((out / "export.json").read_text())
    lo, hi = info["height_range"]
    h = read_image(out / "brick_height.png")[..., 0] * (hi - lo) + lo
    assert np.abs(h - maps["height"][..., 0]).max() < 1e-4 * max(hi - lo, 1.0)
    assert info["size"] == [96, 64] and info["seed"] == 7 and info["scale"] == 1.5


def _validated(path):
    doc = mx.createDocument()
    mx.readFromXmlFile(doc, str(path))
    lib = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), lib)
    doc.importLibrary(lib)
    ok, msg = doc.validate()
    assert ok, msg
    return doc


def test_materialx_validates_and_references_existing_files(tmp_path):
    out, _ = _export(tmp_path)
    doc = _validated(out / "brick.mtlx")
    files = [i.getValueString() for n in doc.getNodeGraphs()[0].getNodes("image") for i in n.getInputs()
             if i.getType() == "filename"]
    assert {"brick_basecolor.png", "brick_normal_gl.png", "brick_roughness.png", "brick_orm.png"} == set(files)
    assert all((out / f).is_file() for f in files)
    shaders = {n.getCategory(): n for n in doc.getNodes() if n.getType() == "surfaceshader"}
    assert set(shaders) == {"standard_surface", "UsdPreviewSurface"}
    assert {m.getCategory() for m in doc.getMaterialNodes()} == {"surfacematerial"} and len(doc.getMaterialNodes()) == 2
    ss, usd = shaders["standard_surface"], shaders["UsdPreviewSurface"]
    assert {i.getName() for i in ss.getInputs()} >= {"base_color", "specular_roughness", "normal", "metalness"}
    assert {i.getName() for i in usd.getInputs()} >= {"diffuseColor", "roughness", "normal", "metallic"}
    ng = doc.getNodeGraphs()[0]
    # standard_surface gets the world normal of a normalmap node; UsdPreviewSurface its tangent normal in [-1, 1]
    assert ng.getOutput(ss.getInput("normal").getOutputString()).getConnectedNode().getCategory() == "normalmap"
    assert ng.getOutput(usd.getInput("normal").getOutputString()).getConnectedNode().getCategory() == "subtract"
    base = next(n for n in ng.getNodes("image") if n.getInput("file").getValueString() == "brick_basecolor.png")
    assert base.getInput("file").getColorSpace() == "srgb_texture"


def test_export_without_metallic_and_without_materialx(tmp_path):
    out, maps = _export(tmp_path, metallic=False, extra=("--name", "plain", "--no-materialx"))
    assert not list(out.glob("*.mtlx"))
    orm = read_image(out / "plain_orm.png")
    assert np.all(orm[..., 2] == 0.0) and "metallic" not in maps


def test_export_bad_input_exits_2(tmp_path, capsys):
    assert main(["export", str(tmp_path / "none.json"), "--size", "8x8", "--out", str(tmp_path / "o")]) == 2
    assert "none.json: file not found" in capsys.readouterr().err
    assert main(["export", "x.json", "--size", "0x8", "--out", str(tmp_path / "o")]) == 2
