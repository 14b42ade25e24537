"""The SQLite job store: schema migration, stage item lifecycle, resume checks, two writers at once."""
from __future__ import annotations

import multiprocessing as mp
import sqlite3
import time
from pathlib import Path

import pytest

from pptbf_db.errors import DatabaseError
from service.store import SCHEMA_VERSION, Store, file_checksum


def _artefact(root: Path, rel: str, data: bytes) -> dict:
    p = root / rel
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_bytes(data)
    return {"path": rel, "kind": "test", "checksum": file_checksum(p), "bytes": len(data)}


def test_new_database_is_wal_and_current(tmp_path):
    with Store(tmp_path / "j.db") as s:
        assert s.version == SCHEMA_VERSION
        assert s.db.journal_mode == "wal"
        assert {"jobs", "materials", "stages", "artefacts", "errors", "meta"} <= set(s.db.table_names())
        assert s.db.execute("PRAGMA busy_timeout").fetchone()[0] >= 10000


def test_migration_from_version_1_keeps_rows(tmp_path):
    path = tmp_path / "old.db"
    with Store(path, migrate_to=1) as s:
        assert s.version == 1 and "errors" not in s.db.table_names()
        s.db["jobs"].insert({"name": "old", "output": "/x", "status": "done"})
        assert "runs" not in s.db["jobs"].columns_dict
    with Store(path) as s:
        assert s.version == SCHEMA_VERSION
        assert s.job("old")["status"] == "done" and s.job("old")["runs"] == 0
        assert s.register_job("old", None, "/x", {}) == 1
        assert "errors" in s.db.table_names()


def test_newer_or_foreign_file_is_refused(tmp_path):
    path = tmp_path / "new.db"
    with Store(path) as s:
        s.db.execute("UPDATE meta SET value = '99' WHERE key = 'schema_version'")
    with pytest.raises(DatabaseError, match="newer than this proceduralize"):
        Store(path)
    junk = tmp_path / "junk.db"
    junk.write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(DatabaseError, match="junk.db"):
        Store(junk)


def test_item_lifecycle_and_resume_check(tmp_path):
    with Store(tmp_path / "j.db") as s:
        s.register_job("j", None, str(tmp_path), {})
        s.sync_materials("j", [{"name": "m", "output": "m", "spec_hash": "h1", "spec": {}}])
        assert s.start_item("j", "m", "load") == 1
        assert s.item("j", "m", "load")["status"] == "running"
        s.fail_item("j", "m", "load", "", "WorkerCrashedError: gone", "WorkerCrashedError", final=False)
        assert s.item("j", "m", "load")["status"] == "pending"
        assert s.start_item("j", "m", "load") == 2
        art = _artefact(tmp_path, "m/load/maps.npz", b"abc")
        s.finish_item("j", "m", "load", "", {"artefacts": [art], "info": {"size": [8, 8]}, "duration": 0.5,
                                            "worker": "w:1"})
        row = s.item("j", "m", "load")
        assert (row["status"], row["attempts"], row["executions"], row["worker"]) == ("done", 2, 1, "w:1")
        assert s.done_info("j", "m", "load") == {"size": [8, 8]}
        assert s.is_done("j", "m", "load", "", tmp_path)
        (tmp_path / "m/load/maps.npz").write_bytes(b"abd")  # changed content -> recompute
        assert not s.is_done("j", "m", "load", "", tmp_path)
        (tmp_path / "m/load/maps.npz").unlink()
        assert not s.is_done("j", "m", "load", "", tmp_path)
        errs = s.errors("j")
        assert len(errs) == 1 and errs[0]["kind"] == "WorkerCrashedError" and errs[0]["final"] == 0
        summ = s.stage_summary("j")
        assert summ[0]["stage"] == "load" and summ[0]["status"] == "done" and summ[0]["attempts"] == 2


def test_changed_material_spec_resets_its_stages(tmp_path):
    with Store(tmp_path / "j.db") as s:
        s.register_job("j", None, str(tmp_path), {})
        mats = [{"name": n, "output": n, "spec_hash": "h", "spec": {}} for n in ("a", "b")]
        s.sync_materials("j", mats)
        for n in ("a", "b"):
            s.finish_item("j", n, "load", "", {"artefacts": [_artefact(tmp_path, f"{n}/x", n.encode())]})
        mats[1]["spec_hash"] = "h2"
        assert s.sync_materials("j", mats) == ["b"]
        assert s.item("j", "a", "load")["status"] == "done"
        assert s.item("j", "b", "load") is None and not s.artefacts("j", "b")


def _hammer(path: str, job: str, n: int, root: str) -> None:
    """One writer process: n items of its own job, each started then finished with an artefact."""
    s = Store(path)
    s.register_job(job, None, root, {"writer": job})
    s.sync_materials(job, [{"name": "m", "output": "m", "spec_hash": "h", "spec": {}}])
    for i in range(n):
        s.start_item(job, "m", "noise", str(i))
        s.finish_item(job, "m", "noise", str(i), {"artefacts": [{"path": f"{job}/{i}", "checksum": "c" * 64}],
                                                  "duration": 0.001, "worker": job})
    s.finish_job(job, "done")
    s.close()


def test_two_writer_processes_do_not_corrupt_the_database(tmp_path):
    path = tmp_path / "shared.db"
    Store(path).close()
    n = 150
    ctx = mp.get_context("spawn")
    procs = [ctx.Process(target=_hammer, args=(str(path), f"job{k}", n, str(tmp_path))) for k in range(2)]
    t0 = time.perf_counter()
    for p in procs:
        p.start()
    # a reader polls while both write (WAL: readers never block writers)
    with Store(path) as reader:
        while any(p.is_alive() for p in procs):
            reader.stage_summary("job0")
            time.sleep(0.01)
    for p in procs:
        p.join(60)
        assert p.exitcode == 0
    seconds = time.perf_counter() - t0
    with Store(path) as s:
        assert s.integrity_ok()
        for k in range(2):
            rows = s.items(f"job{k}")
            assert len(rows) == n and all(r["status"] == "done" and r["executions"] == 1 for r in rows)
            assert len(s.artefacts(f"job{k}")) == n and s.job(f"job{k}")["status"] == "done"
    print(f"2 x {n} items written concurrently in {seconds:.2f} s")


def test_busy_writer_waits_instead_of_failing(tmp_path):
    path = tmp_path / "j.db"
    s = Store(path, timeout=10)
    s.register_job("j", None, str(tmp_path), {})
    blocker = sqlite3.connect(str(path), timeout=1, check_same_thread=False)
    blocker.execute("BEGIN IMMEDIATE")
    blocker.execute("UPDATE jobs SET status = 'x'")
    import threading

    threading.Timer(0.5, blocker.commit).start()
    t0 = time.perf_counter()
    s.finish_job("j", "done")  # waits for the lock (busy timeout) rather than raising "database is locked"
    assert time.perf_counter() - t0 >= 0.4
    assert s.job("j")["status"] == "done"
    s.close()
    blocker.close()
