"""``proceduralize status [JOB]``: the jobs this machine ran, or one job's materials and stages."""
from __future__ import annotations

import json
import os
import socket
import time

from service.commands.common import common_parser, print_table
from service.commands.jobs import known_databases, open_job


def register(sub) -> None:
    p = sub.add_parser("status", parents=[common_parser()], help="list jobs, or one job's materials and stages",
                       description="Without JOB: the jobs this machine ran (and ./out/*/proceduralize.db). "
                                   "With JOB (a job name, its manifest, output folder or database file): each "
                                   "material's stages with status, items, attempts, executions and errors.")
    p.add_argument("job", nargs="?", default=None, metavar="JOB")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(handler=handle)


def job_state(job: dict) -> str:
    """The job's status; a 'running' job whose driver process on this host is gone shows as interrupted."""
    if job["status"] != "running" or not job.get("driver"):
        return job["status"]
    host, _, pid = job["driver"].rpartition(":")
    if host == socket.gethostname() and pid.isdigit():
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            return "interrupted (driver gone; rerun to resume)"
        except PermissionError:
            pass
    return "running"


def _fmt_time(t: float | None) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(t)) if t else "-"


def handle(args) -> int:
    from service.store import Store

    if args.job is None:
        rows = []
        for _name, db in sorted(known_databases().items()):
            with Store(db, readonly=True) as store:
                for j in store.jobs():
                    mats = store.materials(j["name"])
                    rows.append({"job": j["name"], "status": job_state(j), "runs": j.get("runs"),
                                 "done": sum(m["status"] == "done" for m in mats),
                                 "failed": sum(m["status"] == "failed" for m in mats), "materials": len(mats),
                                 "started": _fmt_time(j["started"]), "database": str(db)})
        if args.json:
            print(json.dumps(rows, indent=1))
        elif not rows:
            print("no jobs found (run `proceduralize run MANIFEST` first)")
        else:
            print_table([tuple(r.values()) for r in rows], header=tuple(rows[0]))
        return 0
    store, name = open_job(args.job)
    with store:
        job = store.job(name)
        summary = store.stage_summary(name)
        mats = store.materials(name)
    if args.json:
        print(json.dumps({"job": job["name"], "status": job["status"], "runs": job.get("runs"),
                          "materials": [{k: m.get(k) for k in ("name", "status", "error", "device", "device_note")}
                                        for m in mats],
                          "stages": summary}, indent=1))
        return 0
    print(f"job {name}: {job_state(job)} (run {job.get('runs')}, started {_fmt_time(job['started'])}, "
          f"finished {_fmt_time(job['finished'])})")
    print_table([(s["material"], s["stage"], s["status"], f"{s['done']}/{s['items']}", s["attempts"],
                  s["executions"], f"{s['seconds']:.1f}" if s["seconds"] else "-",
                  f"{s['wait']:.1f}" if s["wait"] else "-", (s["error"] or "")[:100])
                 for s in summary],
                header=("material", "stage", "status", "items", "attempts", "runs", "seconds", "waited", "error"))
    for m in mats:
        if m.get("device"):
            print(f"{m['name']}: recomposed on {m['device']}" + (f" ({m['device_note']})" if m.get("device_note")
                                                                  else ""))
    return 0
