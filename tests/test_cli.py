"""service.cli: inspect, render, demo, help and exit codes (called in-process through main())."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from service.cli import COMMANDS, build_parser, main
from workers.graph import new_material, save
from workers.maps import inspect_image, read_image, write_image


def test_help_for_every_command(capsys):
    assert main(["--help"]) == 0
    top = capsys.readouterr().out
    names = list(build_parser()._subparsers._group_actions[0].choices)
    assert len(names) == len(COMMANDS) and {"inspect", "render", "demo"} <= set(names)
    for name in names:
        assert name in top
        assert main([name, "--help"]) == 0
        assert "usage: proceduralize " + name in capsys.readouterr().out


def test_usage_errors_exit_2(capsys):
    assert main([]) == 2
    assert main(["frobnicate"]) == 2
    assert main(["render", "m.json", "--size", "big", "--out", "x"]) == 2
    assert "WxH" in capsys.readouterr().err


def test_help_is_fast_and_imports_nothing_heavy():
    code = ("import sys; from service.cli import main; main(['--help']); "
            "print(sorted(m for m in ('torch', 'ray', 'OpenImageIO', 'scipy', 'workers.maps') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.strip().splitlines()[-1] == "[]"


def test_inspect_good_and_bad(tmp_path, capsys):
    a = np.random.default_rng(0).random((20, 30, 3)).astype(np.float32)
    good = write_image(tmp_path / "good.png", a, bits=16)
    assert main(["inspect", str(good)]) == 0
    out = capsys.readouterr().out
    assert "good.png: png 30x20, 3 channel(s) (R,G,B), uint16 (16-bit)" in out
    assert f"mean {a[..., 1].mean():.4f}" in out
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"junk" * 10)
    assert main(["inspect", str(good), str(tmp_path / "bad.png")]) == 2
    cap = capsys.readouterr()
    assert "good.png" in cap.out and "bad.png" in cap.err and cap.err.startswith("error:")
    assert main(["inspect", str(tmp_path / "missing.exr")]) == 2
    assert "missing.exr: file not found" in capsys.readouterr().err
    assert main(["inspect", "--json", str(good)]) == 0
    assert json.loads(capsys.readouterr().out)["bit_depth"] == 16


def small_material(path):
    m = new_material(seed=3, working_size=(32, 32))
    m.add("c", "constant", {"value": [0.5, 0.25, 0.1]})
    m.add("r", "constant", {"value": 0.6})
    m.add("h0", "constant", {"value": 0.3})
    m.add("h", "level", {"a": 1.0, "d": 0.2}, input="h0")
    m.maps = [{"name": "albedo", "node": "c"}, {"name": "roughness", "node": "r"}, {"name": "height", "node": "h"},
              {"name": "normal", "from_height": "height", "strength": 2.0}]
    return save(m, path)


def test_render_writes_maps(tmp_path, capsys):
    mj = small_material(tmp_path / "material.json")
    out = tmp_path / "render"
    assert main(["render", str(mj), "--size", "40x24", "--scale", "2", "--seed", "5", "--out", str(out),
                 "--no-preview"]) == 0
    assert "40x24" in capsys.readouterr().out
    info = json.loads((out / "render.json").read_text())
    assert info["seed"] == 5 and info["size"] == [40, 24] and info["scale"] == 2.0
    albedo = read_image(out / "albedo.png")
    assert albedo.shape == (24, 40, 3)
    assert np.allclose(albedo[0, 0], [0.7354, 0.5371, 0.3492], atol=2 / 255)  # linear -> sRGB
    assert inspect_image(out / "height.png")["bit_depth"] == 16
    assert inspect_image(out / "roughness.png")["bit_depth"] == 16
    assert read_image(out / "height.png")[0, 0, 0] == pytest.approx(0.5, abs=1e-4)
    assert np.allclose(read_image(out / "normal.png")[0, 0], [0.5, 0.5, 1.0], atol=1 / 255)


def test_render_bad_material_exit_2(tmp_path, capsys):
    (tmp_path / "bad.json").write_text('{"format": "proceduralize/9", "nodes": [], "maps": []}')
    assert main(["render", str(tmp_path / "bad.json"), "--size", "8x8", "--out", str(tmp_path / "o")]) == 2
    assert "bad.json: unsupported format" in capsys.readouterr().err


def test_render_preview_when_renderer_exists(tmp_path):
    pytest.importorskip("workers.render")
    mj = small_material(tmp_path / "material.json")
    assert main(["render", str(mj), "--size", "32x32", "--out", str(tmp_path / "r")]) == 0
    prev = read_image(tmp_path / "r" / "preview.png")
    assert prev.shape[0] == 32 and prev.shape[1] == 64 and float(prev.max()) > 0.0


def test_demo_small(tmp_path, materials_dir, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--maps-dir", str(materials_dir), "--working-size", "128", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "angular error mean (deg)" in printed and "castle_brick_broken_06" in printed
    rep = json.loads((out / "report.json").read_text())
    assert rep["working_size"] == [128, 128] and rep["normal_orientation"] == "opengl"
    assert 0.1 < rep["angular_error_deg"]["mean"] < 5.0 and rep["height_scale"] > 1.0
    for name in ("height.png", "normal_from_height.png", "albedo.png", "normal.png", "roughness.png"):
        assert (out / name).is_file(), name
    assert inspect_image(out / "height.png")["bit_depth"] == 16


def test_demo_missing_folder_exit_2(tmp_path, capsys):
    assert main(["demo", "--maps-dir", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o")]) == 2
    assert "nowhere" in capsys.readouterr().err


def test_verbose_flag_before_or_after_command(tmp_path, capsys):
    good = write_image(tmp_path / "g.png", np.zeros((4, 4)))
    assert main(["-v", "inspect", str(good)]) == 0
    assert main(["inspect", "-vv", str(good)]) == 0


def test_render_calls_preview_image_with_the_maps(tmp_path, monkeypatch):
    """Contract with workers.render.preview_image(maps): gets every evaluated map, its image is written."""
    import types

    seen = {}

    def preview_image(maps):
        seen.update({k: v.shape for k, v in maps.items()})
        return np.concatenate([maps["albedo"], maps["albedo"]], axis=1)

    monkeypatch.setitem(sys.modules, "workers.render", types.SimpleNamespace(preview_image=preview_image))
    mj = small_material(tmp_path / "material.json")
    assert main(["render", str(mj), "--size", "16x8", "--out", str(tmp_path / "r")]) == 0
    assert seen == {"albedo": (8, 16, 3), "roughness": (8, 16, 1), "height": (8, 16, 1), "normal": (8, 16, 3)}
    assert read_image(tmp_path / "r" / "preview.png").shape == (8, 32, 3)
    assert json.loads((tmp_path / "r" / "render.json").read_text())["preview"] == "preview.png"
