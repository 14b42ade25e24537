"""Ownership of material folders: a folder a job writes to belongs to that job alone.

Two jobs that share an output folder and both name a material ``tile`` would otherwise write into the same
folder and overwrite each other's artefacts. Before a job writes anything for a material, the driver claims
the material's folder by creating ``.proceduralize-owner.json`` in it (atomically: a fully written temporary
file is hard-linked to the marker name, which fails when the marker exists). A folder claimed by another
job (or by the same job name recorded in another database) is refused; the material fails with a message
that says which job owns it and how to avoid the clash.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

from workers.errors import InputError

MARKER = ".proceduralize-owner.json"


def owner(folder: Path) -> dict | None:
    """The owner record of a material folder, or None when the folder is unclaimed."""
    try:
        doc = json.loads((Path(folder) / MARKER).read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None
    except (OSError, ValueError):
        return {"job": "?", "database": "?"}  # unreadable marker: treat as someone else's
    return doc if isinstance(doc, dict) else {"job": "?", "database": "?"}


def _same(rec: dict, job: str, database: Path) -> bool:
    """The record is this job's: same name, and the same database (or the recorded one is gone: a job folder
    moved or copied elsewhere with its database)."""
    if rec.get("job") != job:
        return False
    recorded = rec.get("database")
    return recorded == str(Path(database).resolve()) or not (isinstance(recorded, str) and Path(recorded).is_file())


def claim(folder: Path, job: str, database: Path) -> None:
    """Make ``folder`` belong to ``job`` (recorded in ``database``); InputError when another job owns it."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    me = {"job": job, "database": str(Path(database).resolve())}
    marker = folder / MARKER
    tmp = folder / f".{MARKER}.{os.getpid()}.tmp"
    tmp.write_text(json.dumps(me), encoding="utf-8")
    try:
        os.link(tmp, marker)
    except FileExistsError:
        pass
    except OSError:  # a file system without hard links: exclusive create (a reader may briefly see it empty)
        try:
            fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            pass
        else:
            os.write(fd, json.dumps(me).encode())
            os.close(fd)
    finally:
        tmp.unlink(missing_ok=True)
    rec = owner(folder)
    if rec is None or not _same(rec, job, database):
        raise InputError(f"{folder}: this material folder belongs to job {rec.get('job') if rec else '?'!r} "
                         f"(database {rec.get('database') if rec else '?'}); a job never writes into another "
                         "job's folder. Give this material another `output` folder or the job another "
                         "`job.output`")


def check(folder: Path, job: str, database: Path) -> str | None:
    """None when ``folder`` belongs to ``job``; else a sentence saying who owns it now."""
    rec = owner(folder)
    if rec is None:  # written before folders were claimed, or the record was deleted: nothing to compare
        return None
    if not _same(rec, job, database):
        return f"{folder}: the folder now belongs to job {rec.get('job')!r} (database {rec.get('database')})"
    return None
