"""Batch throughput: materials per hour of one job on a local Ray with 1 vs 2 (or more) worker CPUs.

    python bench/throughput.py                          # 4 materials, working size 128, every available stage
    python bench/throughput.py --cpus 1 2 4 --materials 6 --working-size 256 --stages load decompose noise

Each configuration runs the same job from scratch (fresh output folder, fresh Ray) and prints a table:
wall seconds, materials/hour, stage items run, and the summed per-stage seconds from the job database.
"""
from __future__ import annotations

import argparse
import importlib.util
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

from tests.conftest import REAL_MATERIALS, SHARED_MATERIALS, real_material_files  # noqa: E402


def _bundled_db() -> bool:
    from pptbf_db.index import default_database_path

    return (default_database_path() / "meta.json").is_file()


def job_doc(n: int, working_size: int, stages: list[str] | None, iterations: int, out_size: int,
            decompose: str = "auto", pptbf_db: str | None = None) -> dict:
    """A job of ``n`` real materials (cycling through the shared set under distinct names)."""
    names = list(REAL_MATERIALS)
    mats = []
    for i in range(n):
        src = names[i % len(names)]
        f = real_material_files(src)
        mats.append({"name": f"{src}_{i}", "albedo": str(f["albedo"]), "normal": str(f["normal"]),
                     "roughness": {"file": str(f["roughness"]), "channel": f["roughness_channel"] or 0},
                     "seed": i})
    job = {"name": "bench", "output": "out"}
    if pptbf_db:
        job["pptbf_database"] = str(Path(pptbf_db).resolve())
    if stages:
        job["stages"] = stages
    return {"job": job, "materials": mats,
            "defaults": {"working_size": working_size, "recompose": {"iterations": iterations},
                         "masks": {"max_evals": 40, "rounds": 1, "time_budget_s": 20.0},
                         "decompose": {"mode": decompose, "layers": 2} if decompose == "auto" else {"mode": "none"},
                         "outputs": {"sizes": [out_size], "seeds": [0]}}}


def run_once(cpus: int, doc: dict, folder: Path) -> dict:
    """Run the job on a fresh local Ray with ``cpus`` CPUs; returns timing and counts."""
    import ray

    from service.manifest import validate
    from service.scheduler import Scheduler
    from service.store import Store

    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    man = validate(doc, root=folder)
    ray.init(num_cpus=cpus, include_dashboard=False, logging_level="ERROR")
    try:
        ray.get(ray.remote(lambda: 0).remote())  # worker start-up outside the timing
        t0 = time.perf_counter()
        with Store(man.database) as store:
            sched = Scheduler(man, store=store, progress=False)
            report = sched.run()
            seconds = time.perf_counter() - t0
            per_stage: dict[str, float] = {}
            for r in store.items(man.name):
                per_stage[r["stage"]] = per_stage.get(r["stage"], 0.0) + (r["duration"] or 0.0)
    finally:
        ray.shutdown()
    done = sum(s == "done" for s in report.materials.values())
    return {"cpus": cpus, "seconds": seconds, "done": done, "failed": len(report.materials) - done,
            "per_hour": done / seconds * 3600.0, "items": report.executed, "per_stage": per_stage,
            "errors": report.errors}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cpus", type=int, nargs="+", default=[1, 2], help="worker CPU counts to compare")
    ap.add_argument("--materials", type=int, default=4)
    ap.add_argument("--working-size", type=int, default=128)
    ap.add_argument("--stages", nargs="+", default=None, help="stage subset (default: every available stage)")
    ap.add_argument("--iterations", type=int, default=20, help="recompose iterations")
    ap.add_argument("--out-size", type=int, default=256, help="output map size")
    ap.add_argument("--decompose", choices=("auto", "none"), default=None,
                    help="split mode (default: auto when a PPTBF database is available, else none)")
    ap.add_argument("--pptbf-db", default=None, help="PPTBF database folder (default: the bundled one)")
    args = ap.parse_args(argv)
    if not SHARED_MATERIALS.is_dir():
        print(f"shared materials not found at {SHARED_MATERIALS}", file=sys.stderr)
        return 2
    dec = args.decompose or ("auto" if importlib.util.find_spec("workers.decompose") and (args.pptbf_db or _bundled_db())
                             else "none")
    doc = job_doc(args.materials, args.working_size, args.stages, args.iterations, args.out_size, dec, args.pptbf_db)
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-service-") as tmp:
        for cpus in args.cpus:
            r = run_once(cpus, doc, Path(tmp) / f"cpus{cpus}")
            rows.append(r)
            for name, err in r["errors"].items():
                print(f"  [{cpus} cpu] {name} failed: {err}", file=sys.stderr)
    stages = sorted({s for r in rows for s in r["per_stage"]},
                    key=lambda s: ["load", "decompose", "noise", "masks", "recompose", "output"].index(s))
    print(f"\n{args.materials} materials, working size {args.working_size}, decompose {dec}, stages "
          f"{' '.join(stages)} (timings noisy on a shared machine)")
    head = ["cpus", "wall s", "done", "failed", "materials/h", "speed-up", "items"] + [f"{s} s" for s in stages]
    print(" | ".join(head))
    base = rows[0]["seconds"]
    for r in rows:
        cells = [r["cpus"], f"{r['seconds']:.1f}", r["done"], r["failed"], f"{r['per_hour']:.0f}",
                 f"{base / r['seconds']:.2f}x", r["items"]] + [f"{r['per_stage'].get(s, 0):.1f}" for s in stages]
        print(" | ".join(str(c) for c in cells))
    return 0


if __name__ == "__main__":
    sys.exit(main())
