"""PPTBF database build: the pure work (no Ray, no SQLite; the driver is `service.db_build`).

N parameter vectors are sampled (seeded, `BuildConfig.sample`), split into chunks; each chunk's masks are
rendered and described (`render_and_describe` / `describe_chunk`, given the mask-analysis function that
measures each mask's lattice) and stored as raw_XXXX.npy, white_XXXX.npy and lattice_XXXX.npy
(`save_chunk`). At the end `finish_database` fits the PCA (numpy SVD) and writes reduced.npy, pca.npz,
white.npy, lattice.npy, params.npy and meta.json (written last: its presence marks a complete database).
See `pptbf_db.index` for the folder layout.
"""
from __future__ import annotations

import datetime as _dt
import json
import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Protocol

import numpy as np

from pptbf_db import pptbf
from pptbf_db.descriptor import DescriptorConfig, block_slices, describe_masks, fit_pca
from pptbf_db.files import atomic_path, write_text
from pptbf_db.index import DEGENERATE_WHITE, FORMAT
from pptbf_db.pptbf import GENERATOR

logger = logging.getLogger(__name__)

DEFAULT_SIZE = 5000
DEFAULT_RESOLUTION = 128
#: strata of the sampled vectors: nearly regular layouts, crisp cells (bricks, tiles, plates), the rest uniform;
#: every tiling family gets the same number of vectors
DEFAULT_REGULAR_SHARE = 0.15
DEFAULT_CRISP_SHARE = 0.35
DEFAULT_CHUNK = 100
#: lattice kinds stored per entry (the `kind` of what the mask-analysis function returns)
LATTICE_KINDS = ("none", "rows", "2d")


class LatticeLike(Protocol):
    """What the mask-analysis function returns (e.g. workers.lattice.Lattice)."""

    kind: str               # one of LATTICE_KINDS
    significance: float     # the repeat's height in ring standard deviations


#: the mask-analysis function of a build: binary mask (HxW bool) -> its lattice (e.g.
#: workers.lattice.analyse_lattice, passed by the caller: pptbf_db does not import workers)
LatticeOf = Callable[[np.ndarray], LatticeLike]


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


# ------------------------------------------------------------------------------------------------ pure work

def render_and_describe(params: np.ndarray, resolution: int, config: DescriptorConfig,
                        lattice_of: LatticeOf) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render each parameter vector as a `resolution` px mask and describe it: raw (n, D) float32, white (n,) and
    lattice (n, 2) float32 = (index of the lattice kind in LATTICE_KINDS, significance) of each mask, measured by
    `lattice_of` (binary mask -> object with .kind and .significance, e.g. workers.lattice.analyse_lattice).

    A vector whose render fails gives an empty mask (white 0, so the index never returns it).
    """
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
            lat = lattice_of(m > 0.5)
            lattice[i] = (LATTICE_KINDS.index(lat.kind), lat.significance)
    return describe_masks(masks, None, config), white, lattice


def describe_chunk(params: np.ndarray, resolution: int, config_dict: dict,
                   lattice_of: LatticeOf) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """One chunk's task body: single-threaded render + describe, with its duration (raw, white, lattice, s)."""
    import torch

    torch.set_num_threads(1)
    t0 = time.perf_counter()
    raw, white, lattice = render_and_describe(params, resolution, DescriptorConfig.from_dict(config_dict),
                                              lattice_of)
    return raw, white, lattice, time.perf_counter() - t0


# ------------------------------------------------------------------------------------------------ storage

def n_chunks_of(cfg: BuildConfig) -> int:
    """Number of chunks of a build."""
    return (cfg.size + cfg.chunk - 1) // cfg.chunk


def raw_path(folder: Path, cid: int) -> Path:
    """A chunk's raw descriptors file."""
    return folder / f"raw_{cid:04d}.npy"


def _save_npy(path: Path, arr: np.ndarray) -> None:
    """Atomic np.save (write a temporary file, then rename)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.save(fh, arr, allow_pickle=False)


def save_chunk(folder: Path, cid: int, raw: np.ndarray, white: np.ndarray, lattice: np.ndarray) -> None:
    """Store a finished chunk (raw descriptors, lattice, white share), each file atomically."""
    _save_npy(raw_path(folder, cid), raw)
    _save_npy(folder / f"lattice_{cid:04d}.npy", lattice)
    _save_npy(folder / f"white_{cid:04d}.npy", white)


# ------------------------------------------------------------------------------------------------ finish

def finish_database(folder: Path, cfg: BuildConfig, params: np.ndarray, n_chunks: int, keep_raw: bool,
                    task_core_seconds: float, write_entries: Callable[[Iterable[dict]], None] | None = None) -> dict:
    """Fit the PCA on all raw chunks, write reduced/pca/white/lattice/params, hand the per-entry rows to
    `write_entries` (the caller's bookkeeping, before meta.json), then write meta.json (last) and return it."""
    raws = [np.load(raw_path(folder, c), allow_pickle=False) for c in range(n_chunks)]
    white = np.concatenate([np.load(folder / f"white_{c:04d}.npy", allow_pickle=False) for c in range(n_chunks)])
    raw = np.concatenate(raws, axis=0)
    lattice = np.concatenate([_load_lattice(folder, c, len(r)) for c, r in enumerate(raws)])
    usable = (white > DEGENERATE_WHITE) & (white < 1.0 - DEGENERATE_WHITE)
    t0 = time.perf_counter()
    pca = fit_pca(raw[usable] if usable.sum() > 2 else raw, cfg.descriptor)
    reduced = pca.transform(raw).astype(cfg.reduced_dtype)
    pca_seconds = time.perf_counter() - t0
    with atomic_path(folder / "pca.npz") as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **pca.to_arrays())
    _save_npy(folder / "reduced.npy", reduced)
    _save_npy(folder / "white.npy", white)
    _save_npy(folder / "lattice.npy", lattice)
    _save_npy(folder / "params.npy", params)
    strata = cfg.strata()
    chunk_of = np.repeat(np.arange(n_chunks), [len(r) for r in raws])
    entries = ({"id": i, "chunk": int(chunk_of[i]), "white": float(white[i]),
                "tiling": int(params[i, 1]), "window_shape": int(params[i, 9]),
                "mixture": int(params[i, 16]), "degenerate": int(not usable[i]),
                "stratum": str(strata[i]), "lattice": _lattice_kind(lattice[i, 0]),
                "significance": float(lattice[i, 1])}
               for i in range(len(params)))
    if write_entries is not None:
        write_entries(entries)
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
            "task_core_seconds": round(float(task_core_seconds), 2), "pca_seconds": round(pca_seconds, 2),
            "raw_kept": bool(keep_raw),
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")}
    write_text(folder / "meta.json", json.dumps(meta, indent=1))
    if not keep_raw:
        drop_raw(folder, n_chunks)
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
    """Share of usable entries whose mask has a lattice (a 2-D lattice or rows, by the
    significance of its repeat), over all and per stratum; None where unknown."""
    known = usable & np.isfinite(lattice[:, 0])
    out: dict[str, float | None] = {}
    for name, sel in [("all", known)] + [(s, known & (strata == s)) for s in ("uniform", "regular", "crisp")]:
        out[name] = round(float((lattice[sel, 0] > 0).mean()), 4) if sel.any() else None
    return out


def refit_needed(folder: Path, cfg: BuildConfig) -> bool:
    """A complete folder needs its PCA refitted only when another dimension or storage type is asked for."""
    meta = json.loads((folder / "meta.json").read_text(encoding="utf-8"))
    return int(meta["descriptor"]["dim"]) != cfg.descriptor.dim or meta.get("reduced_dtype") != cfg.reduced_dtype


def dtype_only(folder: Path, cfg: BuildConfig) -> bool:
    """True when a complete folder differs from the request only in the storage type of reduced.npy."""
    meta = json.loads((folder / "meta.json").read_text(encoding="utf-8"))
    return int(meta["descriptor"]["dim"]) == cfg.descriptor.dim and meta.get("reduced_dtype") != cfg.reduced_dtype


def cast_reduced(folder: Path, dtype: str) -> None:
    """Store reduced.npy with another dtype (no raw chunks needed; float16 -> float32 keeps float16 precision)."""
    _save_npy(folder / "reduced.npy", np.load(folder / "reduced.npy", allow_pickle=False).astype(dtype))
    meta = json.loads((folder / "meta.json").read_text(encoding="utf-8"))
    meta["reduced_dtype"] = dtype
    (folder / "meta.json").write_text(json.dumps(meta, indent=1), encoding="utf-8")


def drop_raw(folder: Path, n_chunks: int) -> None:
    """Delete the raw chunk files of a complete database (and say so in meta.json)."""
    for c in range(n_chunks):
        raw_path(folder, c).unlink(missing_ok=True)
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

def with_dim(config: BuildConfig, dim: int) -> BuildConfig:
    """A copy of `config` with another PCA dimension."""
    return replace(config, descriptor=replace(config.descriptor, dim=dim))
