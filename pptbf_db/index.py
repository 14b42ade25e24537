"""PPTBF database storage and exact nearest-neighbour query on reduced descriptors.

A database folder (written by `pptbf_db.build`, the build driven by `service.db_build`) holds:
  meta.json     {"format": "proceduralize-pptbf-db/1", "size", "resolution", "seed", "descriptor", "dim", ...}
  params.npy    (N, 29) float64 parameter vectors
  reduced.npy   (N, d) float32 (or float16) PCA-reduced descriptors
  pca.npz       mean, scales, components, explained (no pickles)
  white.npy     (N,) float32 white fraction of each entry's mask
  db.sqlite     chunk status of the build and per-entry metadata (service.db_build's bookkeeping)
  raw_XXXX.npy  raw descriptor chunks (optional, may be deleted after the PCA)
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pptbf_db.descriptor import DEFAULT_EXTRACTOR, DescriptorConfig, PCAModel, describe_masks
from pptbf_db.errors import DatabaseError
from pptbf_db.pptbf import GENERATOR

logger = logging.getLogger(__name__)

FORMAT = "proceduralize-pptbf-db/1"
REQUIRED_FILES = ("meta.json", "params.npy", "reduced.npy", "pca.npz")
#: entries whose mask is (almost) all black or all white carry no pattern and are never returned
DEGENERATE_WHITE = 0.01


def default_database_path() -> Path:
    """The database bundled with the package (pptbf_db/data/default)."""
    return Path(__file__).resolve().parent / "data" / "default"


@dataclass(frozen=True)
class Match:
    """One query result: the entry's parameter vector, its descriptor distance and its row in the database."""

    params: np.ndarray
    distance: float
    entry_id: int


def resize_mask(mask: np.ndarray, height: int, width: int) -> np.ndarray:
    """Area-average resize of an (H, W) mask in [0, 1] (float32)."""
    m = np.asarray(mask, dtype=np.float32)
    if m.shape == (height, width):
        return m
    import torch
    import torch.nn.functional as F

    t = torch.from_numpy(np.ascontiguousarray(m))[None, None]
    if height <= m.shape[0] and width <= m.shape[1]:
        out = F.adaptive_avg_pool2d(t, (height, width))
    else:
        out = F.interpolate(t, size=(height, width), mode="bilinear", align_corners=False)
    return out[0, 0].numpy()


def read_meta(folder: Path) -> dict:
    """meta.json of a complete database folder (DatabaseError naming the folder and the fix otherwise)."""
    folder = Path(folder)
    fix = "rebuild it with `proceduralize db rebuild --out DIR` or point to another database folder"
    if not folder.is_dir():
        raise DatabaseError(f"{folder}: PPTBF database folder not found; {fix}")
    missing = [f for f in REQUIRED_FILES if not (folder / f).is_file()]
    if missing:
        raise DatabaseError(f"{folder}: incomplete PPTBF database (missing {', '.join(missing)}); "
                            f"an interrupted rebuild resumes with the same command; {fix}")
    try:
        meta = json.loads((folder / "meta.json").read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise DatabaseError(f"{folder / 'meta.json'}: unreadable ({exc}); {fix}") from exc
    if meta.get("format") != FORMAT:
        raise DatabaseError(f"{folder / 'meta.json'}: format {meta.get('format')!r} is not {FORMAT!r}; {fix}")
    for key in ("size", "resolution", "descriptor"):
        if key not in meta:
            raise DatabaseError(f"{folder / 'meta.json'}: field {key!r} missing; {fix}")
    return meta


def check_extractor(folder: Path, meta: dict, expected: str | None) -> None:
    """DatabaseError when the database's descriptor was built with another Gram extractor than `expected`:
    its descriptors and the masks fitted against it would not be comparable."""
    try:
        built = DescriptorConfig.from_dict(meta["descriptor"]).extractor
    except (TypeError, ValueError) as exc:
        raise DatabaseError(f"{folder / 'meta.json'}: field 'descriptor' unreadable ({exc}); rebuild it") from exc
    if expected is not None and built != expected:
        raise DatabaseError(
            f"{folder}: PPTBF database built with the {built!r} Gram feature extractor, this run describes masks "
            f"with {expected!r}; rebuild it with `proceduralize db rebuild --out {folder}` (the descriptor "
            f"changed) or point to a database built with {expected!r}")


class PPTBFIndex:
    """A loaded PPTBF database: describe masks like the database and find the nearest parameter vectors."""

    def __init__(self, params: np.ndarray, reduced: np.ndarray, pca: PCAModel, config: DescriptorConfig,
                 resolution: int, white: np.ndarray | None = None, meta: dict | None = None,
                 folder: Path | None = None):
        self.params = np.asarray(params, dtype=np.float64)
        self.reduced = np.ascontiguousarray(reduced, dtype=np.float32)
        self.pca = pca
        self.config = config
        self.resolution = int(resolution)
        self.meta = meta or {}
        self.folder = folder
        self.white = None if white is None else np.asarray(white, dtype=np.float32)
        self._sq = np.einsum("ij,ij->i", self.reduced, self.reduced)
        usable = np.ones(len(self.params), dtype=bool)
        if self.white is not None:
            usable &= (self.white > DEGENERATE_WHITE) & (self.white < 1.0 - DEGENERATE_WHITE)
        self.usable = usable

    def __len__(self) -> int:
        return len(self.params)

    @classmethod
    def load(cls, folder: str | Path | None = None, extractor: str | None = DEFAULT_EXTRACTOR) -> "PPTBFIndex":
        """Load a database folder (default: the bundled one); DatabaseError if missing/incomplete/other version,
        or built with another Gram feature extractor than `extractor` (None accepts any)."""
        folder = Path(folder) if folder is not None else default_database_path()
        meta = read_meta(folder)
        check_extractor(folder, meta, extractor)
        try:
            params = np.load(folder / "params.npy", allow_pickle=False)
            reduced = np.load(folder / "reduced.npy", allow_pickle=False)
            with np.load(folder / "pca.npz", allow_pickle=False) as z:
                pca = PCAModel.from_arrays(z)
            white = np.load(folder / "white.npy", allow_pickle=False) if (folder / "white.npy").is_file() else None
            config = DescriptorConfig.from_dict(meta["descriptor"])
        except (OSError, ValueError, KeyError) as exc:
            raise DatabaseError(f"{folder}: corrupt PPTBF database ({exc}); rebuild it") from exc
        n = int(meta["size"])
        if params.shape != (n, 29) or reduced.shape != (n, pca.dim) or (white is not None and len(white) != n):
            raise DatabaseError(f"{folder}: inconsistent PPTBF database (meta size {n}, params {params.shape}, "
                                f"reduced {reduced.shape}, pca dim {pca.dim}); rebuild it")
        logger.info("loaded PPTBF database %s: %d entries, %d px, dim %d", folder, n, meta["resolution"], pca.dim)
        generator = meta.get("generator", "pptbf/1")   # databases before the field was recorded
        if generator != GENERATOR:
            logger.warning("%s was rendered by PPTBF generator %s, this code renders %s: queries still work, but "
                           "`proceduralize db rebuild` makes the descriptors match the fields fitted here",
                           folder, generator, GENERATOR)
        return cls(params, reduced, pca, config, meta["resolution"], white, meta, folder)

    # -------------------------------------------------------------------------------------------- describe
    def _prepare(self, mask: np.ndarray, valid: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
        """Resize a mask (and valid) to the database resolution: width -> resolution, aspect kept."""
        m = np.asarray(mask)
        if m.ndim != 2:
            raise ValueError(f"mask must be 2-D (H, W), got shape {m.shape}")
        h, w = m.shape
        th, tw = max(8, int(round(h * self.resolution / w))), self.resolution
        out = resize_mask(m.astype(np.float32), th, tw)
        if m.dtype == bool and (th, tw) != (h, w):
            out = (out > 0.5).astype(np.float32)
        if valid is None:
            return out, None
        v = np.asarray(valid, dtype=bool)
        if v.shape != m.shape:
            raise ValueError(f"valid mask shape {v.shape} does not match mask {m.shape}")
        vr = resize_mask(v.astype(np.float32), th, tw) > 0.5
        if not vr.any():
            raise ValueError("valid mask has no valid pixel at the database resolution")
        return out, (None if vr.all() else vr)

    def describe(self, mask: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """Reduced descriptor (d,) of one (H, W) mask, resized to the database resolution first."""
        m, v = self._prepare(mask, valid)
        return self.pca.transform(describe_masks(m, v, self.config))[0]

    def describe_many(self, masks, valid: np.ndarray | None = None) -> np.ndarray:
        """Reduced descriptors (N, d) of same-size masks (a sequence of (H, W)) sharing one optional valid mask."""
        prepped = [self._prepare(m, valid) for m in masks]
        vv = prepped[0][1]
        raw = describe_masks(np.stack([p[0] for p in prepped]), vv, self.config)
        return self.pca.transform(raw)

    # -------------------------------------------------------------------------------------------- query
    def query_vector(self, vec: np.ndarray, k: int = 5) -> list[Match]:
        """The k nearest usable entries to a reduced descriptor (exact search, one matrix product)."""
        q = np.asarray(vec, dtype=np.float32).reshape(-1)
        d2 = self._sq - 2.0 * (self.reduced @ q) + float(q @ q)
        d2 = np.where(self.usable, d2, np.inf)
        k = int(min(max(k, 1), int(self.usable.sum())))
        idx = np.argpartition(d2, k - 1)[:k] if k < len(d2) else np.arange(len(d2))
        idx = idx[np.argsort(d2[idx], kind="stable")]
        return [Match(self.params[i].copy(), float(np.sqrt(max(d2[i], 0.0))), int(i)) for i in idx]

    def query(self, mask: np.ndarray, k: int = 5, valid: np.ndarray | None = None) -> list[Match]:
        """The k database entries whose masks are nearest to `mask` (H, W) in descriptor distance."""
        return self.query_vector(self.describe(mask, valid), k)

    def distances_to(self, mask: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """Descriptor distance (N,) from `mask` to every entry (inf for unusable entries)."""
        q = self.describe(mask, valid)
        d2 = self._sq - 2.0 * (self.reduced @ q) + float(q @ q)
        return np.where(self.usable, np.sqrt(np.maximum(d2, 0.0)), np.inf)

    def distance(self, mask_a: np.ndarray, mask_b: np.ndarray, valid: np.ndarray | None = None) -> float:
        """Descriptor distance between two masks of the same size (the mask fitter's loss)."""
        if np.shape(mask_a) != np.shape(mask_b):
            raise ValueError(f"masks differ in shape: {np.shape(mask_a)} vs {np.shape(mask_b)}")
        va, vb = self.describe_many([mask_a, mask_b], valid)
        return float(np.linalg.norm(va - vb))
