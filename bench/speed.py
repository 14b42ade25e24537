"""Speed and memory per pipeline stage: one material run in-process, or a batch job's store.

    python bench/speed.py one examples/quick.toml                      # first material, stages in this process
    python bench/speed.py one examples/quick.toml --working-size 256 --isolate
    python bench/speed.py batch /tmp/job_small                         # per-stage times recorded by a Ray job

``one`` runs every stage item of one material through ``service.stages.run_stage`` (no Ray) into a scratch
folder and reports per stage: items, seconds, the peak of the Python/numpy heap (tracemalloc; torch tensors
are not counted) and the process's resident-set high-water mark (ru_maxrss) after the stage. ru_maxrss only
grows, so in-process it shows the highest stage so far; ``--isolate`` runs each item in a fresh process and
reports that process's own peak RSS instead (imports included: see the ``baseline`` row).
``batch`` reads a finished job's SQLite store: per stage items, summed/mean/max item seconds, share of the
summed time, and per material its wall time; the job's wall time vs the summed stage time gives the speedup.
"""
from __future__ import annotations

import argparse
import concurrent.futures as cf
import multiprocessing as mp
import os
import resource
import shutil
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

MIB = 1024.0 * 1024.0
# imported before any clock starts (lazy imports inside the stages would otherwise be timed, slowed by tracemalloc)
WARM_MODULES = ("torch", "workers.maps", "workers.graph", "workers.render", "workers.tree", "workers.decompose",
                "workers.noise", "workers.masks", "workers.recompose", "workers.actors", "pptbf_db.index",
                "service.pipeline", "service.stages")


def _print_table(rows: list[tuple], header: tuple) -> None:
    from service.commands.common import print_table as pt

    pt(rows, header)


def _maxrss_mib() -> float:
    """This process's peak resident set size so far (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def warm_imports() -> float:
    """Import every stage module (those installed); returns the peak RSS so far (MiB)."""
    import importlib

    for mod in WARM_MODULES:
        try:
            importlib.import_module(mod)
        except ModuleNotFoundError as exc:
            if exc.name != mod:
                raise
    return _maxrss_mib()


def measure_item(call) -> dict:
    """Run one stage item; its seconds, tracemalloc peak and the RSS high-water mark after it (MiB).

    Modules are imported before the clock starts, so a fresh process times the work, not imports."""
    from service.stages import run_stage

    warm_imports()
    tracemalloc.start()
    tracemalloc.reset_peak()
    t0 = time.perf_counter()
    res = run_stage(call)
    seconds = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1] / MIB
    tracemalloc.stop()
    gpu = None
    if "torch" in sys.modules and sys.modules["torch"].cuda.is_available():
        gpu = sys.modules["torch"].cuda.max_memory_allocated() / MIB
    return {"seconds": seconds, "py_peak": peak, "rss": _maxrss_mib(), "gpu": gpu, "info": res["info"]}


def run_one(args) -> int:
    """Run the stages of one material of a manifest and print the per-stage table."""
    from service.manifest import load_manifest
    from service.stages import STAGES, StageCall
    from workers.errors import InputError

    man = load_manifest(args.manifest)
    names = [m.name for m in man.materials]
    if args.material and args.material not in names:
        raise InputError(f"{args.manifest}: no material {args.material!r} (has: {', '.join(names)})")
    spec = man.material(args.material) if args.material else man.materials[0]
    if args.working_size:
        spec.working_size = (args.working_size, args.working_size)
    out = Path(args.out or tempfile.mkdtemp(prefix="speed_"))
    shutil.rmtree(out / spec.output, ignore_errors=True)
    pool = None
    if args.isolate:
        ctx = mp.get_context("spawn")
        pool = cf.ProcessPoolExecutor(max_workers=1, mp_context=ctx, max_tasks_per_child=1)
    rows, infos, total = [], {}, 0.0
    try:
        if pool is not None:
            rows.append(("baseline (imports)", "", "", "", "", f"{pool.submit(warm_imports).result():.0f}"))
        for st in STAGES:  # items planned as the scheduler plans them
            stage = st.name
            res = []
            for item in st.items(spec, lambda s: infos.get(s, {})):
                call = StageCall(job="speed", root=str(out), spec=spec, stage=stage, item=item)
                res.append(pool.submit(measure_item, call).result() if pool else measure_item(call))
            infos[stage] = res[0]["info"] if res else {}
            secs = sum(r["seconds"] for r in res)
            total += secs
            gpu = [r["gpu"] for r in res if r["gpu"] is not None]
            rows.append((stage, len(res), f"{secs:.2f}", f"{max((r['seconds'] for r in res), default=0):.2f}",
                         f"{max((r['py_peak'] for r in res), default=0):.0f}",
                         f"{max((r['rss'] for r in res), default=0):.0f}") + ((f"{max(gpu):.0f}",) if gpu else ()))
    finally:
        if pool is not None:
            pool.shutdown()
    w, h = infos.get("load", {}).get("size", ["?", "?"])
    print(f"{spec.name}: working size {w}x{h}, {'one fresh process per item' if pool else 'in-process'}, "
          f"outputs in {out}")
    rss = "peak RSS MiB" if pool else "RSS high-water MiB"
    header = ("stage", "items", "seconds", "max item s", "py heap peak MiB", rss)
    _print_table(rows + [("total", sum(int(r[1] or 0) for r in rows), f"{total:.2f}", "", "", "")],
                 header + (("GPU peak MiB",) if any(len(r) > 6 for r in rows) else ()))
    return 0


def run_batch(args) -> int:
    """Per-stage and per-material times of a finished job, from its SQLite store."""
    from service.commands.jobs import open_job

    store, job = open_job(args.job)
    try:
        items = store.items(job)
        mats = store.materials(job)
        jrow = store.job(job)
    finally:
        store.close()
    done = [i for i in items if i["status"] == "done" and i["duration"] is not None]
    order = ("load", "decompose", "noise", "masks", "recompose", "output")
    summed = sum(i["duration"] for i in done) or 1e-9
    rows = []
    for stage in sorted({i["stage"] for i in done}, key=lambda s: order.index(s) if s in order else 99):
        d = [i["duration"] for i in done if i["stage"] == stage]
        rows.append((stage, len(d), f"{sum(d):.2f}", f"{sum(d) / len(d):.2f}", f"{max(d):.2f}",
                     f"{100 * sum(d) / summed:.0f}%"))
    wall = (jrow["finished"] or time.time()) - jrow["started"] if jrow.get("started") else float("nan")
    print(f"job {job}: {len(mats)} material(s), {len(done)} stage items done, wall {wall:.1f} s, "
          f"summed stage time {summed:.1f} s (x{summed / wall:.2f} parallel)")
    _print_table(rows, ("stage", "items", "seconds", "mean item s", "max item s", "share"))
    print()
    per = []
    for m in mats:
        secs = sum(i["duration"] for i in done if i["material"] == m["name"])
        mw = (m["finished"] - m["started"]) if m.get("finished") and m.get("started") else None
        per.append((m["name"], m["status"], f"{secs:.2f}", "-" if mw is None else f"{mw:.2f}"))
    _print_table(per, ("material", "status", "stage seconds", "wall seconds"))
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog=__doc__.split("\n\n", 1)[1])
    sub = p.add_subparsers(dest="mode", required=True)
    one = sub.add_parser("one", help="run one material's stages in-process and time them")
    one.add_argument("manifest", type=Path, help="job manifest (TOML/JSON/YAML)")
    one.add_argument("--material", default=None, help="material name (default: the first)")
    one.add_argument("--working-size", type=int, default=None, help="override the working size (pixels)")
    one.add_argument("--out", type=Path, default=None, help="scratch output folder (default: a new temp folder)")
    one.add_argument("--isolate", action="store_true", help="each item in a fresh process: per-stage peak RSS")
    one.set_defaults(func=run_one)
    batch = sub.add_parser("batch", help="per-stage times of a finished job from its store")
    batch.add_argument("job", help="job name, manifest, output folder or database file")
    batch.set_defaults(func=run_batch)
    args = p.parse_args(argv)
    from pptbf_db.errors import ProceduralizeError

    try:
        return args.func(args)
    except ProceduralizeError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
