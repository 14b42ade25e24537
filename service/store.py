"""The job database (SQLite via sqlite-utils): jobs, materials, stage items, artefacts and errors.

The database file is each job's record of truth. It runs in WAL mode with a busy timeout and short
``BEGIN IMMEDIATE`` transactions, so two drivers (two jobs) may share one file. The schema carries a
version (table ``meta``) and is migrated forward on open; a newer file than this code is refused.
Only the scheduler's driver writes (workers return results; the driver records them).
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import socket
import sqlite3
import time
from pathlib import Path
from typing import Any, Callable, Iterator

import sqlite_utils

from pptbf_db.errors import DatabaseError
from service.stages import STAGE_NAMES

logger = logging.getLogger(__name__)

BUSY_TIMEOUT_S = 60.0


def file_checksum(path: str | Path) -> str:
    """sha256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _now() -> float:
    return time.time()


# ----------------------------------------------------------------------------- schema and migrations


def _v1(db: sqlite_utils.Database) -> None:
    """Initial schema: jobs, materials, stage items, artefacts."""
    db["jobs"].create({"name": str, "manifest": str, "output": str, "spec": str, "status": str,
                       "created": float, "started": float, "finished": float, "driver": str}, pk="name")
    db["materials"].create({"id": str, "job": str, "name": str, "output": str, "status": str, "spec_hash": str,
                            "spec": str, "error": str, "started": float, "finished": float}, pk="id")
    db["materials"].create_index(["job", "name"], unique=True)
    db["stages"].create({"id": int, "job": str, "material": str, "stage": str, "item": str, "status": str,
                         "attempts": int, "executions": int, "started": float, "finished": float,
                         "duration": float, "worker": str, "error": str, "info": str}, pk="id",
                        defaults={"attempts": 0, "executions": 0, "item": ""})
    db["stages"].create_index(["job", "material", "stage", "item"], unique=True)
    db["artefacts"].create({"id": int, "job": str, "material": str, "stage": str, "item": str, "path": str,
                            "kind": str, "checksum": str, "bytes": int, "created": float}, pk="id")
    db["artefacts"].create_index(["job", "material", "stage", "item", "path"], unique=True)


def _v2(db: sqlite_utils.Database) -> None:
    """Every failed attempt kept in ``errors``; ``jobs.runs`` counts driver runs (resumes)."""
    db["errors"].create({"id": int, "job": str, "material": str, "stage": str, "item": str, "time": float,
                         "attempt": int, "kind": str, "message": str, "final": int}, pk="id")
    db["errors"].create_index(["job", "material"])
    db["jobs"].add_column("runs", int, not_null_default=0)


def _v3(db: sqlite_utils.Database) -> None:
    """Placement: the device a material was recomposed on (and why, when not the one asked for); per stage item
    the seconds it waited for a slot (from ready to started)."""
    db["materials"].add_column("device", str)
    db["materials"].add_column("device_note", str)
    db["stages"].add_column("wait", float)


MIGRATIONS: list[Callable[[sqlite_utils.Database], None]] = [_v1, _v2, _v3]
SCHEMA_VERSION = len(MIGRATIONS)


class Store:
    """One connection to a job database; every write is one short transaction."""

    def __init__(self, path: str | Path, timeout: float = BUSY_TIMEOUT_S, migrate_to: int = SCHEMA_VERSION,
                 readonly: bool = False):
        self.path = Path(path)
        self.readonly = readonly
        if readonly and not self.path.is_file():
            raise DatabaseError(f"{self.path}: no job database here")
        if not readonly:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        try:  # read-only: the file is never created, migrated, switched to WAL or otherwise written
            conn = sqlite3.connect(f"file:{self.path.resolve()}?mode=ro" if readonly else str(self.path),
                                   timeout=timeout, check_same_thread=False, uri=readonly)
        except sqlite3.Error as exc:
            raise DatabaseError(f"{self.path}: cannot open the job database ({exc})") from None
        self.db = sqlite_utils.Database(conn)
        try:
            self.db.execute(f"PRAGMA busy_timeout = {int(timeout * 1000)}")
            if readonly:
                self._check_readable()
            else:
                self._enable_wal()
                self._migrate(migrate_to)
        except sqlite3.DatabaseError as exc:
            conn.close()
            raise DatabaseError(f"{self.path}: not a usable SQLite job database ({exc})") from None
        except DatabaseError:
            conn.close()
            raise

    def _check_readable(self) -> None:
        """A read-only open must find a job database of a schema this code knows (nothing is migrated)."""
        if self.path.stat().st_size == 0 or "meta" not in self.db.table_names():
            raise DatabaseError(f"{self.path}: empty or not a proceduralize job database (no schema); "
                                "run a job to create one")
        v = self.version
        if v != SCHEMA_VERSION:
            raise DatabaseError(f"{self.path}: schema version {v}, this proceduralize reads {SCHEMA_VERSION}; "
                                "rerun the job with this version (it migrates the file) to read it")

    # -- connection plumbing

    def _enable_wal(self) -> None:
        """WAL lets readers (status) run while a driver writes; retried while another process holds a lock."""
        for i in range(50):
            try:
                self.db.enable_wal()
                return
            except sqlite3.OperationalError as exc:
                if "locked" not in str(exc) and "busy" not in str(exc):
                    raise
                time.sleep(0.05 * (i + 1))
        self.db.enable_wal()

    @contextlib.contextmanager
    def tx(self) -> Iterator[sqlite_utils.Database]:
        """A short write transaction (BEGIN IMMEDIATE: takes the write lock up front, waits on busy)."""
        self.db.conn.execute("BEGIN IMMEDIATE")
        try:
            yield self.db
        except BaseException:
            if self.db.conn.in_transaction:
                self.db.conn.execute("ROLLBACK")
            raise
        else:
            self.db.conn.execute("COMMIT")

    def close(self) -> None:
        """Close the connection."""
        self.db.conn.close()

    def __enter__(self) -> "Store":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    @property
    def version(self) -> int:
        """Schema version of the file."""
        if "meta" not in self.db.table_names():
            return 0
        row = self.db.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
        return int(row[0]) if row else 0

    def _migrate(self, target: int) -> None:
        """Apply missing migrations (each with its version bump in one transaction)."""
        with self.tx() as db:
            if "meta" not in db.table_names():
                db["meta"].create({"key": str, "value": str}, pk="key")
            current = self.version
            if current > SCHEMA_VERSION:
                raise DatabaseError(f"{self.path}: schema version {current} is newer than this proceduralize "
                                    f"(knows {SCHEMA_VERSION}); upgrade proceduralize or use another output folder")
            for v in range(current, min(target, SCHEMA_VERSION)):
                MIGRATIONS[v](db)
                db["meta"].upsert({"key": "schema_version", "value": str(v + 1)}, pk="key")
                logger.info("%s: schema migrated to version %d", self.path, v + 1)

    # -- jobs and materials

    def register_job(self, name: str, manifest: str | None, output: str, spec: dict) -> int:
        """Create or refresh a job row for a (re)run; returns how many runs the job has had (1 = first)."""
        now = _now()
        with self.tx() as db:
            row = db.execute("SELECT runs FROM jobs WHERE name = ?", [name]).fetchone()
            runs = (row[0] or 0) + 1 if row else 1
            db["jobs"].upsert({"name": name, "manifest": manifest, "output": output, "spec": json.dumps(spec),
                               "status": "running", "started": now, "finished": None, "runs": runs,
                               "driver": f"{socket.gethostname()}:{os.getpid()}"}, pk="name")
            if not row:
                db.execute("UPDATE jobs SET created = ? WHERE name = ?", [now, name])
        return runs

    def finish_job(self, name: str, status: str) -> None:
        """Mark a job done / failed (some materials failed) / interrupted."""
        with self.tx() as db:
            db.execute("UPDATE jobs SET status = ?, finished = ? WHERE name = ?", [status, _now(), name])

    def sync_materials(self, job: str, materials: list[dict]) -> list[str]:
        """Insert new materials; a material whose spec hash changed loses its finished stages. Returns reset names.

        Each dict has name, output, spec_hash, spec (dict).
        """
        reset: list[str] = []
        with self.tx() as db:
            for m in materials:
                mid = f"{job}/{m['name']}"
                row = db.execute("SELECT spec_hash FROM materials WHERE id = ?", [mid]).fetchone()
                if row and row[0] != m["spec_hash"]:
                    reset.append(m["name"])
                    for t in ("stages", "artefacts"):
                        db.execute(f"DELETE FROM {t} WHERE job = ? AND material = ?", [job, m["name"]])
                db["materials"].upsert({"id": mid, "job": job, "name": m["name"], "output": m["output"],
                                        "spec_hash": m["spec_hash"], "spec": json.dumps(m["spec"]),
                                        "status": "pending", "error": None, "finished": None}, pk="id")
        return reset

    def set_material(self, job: str, material: str, status: str, error: str | None = None) -> None:
        """Set a material's status (pending, running, done, failed) and error text."""
        now = _now()
        with self.tx() as db:
            if status == "running":
                db.execute("UPDATE materials SET status = ?, started = COALESCE(started, ?) WHERE id = ?",
                           [status, now, f"{job}/{material}"])
            else:
                db.execute("UPDATE materials SET status = ?, error = ?, finished = ? WHERE id = ?",
                           [status, error, now if status in ("done", "failed") else None, f"{job}/{material}"])

    def set_device(self, job: str, material: str, device: str, note: str | None = None) -> None:
        """Record the torch device a material's recomposition ran on and, if it is not the one asked for, why."""
        with self.tx() as db:
            db.execute("UPDATE materials SET device = ?, device_note = ? WHERE id = ?",
                       [device, note, f"{job}/{material}"])

    # -- stage items

    def item(self, job: str, material: str, stage: str, item: str = "") -> dict | None:
        """The row of one stage item, or None."""
        rows = list(self.db["stages"].rows_where("job = ? AND material = ? AND stage = ? AND item = ?",
                                                 [job, material, stage, item]))
        return rows[0] if rows else None

    def _ensure_item(self, db: sqlite_utils.Database, job: str, material: str, stage: str, item: str) -> None:
        db.execute("INSERT OR IGNORE INTO stages (job, material, stage, item, status, attempts, executions) "
                   "VALUES (?, ?, ?, ?, 'pending', 0, 0)", [job, material, stage, item])

    def start_item(self, job: str, material: str, stage: str, item: str = "") -> int:
        """Mark an item submitted (status running, attempts + 1); returns the attempt number."""
        with self.tx() as db:
            self._ensure_item(db, job, material, stage, item)
            db.execute("UPDATE stages SET status = 'running', attempts = attempts + 1, started = ?, error = NULL "
                       "WHERE job = ? AND material = ? AND stage = ? AND item = ?",
                       [_now(), job, material, stage, item])
            return db.execute("SELECT attempts FROM stages WHERE job = ? AND material = ? AND stage = ? AND item = ?",
                              [job, material, stage, item]).fetchone()[0]

    def finish_item(self, job: str, material: str, stage: str, item: str, result: dict,
                    wait: float | None = None) -> None:
        """Record a finished execution: its artefacts (replacing older ones), timing, worker, info and the seconds
        it waited for a slot."""
        now = _now()
        with self.tx() as db:
            self._ensure_item(db, job, material, stage, item)
            db.execute("DELETE FROM artefacts WHERE job = ? AND material = ? AND stage = ? AND item = ?",
                       [job, material, stage, item])
            for a in result.get("artefacts", []):
                db.execute("INSERT INTO artefacts (job, material, stage, item, path, kind, checksum, bytes, created) "
                           "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                           [job, material, stage, item, a["path"], a.get("kind", ""), a["checksum"],
                            a.get("bytes"), now])
            db.execute("UPDATE stages SET status = 'done', executions = executions + 1, started = ?, finished = ?, "
                       "duration = ?, worker = ?, error = NULL, info = ?, wait = ? "
                       "WHERE job = ? AND material = ? AND stage = ? AND item = ?",
                       [result.get("started", now), result.get("finished", now), result.get("duration"),
                        result.get("worker"), json.dumps(result.get("info", {}), default=str), wait,
                        job, material, stage, item])

    def fail_item(self, job: str, material: str, stage: str, item: str, message: str, kind: str = "",
                  final: bool = True, status: str | None = None, detail: str | None = None) -> None:
        """Record a failed attempt (kept in ``errors`` with ``detail``, e.g. the remote traceback); ``final`` marks
        the item failed, else pending (retry)."""
        now = _now()
        with self.tx() as db:
            self._ensure_item(db, job, material, stage, item)
            attempt = db.execute("SELECT attempts FROM stages "
                                 "WHERE job = ? AND material = ? AND stage = ? AND item = ?",
                                 [job, material, stage, item]).fetchone()[0]
            db.execute("INSERT INTO errors (job, material, stage, item, time, attempt, kind, message, final) "
                       "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)", [job, material, stage, item, now, attempt, kind,
                                                              detail or message, int(final)])
            st = status or ("failed" if final else "pending")
            db.execute("UPDATE stages SET status = ?, error = ?, finished = ? "
                       "WHERE job = ? AND material = ? AND stage = ? AND item = ?",
                       [st, message, now, job, material, stage, item])

    def mark_item(self, job: str, material: str, stage: str, item: str, status: str, error: str | None = None) -> None:
        """Set an item's status without an execution (e.g. 'unavailable', 'pending' after an interrupted run)."""
        with self.tx() as db:
            self._ensure_item(db, job, material, stage, item)
            db.execute("UPDATE stages SET status = ?, error = ? WHERE job = ? AND material = ? AND stage = ? "
                       "AND item = ?", [status, error, job, material, stage, item])

    def is_done(self, job: str, material: str, stage: str, item: str, root: str | Path) -> bool:
        """True when the item finished and every artefact it recorded is on disk with the same checksum."""
        row = self.item(job, material, stage, item)
        if not row or row["status"] != "done":
            return False
        root = Path(root)
        for a in self.db["artefacts"].rows_where("job = ? AND material = ? AND stage = ? AND item = ?",
                                                 [job, material, stage, item]):
            p = root / a["path"]
            if not p.is_file() or file_checksum(p) != a["checksum"]:
                logger.info("%s/%s %s[%s]: artefact %s missing or changed, recomputing", job, material, stage,
                            item, a["path"])
                return False
        return True

    def done_info(self, job: str, material: str, stage: str, item: str = "") -> dict:
        """The ``info`` dict a finished item recorded."""
        row = self.item(job, material, stage, item)
        return json.loads(row["info"]) if row and row.get("info") else {}

    # -- reading

    def jobs(self) -> list[dict]:
        """All job rows, newest first."""
        return list(self.db["jobs"].rows_where(order_by="started DESC"))

    def job(self, name: str) -> dict | None:
        """One job row."""
        rows = list(self.db["jobs"].rows_where("name = ?", [name]))
        return rows[0] if rows else None

    def output_root(self, job: str) -> Path:
        """The job's output folder: this database's own folder when it holds the material folders (a job folder
        moved or copied elsewhere), else the folder recorded when the job ran."""
        here = self.path.resolve().parent
        if any((here / m["output"]).is_dir() for m in self.materials(job)):
            return here
        row = self.job(job)
        return Path(row["output"]) if row else here

    def materials(self, job: str) -> list[dict]:
        """A job's material rows in insertion order."""
        return list(self.db["materials"].rows_where("job = ?", [job], order_by="rowid"))

    def items(self, job: str, material: str | None = None, stage: str | None = None) -> list[dict]:
        """Stage item rows of a job (optionally one material / stage)."""
        return self._rows("stages", job, material, stage)

    def artefacts(self, job: str, material: str | None = None, stage: str | None = None) -> list[dict]:
        """Artefact rows (paths relative to the job's output folder)."""
        return self._rows("artefacts", job, material, stage)

    def _rows(self, table: str, job: str, material: str | None, stage: str | None) -> list[dict]:
        """Rows of ``table`` for a job, optionally one material and stage, in insertion order."""
        where, args = "job = ?", [job]
        if material is not None:
            where, args = where + " AND material = ?", args + [material]
        if stage is not None:
            where, args = where + " AND stage = ?", args + [stage]
        return list(self.db[table].rows_where(where, args, order_by="id"))

    def errors(self, job: str, material: str | None = None) -> list[dict]:
        """Every recorded failed attempt of a job."""
        where, args = ("job = ?", [job]) if material is None else ("job = ? AND material = ?", [job, material])
        return list(self.db["errors"].rows_where(where, args, order_by="id"))

    def stage_summary(self, job: str) -> list[dict]:
        """Per material and stage: status, items done/total, attempts, executions, seconds, seconds waiting for a
        slot."""
        order = "CASE stage " + " ".join(f"WHEN '{s}' THEN {i}" for i, s in enumerate(STAGE_NAMES)) + " ELSE 99 END"
        sql = (f"SELECT material, stage, COUNT(*) AS items, SUM(status = 'done') AS done, "
               f"SUM(status = 'failed') AS failed, SUM(status = 'unavailable') AS unavailable, "
               f"SUM(status = 'running') AS running, "
               f"SUM(attempts) AS attempts, SUM(executions) AS executions, SUM(duration) AS seconds, "
               f"SUM(wait) AS wait, "
               f"GROUP_CONCAT(DISTINCT worker) AS workers, MAX(error) AS error "
               f"FROM stages WHERE job = ? GROUP BY material, stage ORDER BY material, {order}")
        cur = self.db.execute(sql, [job])
        cols = [c[0] for c in cur.description]
        out = []
        for r in cur.fetchall():
            d = dict(zip(cols, r))
            d["status"] = ("failed" if d["failed"] else "unavailable" if d["unavailable"] else
                           "done" if d["done"] == d["items"] else "running" if d["running"] else "pending")
            out.append(d)
        return out

    def integrity_ok(self) -> bool:
        """SQLite's own integrity check."""
        return self.db.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
