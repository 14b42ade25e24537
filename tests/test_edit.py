"""`proceduralize edit` and `render --scale`: edits land in the JSON and change the maps as they should;
bad paths exit 2 naming the problem; pattern scale 2 doubles the feature size (measured)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from service.cli import main
from workers import graph
from workers.edit import editable_params, parse_assignment, suggest_edit
from workers.maps import read_image

# a PPTBF parameter vector fitted to castle_brick_broken_06 by the pipeline (a real brick-like mask)
BRICK_PPTBF = [0.73175048828125, 8.0, 0.0, 13.0, 1.4376584760729065, 1.004925592716396, 0.02700216961711729,
               0.9402984990140635, 0.9797678241028196, 3.0, 7.882850157665332, 0.834460599414038, 2.420733221524727,
               0.4286564180697303, 0.7750565137137093, 3.2978408298143473, 2.0, 1.3009103350568463,
               0.168576246534335, 3.291755124847469, 1.0, 8.0, 2.9877893544096668, 0.37356006724416824, 3.0,
               0.18634938093869347, 0.7018115691954749, 0.9272643078203976, 0.2905197560297248]


def pattern_material(path: Path, metallic: bool = True) -> Path:
    """A small real graph: PPTBF mask (features ~4 px at scale 1) -> blended albedo (+ level), roughness,
    metallic, blurred height."""
    m = graph.new_material(seed=5, working_size=(64, 64))
    m.add("mask", "pptbf", {"params": BRICK_PPTBF, "complement": False, "ref_width": 16})
    m.add("inv", "level", {"a": -1.0, "d": 1.0, "clamp": True}, input="mask")
    m.add("brick", "constant", {"value": [0.35, 0.12, 0.06]})
    m.add("mortar", "constant", {"value": [0.45, 0.42, 0.38]})
    m.add("blend_albedo", "blend", {"sigmas": [0.5, 0.5]}, mask0="mask", child0="brick", mask1="inv", child1="mortar")
    m.add("albedo_level", "level", {"a": 1.0, "d": 0.0}, input="blend_albedo")
    m.add("rough", "level", {"a": -0.5, "d": 0.85}, input="mask")
    m.add("height", "blur", {"sigma": 1.0}, input="mask")
    m.maps = [{"name": "albedo", "node": "albedo_level", "colorspace": "linear"},
              {"name": "roughness", "node": "rough"}, {"name": "height", "node": "height"},
              {"name": "normal", "from_height": "height", "strength": 2.0, "convention": "opengl"}]
    if metallic:
        m.maps.insert(2, {"name": "metallic", "node": "inv"})
    return graph.save(m, path)


def test_edit_changes_saved_value_and_shifts_the_map(tmp_path, capsys):
    src = pattern_material(tmp_path / "m.json")
    before = graph.evaluate(graph.load(src), 64, 64)["albedo"]
    out = tmp_path / "edited.json"
    assert main(["edit", str(src), "--set", "albedo_level.d=0.1", "--set", "seed=9", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "albedo_level.d: 0 -> 0.1" in printed and "seed: 5 -> 9" in printed
    doc = json.loads(out.read_text())
    node = next(n for n in doc["nodes"] if n["id"] == "albedo_level")
    assert node["params"]["d"] == 0.1 and doc["seed"] == 9
    assert json.loads(src.read_text())["seed"] == 5  # --out leaves the source alone
    after = graph.evaluate(graph.load(out), 64, 64, seed=5)["albedo"]
    np.testing.assert_allclose(after - before, 0.1, atol=1e-6)  # a level offset shifts every pixel
    # a per-channel list value, written in place
    assert main(["edit", str(src), "--set", "brick.value=[0.6, 0.1, 0.1]"]) == 0
    red = graph.evaluate(graph.load(src), 64, 64)["albedo"]
    mask = graph.evaluate(graph.load(src), 64, 64, maps=["metallic"])["metallic"][..., 0] < 0.5  # brick pixels
    assert red[..., 0][mask].mean() > before[..., 0][mask].mean() + 0.15
    np.testing.assert_allclose(red[..., 2][mask].mean(), before[..., 2][mask].mean(), atol=0.05)


@pytest.mark.parametrize("arg, message", [
    ("nope.d=1", "no node with id 'nope'"),
    ("albedo_level.zzz=1", "has no parameter 'zzz'"),
    ("albedo_level.d=abc", "albedo_level.d"),
    ("mask.params.99=1", "mask.params.99"),
    ("novalue", "expected PATH=VALUE"),
])
def test_edit_bad_paths_exit_2_and_leave_the_file(tmp_path, capsys, arg, message):
    src = pattern_material(tmp_path / "m.json")
    text = src.read_text()
    assert main(["edit", str(src), "--set", arg]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and message in err, err
    assert src.read_text() == text


def test_edit_list_shows_parameters_and_values(tmp_path, capsys):
    src = pattern_material(tmp_path / "m.json")
    assert main(["edit", str(src), "--list"]) == 0
    out = capsys.readouterr().out
    assert "albedo_level.d" in out and "mask.params.0" in out and "[0.35, 0.12, 0.06]" in out
    rows = {r["path"]: r for r in editable_params(graph.load(src))}
    assert rows["blend_albedo.sigmas"]["value"] == [0.5, 0.5]
    assert rows["mask.params.0"]["type"] == "pptbf" and rows["mask.params.0"]["label"]
    assert len([p for p in rows if p.startswith("mask.params.")]) == len(BRICK_PPTBF)
    assert main(["edit", str(src)]) == 2  # nothing to do


def test_insert_warps_a_mask_for_every_map_that_read_it(tmp_path, capsys):
    """--insert puts a warp after the mask: every blend, level and blur that read the mask reads the warp; a
    constant driver of 1 with amount 6 along x shifts all maps by 3 px (exactly, bilinear with whole pixels)."""
    src = pattern_material(tmp_path / "m.json")
    m = graph.load(src)
    m.add("one", "constant", {"value": [1.0]})
    graph.save(m, src)
    out = tmp_path / "warped.json"
    assert main(["edit", str(src), "--insert", "mask=warp(by=one, amount=6, angle=0)", "--out", str(out)]) == 0
    assert "inserted warp node mask_warp after mask" in capsys.readouterr().out
    warped = graph.load(out)
    readers = {nid for nid, n in warped.nodes.items() if "mask_warp" in n["inputs"].values()}
    assert readers == {"inv", "blend_albedo", "rough", "height"}
    assert warped.node("mask_warp")["inputs"] == {"input": "mask", "by": "one"}
    before, after = graph.evaluate(graph.load(src), 64, 64), graph.evaluate(warped, 64, 64)
    for name in ("albedo", "roughness", "height", "metallic"):
        np.testing.assert_allclose(after[name], np.roll(before[name], 3, axis=1), atol=1e-5, err_msg=name)
    # refused: a missing driver, an unknown parameter, a bad value, an unknown type; the file is left alone
    for text, message in (("mask=warp(amount=2)", "needs input(s) by"), ("mask=warp(by=one, gain=2)", "no input or "
                          "parameter 'gain'"), ("mask=warp(by=one, amount=1e9)", "warp.amount"),
                          ("mask=swirl(by=one)", "unknown node type 'swirl'"), ("mask warp", "expected NODE=TYPE")):
        assert main(["edit", str(out), "--insert", text]) == 2, text
        assert message in capsys.readouterr().err, text
    assert graph.load(out).to_json() == warped.to_json()


def test_parse_assignment_and_suggested_edit(tmp_path):
    assert parse_assignment("a.b=[1, 2]") == ("a.b", [1, 2])
    assert parse_assignment("a.b=true") == ("a.b", True)
    assert parse_assignment("a.b=hello") == ("a.b", "hello")
    assert parse_assignment("a.b=x=y") == ("a.b", "x=y")
    e = suggest_edit(graph.load(pattern_material(tmp_path / "m.json")), 0.2)
    assert e is not None and e.path == "albedo_level.d" and e.before == 0.0 and e.after == 0.2


def _correlation_length(img: np.ndarray) -> float:
    """Lag (px) where the radially averaged autocorrelation of a zero-mean map first falls below 1/2."""
    x = img - img.mean()
    f = np.fft.fft2(x)
    ac = np.fft.ifft2(np.abs(f) ** 2).real
    ac = np.fft.fftshift(ac / ac.flat[0])
    h, w = ac.shape
    yy, xx = np.indices(ac.shape)
    r = np.hypot(yy - h // 2, xx - w // 2).astype(int)
    radial = np.bincount(r.ravel(), ac.ravel()) / np.bincount(r.ravel())
    k = int(np.argmax(radial < 0.5))
    return k - 1 + (radial[k - 1] - 0.5) / (radial[k - 1] - radial[k])  # linear interpolation


def test_render_scale_2_doubles_the_feature_size(tmp_path):
    src = pattern_material(tmp_path / "m.json")
    lengths = {}
    for s in (1, 2):
        out = tmp_path / f"s{s}"
        assert main(["render", str(src), "--size", "256x256", "--scale", str(s), "--out", str(out),
                     "--no-preview"]) == 0
        rough = read_image(out / "roughness.png")[..., 0]
        assert rough.shape == (256, 256)
        lengths[s] = _correlation_length(rough)
    ratio = lengths[2] / lengths[1]
    assert 1.7 < ratio < 2.3, lengths
