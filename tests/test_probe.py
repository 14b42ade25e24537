"""A probe of bad inputs through the real command line (in-process ``service.cli.main``): each case is an input a
careless or hostile user gives, the exit code it must get (2: bad input; 0: handled) and what the message must
name (the file, the field or the value), so that no case ends in a traceback, a raw exception or a silent write.
Nothing here starts Ray: bad manifests are refused before it starts."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from service.cli import main
from service.commands.mask import fit_document
from tests.conftest import small_material
from workers.maps import write_image


def _mask(folder: Path, arr: np.ndarray, name: str = "mask.png") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    return write_image(folder / name, arr.astype(np.float32))


def _fit_json(folder: Path, params) -> Path:
    """A mask fit file as `mask fit` writes it, with `params` (None: the key removed) as the fit's vector."""
    from workers import lattice as L
    from workers.masks import MaskFit

    p = L.layout_params(L.LatticeMatch(4, 12.0, 2.0, 0.0, 0.0), 0.8)
    fit = MaskFit(params=p, complement=False, loss_query=0.0, loss_final=0.0, evaluations=0, seconds=0.0,
                  history=[], fit_size=(64, 64))
    doc = fit_document(fit, folder / "mask.png", (64, 64))
    if params is None:
        doc["fit"].pop("params")
    else:
        doc["fit"]["params"] = params
    path = folder / "fit.json"
    path.write_text(json.dumps(doc))
    return path


def _manifest(folder: Path, material: dict | None = None, **top) -> Path:
    """A manifest (JSON) of one material whose maps exist, with `material` merged into it and `top` sections."""
    maps = folder / "maps"
    maps.mkdir(parents=True, exist_ok=True)
    alb = write_image(maps / "a.png", np.full((32, 32, 3), 0.5, np.float32))
    doc = {"job": {"name": "probe", "output": "out"},
           "materials": [{"name": "m", "albedo": str(alb), **(material or {})}]}
    doc.update(top)
    path = folder / "job.json"
    path.write_text(json.dumps(doc))
    return path


def _material_doc(folder: Path, mutate) -> Path:
    doc = json.loads(small_material(folder / "base.json").read_text())
    mutate(doc)
    path = folder / "material.json"
    path.write_text(json.dumps(doc))
    return path


def _text(folder: Path, name: str, text: str | bytes) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    p = folder / name
    p.write_bytes(text if isinstance(text, bytes) else text.encode())
    return p


def _folder(p: Path) -> Path:
    p.mkdir(parents=True)
    return p


def _set(doc: dict, path: tuple, value) -> None:
    d = doc
    for k in path[:-1]:
        d = d[k]
    d[path[-1]] = value


# each case: label -> (argv from the tmp folder, exit code, substrings the stderr must hold)
CASES = {
    # render / export / edit: the material file itself
    "render: material.json is a JSON list": (
        lambda t: ["render", str(_text(t, "m.json", "[1, 2]")), "--size", "8x8", "--out", str(t / "o")], 2,
        ["m.json"]),
    "render: material.json is truncated JSON": (
        lambda t: ["render", str(_text(t, "m.json", '{"format": ')), "--size", "8x8", "--out", str(t / "o")], 2,
        ["m.json"]),
    "render: material.json is a folder": (
        lambda t: ["render", str(_folder(t / "dirmat.json")), "--size", "8x8", "--out", str(t / "o")], 2,
        ["dirmat.json"]),
    "render: material.json does not exist": (
        lambda t: ["render", str(t / "nope.json"), "--size", "8x8", "--out", str(t / "o")], 2, ["nope.json"]),
    "render: nodes missing": (
        lambda t: ["render", str(_material_doc(t, lambda d: d.pop("nodes"))), "--size", "8x8", "--out",
                   str(t / "o")], 2, ["nodes"]),
    "render: a map names an unknown node": (
        lambda t: ["render", str(_material_doc(t, lambda d: _set(d, ("maps", 0, "node"), "ghost"))), "--size", "8x8",
                   "--out", str(t / "o")], 2, ["ghost"]),
    "render: a node input is a cycle": (
        lambda t: ["render", str(_material_doc(t, lambda d: _set(d, ("nodes", 3, "inputs", "input"), "height"))),
                   "--size", "8x8", "--out", str(t / "o")], 2, ["height"]),
    "render: unknown node type": (
        lambda t: ["render", str(_material_doc(t, lambda d: _set(d, ("nodes", 0, "type"), "laser"))), "--size", "8x8",
                   "--out", str(t / "o")], 2, ["laser"]),
    "render: constant value is a string": (
        lambda t: ["render", str(_material_doc(t, lambda d: _set(d, ("nodes", 0, "params", "value"), "red"))),
                   "--size", "8x8", "--out", str(t / "o")], 2, ["constant.value", "'red'"]),
    "render: albedo of 2 channels": (
        lambda t: ["render", str(_material_doc(t, lambda d: _set(d, ("nodes", 0, "params", "value"), [1, 0]))),
                   "--size", "8x8", "--out", str(t / "o")], 2, ["material.json", "'albedo'", "2 channels"]),
    "render: roughness of 3 channels": (
        lambda t: ["render", str(_material_doc(t, lambda d: _set(d, ("nodes", 1, "params", "value"), [1, 0, 0]))),
                   "--size", "8x8", "--out", str(t / "o")], 2, ["'roughness'", "3 channels"]),
    "render: format from the future": (
        lambda t: ["render", str(_material_doc(t, lambda d: _set(d, ("format",), "proceduralize.material/99.0"))),
                   "--size", "8x8", "--out", str(t / "o")], 2, ["99"]),
    "render: size 0x8": (lambda t: ["render", str(small_material(t / "m.json")), "--size", "0x8", "--out",
                                    str(t / "o")], 2, ["--size"]),
    "render: size 8x-8": (lambda t: ["render", str(small_material(t / "m.json")), "--size", "8x-8", "--out",
                                     str(t / "o")], 2, ["--size"]),
    "render: size 'big'": (lambda t: ["render", str(small_material(t / "m.json")), "--size", "big", "--out",
                                      str(t / "o")], 2, ["--size"]),
    "render: seed -1": (lambda t: ["render", str(small_material(t / "m.json")), "--size", "8", "--seed", "-1",
                                   "--out", str(t / "o")], 2, ["--seed"]),
    "render: seed 2**80": (lambda t: ["render", str(small_material(t / "m.json")), "--size", "8", "--seed",
                                      str(2 ** 80), "--out", str(t / "o")], 2, ["--seed"]),
    "render: scale nan": (lambda t: ["render", str(small_material(t / "m.json")), "--size", "8", "--scale", "nan",
                                     "--out", str(t / "o")], 2, ["--scale"]),
    "render: scale -2": (lambda t: ["render", str(small_material(t / "m.json")), "--size", "8", "--scale", "-2",
                                    "--out", str(t / "o")], 2, ["--scale"]),
    "render: bits 12": (lambda t: ["render", str(small_material(t / "m.json")), "--size", "8", "--bits", "12",
                                   "--out", str(t / "o")], 2, ["--bits"]),
    "render: memory budget 'lots'": (
        lambda t: ["render", str(small_material(t / "m.json")), "--size", "8", "--memory-budget", "lots", "--out",
                   str(t / "o")], 2, ["memory budget", "'lots'"]),
    "edit: unknown node": (lambda t: ["edit", str(small_material(t / "m.json")), "--set", "ghost.value=1"], 2,
                           ["ghost"]),
    "edit: no '=' in --set": (lambda t: ["edit", str(small_material(t / "m.json")), "--set", "alb.value"], 2,
                              ["alb.value"]),
    "edit: albedo value of 2 channels": (
        lambda t: ["edit", str(small_material(t / "m.json")), "--set", "alb.value=[1,2]"], 2, ["'albedo'",
                                                                                             "2 channels"]),
    "edit: level gain 'x'": (
        lambda t: ["edit", str(_material_doc(t, lambda d: d["nodes"].append(
            {"id": "lv", "type": "level", "params": {"a": 1.0, "d": 0.0}, "inputs": {"input": "h0"}}))),
                   "--set", "lv.a=\"x\""], 2, ["level.a"]),
    "export: name with a slash": (
        lambda t: ["export", str(small_material(t / "m.json")), "--size", "8", "--out", str(t / "o"), "--name",
                   "a/b"], 2, ["a/b"]),
    # inspect
    "inspect: a text file named .png": (lambda t: ["inspect", str(_text(t, "fake.png", "hello"))], 2,
                                        ["fake.png"]),
    "inspect: a 0-byte .exr": (lambda t: ["inspect", str(_text(t, "empty.exr", b""))], 2, ["empty.exr"]),
    "inspect: a missing file": (lambda t: ["inspect", str(t / "gone.png")], 2, ["gone.png"]),
    # mask fit / mask render
    "mask fit: not an image": (lambda t: ["mask", "fit", str(_text(t, "m.png", "x")), "--out", str(t / "f.json")], 2,
                               ["m.png"]),
    "mask fit: 4x4 mask": (lambda t: ["mask", "fit", str(_mask(t, np.eye(4))), "--out", str(t / "f.json")], 2,
                           ["mask.png"]),
    "mask fit: all black": (lambda t: ["mask", "fit", str(_mask(t, np.zeros((64, 64)))), "--out",
                                       str(t / "f.json")], 2, ["mask.png"]),
    "mask fit: valid of another size": (
        lambda t: ["mask", "fit", str(_mask(t, np.indices((64, 64)).sum(0) % 16 < 8)), "--valid",
                   str(_mask(t, np.ones((32, 32)), "valid.png")), "--out", str(t / "f.json")], 2, ["valid.png"]),
    "mask fit: budget -5": (lambda t: ["mask", "fit", str(_mask(t, np.eye(64))), "--budget", "-5", "--out",
                                       str(t / "f.json")], 2, ["--budget"]),
    "mask render: params missing": (
        lambda t: ["mask", "render", str(_fit_json(t, None)), "--size", "16", "--out", str(t / "m.png")], 2,
        ["params"]),
    "mask render: params too short": (
        lambda t: ["mask", "render", str(_fit_json(t, [0.5, 4.0])), "--size", "16", "--out",
                   str(t / "m.png")], 2, ["params"]),
    "mask render: tiling 99": (
        lambda t: ["mask", "render", str(_fit_json(t, [0.5, 99.0] + [1.0] * 27)), "--size", "16", "--out",
                   str(t / "m.png")], 2, ["tiling"]),
    "mask render: params hold a string": (
        lambda t: ["mask", "render", str(_fit_json(t, ["a"] * 29)), "--size", "16", "--out",
                   str(t / "m.png")], 2, ["fit.json", "'fit'", "'a'"]),
    # run: manifests refused before Ray starts
    "run: manifest is not TOML": (lambda t: ["run", str(_text(t, "job.toml", "[job\nname = "))], 2, ["job.toml"]),
    "run: unknown section": (lambda t: ["run", str(_manifest(t, shaders={"x": 1}))], 2, ["shaders"]),
    "run: material without albedo": (
        lambda t: ["run", str(_manifest(t, {"albedo": None}))], 2, ["albedo"]),
    "run: working_size 'big'": (lambda t: ["run", str(_manifest(t, {"working_size": "big"}))], 2,
                                ["working_size"]),
    "run: working_size 3": (lambda t: ["run", str(_manifest(t, {"working_size": 3}))], 2, ["working_size"]),
    "run: two materials of one name": (
        lambda t: ["run", str(_manifest(t, None, materials=[{"name": "m", "albedo": "a.png"},
                                                             {"name": "m", "albedo": "a.png"}]))],
        2, ["name used twice"]),
    "run: material name '../x'": (lambda t: ["run", str(_manifest(t, {"name": "../x"}))], 2, ["name"]),
    "run: recompose device 'tpu'": (
        lambda t: ["run", str(_manifest(t, {"recompose": {"device": "tpu"}}))], 2, ["recompose.device"]),
    "run: outputs sizes empty": (
        lambda t: ["run", str(_manifest(t, {"outputs": {"sizes": []}}))], 2, ["outputs.sizes"]),
    "run: seed is a float": (lambda t: ["run", str(_manifest(t, {"seed": 1.5}))], 2, ["seed"]),
    # read commands
    "status: unknown job": (lambda t: ["status", "no-such-job-xyz"], 2, ["no-such-job-xyz"]),
    "results: a text file as database": (lambda t: ["results", str(_text(t, "x.db", "not sqlite"))], 2, ["x.db"]),
    "db info: missing folder": (lambda t: ["db", "info", str(t / "nodb")], 2, ["nodb"]),
}


@pytest.mark.parametrize("label", list(CASES))
def test_probe(tmp_path, capsys, label):
    argv_fn, code, needles = CASES[label]
    argv = argv_fn(tmp_path)
    assert main(argv) == code, (label, capsys.readouterr())
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    err = err.replace(str(tmp_path), "<tmp>")     # the folder's name holds the case's words
    for s in needles:
        assert s in err, (label, err)
