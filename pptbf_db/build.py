"""Parallel, resumable PPTBF database build on Ray.

N parameter vectors are sampled (seeded), split into chunks; one Ray task per chunk renders the masks and
describes them (pure functions `render_and_describe`), the driver stores each finished chunk as raw_XXXX.npy
and marks it done in db.sqlite, so a killed build resumes where it stopped and never recomputes a finished
chunk. At the end the PCA is fitted (numpy SVD) and reduced.npy, pca.npz, white.npy and meta.json (written
last: its presence marks a complete database) are written. See `pptbf_db.index` for the folder layout.
"""
from __future__ import annotations

import datetime as _dt
import json
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from pptbf_db import pptbf
from pptbf_db.pptbf import GENERATOR
from pptbf_db.descriptor import DescriptorConfig, block_slices, describe_masks, fit_pca
from pptbf_db.index import DEGENERATE_WHITE, FORMAT
from workers.errors import DatabaseError

logger = logging.getLogger(__name__)

DEFAULT_SIZE = 5000
DEFAULT_RESOLUTION = 128
#: strata of the sampled vectors: nearly regular layouts, crisp cells (bricks, tiles, plates), the rest uniform;
#: every tiling family gets the same number of vectors
DEFAULT_REGULAR_SHARE = 0.15
DEFAULT_CRISP_SHARE = 0.35
DEFAULT_CHUNK = 100
#: lattice kinds stored per entry (workers.lattice.Lattice.kind)
LATTICE_KINDS = ("none", "rows", "2d")


@dataclass
class BuildConfig:
    """What to build: N entries rendered at `resolution` px, sampled with `seed`, in chunks of `chunk`."""

    size: int = DEFAULT_SIZE
    resolution: int = DEFAULT_RESOLUTION
    seed: int = 0
    chunk: int = DEFAULT_CHUNK
    descriptor: DescriptorConfig = field(default_factory=DescriptorConfig)
    reduced_dtype: str = "float32"          # "float16" halves the bundled database
    regular_share: float = DEFAULT_REGULAR_SHARE  # share of nearly regular layouts (see pptbf.sample_params)
    crisp_share: float = DEFAULT_CRISP_SHARE      # share of crisp-cell layouts (see pptbf.sample_params)
    balanced_tiling: bool = True                  # the same number of vectors per tiling family

    def settings(self) -> dict:
        """The settings a resumed build must match (the PCA dimension may change: it is refitted)."""
        desc = self.descriptor.to_dict()
        desc.pop("dim")
        out = {"format": FORMAT, "size": self.size, "resolution": self.resolution, "seed": self.seed,
               "chunk": self.chunk, "descriptor": desc, "generator": GENERATOR}
        if self.regular_share:  # absent = 0: builds started before the option resume as they were
            out["regular_share"] = self.regular_share
        if self.crisp_share:
            out["crisp_share"] = self.crisp_share
        if self.balanced_tiling:
            out["balanced_tiling"] = True
        return out

    def sample(self) -> np.ndarray:
        """The (size, 29) parameter vectors of this build (seeded)."""
        return np.asarray(pptbf.sample_params(np.random.default_rng(self.seed), self.size, ref_width=self.resolution,
                                              regular_share=self.regular_share, crisp_share=self.crisp_share,
                                              balanced_tiling=self.balanced_tiling), dtype=np.float64)

    def strata(self) -> np.ndarray:
        """Per vector, its stratum: "uniform", "regular" or "crisp"."""
        out = np.full(self.size, "uniform", dtype=object)
        reg, crisp = pptbf.stratum_indices(self.size, self.regular_share, self.crisp_share)
        out[reg], out[crisp] = "regular", "crisp"
        return out

    def validate(self) -> None:
        """ValueError naming the bad field."""
        if self.size < 2:
            raise ValueError(f"size must be >= 2, got {self.size}")
        if not 16 <= self.resolution <= 1024:
            raise ValueError(f"resolution must be in 16..1024 px, got {self.resolution}")
        if self.chunk < 1:
            raise ValueError(f"chunk must be >= 1, got {self.chunk}")
        if self.reduced_dtype not in ("float16", "float32"):
            raise ValueError(f"reduced_dtype must be float16 or float32, got {self.reduced_dtype!r}")
        if not 0.0 <= self.regular_share <= 1.0:
            raise ValueError(f"regular_share must be in [0, 1], got {self.regular_share}")
        if not 0.0 <= self.crisp_share <= 1.0 - self.regular_share:
            raise ValueError(f"crisp_share must be in [0, 1 - regular_share], got {self.crisp_share}")


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


# ------------------------------------------------------------------------------------------------ pure work

def render_and_describe(params: np.ndarray, resolution: int,
                        config: DescriptorConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render each parameter vector as a `resolution` px mask and describe it: raw (n, D) float32, white (n,) and
    lattice (n, 2) float32 = (index of the lattice kind in LATTICE_KINDS, significance) of each mask.

    A vector whose render fails gives an empty mask (white 0, so the index never returns it).
    """
    from workers.lattice import analyse_lattice

    masks = np.zeros((len(params), resolution, resolution), dtype=np.float32)
    for i, p in enumerate(params):              # one render per vector (each is vectorised over pixels)
        try:
            masks[i] = pptbf.render_mask(p, resolution)
        except (ValueError, FloatingPointError) as exc:
            logger.warning("PPTBF render failed for a database entry (%s); stored as an empty mask", exc)
    white = masks.mean(axis=(1, 2)).astype(np.float32)
    lattice = np.zeros((len(params), 2), dtype=np.float32)
    for i, m in enumerate(masks):
        if DEGENERATE_WHITE < white[i] < 1.0 - DEGENERATE_WHITE:
            lat = analyse_lattice(m > 0.5)
            lattice[i] = (LATTICE_KINDS.index(lat.kind), lat.significance)
    return describe_masks(masks, None, config), white, lattice


def _chunk_task_body(params: np.ndarray, resolution: int,
                     config_dict: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Ray task body: single-threaded render + describe of one chunk, with its duration."""
    import torch

    torch.set_num_threads(1)
    t0 = time.perf_counter()
    raw, white, lattice = render_and_describe(params, resolution, DescriptorConfig.from_dict(config_dict))
    return raw, white, lattice, time.perf_counter() - t0


# ------------------------------------------------------------------------------------------------ storage

def _raw_path(folder: Path, cid: int) -> Path:
    return folder / f"raw_{cid:04d}.npy"


def _save_npy(path: Path, arr: np.ndarray) -> None:
    """Atomic np.save (write a temporary file, then rename)."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        np.save(fh, arr, allow_pickle=False)
    os.replace(tmp, path)


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
        if r["status"] == "done" and (finished or _raw_path(folder, r["id"]).is_file()):
            done.append(r["id"])
        else:
            if r["status"] == "done":
                logger.warning("chunk %d was done but %s is missing: recomputing", r["id"], _raw_path(folder, r["id"]))
                db["chunks"].update(r["id"], {"status": "pending"})
            pending.append(r["id"])
    return done, pending


# ------------------------------------------------------------------------------------------------ Ray

def _ray_start(workers: int | None, address: str | None):
    """Use the running Ray, else connect to `address`, else start a local one with `workers` CPUs."""
    import ray

    if ray.is_initialized():
        return ray, False
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    if address:
        ray.init(address=address, logging_level="WARNING")
    else:
        ray.init(address="local", num_cpus=workers or os.cpu_count() or 1, include_dashboard=False,
                 logging_level="WARNING")
    return ray, True


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
            _save_npy(_raw_path(folder, cid), raw)
            _save_npy(folder / f"lattice_{cid:04d}.npy", lattice)
            _save_npy(folder / f"white_{cid:04d}.npy", white)
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


# ------------------------------------------------------------------------------------------------ finish

def _finish(folder: Path, db, cfg: BuildConfig, params: np.ndarray, n_chunks: int, keep_raw: bool) -> dict:
    """Fit the PCA on all raw chunks, write reduced/pca/white, the entries table and meta.json."""
    raws = [np.load(_raw_path(folder, c), allow_pickle=False) for c in range(n_chunks)]
    white = np.concatenate([np.load(folder / f"white_{c:04d}.npy", allow_pickle=False) for c in range(n_chunks)])
    raw = np.concatenate(raws, axis=0)
    lattice = np.concatenate([_load_lattice(folder, c, len(r)) for c, r in enumerate(raws)])
    usable = (white > DEGENERATE_WHITE) & (white < 1.0 - DEGENERATE_WHITE)
    t0 = time.perf_counter()
    pca = fit_pca(raw[usable] if usable.sum() > 2 else raw, cfg.descriptor)
    reduced = pca.transform(raw).astype(cfg.reduced_dtype)
    pca_seconds = time.perf_counter() - t0
    with open(folder / "pca.npz.tmp", "wb") as fh:
        np.savez(fh, **pca.to_arrays())
    os.replace(folder / "pca.npz.tmp", folder / "pca.npz")
    _save_npy(folder / "reduced.npy", reduced)
    _save_npy(folder / "white.npy", white)
    _save_npy(folder / "lattice.npy", lattice)
    _save_npy(folder / "params.npy", params)
    strata = cfg.strata()
    chunk_of = np.repeat(np.arange(n_chunks), [len(r) for r in raws])
    db["entries"].drop(ignore=True)
    db["entries"].insert_all(({"id": i, "chunk": int(chunk_of[i]), "white": float(white[i]),
                               "tiling": int(params[i, 1]), "window_shape": int(params[i, 9]),
                               "mixture": int(params[i, 16]), "degenerate": int(not usable[i]),
                               "stratum": str(strata[i]), "lattice": _lattice_kind(lattice[i, 0]),
                               "significance": float(lattice[i, 1])}
                              for i in range(len(params))), pk="id", batch_size=2000)
    secs = [r["seconds"] or 0.0 for r in db["chunks"].rows]
    meta = {"format": FORMAT, "size": int(len(params)), "resolution": cfg.resolution, "seed": cfg.seed,
            "chunk": cfg.chunk, "chunks": n_chunks, "descriptor": cfg.descriptor.to_dict(), "dim": pca.dim,
            "raw_dim": int(raw.shape[1]),
            "blocks": {k: [v.start, v.stop] for k, v in block_slices(cfg.descriptor, raw.shape[1]).items()},
            "explained_variance": float(pca.explained.sum()), "reduced_dtype": cfg.reduced_dtype,
            "degenerate": int((~usable).sum()),
            "sampler": "pptbf_db.pptbf.sample_params(ref_width=resolution, regular_share=regular_share, "
                       "crisp_share=crisp_share, balanced_tiling=balanced_tiling)",
            "regular_share": cfg.regular_share, "crisp_share": cfg.crisp_share,
            "balanced_tiling": cfg.balanced_tiling, "generator": GENERATOR,
            "lattice_share": lattice_shares(lattice, strata, usable),
            "task_core_seconds": round(float(sum(secs)), 2), "pca_seconds": round(pca_seconds, 2),
            "raw_kept": bool(keep_raw),
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")}
    (folder / "meta.json.tmp").write_text(json.dumps(meta, indent=1), encoding="utf-8")
    os.replace(folder / "meta.json.tmp", folder / "meta.json")
    if not keep_raw:
        _drop_raw(folder, n_chunks)
    logger.info("PPTBF database %s: %d entries, dim %d (%.1f%% variance), %d degenerate",
                folder, len(params), pca.dim, 100 * meta["explained_variance"], meta["degenerate"])
    return meta


def _load_lattice(folder: Path, cid: int, n: int) -> np.ndarray:
    """A chunk's per-entry lattice (kind index, significance); NaN for chunks computed before it was stored."""
    path = folder / f"lattice_{cid:04d}.npy"
    return np.load(path, allow_pickle=False) if path.is_file() else np.full((n, 2), np.nan, np.float32)


def _lattice_kind(code: float) -> str | None:
    return None if not np.isfinite(code) else LATTICE_KINDS[int(code)]


def lattice_shares(lattice: np.ndarray, strata: np.ndarray, usable: np.ndarray) -> dict[str, float | None]:
    """Share of usable entries whose mask has a lattice (workers.lattice: a 2-D lattice or rows, by the
    significance of its repeat), over all and per stratum; None where unknown."""
    known = usable & np.isfinite(lattice[:, 0])
    out: dict[str, float | None] = {}
    for name, sel in [("all", known)] + [(s, known & (strata == s)) for s in ("uniform", "regular", "crisp")]:
        out[name] = round(float((lattice[sel, 0] > 0).mean()), 4) if sel.any() else None
    return out


def _refit_needed(folder: Path, cfg: BuildConfig) -> bool:
    """A complete folder needs its PCA refitted only when another dimension or storage type is asked for."""
    meta = json.loads((folder / "meta.json").read_text(encoding="utf-8"))
    return int(meta["descriptor"]["dim"]) != cfg.descriptor.dim or meta.get("reduced_dtype") != cfg.reduced_dtype


def _dtype_only(folder: Path, cfg: BuildConfig) -> bool:
    """True when a complete folder differs from the request only in the storage type of reduced.npy."""
    meta = json.loads((folder / "meta.json").read_text(encoding="utf-8"))
    return int(meta["descriptor"]["dim"]) == cfg.descriptor.dim and meta.get("reduced_dtype") != cfg.reduced_dtype


def _cast_reduced(folder: Path, dtype: str) -> None:
    """Store reduced.npy with another dtype (no raw chunks needed; float16 -> float32 keeps float16 precision)."""
    _save_npy(folder / "reduced.npy", np.load(folder / "reduced.npy", allow_pickle=False).astype(dtype))
    meta = json.loads((folder / "meta.json").read_text(encoding="utf-8"))
    meta["reduced_dtype"] = dtype
    (folder / "meta.json").write_text(json.dumps(meta, indent=1), encoding="utf-8")


def _drop_raw(folder: Path, n_chunks: int) -> None:
    """Delete the raw chunk files of a complete database (and say so in meta.json)."""
    for c in range(n_chunks):
        _raw_path(folder, c).unlink(missing_ok=True)
        (folder / f"white_{c:04d}.npy").unlink(missing_ok=True)
        (folder / f"lattice_{c:04d}.npy").unlink(missing_ok=True)
    meta_path = folder / "meta.json"
    if meta_path.is_file():
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
        meta["raw_kept"] = False
        meta_path.write_text(json.dumps(meta, indent=1), encoding="utf-8")


BUILD_FILES = ("meta.json", "params.npy", "reduced.npy", "pca.npz", "white.npy", "lattice.npy", "db.sqlite")


def clear_database(folder: str | Path) -> int:
    """Delete a database folder's build files (only names a build writes), so the next build starts afresh."""
    folder = Path(folder)
    n = 0
    chunk_files = [f for pat in ("raw_*.npy*", "white_*.npy*", "lattice_*.npy*") for f in sorted(folder.glob(pat))]
    for f in [folder / b for b in BUILD_FILES] + chunk_files:
        if f.is_file():
            f.unlink()
            n += 1
    return n


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
    n_chunks = (cfg.size + cfg.chunk - 1) // cfg.chunk
    params = cfg.sample()
    done, pending = _sync_chunks(db, folder, cfg.size, cfg.chunk)
    report = BuildReport(folder, False, cfg.size, n_chunks, [], list(done), 0.0, 0.0)
    if (folder / "meta.json").is_file() and not pending:
        have_raw = all(_raw_path(folder, c).is_file() for c in range(n_chunks))
        if not have_raw and _dtype_only(folder, cfg):
            _cast_reduced(folder, cfg.reduced_dtype)
        elif _refit_needed(folder, cfg):
            if not have_raw:
                raise DatabaseError(f"{folder}: raw chunks were deleted, so the PCA cannot be refitted with "
                                    f"dim {cfg.descriptor.dim} / {cfg.reduced_dtype}; rebuild into a new folder")
            _finish(folder, db, cfg, params, n_chunks, keep_raw)
        elif have_raw and not keep_raw:
            _drop_raw(folder, n_chunks)
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


def with_dim(config: BuildConfig, dim: int) -> BuildConfig:
    """A copy of `config` with another PCA dimension."""
    return replace(config, descriptor=replace(config.descriptor, dim=dim))
