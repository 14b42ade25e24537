"""Batch throughput: materials per hour of one job on 1, 2, 4 simulated CPU worker nodes, and where time waits.

    python bench/throughput.py                                  # 4 materials, working size 64, 1/2/4 nodes
    python bench/throughput.py --nodes 1 2 --materials 6 --working-size 96
    python bench/throughput.py --cuda                           # on a GPU machine: CPU vs CUDA recomposition

Each configuration runs the same job from scratch (fresh output folder) on a fresh ``ray.cluster_utils.Cluster``:
a head with no CPUs (it only hosts the driver, as in deploy/) and N worker nodes of ``--cpus-per-node`` CPUs.
Every task and actor reserves the CPUs its threads use, so N one-CPU nodes are N cores' worth of work (on a
machine with fewer cores than N x CPUs they share the cores, so read the 4-node row against ``nproc``).

The table: wall seconds, materials/hour, speed-up over the first row, the machine's own ceiling for that many
workers (``ceiling``: n copies of one single-threaded kernel of the pipeline's kind, torch convolutions and numpy
FFTs, run at once without Ray, n x the time of one copy alone over the time of the n; a machine whose cores slow
each other down cannot give any scheduler more), the same read off the job's own items (``items' ceiling``: the
CPUs over the first row's, times its items' summed run seconds over this row's: what the speed-up would be if
the workers were always full; the speed-up over it is the scheduler's share), how full the workers were
(``busy %``: the items' summed seconds over span x CPUs; ``head`` / ``tail``: seconds at the start and the end
with fewer items running than CPUs), and per stage the share of its items' time spent waiting for a
slot (``wait / (wait + run)`` from the job database: a task waiting for a CPU, a mask
or recomposition call waiting in the driver's queue for an actor) and the CPU seconds the worker process spent
over the items' run seconds (``cpu %``: above 100 a stage runs more threads than it reserved, well under 100 it
waits for cores its neighbours hold).

``--cuda`` runs the job once with ``recompose.device = "cpu"`` and once with ``"cuda"`` on a local Ray that
sees the machine's GPU, and prints per material the recomposition seconds, device and final loss of both.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

from service.stages import STAGE_NAMES  # noqa: E402
from tests.conftest import REAL_MATERIALS, SHARED_MATERIALS, real_material_files  # noqa: E402

STAGE_ORDER = list(STAGE_NAMES)


def job_doc(n: int, working_size: int, iterations: int, out_size: int, decompose: str = "auto",
            device: str = "auto", pptbf_db: str | None = None) -> dict:
    """A job of ``n`` real materials (cycling through the shared set under distinct names)."""
    names = list(REAL_MATERIALS)
    mats = []
    for i in range(n):
        src = names[i % len(names)]
        f = real_material_files(src)
        mats.append({"name": f"{src}_{i}", "albedo": str(f["albedo"]), "normal": str(f["normal"]),
                     "roughness": {"file": str(f["roughness"]), "channel": f["roughness_channel"] or 0},
                     "seed": i})
    job: dict = {"name": "bench", "output": "out", "gpu_wait_s": 60}
    if pptbf_db:
        job["pptbf_database"] = str(Path(pptbf_db).resolve())
    return {"job": job, "materials": mats,
            "defaults": {"working_size": working_size, "recompose": {"iterations": iterations, "device": device},
                         "masks": {"max_evals": 30, "rounds": 1, "time_budget_s": 15.0},
                         "decompose": {"mode": "auto", "layers": 2} if decompose == "auto" else {"mode": "none"},
                         "outputs": {"sizes": [out_size], "seeds": [0]}}}


def _warm(nodes: list) -> None:
    """Start one worker process per node outside the timing (Ray starts task workers lazily)."""
    import ray
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    @ray.remote(num_cpus=1)
    def ping() -> int:
        import numpy  # noqa: F401  - what every stage imports first

        return os.getpid()

    ray.get([ping.options(scheduling_strategy=NodeAffinitySchedulingStrategy(n.node_id, soft=False)).remote()
             for n in nodes])


def _summarise(store, job: str) -> tuple[dict, dict, dict]:
    """Per stage: summed run seconds, summed wait seconds and summed CPU seconds of the worker process."""
    run: dict[str, float] = {}
    wait: dict[str, float] = {}
    cpu: dict[str, float] = {}
    for r in store.items(job):
        if r["status"] != "done":
            continue
        run[r["stage"]] = run.get(r["stage"], 0.0) + (r["duration"] or 0.0)
        wait[r["stage"]] = wait.get(r["stage"], 0.0) + (r["wait"] or 0.0)
        info = json.loads(r["info"]) if r.get("info") else {}
        cpu[r["stage"]] = cpu.get(r["stage"], 0.0) + float(info.get("cpu_s") or 0.0)
    return run, wait, cpu


def timeline(store, job: str, cpus: int) -> dict:
    """How full the workers were, from the items' start and end times: ``busy`` the items' summed seconds over
    span x CPUs, ``head`` and ``tail`` the seconds at the start and the end of the span when fewer items ran than
    there are CPUs (filling up, and the last items running alone)."""
    spans = [(r["started"], r["finished"]) for r in store.items(job)
             if r["status"] == "done" and r["started"] and r["finished"]]
    if not spans:
        return {"busy": 0.0, "head": 0.0, "tail": 0.0}
    t0, t1 = min(s for s, _ in spans), max(f for _, f in spans)
    running, first, last = 0, t1, t1
    for t, step in sorted([(s, 1) for s, _ in spans] + [(f, -1) for _, f in spans]):
        was_full = running >= cpus
        running += step
        if running >= cpus:
            first = min(first, t)
        elif was_full:
            last = t          # the last time the workers stopped being full
    busy = sum(f - s for s, f in spans) / max((t1 - t0) * cpus, 1e-9)
    return {"busy": busy, "head": first - t0, "tail": t1 - last}


def run_on_nodes(n_nodes: int, cpus_per_node: int, doc: dict, folder: Path) -> dict:
    """Run the job on a fresh cluster of ``n_nodes`` worker nodes; returns timing, counts and waits."""
    import ray
    from ray.cluster_utils import Cluster

    from service.manifest import validate
    from service.scheduler import Scheduler
    from service.store import Store

    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    man = validate(doc, root=folder)
    # the head hosts only the driver; no dashboard: on one machine its processes would take the workers' cores
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 0, "include_dashboard": False})
    try:
        nodes = [cluster.add_node(num_cpus=cpus_per_node) for _ in range(n_nodes)]
        ray.init(address=cluster.address, logging_level="ERROR",
                 runtime_env={"env_vars": {"PYTHONPATH": str(REPO)}})
        cluster.wait_for_nodes()
        _warm(nodes)
        t0 = time.perf_counter()
        with Store(man.database) as store:
            report = Scheduler(man, store=store, progress=False).run()
            seconds = time.perf_counter() - t0
            run, wait, cpu = _summarise(store, man.name)
            fill = timeline(store, man.name, n_nodes * cpus_per_node)
            devices = {m["name"]: m["device"] for m in store.materials(man.name)}
    finally:
        ray.shutdown()
        cluster.shutdown()
    done = sum(s == "done" for s in report.materials.values())
    return {"nodes": n_nodes, "cpus": n_nodes * cpus_per_node, "seconds": seconds, "done": done,
            "failed": len(report.materials) - done, "per_hour": done / seconds * 3600.0, "items": report.executed,
            "run": run, "wait": wait, "cpu": cpu, "fill": fill, "errors": report.errors, "devices": devices}


def _kernel(_: int = 0) -> float:
    """Seconds of a fixed single-threaded workload like the pipeline's (torch convolutions, numpy FFTs)."""
    import numpy as np
    import torch

    torch.set_num_threads(1)
    x, w = torch.rand(1, 64, 128, 128), torch.rand(64, 64, 3, 3)
    a = np.random.default_rng(0).random((512, 512))
    t0 = time.perf_counter()
    for _ in range(300):
        torch.nn.functional.conv2d(x, w, padding=1)
    for _ in range(100):
        np.fft.fft2(a)
    return time.perf_counter() - t0


def machine_ceiling(n: int) -> float:
    """Speed-up of n concurrent copies of ``_kernel`` over one (n x t1 / t_n), in separate processes."""
    import multiprocessing as mp

    if n <= 1:
        return 1.0
    ctx = mp.get_context("spawn")
    with ctx.Pool(1) as pool:
        one = pool.apply(_kernel)
    with ctx.Pool(n) as pool:
        many = pool.map(_kernel, range(n))
    return n * one / max(many)


def _load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def throughput(args: argparse.Namespace, dec: str) -> int:
    doc = job_doc(args.materials, args.working_size, args.iterations, args.out_size, dec, "cpu", args.pptbf_db)
    stages = [s for s in STAGE_ORDER if dec == "auto" or s != "masks"]
    print(f"{args.materials} materials, working size {args.working_size}, decompose {dec}, recompose "
          f"{args.iterations} iterations on CPU, {args.cpus_per_node} CPU per node, head 0 CPU; "
          f"machine: {os.cpu_count()} cores")
    head = ["nodes", "CPUs", "wall s", "done", "failed", "materials/h", "speed-up", "ceiling", "items' ceiling",
            "items", "busy % / head s / tail s"] + \
           [f"{s} run s / wait % / cpu %" for s in stages] + ["load avg (1/5/15 min) before -> after"]
    print(" | ".join(head))
    print(" | ".join("---" for _ in head), flush=True)
    failed = 0
    base = base_items = None
    with tempfile.TemporaryDirectory(prefix="bench-throughput-") as tmp:
        for n in args.nodes:   # each row printed as soon as it is measured
            ceiling = machine_ceiling(n * args.cpus_per_node)
            before = _load()
            r = run_on_nodes(n, args.cpus_per_node, doc, Path(tmp) / f"nodes{n}")
            base = base or r["seconds"]
            item_s = sum(r["run"].values())
            base_items = base_items or (item_s, r["cpus"])
            items_ceiling = r["cpus"] / base_items[1] * base_items[0] / item_s
            for name, err in r["errors"].items():
                print(f"  [{n} nodes] {name} failed: {err}", file=sys.stderr)
            cells = [r["nodes"], r["cpus"], f"{r['seconds']:.1f}", r["done"], r["failed"], f"{r['per_hour']:.0f}",
                     f"{base / r['seconds']:.2f}x", f"{ceiling:.2f}x", f"{items_ceiling:.2f}x", r["items"],
                     f"{100 * r['fill']['busy']:.0f} / {r['fill']['head']:.1f} / {r['fill']['tail']:.1f}"]
            for s in stages:
                run, wait = r["run"].get(s, 0.0), r["wait"].get(s, 0.0)
                cpu = r["cpu"].get(s, 0.0)
                cells.append(f"{run:.1f} / {100 * wait / (run + wait) if run + wait else 0:.0f}% / "
                             f"{100 * cpu / run if run else 0:.0f}%")
            cells.append(f"{before} -> {_load()}")
            print(" | ".join(str(c) for c in cells), flush=True)
            failed += r["failed"]
    return 0 if failed == 0 else 1


def cuda_compare(args: argparse.Namespace, dec: str) -> int:
    """The same job with recomposition on CPU and on CUDA (local Ray with the machine's GPU)."""
    import ray
    import torch

    from service.manifest import validate
    from service.scheduler import Scheduler
    from service.store import Store

    if not torch.cuda.is_available():
        print("--cuda needs a machine where torch sees a CUDA device", file=sys.stderr)
        return 2
    out: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="bench-cuda-") as tmp:
        ray.init(include_dashboard=False, logging_level="ERROR",
                 runtime_env={"env_vars": {"PYTHONPATH": str(REPO)}})
        try:
            for device in ("cpu", "cuda"):
                doc = job_doc(args.materials, args.working_size, args.iterations, args.out_size, dec, device,
                              args.pptbf_db)
                doc["job"]["stages"] = ["load", "decompose", "noise", "masks", "recompose"]
                folder = Path(tmp) / device
                folder.mkdir()
                man = validate(doc, root=folder)
                t0 = time.perf_counter()
                with Store(man.database) as store:
                    report = Scheduler(man, store=store, progress=False).run()
                    devices = {m["name"]: m["device"] for m in store.materials(man.name)}
                wall = time.perf_counter() - t0
                for name in report.materials:
                    p = man.output / name / "recompose" / "report.json"
                    rep = json.loads(p.read_text()) if p.is_file() else {}
                    out.setdefault(name, {})[device] = {"seconds": rep.get("seconds_total"),
                                                        "loss": rep.get("loss_after"), "device": devices.get(name),
                                                        "error": report.errors.get(name)}
                print(f"  {device}: job wall {wall:.1f} s", file=sys.stderr)
        finally:
            ray.shutdown()
    gpu = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True,
                         text=True).stdout.strip() or torch.cuda.get_device_name(0)
    print(f"\n{args.materials} materials, working size {args.working_size}, {args.iterations} iterations; GPU {gpu}; "
          f"CPU side {torch.get_num_threads()} threads max; load average {_load()}")
    print("material | cpu s | cuda s | speed-up | cpu loss | cuda loss | loss diff % | devices")
    print("--- | --- | --- | --- | --- | --- | --- | ---")
    worst = 0.0
    for name, d in out.items():
        c, g = d.get("cpu", {}), d.get("cuda", {})
        if c.get("loss") is None or g.get("loss") is None:
            print(f"{name} | failed: {c.get('error') or g.get('error')}")
            continue
        diff = 100 * abs(g["loss"] - c["loss"]) / max(abs(c["loss"]), 1e-12)
        worst = max(worst, diff)
        print(f"{name} | {c['seconds']:.1f} | {g['seconds']:.1f} | {c['seconds'] / g['seconds']:.2f}x | "
              f"{c['loss']:.5f} | {g['loss']:.5f} | {diff:.2f} | {c['device']}/{g['device']}")
    print(f"largest final-loss difference {worst:.2f} % (acceptance: within 5 %)")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--nodes", type=int, nargs="+", default=[1, 2, 4], help="worker node counts to compare")
    ap.add_argument("--cpus-per-node", type=int, default=1)
    ap.add_argument("--materials", type=int, default=4)
    ap.add_argument("--working-size", type=int, default=64)
    ap.add_argument("--iterations", type=int, default=20, help="recompose iterations")
    ap.add_argument("--out-size", type=int, default=128, help="output map size")
    ap.add_argument("--decompose", choices=("auto", "none"), default="auto")
    ap.add_argument("--pptbf-db", default=None, help="PPTBF database folder (default: the bundled one)")
    ap.add_argument("--cuda", action="store_true", help="compare CPU and CUDA recomposition instead")
    args = ap.parse_args(argv)
    if not SHARED_MATERIALS.is_dir():
        print(f"shared materials not found at {SHARED_MATERIALS}", file=sys.stderr)
        return 2
    return cuda_compare(args, args.decompose) if args.cuda else throughput(args, args.decompose)


if __name__ == "__main__":
    sys.exit(main())
