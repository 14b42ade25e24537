"""The batch scheduler on a real local Ray (2 CPUs) and a real SQLite store: no mocks.

Most jobs run the fast stage subset (load + decompose at 64 px); the whole pipeline runs with tiny budgets in
the four-material test and in the split-material tests.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from service.commands.status import job_state
from service.manifest import load_manifest, validate
from service.scheduler import Scheduler
from service.stages import STAGE_NAMES
from service.store import Store
from tests.conftest import REAL_MATERIALS, real_material_files
from workers.errors import ManifestError

pytestmark = pytest.mark.ray
REPO = Path(__file__).resolve().parents[1]
FAST = ["load", "decompose"]


def _material(source: str, **over) -> dict:
    f = real_material_files(source)
    m = {"name": source, "albedo": str(f["albedo"]), "normal": str(f["normal"]),
         "roughness": {"file": str(f["roughness"]), "channel": f["roughness_channel"] or 0}}
    m.update(over)
    return m


def _doc(name: str, materials: list[dict], stages=FAST, **job) -> dict:
    return {"job": {"name": name, "output": f"out/{name}", "stages": stages, **job},
            "defaults": {"working_size": 64, "outputs": {"sizes": [64], "seeds": [0]}, "decompose": {"mode": "none"}},
            "materials": materials}


def _run(doc: dict, root: Path, **kw):
    man = validate(doc, root=root)
    with Store(man.database) as store:
        report = Scheduler(man, store=store, progress=False, **kw).run()
    return man, report


def test_four_materials_complete_and_every_stage_is_recorded(ray_session, materials_dir, tmp_path):
    """The whole pipeline (every stage), tiny budgets; one material's
    recomposition actor dies mid-stage (os._exit once): the driver replaces the actor and retries."""
    names = list(REAL_MATERIALS)[:4]
    crashed = names[2]
    marker = tmp_path / "actor.marker"
    doc = _doc("four", [_material(n) for n in names], stages=None)
    # iterations 0: assemble the graph only (the optimiser has its own tests; the split test below runs it)
    doc["defaults"].update(recompose={"iterations": 0}, masks={"max_evals": 20, "rounds": 1})
    faults = {"crash_once": {"stage": "recompose", "marker": str(marker), "material": crashed}}
    man, report = _run(doc, tmp_path, faults=faults)
    assert report.exit_code == 0, report.errors
    assert report.materials == {n: "done" for n in names}
    with Store(man.database) as s:
        assert s.job("four")["status"] == "done"
        ran = [st for st in STAGE_NAMES if s.items("four", names[0], st)
               and s.items("four", names[0], st)[0]["status"] != "unavailable"]
        assert ran[:2] == FAST
        for n in names:
            assert s.materials("four")[names.index(n)]["status"] == "done"
            for stage in ran:
                rows = [r for r in s.items("four", n, stage) if r["attempts"]]  # zero-item stages have none
                # calls queued on the dying actor fail with it and are retried too
                tries = {2} if (n, stage) == (crashed, "recompose") else {1, 2} if stage == "recompose" else {1}
                assert all(r["status"] == "done" and r["executions"] == 1 and r["attempts"] in tries
                           and r["duration"] is not None and r["worker"] for r in rows), rows
                if not rows:
                    continue
                assert s.is_done("four", n, stage, rows[0]["item"], man.output)
            arts = {a["path"] for a in s.artefacts("four", n)}
            assert {f"{n}/load/maps.npz", f"{n}/load/material.json", f"{n}/decompose/tree.json",
                    f"{n}/decompose/masks.npz"} <= arts
            if "output" in ran:
                assert f"{n}/material.json" in arts and f"{n}/maps/64x64_seed0/albedo.png" in arts
            if "recompose" in ran:  # GPU actor only when the cluster has GPUs
                rep = json.loads((man.output / n / "recompose" / "report.json").read_text())
                gpus = ray_session.cluster_resources().get("GPU", 0)
                assert rep["device"].startswith("cuda" if gpus else "cpu")
        workers = {r["worker"] for r in s.items("four")}
        errs = s.errors("four")
        if "recompose" in ran:
            assert marker.is_file()
            assert crashed in {e["material"] for e in errs}
            assert all(e["stage"] == "recompose" and not e["final"] and e["kind"] in ("ActorDiedError", "RayActorError")
                       for e in errs), errs
        else:
            assert not errs
    with np.load(man.output / names[0] / "load" / "maps.npz", allow_pickle=False) as z:
        assert z["albedo"].shape == (64, 64, 3) and z["roughness"].shape == (64, 64, 1)
        assert z["normal"].shape == (64, 64, 3) and np.allclose(np.linalg.norm(z["normal"], axis=2), 1, atol=1e-3)
    assert len(workers) >= 2, f"expected the 2 CPUs to run tasks in parallel, got workers {workers}"


def test_bad_inputs_fail_only_their_material_and_name_the_file(ray_session, materials_dir, tmp_path):
    from workers.maps import read_image, write_image

    good = real_material_files("metal_plate_02")
    corrupt = tmp_path / "corrupt_diff.png"
    corrupt.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 8)
    small = tmp_path / "small_nor.png"
    write_image(small, read_image(good["normal"])[::2, ::2] * 0.5 + 0.25)
    mats = [
        _material("metal_plate_02"),
        _material("roof_slates_02", name="corrupt", albedo=str(corrupt)),
        _material("metal_plate_02", name="mismatch", normal=str(small)),
        _material("roof_slates_02", name="missing", albedo=str(tmp_path / "missing_diff.png")),
    ]
    man, report = _run(_doc("bad", mats), tmp_path)
    assert report.exit_code == 1
    assert report.materials == {"metal_plate_02": "done", "corrupt": "failed", "mismatch": "failed",
                                "missing": "failed"}
    with Store(man.database) as s:
        rows = {m["name"]: m for m in s.materials("bad")}
        assert "corrupt_diff.png" in rows["corrupt"]["error"]
        assert "small_nor.png" in rows["mismatch"]["error"] and "same size" in rows["mismatch"]["error"]
        assert "missing_diff.png" in rows["missing"]["error"] and "not found" in rows["missing"]["error"]
        errs = s.errors("bad")
        assert {e["material"] for e in errs} == {"corrupt", "mismatch", "missing"}
        assert all(e["stage"] == "load" and e["kind"] == "InputError" and e["final"] for e in errs)
        assert s.item("bad", "metal_plate_02", "decompose")["status"] == "done"
        assert s.item("bad", "missing", "decompose") is None  # never started after the failed load


def test_worker_killed_mid_job_is_retried_and_job_completes(ray_session, materials_dir, tmp_path):
    marker = tmp_path / "crashed.marker"
    doc = _doc("crash", [_material("castle_brick_broken_06"), _material("coast_sand_rocks_02")])
    faults = {"crash_once": {"stage": "decompose", "marker": str(marker), "material": "coast_sand_rocks_02"}}
    man, report = _run(doc, tmp_path, faults=faults)
    assert marker.is_file(), "the crash hook did not fire"
    assert report.exit_code == 0, report.errors
    with Store(man.database) as s:
        row = s.item("crash", "coast_sand_rocks_02", "decompose")
        assert row["status"] == "done" and row["attempts"] == 2 and row["executions"] == 1
        errs = s.errors("crash")
        assert len(errs) == 1 and not errs[0]["final"]
        assert errs[0]["kind"] in ("WorkerCrashedError", "RayActorError", "ActorDiedError", "LocalRayletDiedError")
        assert s.item("crash", "castle_brick_broken_06", "decompose")["attempts"] == 1


def test_killed_driver_resumes_without_recomputing_finished_stages(ray_session, materials_dir, tmp_path):
    import ray

    names = ["roof_slates_02", "plastered_stone_wall"]
    doc = _doc("resume", [_material(n) for n in names])
    (tmp_path / "slow.json").write_text(json.dumps(doc))
    (tmp_path / "fast.json").write_text(json.dumps(doc))
    address = ray.get_runtime_context().gcs_address
    env = dict(os.environ, PYTHONPATH=str(REPO), PROCEDURALIZE_HOME=str(tmp_path / "home"),
               PROCEDURALIZE_FAULTS=json.dumps({"sleep": {"stage": "decompose", "seconds": 120}}))
    proc = subprocess.Popen([sys.executable, "-m", "service.cli", "run", str(tmp_path / "slow.json"),
                             "--address", address, "--quiet"], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)
    db = tmp_path / "out" / "resume" / "proceduralize.db"
    try:
        deadline = time.time() + 90
        while time.time() < deadline:
            if db.is_file():
                with Store(db) as s:
                    loads = [s.item("resume", n, "load") for n in names]
                    decs = [s.item("resume", n, "decompose") for n in names]
                if all(r and r["status"] == "done" for r in loads) and \
                        all(r and r["status"] == "running" for r in decs):
                    break
            assert proc.poll() is None, proc.stdout.read().decode()
            time.sleep(0.3)
        else:
            pytest.fail("the driver did not reach the decompose stage in time")
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    with Store(db) as s:
        assert job_state(s.job("resume")).startswith("interrupted")
    man = load_manifest(tmp_path / "fast.json")
    with Store(man.database) as store:
        sched = Scheduler(man, store=store, progress=False)
        report = sched.run()
        assert report.exit_code == 0, report.errors
        assert sched.reused == len(names) and sched.executed == len(names)
        assert store.job("resume")["runs"] == 2
        for n in names:
            load, dec = store.item("resume", n, "load"), store.item("resume", n, "decompose")
            assert (load["executions"], load["attempts"]) == (1, 1), load
            assert dec["status"] == "done" and dec["executions"] == 1 and dec["attempts"] == 2
    # a changed artefact is recomputed, and so is everything downstream of it; the other material is untouched
    npz = man.output / names[0] / "load" / "maps.npz"
    npz.write_bytes(npz.read_bytes() + b"\0")
    with Store(man.database) as store:
        report = Scheduler(man, store=store, progress=False).run()
        assert report.exit_code == 0, report.errors
        assert [store.item("resume", names[0], st)["executions"] for st in FAST] == [2, 2]
        assert [store.item("resume", names[1], st)["executions"] for st in FAST] == [1, 1]


def test_two_jobs_at_once_share_one_database_safely(ray_session, materials_dir, tmp_path):
    # one output folder (a job's database must lie inside its output folder), distinct materials
    shared = tmp_path / "out" / "shared" / "shared.db"
    docs = [{**d, "job": {**d["job"], "output": "out/shared"}}
            for d in (_doc(f"job{k}", [_material(n) for n in names], database="shared.db")
            for k, names in enumerate((["castle_brick_broken_06", "rusty_metal_05"],
                                       ["metal_plate_02", "coast_sand_rocks_02"])))]
    reports: dict[int, object] = {}

    def go(k: int) -> None:
        reports[k] = _run(docs[k], tmp_path)[1]

    threads = [threading.Thread(target=go, args=(k,)) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(300)
    assert all(reports[k].exit_code == 0 for k in range(2)), [reports[k].errors for k in reports]
    with Store(shared) as s:
        assert s.integrity_ok()
        assert {j["name"]: j["status"] for j in s.jobs()} == {"job0": "done", "job1": "done"}
        for k in range(2):
            rows = s.items(f"job{k}")
            assert len(rows) == 4 and all(r["status"] == "done" and r["executions"] == 1 for r in rows)
            assert len({a["path"] for a in s.artefacts(f"job{k}")}) == len(s.artefacts(f"job{k}"))


def test_cli_run_status_results_exit_codes(ray_session, materials_dir, tmp_path, capsys, monkeypatch):
    from service.cli import main

    monkeypatch.setenv("PROCEDURALIZE_HOME", str(tmp_path / "home"))
    monkeypatch.chdir(tmp_path)
    doc = _doc("cli", [_material("metal_plate_02"), _material("roof_slates_02", albedo="nope.png")])
    path = tmp_path / "cli.json"
    path.write_text(json.dumps(doc))
    assert main(["run", str(path), "--quiet"]) == 1
    out = capsys.readouterr().out
    assert "1/2 materials done" in out and "nope.png" in out
    assert main(["status"]) == 0 and "cli" in capsys.readouterr().out
    assert main(["status", "cli"]) == 0
    out = capsys.readouterr().out
    assert "metal_plate_02" in out and "decompose" in out and "failed" in out
    assert main(["results", str(path), "--json"]) == 1
    res = json.loads(capsys.readouterr().out)
    assert {m["name"]: m["status"] for m in res["materials"]} == {"metal_plate_02": "done", "roof_slates_02": "failed"}
    assert all(len(a["checksum"]) == 64 for m in res["materials"] for a in m["artefacts"])
    bad = tmp_path / "bad.toml"
    bad.write_text('[job]\nname = "x"\n')
    assert main(["run", str(bad)]) == 2
    assert "job.output" in capsys.readouterr().err
    assert main(["results", "no-such-job"]) == 2
    # submit validates the manifest before contacting the cluster: bad manifest -> 2, unreachable cluster -> 1
    assert main(["submit", str(bad), "--address", "http://127.0.0.1:9"]) == 2
    assert main(["submit", str(path), "--address", "http://127.0.0.1:9"]) == 1


def _bundled_db() -> Path | None:
    try:
        from pptbf_db.index import default_database_path
    except ImportError:
        return None
    p = default_database_path()
    return p if (p / "meta.json").is_file() else None


# building a tiny database costs ~20 s on 2 shared cores: that run is slow; with the bundled one it is not
_SLOW_WITHOUT_BUNDLED_DB = pytest.mark.slow if _bundled_db() is None else (lambda f: f)


@pytest.fixture(scope="module")
def tiny_pptbf_db(ray_session, tmp_path_factory):
    """The bundled PPTBF database, else a small real one built on the test's Ray, for the mask-fitting actors."""
    pytest.importorskip("pptbf_db.build")
    if _bundled_db() is not None:
        return _bundled_db()
    from pptbf_db.build import BuildConfig
    from pptbf_db.descriptor import DescriptorConfig
    from service.db_build import build_database

    folder = tmp_path_factory.mktemp("pptbf") / "db"
    build_database(folder, BuildConfig(size=32, resolution=48, seed=3, chunk=16, descriptor=DescriptorConfig(dim=8)),
                   workers=2, progress=False)
    return folder


@_SLOW_WITHOUT_BUNDLED_DB
def test_split_material_runs_masks_on_actors_and_renders(ray_session, materials_dir, tmp_path, tiny_pptbf_db):
    """Automatic 3-layer split: 2 PPTBF fits on one actor (index loaded once), recomposition, maps at 2 sizes x 2
    seeds."""
    pytest.importorskip("workers.decompose")
    doc = _doc("split", [_material("castle_brick_broken_06")], stages=None,
               pptbf_database=str(tiny_pptbf_db))
    doc["defaults"].update(decompose={"mode": "auto", "layers": 3}, recompose={"iterations": 2},
                           masks={"max_evals": 15, "rounds": 1, "time_budget_s": 10.0},
                           outputs={"sizes": [64, [96, 48]], "seeds": [0, 5]})
    doc["job"]["mask_actors"] = 1       # (2 CPUs would give masks two actors: recompositions take both CPUs)
    man, report = _run(doc, tmp_path)
    assert report.exit_code == 0, report.errors
    n = "castle_brick_broken_06"
    mdir = man.output / n
    with Store(man.database) as s:
        leaves = s.done_info("split", n, "decompose")["leaves"]
        masks = s.items("split", n, "masks")
        assert [r["item"] for r in masks] == leaves[:-1]  # the last layer is 1 - the fitted ones
        infos = [json.loads(r["info"]) for r in masks]
        assert all(r["status"] == "done" for r in masks) and len(masks) >= 1
        # one actor (job.mask_actors = 1) fitted every mask and loaded the index once
        assert sorted(i["holder_fits"] for i in infos) == list(range(1, len(masks) + 1))
        assert all(i["holder_index_loads"] == 1 for i in infos)
        assert len(s.items("split", n, "noise")) == len(leaves) * 3  # leaves x albedo, height, roughness
        renders = sorted(r["item"] for r in s.items("split", n, "output"))  # one task per size x seed
        assert renders == ["64x64_seed0", "64x64_seed5", "96x48_seed0", "96x48_seed5"]
    fit = json.loads((mdir / "masks" / f"{leaves[0]}.json").read_text())
    assert len(fit["fit"]["params"]) == 29 and fit["node_params"]["ref_width"] == 64
    from workers import graph

    mat = graph.load(mdir / "material.json")
    types = {nd["type"] for nd in mat.nodes.values()}
    assert {"noise", "pptbf", "blend", "level"} <= types
    out = graph.evaluate(mat, 96, 48, seed=5)
    assert out["albedo"].shape == (48, 96, 3) and out["normal"].shape == (48, 96, 3)
    for tag in ("64x64_seed0", "64x64_seed5", "96x48_seed0", "96x48_seed5"):
        assert (mdir / "maps" / tag / "albedo.png").is_file()
    # each map set carries a MaterialX document whose image nodes point at files that are there
    import MaterialX as mx

    doc = mx.createDocument()
    mx.readFromXmlFile(doc, str(mdir / "maps" / "96x48_seed5" / "material.mtlx"))
    files = {nd.getInputValue("file") for nd in doc.traverseTree() if nd.getCategory() == "image"}
    assert files == {"albedo.png", "normal.png", "roughness.png"}
    assert all((mdir / "maps" / "96x48_seed5" / f).is_file() for f in files)
    assert {m.getName() for m in doc.getMaterialNodes()} == {f"M_{n}", f"M_{n}_usd"}
    report_json = json.loads((mdir / "recompose" / "report.json").read_text())
    # the recorded loss is the loss of the material.json written (recomputed independently against the
    # working maps with the job's options), not merely the smaller of the two numbers the optimiser compared
    from service.pipeline import load_working_material
    from workers.recompose import RecomposeConfig, optimise

    again = optimise(graph.load(mdir / "recompose" / "material.json"), load_working_material(mdir),
                     RecomposeConfig.from_dict({"iterations": 0, "seed": 0, "device": "cpu"}))
    assert again.loss_before == pytest.approx(report_json["loss_after"], rel=1e-3)


def test_sub_layer_mask_by_the_inpainting_variant(ray_session, materials_dir, tmp_path, tiny_pptbf_db):
    """masks.incomplete = "inpaint": a nested split's mask is fitted on the completed, re-segmented maps
    (whole image), and the fit records the lattice it found; the top-level mask is fitted as usual; the
    nested tree recomposes (tree ids with dots become graph ids without) and evaluates."""
    doc = _doc("inp", [_material("castle_brick_broken_06")],
               stages=["load", "decompose", "noise", "masks", "recompose"], pptbf_database=str(tiny_pptbf_db))
    doc["defaults"].update(decompose={"mode": "auto", "layers": 2, "structure": False,
                                      "children": {"0": {"layers": 2}}},
                           masks={"max_evals": 8, "rounds": 1, "time_budget_s": 10.0, "incomplete": "inpaint"},
                           recompose={"iterations": 2})
    man, report = _run(doc, tmp_path)
    assert report.exit_code == 0, report.errors
    mdir = man.output / "castle_brick_broken_06"
    fits = {p.stem: json.loads(p.read_text()) for p in (mdir / "masks").glob("*.json")}
    assert set(fits) == {"root.0", "root.0.0"}
    assert "inpaint" not in fits["root.0"]
    inp = fits["root.0.0"]["inpaint"]
    assert 0.0 < inp["white_fraction"] < 1.0 and 0.0 <= inp["lattice_fill_share"] <= 1.0
    assert fits["root.0.0"]["parent"] == "root.0"
    from workers import graph

    mat = graph.load(mdir / "recompose" / "material.json")
    assert {"blend_root_albedo", "blend_root_0_albedo"} <= set(mat.nodes)
    assert graph.evaluate(mat, 48, 32, seed=3)["albedo"].shape == (32, 48, 3)
    doc["defaults"]["masks"]["incomplete"] = "guess"   # a bad value is refused at validation, naming the field
    with pytest.raises(ManifestError, match=r"masks\.incomplete: 'guess' is not one of the known values"):
        _run(dict(doc, job=dict(doc["job"], name="inp2", output="out/inp2")), tmp_path)


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_submit_runs_the_job_through_the_ray_jobs_api(materials_dir, tmp_path, monkeypatch):
    """`proceduralize submit` against a real Ray head with a dashboard (started with --block, stopped by pid)."""
    from ray.job_submission import JobSubmissionClient

    from service.cli import main

    gcs, dash = _free_port(), _free_port()
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
               PYTHONPATH=str(REPO), PROCEDURALIZE_HOME=str(tmp_path / "home"))
    head = subprocess.Popen(["ray", "start", "--head", "--block", f"--port={gcs}", "--num-cpus=2",
                             "--include-dashboard=true", "--dashboard-host=127.0.0.1", f"--dashboard-port={dash}"],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    address = f"http://127.0.0.1:{dash}"
    try:
        deadline = time.time() + 120
        while True:
            try:
                JobSubmissionClient(address).list_jobs()
                break
            except Exception:  # noqa: BLE001 - dashboard not up yet
                assert time.time() < deadline and head.poll() is None, "Ray head with dashboard did not start"
                time.sleep(1)
        path = tmp_path / "submit.json"
        path.write_text(json.dumps(_doc("submitted", [_material("metal_plate_02")])))
        monkeypatch.setenv("PATH", env["PATH"])
        assert main(["submit", str(path), "--address", address, "--wait"]) == 0
        with Store(tmp_path / "out" / "submitted" / "proceduralize.db") as s:
            assert s.job("submitted")["status"] == "done"
            assert all(r["status"] == "done" for r in s.items("submitted"))
    finally:
        os.killpg(head.pid, signal.SIGTERM)
        head.wait(60)


@pytest.mark.slow
def test_two_node_cluster_spreads_stages_over_both_nodes(materials_dir, tmp_path):
    """A real 2-node Ray cluster (ray.cluster_utils.Cluster, 1 CPU each); the driver runs in a subprocess."""
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    cluster.add_node(num_cpus=1)
    try:
        cluster.wait_for_nodes()
        names = list(REAL_MATERIALS)[:4]
        path = tmp_path / "two.json"
        path.write_text(json.dumps(_doc("two", [_material(n) for n in names])))
        env = dict(os.environ, PYTHONPATH=str(REPO), PROCEDURALIZE_HOME=str(tmp_path / "home"))
        out = subprocess.run([sys.executable, "-m", "service.cli", "run", str(path), "--address", cluster.address,
                              "--quiet"], env=env, capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stdout + out.stderr
        with Store(tmp_path / "out" / "two" / "proceduralize.db") as s:
            rows = s.items("two")
            assert len(rows) == 2 * len(names) and all(r["status"] == "done" for r in rows)
            nodes = {r["worker"].rsplit("@", 1)[1] for r in rows}
        assert len(nodes) == 2, nodes
    finally:
        cluster.shutdown()
