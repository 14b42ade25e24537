"""Finding a job from the command line: the registry of job databases this machine ran, JOB references
(a job name, its manifest, output folder or database file) and manifests with every problem reported."""
from __future__ import annotations

import json
import logging
import os
import sys
from pathlib import Path

from pptbf_db.files import write_text
from workers.errors import InputError, ManifestError

logger = logging.getLogger("proceduralize")


def job_registry() -> Path:
    """Where ``run`` remembers job databases so ``status`` without JOB can list them."""
    home = os.environ.get("PROCEDURALIZE_HOME")
    return (Path(home) if home else Path.home() / ".proceduralize") / "jobs.json"


def remember_job(name: str, database: Path) -> None:
    """Add a job's database to the registry (best effort: a read-only home is not an error)."""
    reg = job_registry()
    try:
        known = json.loads(reg.read_text(encoding="utf-8")) if reg.is_file() else {}
        known[name] = str(Path(database).resolve())
        write_text(reg, json.dumps(known, indent=1))
    except (OSError, ValueError) as exc:
        logger.debug("job registry %s not updated: %s", reg, exc)


def known_databases() -> dict[str, Path]:
    """Job name -> database from the registry and ./out/*/proceduralize.db."""
    found: dict[str, Path] = {}
    for db in sorted(Path.cwd().glob("out/*/proceduralize.db")):
        found.setdefault(db.parent.name, db)
    reg = job_registry()
    try:
        for name, db in (json.loads(reg.read_text(encoding="utf-8")) if reg.is_file() else {}).items():
            if Path(db).is_file():
                found[name] = Path(db)
    except (OSError, ValueError):
        pass
    return found


def open_job(ref: str):
    """(Store, job name) for a manifest, output folder, database file or job name; InputError if none."""
    from service.manifest import DEFAULT_DATABASE, load_manifest
    from service.store import Store

    p = Path(ref)
    name = None
    if p.is_file() and p.suffix.lower() in (".toml", ".json", ".yaml", ".yml"):
        man = load_manifest(p)
        db, name = man.database, man.name
    elif p.is_dir():
        db = p / DEFAULT_DATABASE
    elif p.is_file():
        db = p
    else:
        known = known_databases()
        if ref not in known:
            raise InputError(f"job {ref!r} not found: pass its manifest, output folder or database file "
                             f"(known jobs: {', '.join(sorted(known)) or 'none'})")
        db, name = known[ref], ref
    if not Path(db).is_file():
        raise InputError(f"{db}: no job database here (has the job been run?)")
    store = Store(db, readonly=True)  # status, results, report and evaluate only read
    jobs = store.jobs()
    if name is None:
        if not jobs:
            raise InputError(f"{db}: database holds no job")
        name = ref if any(j["name"] == ref for j in jobs) else jobs[0]["name"]
    if store.job(name) is None:
        raise InputError(f"{db}: no job named {name!r} (has: {', '.join(j['name'] for j in jobs)})")
    return store, name


def load_manifest_or_report(path: Path, output: Path | None = None):
    """The validated manifest, or None after printing every problem on its own line (exit code 2)."""
    from service.manifest import load_manifest

    try:
        return load_manifest(path, output=output)
    except ManifestError as exc:
        print(f"error: {exc.path or path}: {len(exc.problems)} problem(s) in the manifest:", file=sys.stderr)
        for prob in exc.problems:
            print(f"  - {prob}", file=sys.stderr)
        return None
