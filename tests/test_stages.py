"""The stage registry (service.stages) and the material folder layout (service.folder), without Ray."""
from __future__ import annotations

import dataclasses
import pickle
from pathlib import Path

import numpy as np
import pytest

from service.folder import MaterialFolder
from service.manifest import validate
from service.stages import NOISE_MAPS, STAGE_NAMES, STAGES, Placement, Stage, StageCall, _check_order, run_stage, stage


def _spec(tmp_path: Path, **material):
    doc = {"job": {"name": "j", "output": "out"},
           "materials": [{"name": "m", "albedo": "a.png", "output": "nested/m", **material}]}
    man = validate(doc, root=tmp_path)
    return man, man.materials[0]


def test_registry_order_needs_and_placement():
    assert STAGE_NAMES == ("load", "decompose", "noise", "masks", "recompose", "output")
    assert [s.needs for s in STAGES] == [(), ("load",), ("decompose",), ("decompose",), ("noise", "masks"),
                                         ("recompose",)]
    assert {s.name: s.placement for s in STAGES if s.placement is not Placement.TASK} == {
        "masks": Placement.MASK_ACTOR, "recompose": Placement.RECOMPOSE_ACTOR}
    assert stage("noise") is STAGES[2]
    with pytest.raises(KeyError, match="no stage 'nois'; stages are"):
        stage("nois")
    run = STAGES[0].run
    with pytest.raises(ValueError, match="needs \\['b'\\]"):
        _check_order((Stage("a", needs=("b",), run=run), Stage("b", run=run)))
    with pytest.raises(ValueError, match="declared twice"):
        _check_order((Stage("a", run=run), Stage("a", run=run)))


def test_items_are_planned_from_the_recorded_info(tmp_path):
    _, spec = _spec(tmp_path, outputs={"sizes": [64, [96, 48]], "seeds": [0, 5], "scales": [1, 2.5]})
    info = {"load": {"maps": ["albedo", "normal", "roughness"]},
            "decompose": {"leaves": ["root.0", "root.1"], "nodes": ["root", "root.0", "root.1"],
                          "fit_masks": ["root.0"]}}
    assert stage("load").items(spec, info.__getitem__) == [""]
    assert stage("noise").items(spec, info.__getitem__) == [
        f"{leaf}/{m}" for leaf in ("root.0", "root.1") for m in ("albedo", "roughness")]
    assert set(NOISE_MAPS) >= {"albedo", "roughness", "height"}
    assert stage("masks").items(spec, info.__getitem__) == ["root.0"]
    # without fit_masks (older records): every node but the root
    assert stage("masks").items(spec, {"decompose": {"nodes": ["root", "root.0"]}}.__getitem__) == ["root.0"]
    assert stage("output").items(spec, info.__getitem__) == [
        "64x64_seed0", "64x64_seed0_scale2.5", "64x64_seed5", "64x64_seed5_scale2.5",
        "96x48_seed0", "96x48_seed0_scale2.5", "96x48_seed5", "96x48_seed5_scale2.5"]
    assert stage("noise").items(spec, lambda s: {}) == []


def test_stage_configs_and_options(tmp_path):
    assert [s.name for s in STAGES if s.config is not None] == ["noise", "masks", "recompose"]
    assert "device" in stage("recompose").config_fields() and "max_evals" in stage("masks").config_fields()
    assert stage("load").config_class() is None and stage("load").config_fields() == set()

    @dataclasses.dataclass
    class Cheap:
        strength: float = 1.0

    assert Stage("x", config=Cheap, run=STAGES[0].run).config_fields() == {"strength"}
    _, spec = _spec(tmp_path, recompose={"iterations": 3})
    assert spec.stage_options("recompose") == {"iterations": 3} and spec.stage_options("noise") == {}
    cpu = spec.with_options("recompose", device="cpu")
    assert cpu.stage_options("recompose") == {"iterations": 3, "device": "cpu"}
    assert spec.stage_options("recompose") == {"iterations": 3}  # the original is untouched
    assert cpu.to_json()["recompose"] == {"iterations": 3, "device": "cpu"}


def test_stage_call_pickles_names_its_folder_and_copies_options(tmp_path):
    man, spec = _spec(tmp_path, masks={"max_evals": 5, "starts": 2})
    call = StageCall(job=man.name, root=str(man.output), spec=spec, stage="masks", item="root.0")
    back = pickle.loads(pickle.dumps(call))
    assert back == call and back.spec.to_json() == spec.to_json()
    assert call.folder == MaterialFolder(man.output / "nested" / "m") == MaterialFolder.of(man.material_dir(spec))
    opts = call.options
    opts["max_evals"] = 99
    assert call.options == {"max_evals": 5, "starts": 2}


def test_material_folder_layout(tmp_path):
    f = MaterialFolder(tmp_path / "m")
    rel = {k: str(getattr(f, k).relative_to(f.path)) for k in (
        "working_maps", "working_meta", "working_pngs", "tree_masks", "tree", "recomposed", "recompose_report",
        "published", "evaluation")}
    assert rel == {"working_maps": "load/maps.npz", "working_meta": "load/material.json", "working_pngs": "load/maps",
                   "tree_masks": "decompose/masks.npz", "tree": "decompose/tree.json",
                   "recomposed": "recompose/material.json", "recompose_report": "recompose/report.json",
                   "published": "material.json", "evaluation": "evaluation.json"}
    assert f.mask_png("root.0") == f.path / "decompose" / "masks" / "root.0.png"
    assert f.noise_model("root/1", "albedo") == f.path / "noise" / "root_1__albedo.json"
    assert f.mask_fit("root.0") == f.path / "masks" / "root.0.json"
    assert f.preview("64x64_seed0") == f.path / "maps" / "64x64_seed0" / "preview.png"
    assert f.materialx("t").name == "material.mtlx" and f.orm("t").name == "orm.png"
    assert f.noise_models() == f.mask_fits() == f.previews() == []
    for p in (f.noise_model("b", "height"), f.noise_model("a", "albedo"), f.preview("x")):
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text("{}")
    assert f.noise_models() == [f.noise_model("a", "albedo"), f.noise_model("b", "height")]
    assert f.previews() == [f.preview("x")]


def test_load_and_decompose_write_the_folder_layout(tmp_path):
    """run_stage in-process: every artefact recorded is a path the MaterialFolder names."""
    from workers.maps import write_image

    write_image(tmp_path / "a.png", np.random.default_rng(0).random((24, 32, 3)).astype(np.float32))
    man, spec = _spec(tmp_path, working_size=16, decompose={"mode": "none"})
    folder = MaterialFolder(man.material_dir(spec))
    arts = {}
    for name in ("load", "decompose"):
        res = run_stage(StageCall(job=man.name, root=str(man.output), spec=spec, stage=name))
        arts[name] = {a["path"] for a in res["artefacts"]}
        assert all(a["kind"].startswith(f"{name}:") and len(a["checksum"]) == 64 for a in res["artefacts"])
    rel = lambda p: str(p.relative_to(man.output))  # noqa: E731
    assert {rel(folder.working_maps), rel(folder.working_meta)} <= arts["load"]
    assert arts["decompose"] == {rel(folder.tree_masks), rel(folder.tree), rel(folder.mask_png("root"))}
    assert res["info"]["leaves"] == ["root"] and res["info"]["fit_masks"] == []


def test_output_stage_writes_the_procedural_materialx(tmp_path):
    """outputs.procedural: each render's material.mtlx also holds M_<name>_procedural over our node library."""
    from pptbf_db import pptbf as pp
    from workers import graph as G

    params = [float(x) for x in pp.sample_params(np.random.default_rng(4), 1, ref_width=64)[0]]

    man, spec = _spec(tmp_path, outputs={"sizes": [[64, 64]], "seeds": [3], "preview": False, "procedural": True})
    mat = G.new_material(seed=1, working_size=(64, 64))
    mat.add("mortar", "pptbf", {"params": params, "ref_width": 64})
    mat.add("dark", "constant", {"value": [0.2, 0.1, 0.1]})
    mat.add("light", "constant", {"value": [0.8, 0.7, 0.6]})
    mat.add("albedo_out", "blend", {}, mask="mortar", fg="light", bg="dark")
    mat.add("rough", "constant", {"value": 0.7})
    mat.maps = [{"name": "albedo", "node": "albedo_out"}, {"name": "roughness", "node": "rough"},
                {"name": "height", "node": "mortar"}, {"name": "normal", "from_height": "height"}]
    folder = MaterialFolder(man.material_dir(spec))
    G.save(mat, folder.recomposed)
    res = run_stage(StageCall(job=man.name, root=str(man.output), spec=spec, stage="output"))
    doc_path = folder.materialx("64x64_seed3")
    text = doc_path.read_text()
    assert "M_m_procedural" in text and "M_m\"" in text and "ND_pptbf_float" not in text   # nodes, not defs
    assert (doc_path.parent / "proceduralize_library" / "proceduralize_defs.mtlx").is_file()
    assert str(doc_path.relative_to(man.output)) in {a["path"] for a in res["artefacts"]}
    assert 'seed" type="integer" value="0"' in text      # the document's seed 0 = this render's realisation (3)
