"""Quality scorecard (workers.evaluate, service.evaluate, ``proceduralize evaluate``) with real maps and a real job.

The job is built without Ray: a manifest validated by service.manifest, its stages run in-process through
service.stages.run_stage and recorded in a real SQLite Store, as the scheduler would record them.
"""
from __future__ import annotations

import csv
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from service.cli import main
from service.manifest import validate
from service.stages import STAGES, StageCall, run_stage
from service.store import Store
from tests.conftest import real_material_files
from workers.evaluate import (
    METHODS,
    METRICS,
    EvalConfig,
    baselines,
    crop_to,
    evaluate_material,
    reference_size,
    summarise,
)

MAPS = ("albedo", "normal", "roughness", "height")


@pytest.fixture(scope="module")
def bricks(materials_dir) -> dict[str, np.ndarray]:
    """Working-size (128 px) maps of a textured real material."""
    from workers.maps import load_material

    f = real_material_files("castle_brick_broken_06")
    m = load_material(f["albedo"], f["normal"], f["roughness"], roughness_channel=f["roughness_channel"],
                      working_size=128)
    return {k: v for k, v in m.maps().items() if v is not None}


def _rows(rows, map_name: str) -> dict:
    return {r.method: r for r in rows if r.map == map_name}


def test_identical_maps_score_near_zero_and_baselines_rank_as_expected(bricks):
    rows = evaluate_material(bricks, bricks, seed=0, material="bricks", config=EvalConfig(lights=4))
    assert {(r.map, r.method) for r in rows} == {(m, k) for m in (*MAPS, "render") for k in METHODS}
    for name in (*MAPS, "render"):
        by = _rows(rows, name)
        proc, half, flat, rpn = by["procedural"], by["half"], by["flat"], by["rpn"]
        # the input itself as 'procedural' output: exact spectrum and histogram, SWD at its sampling floor
        assert proc.spectrum < 1e-9 and proc.histogram < 1e-9, (name, proc)
        assert proc.swd < 0.5 * half.swd, (name, proc.swd, half.swd)
        # a flat material is far worse than the material's other half on every metric
        for m in METRICS:
            assert getattr(flat, m) > 2.0 * getattr(half, m), (name, m, flat, half)
        # random phase noise keeps the spectrum: it beats flat on it by orders of magnitude
        assert rpn.spectrum < 0.1 * flat.spectrum, (name, rpn.spectrum, flat.spectrum)
        assert rpn.spectrum < 3.0 * half.spectrum, (name, rpn.spectrum, half.spectrum)


def test_gram_sees_structure_in_units_of_the_floor(bricks):
    """The VGG-19 Gram distance loses what random-phase noise loses (bricks): noise of the input is several
    times the input's own half-to-half distance on albedo and height, the input itself is at 0, and the
    summary counts the pairs where the procedural maps beat the noise."""
    from workers.evaluate import gram_ratios, gram_summary

    rows = evaluate_material(bricks, bricks, seed=0, material="bricks", config=EvalConfig(lights=2))
    table = {d["map"]: d for d in gram_ratios(rows)}
    assert set(table) == {*MAPS, "render"}
    for name in ("albedo", "height"):
        assert table[name]["rpn"] > 1.5, table[name]
        assert table[name]["flat"] > table[name]["rpn"], table[name]
        assert table[name]["procedural"] < 1e-3
    s = gram_summary(rows)
    assert s["maps"]["pairs"] == 4 and s["render"]["pairs"] == 1
    assert s["maps"]["beats_rpn"] == 1.0 and s["maps"]["median_procedural"] < 1e-3
    assert s["maps"]["median_rpn"] > 1.0
    # a candidate worse than the noise on every map: no pair beaten
    worse = [type(r)(**{**r.to_dict(), "gram": 1e3}) if r.method == "procedural" else r for r in rows]
    assert gram_summary(worse)["maps"]["beats_rpn"] == 0.0


def test_baselines_protocol_sizes_units_and_determinism(bricks):
    b = baselines(bricks, seed=3)
    w, h = reference_size(bricks)
    assert (w, h) == (64, 128)
    for method in ("reference", "half", "rpn", "flat"):
        for k, v in b[method].items():
            assert v.shape[:2] == (h, w), (method, k, v.shape)
    np.testing.assert_array_equal(b["reference"]["albedo"], bricks["albedo"][:, :64])
    np.testing.assert_array_equal(b["half"]["albedo"], bricks["albedo"][:, 64:128])
    for method in ("rpn", "flat"):
        assert np.allclose(np.linalg.norm(b[method]["normal"], axis=2), 1.0, atol=1e-5)
        assert b[method]["normal"][..., 2].min() > 0
        assert 0.0 <= b[method]["roughness"].min() and b[method]["roughness"].max() <= 1.0
    assert np.allclose(b["flat"]["albedo"], bricks["albedo"].mean(axis=(0, 1)), atol=1e-6)
    assert abs(float(b["rpn"]["height"].std()) - float(bricks["height"].std())) < 0.5 * float(bricks["height"].std())
    again = baselines(bricks, seed=3)
    np.testing.assert_array_equal(b["rpn"]["height"], again["rpn"]["height"])
    assert not np.array_equal(b["rpn"]["height"], baselines(bricks, seed=4)["rpn"]["height"])
    # procedural maps larger than the reference are cropped, smaller ones refused
    assert crop_to({"a": np.zeros((200, 100))}, (w, h))["a"].shape == (h, w, 1)
    with pytest.raises(ValueError, match="smaller than the reference"):
        evaluate_material(bricks, {k: v[:32, :32] for k, v in bricks.items()}, config=EvalConfig(render=False))


def test_missing_procedural_map_gives_nan_row_and_summary_ratios(bricks):
    proc = {k: v for k, v in bricks.items() if k != "roughness"}
    rows = evaluate_material(bricks, proc, config=EvalConfig(render=False), material="m")
    assert all(math.isnan(getattr(_rows(rows, "roughness")["procedural"], m)) for m in METRICS)
    s = {d["method"]: d for d in summarise(rows)}
    assert s["procedural"]["rows"] == 3 and s["half"]["rows"] == 4
    assert all(s["half"][f"{m}_ratio_to_half"] == pytest.approx(1.0) for m in METRICS)
    assert all(s["flat"][f"{m}_ratio_to_half"] > 2.0 for m in METRICS)
    assert s["procedural"]["spectrum_ratio_to_half"] < 1e-3  # identical maps: far below the floor


# ----------------------------------------------------------------------------- a real job, built without Ray


def _run_material(store: Store, man, spec) -> None:
    """Run one material's stages in-process and record them as the scheduler does (a failure ends the material)."""
    store.set_material(man.name, spec.name, "running")
    infos: dict = {}
    for st in STAGES:
        stage = st.name
        for item in st.items(spec, infos.__getitem__):
            store.start_item(man.name, spec.name, stage, item)
            call = StageCall(job=man.name, root=str(man.output), spec=spec, stage=stage, item=item)
            try:
                res = run_stage(call)
            except Exception as exc:  # noqa: BLE001 - recorded like the scheduler records it
                msg = f"{type(exc).__name__}: {exc}"
                store.fail_item(man.name, spec.name, stage, item, msg, kind=type(exc).__name__)
                store.set_material(man.name, spec.name, "failed", msg)
                return
            store.finish_item(man.name, spec.name, stage, item, res)
            infos[stage] = res["info"]
    store.set_material(man.name, spec.name, "done")


@pytest.fixture(scope="module")
def job_dir(materials_dir, tmp_path_factory) -> Path:
    """A finished two-leaf 64 px job with one good material, one with a corrupt albedo, one missing its graph."""
    root = tmp_path_factory.mktemp("evaljob")
    f = real_material_files("castle_brick_broken_06")
    corrupt = root / "corrupt_diff.png"
    corrupt.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 8)
    good = {"name": "bricks", "albedo": str(f["albedo"]), "normal": str(f["normal"]),
            "roughness": {"file": str(f["roughness"]), "channel": f["roughness_channel"]}, "seed": 1}
    doc = {"job": {"name": "evaljob", "output": "out"},
           "defaults": {"working_size": 64, "decompose": {"mode": "auto", "layers": 2},
                        "masks": {"max_evals": 4}, "recompose": {"iterations": 3},
                        "outputs": {"sizes": [[64, 64]], "seeds": [0], "preview": False}},
           "materials": [good, {**good, "name": "corrupt", "albedo": str(corrupt)}]}
    man = validate(doc, root=root)
    man.output.mkdir(parents=True)
    with Store(man.database) as store:
        store.register_job(man.name, None, str(man.output), man.to_json())
        store.sync_materials(man.name, [{"name": m.name, "output": m.output, "spec_hash": m.spec_hash(),
                                         "spec": m.to_json()} for m in man.materials])
        for spec in man.materials:
            _run_material(store, man, spec)
        # a third material whose output stage never finished: a copy of the good one without its graph
        shutil.copytree(man.output / "bricks", man.output / "nograph")
        (man.output / "nograph" / "material.json").unlink()
        store.sync_materials(man.name, [{"name": "nograph", "output": "nograph", "spec_hash": "x", "spec": {}}])
        store.set_material(man.name, "nograph", "running")
        store.finish_job(man.name, "failed")
    return man.output


def test_evaluate_job_writes_every_row_and_names_the_failures(job_dir, capsys):
    assert main(["evaluate", str(job_dir), "--lights", "2"]) == 1  # some materials could not be scored
    out = capsys.readouterr().out
    assert "not evaluated: corrupt: material failed" in out and "corrupt_diff.png" in out
    assert "not evaluated: nograph: no material.json" in out
    assert "procedural" in out and "spectrum/half" in out

    ev = job_dir / "evaluation"
    with open(ev / "metrics.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [tuple(r) for r in rows[:1]] == [("material", "map", "method", "swd", "spectrum", "histogram", "gram")]
    assert {(r["material"], r["map"], r["method"]) for r in rows} == {
        ("bricks", m, k) for m in (*MAPS, "render") for k in METHODS}
    assert all(float(r[m]) >= 0 for r in rows for m in METRICS)
    doc = json.loads((ev / "metrics.json").read_text())
    assert len(doc["rows"]) == len(rows) == 20 and doc["seed_offset"] == 1000
    assert {s["material"] for s in doc["skipped"]} == {"corrupt", "nograph"}
    summary = {s["method"]: s for s in doc["summary"]}
    assert set(summary) == set(METHODS) and summary["half"]["swd_ratio_to_half"] == pytest.approx(1.0)
    # the procedural output is a real material: far closer to the input than a flat one
    assert summary["procedural"]["spectrum"] < 0.2 * summary["flat"]["spectrum"]
    assert summary["procedural"]["histogram"] < summary["flat"]["histogram"]
    per = json.loads((job_dir / "bricks" / "evaluation.json").read_text())
    assert per["reference_size"] == [32, 64] and per["evaluation_seed"] == per["graph_seed"] + 1000
    assert len(per["rows"]) == 20
    assert not (job_dir / "corrupt" / "evaluation.json").exists()


def test_evaluate_is_deterministic_and_rejects_bad_references(job_dir, tmp_path, capsys):
    a, b = tmp_path / "a", tmp_path / "b"
    for out in (a, b):
        assert main(["evaluate", str(job_dir), "--material", "bricks", "--no-render", "--out", str(out)]) == 0
    assert (a / "metrics.csv").read_text() == (b / "metrics.csv").read_text()
    assert len(json.loads((a / "metrics.json").read_text())["rows"]) == 16
    capsys.readouterr()
    assert main(["evaluate", str(tmp_path / "nowhere")]) == 2
    assert main(["evaluate", str(job_dir), "--material", "nosuch"]) == 2
    assert "nosuch" in capsys.readouterr().err


def test_service_and_worker_agree_on_metric_names():
    from service import evaluate as sev

    assert sev.METRICS == METRICS
