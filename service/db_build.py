"""Parallel, resumable PPTBF database build: the Ray driver and the SQLite chunk bookkeeping.

N parameter vectors are sampled (seeded), split into chunks; one Ray task per chunk renders the masks and
describes them (the pure `pptbf_db.build.describe_chunk`, with `workers.lattice.analyse_lattice` measuring each
mask's lattice), the driver stores each finished chunk as raw_XXXX.npy and marks it done in db.sqlite, so a
killed build resumes where it stopped and never recomputes a finished chunk. At the end the PCA is fitted and
the database files are written (`pptbf_db.build.finish_database`; meta.json last: its presence marks a complete
database). The tasks run on the Ray the jobs use (`service.scheduler.ensure_ray`). See `pptbf_db.index` for the
folder layout.
"""
from __future__ import annotations

import datetime as _dt
import json
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pptbf_db import build as pure
from pptbf_db.build import BuildConfig
from pptbf_db.errors import DatabaseError
from workers.lattice import analyse_lattice

logger = logging.getLogger(__name__)


@dataclass
class BuildReport:
    """What a build call did."""

    folder: Path
    complete: bool
    size: int
    chunks_total: int
    computed: list[int]             # chunk ids computed by this call
    skipped: list[int]              # chunk ids found finished
    seconds: float                  # wall time of this call
    task_seconds: float             # summed task time of the chunks computed by this call (core-seconds)
    workers: int = 0                # tasks in flight
    entries: int = 0                # entries computed by this call

    @property
    def entries_per_core_minute(self) -> float:
        """Render+describe throughput of one core (from the chunks computed by this call)."""
        return 0.0 if self.task_seconds <= 0 else 60.0 * self.entries / self.task_seconds


# ------------------------------------------------------------------------------------------------ bookkeeping

def _open_db(folder: Path):
    import sqlite_utils

    db = sqlite_utils.Database(folder / "db.sqlite")
    if "settings" not in db.table_names():
        db["settings"].create({"key": str, "value": str}, pk="key")
    if "chunks" not in db.table_names():
        db["chunks"].create({"id": int, "start": int, "stop": int, "status": str, "runs": int,
                             "seconds": float, "white_mean": float, "finished_at": str}, pk="id")
    return db


def _check_settings(db, folder: Path, settings: dict) -> None:
    """Store the settings of a new build, or check that a resumed build asks for the same ones."""
    stored = {r["key"]: json.loads(r["value"]) for r in db["settings"].rows}
    if not stored:
        db["settings"].insert_all([{"key": k, "value": json.dumps(v)} for k, v in settings.items()])
        return
    diff = [k for k in settings if stored.get(k) != settings[k]]
    if diff:
        got = ", ".join(f"{k}={stored.get(k)!r} (asked {settings[k]!r})" for k in diff)
        raise DatabaseError(f"{folder}: holds a build with other settings: {got}; use another --out folder, "
                            f"the same settings to resume, or delete the folder to start again")


def _sync_chunks(db, folder: Path, n: int, chunk: int) -> tuple[list[int], list[int]]:
    """Create missing chunk rows; a 'done' chunk whose raw file vanished becomes pending again (unless the PCA
    is already written). Returns (done ids, pending ids)."""
    n_chunks = (n + chunk - 1) // chunk
    rows = {r["id"]: r for r in db["chunks"].rows}
    new = [{"id": c, "start": c * chunk, "stop": min(n, (c + 1) * chunk), "status": "pending", "runs": 0,
            "seconds": 0.0, "white_mean": None, "finished_at": None} for c in range(n_chunks) if c not in rows]
    if new:
        db["chunks"].insert_all(new)
    finished = (folder / "reduced.npy").is_file()
    done, pending = [], []
    for r in db["chunks"].rows_where(order_by="id"):
        if r["status"] == "done" and (finished or pure.raw_path(folder, r["id"]).is_file()):
            done.append(r["id"])
        else:
            if r["status"] == "done":
                logger.warning("chunk %d was done but %s is missing: recomputing", r["id"],
                               pure.raw_path(folder, r["id"]))
                db["chunks"].update(r["id"], {"status": "pending"})
            pending.append(r["id"])
    return done, pending


def _write_entries(db) -> Callable:
    """The entries table writer handed to `finish_database` (replaces the table of an earlier fit)."""
    def write(entries) -> None:
        db["entries"].drop(ignore=True)
        db["entries"].insert_all(entries, pk="id", batch_size=2000)
    return write


def _finish(folder: Path, db, cfg: BuildConfig, params: np.ndarray, n_chunks: int, keep_raw: bool) -> dict:
    """Fit the PCA and write the database files, the entries table and meta.json."""
    secs = [r["seconds"] or 0.0 for r in db["chunks"].rows]
    return pure.finish_database(folder, cfg, params, n_chunks, keep_raw, float(sum(secs)), _write_entries(db))


# ------------------------------------------------------------------------------------------------ Ray

def _chunk_task_body(params: np.ndarray, resolution: int,
                     config_dict: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Ray task body: single-threaded render + describe of one chunk (lattice by workers.lattice), its duration."""
    return pure.describe_chunk(params, resolution, config_dict, analyse_lattice)


def _ray_start(workers: int | None, address: str | None):
    """Use the running Ray (the jobs' one), else connect to `address`, else start a local one with `workers`
    CPUs; (ray, True when this call started it)."""
    import ray

    from service.scheduler import ensure_ray

    started = ensure_ray(address, None if address else (workers or os.cpu_count() or 1))
    return ray, started


def _run_chunks(ray, pending: list[int], params: np.ndarray, db, folder: Path, cfg: BuildConfig, workers: int,
                max_chunks: int | None, on_chunk: Callable[[int, int], None] | None,
                progress: bool) -> tuple[list[int], float, int]:
    """Run pending chunks with at most `workers` tasks in flight; store each as it finishes."""
    from tqdm import tqdm

    task = ray.remote(num_cpus=1, max_retries=2)(_chunk_task_body)
    cfg_dict = cfg.descriptor.to_dict()
    res_ref = cfg.resolution
    todo = list(pending if max_chunks is None else pending[:max(0, max_chunks)])
    rows = {r["id"]: r for r in db["chunks"].rows}
    in_flight: dict = {}
    computed: list[int] = []
    task_seconds, entries = 0.0, 0
    bar = tqdm(total=sum(rows[c]["stop"] - rows[c]["start"] for c in todo), unit="mask", desc="pptbf db",
               disable=not progress)

    def submit(cid: int) -> None:
        r = rows[cid]
        db["chunks"].update(cid, {"runs": (db["chunks"].get(cid)["runs"] or 0) + 1})
        in_flight[task.remote(np.array(params[r["start"]:r["stop"]]), res_ref, cfg_dict)] = cid

    try:
        while todo or in_flight:
            while todo and len(in_flight) < workers:
                submit(todo.pop(0))
            ready, _ = ray.wait(list(in_flight), num_returns=1)
            cid = in_flight.pop(ready[0])
            raw, white, lattice, secs = ray.get(ready[0])
            pure.save_chunk(folder, cid, raw, white, lattice)
            db["chunks"].update(cid, {"status": "done", "seconds": secs, "white_mean": float(white.mean()),
                                      "finished_at": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")})
            computed.append(cid)
            task_seconds += secs
            entries += len(white)
            bar.update(len(white))
            if on_chunk is not None:
                on_chunk(cid, len(computed))
    finally:
        bar.close()
        for ref in in_flight:
            ray.cancel(ref, force=True)
    return computed, task_seconds, entries


# ------------------------------------------------------------------------------------------------ public

def build_database(out: str | Path, config: BuildConfig | None = None, *, workers: int | None = None,
                   address: str | None = None, keep_raw: bool = True, max_chunks: int | None = None,
                   on_chunk: Callable[[int, int], None] | None = None, progress: bool = True) -> BuildReport:
    """Build (or resume) the PPTBF database in folder `out`.

    workers: tasks in flight (default: the Ray cluster's CPUs); address: Ray cluster to connect to when Ray is
    not initialised (else a local Ray with `workers` CPUs is started and shut down). max_chunks stops after that
    many chunks (resume later); on_chunk(chunk_id, n_done_this_call) is called after each stored chunk (an
    exception there stops the build; finished chunks stay done).
    """
    cfg = config or BuildConfig()
    cfg.validate()
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    db = _open_db(folder)
    _check_settings(db, folder, cfg.settings())
    n_chunks = pure.n_chunks_of(cfg)
    params = cfg.sample()
    done, pending = _sync_chunks(db, folder, cfg.size, cfg.chunk)
    report = BuildReport(folder, False, cfg.size, n_chunks, [], list(done), 0.0, 0.0)
    if (folder / "meta.json").is_file() and not pending:
        have_raw = all(pure.raw_path(folder, c).is_file() for c in range(n_chunks))
        if not have_raw and pure.dtype_only(folder, cfg):
            pure.cast_reduced(folder, cfg.reduced_dtype)
        elif pure.refit_needed(folder, cfg):
            if not have_raw:
                raise DatabaseError(f"{folder}: raw chunks were deleted, so the PCA cannot be refitted with "
                                    f"dim {cfg.descriptor.dim} / {cfg.reduced_dtype}; rebuild into a new folder")
            _finish(folder, db, cfg, params, n_chunks, keep_raw)
        elif have_raw and not keep_raw:
            pure.drop_raw(folder, n_chunks)
        report.complete = True
        report.seconds = time.perf_counter() - t0
        logger.info("%s: database already complete", folder)
        return report
    if pending:
        ray, started = _ray_start(workers, address)
        try:
            k = workers or max(1, int(ray.cluster_resources().get("CPU", 1)))
            report.workers = k
            computed, task_secs, entries = _run_chunks(ray, pending, params, db, folder, cfg, k, max_chunks,
                                                       on_chunk, progress)
        finally:
            if started:
                ray.shutdown()
        report.computed, report.task_seconds, report.entries = computed, task_secs, entries
    if len(report.skipped) + len(report.computed) == n_chunks:
        _finish(folder, db, cfg, params, n_chunks, keep_raw)
        report.complete = True
    report.seconds = time.perf_counter() - t0
    return report
