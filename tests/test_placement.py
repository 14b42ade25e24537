"""Where stage work lands on a real multi-node Ray (``ray.cluster_utils.Cluster``, one per module): a head with
no CPUs, a node advertising a fake ``GPU`` resource, a GPU node that joins after the driver started, and the
"auto" fallback to CPU when no GPU comes. Jobs use decompose "none" (no mask fits) unless masks are the point.
"""
from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

import pytest

from service import placement
from service.manifest import validate
from service.scheduler import Scheduler
from service.store import Store
from tests.conftest import REPO, real_material_files, start_local_ray

pytestmark = pytest.mark.ray


# ----------------------------------------------------------------------------- without Ray


def test_route_and_reservation_rules():
    cpu_only = placement.Capacity(cpus=8, node_cpus=4, gpus=0, max_gpus=0)
    scales_from_zero = placement.Capacity(cpus=8, node_cpus=4, gpus=0, max_gpus=4)
    assert [placement.recompose_route(d, cpu_only) for d in ("auto", "cuda", "cpu")] == ["cpu", "gpu", "cpu"]
    assert [placement.recompose_route(d, scales_from_zero) for d in ("auto", "cuda", "cpu")] == ["gpu", "gpu", "cpu"]
    # a CPU recomposer reserves its threads, but never more than the largest node has (it must stay placeable)
    assert placement.cpu_threads(2, cpu_only) == 2
    assert placement.cpu_threads(8, cpu_only) == 4
    assert placement.cpu_threads(2, placement.Capacity(cpus=3, node_cpus=1)) == 1
    assert placement.actor_options("gpu", 1, scales_from_zero) == {"num_cpus": 1, "num_gpus": 1}
    assert placement.actor_options("cpu", 3, cpu_only) == {"num_cpus": 3}
    assert placement.actor_options("masks", 1, placement.Capacity(mask_slots=4)) == {
        "num_cpus": 1, "resources": {placement.MASK_RESOURCE: 1}}


def _pools_scheduler(capacity: placement.Capacity, **pools):
    """A Scheduler with only the pool bookkeeping set (no Ray, no store): what _adopt reads."""
    from service.scheduler import _Pool

    s = Scheduler.__new__(Scheduler)
    s.capacity, s._starting = capacity, {}
    s._pools = {k: _Pool(kind=k, limit=limit, cpus=1.0) for k, limit in pools.items()}
    return s


def test_a_pool_adopts_idle_actors_of_its_shape_and_withdraws_a_pending_one():
    """The CPU pool, at its bound with one actor still waiting for a node, takes the idle mask actor (same shape,
    its pool has nothing queued) and withdraws the waiting one; a busy actor, a pool with work queued, or a mask
    actor pinned by the ``mask_fitter`` resource (another shape) is never taken."""
    from service.scheduler import _Slot

    shape = {"num_cpus": 1}
    s = _pools_scheduler(placement.Capacity(cpus=2, node_cpus=1), masks=1, cpu=2)
    idle = _Slot(handle=None, ready_ref="m", ready=True, options=shape)
    running = _Slot(handle=None, ready_ref="c1", ready=True, busy="ref", options=shape)
    pending = _Slot(handle=None, ready_ref="c2", options=shape)
    s._pools["masks"].slots.append(idle)
    s._pools["cpu"].slots += [running, pending]
    s._pools["cpu"].queue.append(("a", "recompose", "", 1, 0.0))
    s._pools["masks"].queue.append(("b", "masks", "root.0", 1, 0.0))
    s._adopt(s._pools["cpu"])   # the masks pool has work queued: its idle actor stays
    assert s._pools["cpu"].slots == [running, pending] and s._pools["masks"].slots == [idle]
    s._pools["masks"].queue.clear()
    s._adopt(s._pools["cpu"])
    assert s._pools["cpu"].slots == [running, idle] and s._pools["masks"].slots == []

    pinned = _pools_scheduler(placement.Capacity(cpus=2, node_cpus=1, mask_slots=2), masks=1, cpu=2)
    other = _Slot(handle=None, ready_ref="m", ready=True, options={"num_cpus": 1, "resources": {"mask_fitter": 1}})
    pinned._pools["masks"].slots.append(other)
    pinned._pools["cpu"].queue.append(("a", "recompose", "", 1, 0.0))
    pinned._adopt(pinned._pools["cpu"])
    assert pinned._pools["cpu"].slots == [] and pinned._pools["masks"].slots == [other]


def test_masks_take_every_cpu_where_a_recomposition_cannot_run_beside_them():
    """A 2-CPU machine with 2-thread CPU recompositions gets 2 mask actors (with CPUs/2 the second CPU sat idle
    through the whole mask phase: the recomposition it was kept for cannot start beside a mask actor); a node
    that holds both keeps CPUs/2 for masks, and so do 1-thread recompositions (their actors change pools);
    job.mask_actors still decides when given."""
    from types import SimpleNamespace

    def limit(cpus: float, node_cpus: float, recompose_cpus: int = 2, mask_actors=None) -> int:
        s = _pools_scheduler(placement.Capacity(cpus=cpus, node_cpus=node_cpus))
        s.manifest = SimpleNamespace(mask_actors=mask_actors, recompose_cpus=recompose_cpus)
        return s._limit("masks")

    assert limit(2, 2) == 2
    assert limit(4, 2) == 4                 # two 2-CPU nodes: a recomposition takes a whole node
    assert limit(4, 4) == 2 and limit(16, 16) == 8
    assert limit(2, 2, recompose_cpus=1) == 1 and limit(4, 1) == 2
    assert limit(2, 2, mask_actors=1) == 1


def test_declared_gpus_from_the_environment(monkeypatch):
    monkeypatch.setenv(placement.MAX_GPUS_ENV, "3")
    assert placement.declared_gpus() == 3
    monkeypatch.setenv(placement.MAX_GPUS_ENV, "many")
    assert placement.declared_gpus() == 0


def test_manifest_placement_options_are_validated(tmp_path):
    from workers.errors import ManifestError

    doc = {"job": {"name": "p", "output": "out", "gpu_wait_s": -1, "recompose_cpus": 0},
           "materials": [{"name": "a", "albedo": "a.png", "recompose": {"device": "tpu"}}]}
    with pytest.raises(ManifestError) as e:
        validate(doc, root=tmp_path)
    text = str(e.value)
    assert "job.gpu_wait_s" in text and "job.recompose_cpus" in text and "recompose.device" in text
    doc["job"].update(gpu_wait_s=30, recompose_cpus=3)
    doc["materials"][0]["recompose"]["device"] = "cuda"
    man = validate(doc, root=tmp_path)
    device = man.materials[0].stage_options("recompose")["device"]
    assert (man.gpu_wait_s, man.recompose_cpus, device) == (30.0, 3, "cuda")


# ----------------------------------------------------------------------------- on a multi-node cluster


class _Nodes:
    """The module's cluster: head (0 CPU) + one 2-CPU node, and a 1-CPU node with a fake GPU when asked."""

    def __init__(self) -> None:
        from ray.cluster_utils import Cluster

        self.cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 0})
        self.head = self.cluster.head_node.node_id[:8]
        self.cpu = self.cluster.add_node(num_cpus=2).node_id[:8]
        self.gpu_node = None

    @property
    def gpu(self) -> str | None:
        return self.gpu_node.node_id[:8] if self.gpu_node is not None else None

    def add_gpu(self) -> str:
        if self.gpu_node is None:
            self.gpu_node = self.cluster.add_node(num_cpus=1, num_gpus=1)
        return self.gpu

    def drop_gpu(self) -> None:
        if self.gpu_node is not None:
            self.cluster.remove_node(self.gpu_node)
            self.gpu_node = None
            _until(lambda: placement.read_capacity().gpus == 0, 60, "the GPU node to leave")


def _until(cond, seconds: float, what: str) -> None:
    deadline = time.time() + seconds
    while time.time() < deadline:
        if cond():
            return
        time.sleep(0.5)
    pytest.fail(f"timed out after {seconds} s waiting for {what}")


@pytest.fixture(scope="module")
def nodes():
    import ray

    had_session = ray.is_initialized()
    if had_session:  # the session's local Ray: give it back afterwards
        ray.shutdown()
    n = _Nodes()
    try:
        ray.init(address=n.cluster.address, logging_level="WARNING",
                 runtime_env={"env_vars": {"PYTHONPATH": str(REPO)}})
        yield n
    finally:
        ray.shutdown()
        n.cluster.shutdown()
        if had_session:
            start_local_ray()


def _doc(name: str, materials: list[tuple[str, dict]], split: bool = False, **job) -> dict:
    mats = []
    for source, over in materials:
        f = real_material_files(source)
        mats.append({"name": over.pop("name", source), "albedo": str(f["albedo"]), "normal": str(f["normal"]),
                     "roughness": {"file": str(f["roughness"]), "channel": f["roughness_channel"] or 0}, **over})
    return {"job": {"name": name, "output": f"out/{name}", "stages": ["load", "decompose", "noise", "masks",
                                                                      "recompose"], **job},
            "defaults": {"working_size": 48, "recompose": {"iterations": 2},
                         "decompose": {"mode": "auto", "layers": 2} if split else {"mode": "none"},
                         "masks": {"max_evals": 6, "rounds": 1, "time_budget_s": 5.0}},
            "materials": mats}


def _run(doc: dict, root: Path):
    man = validate(doc, root=root)
    with Store(man.database) as store:
        report = Scheduler(man, store=store, progress=False).run()
    return man, report


def _rows(man, material: str) -> tuple[dict, list[dict]]:
    with Store(man.database) as s:
        return ({m["name"]: m for m in s.materials(man.name)}[material], s.items(man.name, material))


def test_head_without_cpus_hosts_no_stage_work(nodes, materials_dir, tmp_path):
    """Tasks and both kinds of actors (masks, CPU recomposition) reserve CPUs, so none lands on the 0-CPU head;
    every item records the seconds it waited for a slot, and the material its device."""
    pytest.importorskip("pptbf_db.index")
    nodes.drop_gpu()
    man, report = _run(_doc("head", [("castle_brick_broken_06", {})], split=True), tmp_path)
    assert report.exit_code == 0, report.errors
    mat, rows = _rows(man, "castle_brick_broken_06")
    ran = [r for r in rows if r["status"] == "done" and r["worker"]]
    stages = {r["stage"] for r in ran}
    assert {"load", "decompose", "noise", "masks", "recompose"} <= stages, stages
    assert {placement.node_of(r["worker"]) for r in ran} == {nodes.cpu}, (nodes.head, [r["worker"] for r in ran])
    assert all(r["wait"] is not None and r["wait"] >= 0 for r in ran)
    assert mat["device"] == "cpu" and mat["device_note"] is None


def test_an_idle_mask_actor_of_the_same_shape_runs_the_recomposition(nodes, materials_dir, tmp_path):
    """With one-CPU recomposition actors, the mask actor left idle when the masks are done takes the recomposition
    (the same process, no second actor started), and no item waits for an actor's start."""
    pytest.importorskip("pptbf_db.index")
    nodes.drop_gpu()
    man, report = _run(_doc("adopt", [("castle_brick_broken_06", {})], split=True, recompose_cpus=1), tmp_path)
    assert report.exit_code == 0, report.errors
    _, rows = _rows(man, "castle_brick_broken_06")
    pid = {r["stage"]: r["worker"].partition("@")[0] for r in rows if r["status"] == "done" and r["worker"]}
    masks = {r["worker"].partition("@")[0] for r in rows if r["stage"] == "masks" and r["status"] == "done"}
    assert pid["recompose"] in masks, (pid, masks)


def test_auto_falls_back_to_cpu_after_the_wait_and_cuda_fails(nodes, materials_dir, tmp_path, monkeypatch, caplog):
    """A cluster that declares GPUs but never brings one up: after job.gpu_wait_s the "auto" material recomposes on
    CPU (warning, note in SQLite), the "cuda" one fails naming the reason, and the GPU demand is withdrawn."""
    nodes.drop_gpu()
    monkeypatch.setenv(placement.MAX_GPUS_ENV, "1")
    caplog.set_level(logging.WARNING, logger="service.scheduler")
    doc = _doc("fallback", [("metal_plate_02", {"name": "auto"}),
                            ("metal_plate_02", {"name": "insist", "recompose": {"iterations": 2, "device": "cuda"}})],
               gpu_wait_s=4)
    man, report = _run(doc, tmp_path)
    assert report.materials == {"auto": "done", "insist": "failed"}, report.errors
    assert "recompose.device = 'cuda'" in report.errors["insist"] and "gpu_wait_s = 4" in report.errors["insist"]
    mat, rows = _rows(man, "auto")
    assert mat["device"] == "cpu" and "gpu_wait_s = 4" in mat["device_note"]
    rec = next(r for r in rows if r["stage"] == "recompose")
    assert placement.node_of(rec["worker"]) == nodes.cpu
    assert any("no GPU actor started within job.gpu_wait_s" in r.getMessage() for r in caplog.records)
    from service.report import ReportOptions, build_report

    with Store(man.database) as s:   # the report says where and why
        index = build_report(s, "fallback", tmp_path / "report", ReportOptions(editing=False))
    page = index.read_text()
    assert "recompose device" in page and "gpu_wait_s = 4" in page
    assert "gpu_wait_s = 4" in (index.parent / "auto.html").read_text()
    _until(lambda: placement.pending_gpu_demand() == 0.0, 30, "the pending GPU demand to be withdrawn")


def test_gpu_node_joining_after_the_driver_started_gets_the_recomposition(nodes, materials_dir, tmp_path,
                                                                         monkeypatch):
    """The GPU group scales from zero: the driver starts with no GPU in the cluster, its GPU actor request is
    visible as pending demand (what an autoscaler acts on), and the recomposition runs there once the node joins."""
    nodes.drop_gpu()
    monkeypatch.setenv(placement.MAX_GPUS_ENV, "1")   # what deploy/ sets on the head of a GPU-scalable cluster
    man = validate(_doc("late", [("roof_slates_02", {})], gpu_wait_s=600), root=tmp_path)
    out: dict = {}

    def drive() -> None:
        with Store(man.database) as store:
            out["report"] = Scheduler(man, store=store, progress=False).run()

    t = threading.Thread(target=drive, daemon=True)
    t.start()
    try:
        _until(lambda: placement.pending_gpu_demand() >= 1.0, 90, "a pending GPU request from the driver")
        assert t.is_alive()
        gpu = nodes.add_gpu()
    finally:
        t.join(400)
    assert not t.is_alive(), "the job did not finish after the GPU node joined"
    assert out["report"].exit_code == 0, out["report"].errors
    mat, rows = _rows(man, "roof_slates_02")
    rec = next(r for r in rows if r["stage"] == "recompose")
    assert placement.node_of(rec["worker"]) == gpu
    assert all(placement.node_of(r["worker"]) != nodes.head for r in rows if r["worker"])


def test_fake_gpu_node_gets_the_actor_which_runs_cpu_torch(nodes, materials_dir, tmp_path, caplog):
    """A node advertising GPU resources whose torch has no CUDA (here: a fake GPU): the recomposition actor is
    placed there (num_gpus=1), checks torch, runs on CPU, and says so in the log and the material's record."""
    gpu = nodes.add_gpu()
    _until(lambda: placement.read_capacity().gpus == 1, 60, "the GPU node")
    caplog.set_level(logging.INFO, logger="service.scheduler")
    man, report = _run(_doc("fake", [("coast_sand_rocks_02", {})]), tmp_path)
    assert report.exit_code == 0, report.errors
    mat, rows = _rows(man, "coast_sand_rocks_02")
    rec = next(r for r in rows if r["stage"] == "recompose")
    assert placement.node_of(rec["worker"]) == gpu
    assert mat["device"] == "cpu" and "sees no CUDA device" in mat["device_note"]
    ready = [r.getMessage() for r in caplog.records if "gpu actor pid" in r.getMessage()]
    assert ready and f"ready on node {gpu}" in ready[0] and "torch on cpu" in ready[0], ready
    assert all(r.levelno == logging.WARNING for r in caplog.records if "gpu actor pid" in r.getMessage())
