"""``proceduralize results JOB``: a job's materials and output files (with their checksums checked)."""
from __future__ import annotations

import json
from pathlib import Path

from service import claims
from service.commands.common import common_parser, print_table
from service.commands.jobs import open_job


def register(sub) -> None:
    p = sub.add_parser("results", parents=[common_parser()], help="a job's materials and output files",
                       description="Per material: status, error, material.json and the regenerated map folders "
                                   "(JOB: a job name, its manifest, output folder or database file). "
                                   "Exit 0 when every material is done, 1 when some failed.")
    p.add_argument("job", metavar="JOB")
    p.add_argument("--json", action="store_true", help="print JSON (every artefact with its checksum)")
    p.set_defaults(handler=handle)


def _artefact_state(path: Path, checksum: str) -> str:
    """'ok' when the file is there with its recorded checksum, else 'missing' or 'changed'."""
    from service.store import file_checksum

    if not path.is_file():
        return "missing"
    return "ok" if file_checksum(path) == checksum else "changed"


def handle(args) -> int:
    store, name = open_job(args.job)
    with store:
        job = store.job(name)
        mats = store.materials(name)
        arts = store.artefacts(name)
        out = store.output_root(name)
        db = store.path
    docs = []
    for m in mats:
        mine = [a for a in arts if a["material"] == m["name"]]
        graph = next((a["path"] for a in mine if a["stage"] == "output" and a["path"].endswith("material.json")), None)
        maps = sorted({str(Path(a["path"]).parent) for a in mine if a["stage"] == "output" and "/maps/" in a["path"]})
        states = {a["path"]: _artefact_state(out / a["path"], a["checksum"]) for a in mine}
        bad = sorted(p for p, st in states.items() if st != "ok")
        status = m["status"]
        problems = []
        if bad:  # files replaced or deleted after the job recorded them: the record no longer holds
            problems.append(f"{len(bad)} of {len(mine)} files changed or missing since the job wrote them "
                            f"(e.g. {bad[0]}: {states[bad[0]]}); rerun the job to recompute them")
        owned = claims.check(out / m["output"], name, db) if mine else None
        if owned and Path(out / m["output"]).is_dir():
            problems.append(owned)
        if problems and status == "done":
            status = "changed"
        docs.append({"name": m["name"], "status": status, "error": "; ".join(problems) or m["error"],
                     "folder": str(out / m["output"]), "material_json": str(out / graph) if graph else None,
                     "maps": [str(out / p) for p in maps],
                     "artefacts": [{**{k: a[k] for k in ("stage", "item", "path", "kind", "checksum", "bytes")},
                                    "state": states[a["path"]]} for a in mine]})
    if args.json:
        print(json.dumps({"job": name, "status": job["status"], "output": str(out), "materials": docs}, indent=1))
    else:
        print_table([(d["name"], d["status"], d["material_json"] or "-", len(d["maps"]), len(d["artefacts"]),
                      (d["error"] or "")[:160]) for d in docs],
                    header=("material", "status", "material.json", "map sets", "files", "error"))
    return 0 if all(d["status"] == "done" for d in docs) else 1
