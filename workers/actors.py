"""Long-lived stage holders that the scheduler wraps as Ray actors (no Ray here).

``MaskFitter`` loads the PPTBF index once and fits many masks with it; ``Recomposer`` keeps a torch device
(GPU when the scheduler places it on one) for the recomposition optimisation.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from pptbf_db.index import PPTBFIndex, default_database_path

from .assemble import build_material
from .masks import fit_pptbf_mask
from .recompose import RecomposeConfig, choose_cells, optimise
from .structure import cut_is_band

logger = logging.getLogger(__name__)


class MaskFitter:
    """Holds one PPTBF index (loaded on first use) and fits binary masks against it."""

    def __init__(self, database: str | Path | None = None):
        self.database = database
        self._index = None
        self.load_seconds = 0.0
        self.loads = 0
        self.fits = 0

    @property
    def index(self) -> Any:
        """The loaded PPTBFIndex (loaded once per holder)."""
        if self._index is None:
            t0 = time.perf_counter()
            self._index = PPTBFIndex.load(self.database or default_database_path())
            self.load_seconds = time.perf_counter() - t0
            self.loads += 1
            logger.info("PPTBF index loaded in %.2f s", self.load_seconds)
        return self._index

    def fit(self, mask: np.ndarray, valid: np.ndarray | None = None, config: Any = None, seed: int = 0,
            cell_length: float | None = None) -> Any:
        """``workers.masks.fit_pptbf_mask`` with the held index."""
        self.fits += 1
        return fit_pptbf_mask(mask, self.index, valid=valid, config=config, seed=seed, cell_length=cell_length)


class Recomposer:
    """Keeps the torch device (a GPU when the scheduler places it on one) and runs the recomposition of one
    material at a time: :func:`workers.assemble.build_material`, then :func:`workers.recompose.optimise`."""

    def __init__(self, device: str = "cpu"):
        self.device = device

    def run(self, material: Any, tree: Any, noises: dict, fits: dict, options: dict | None = None,
            seed: int = 0, pieces: dict | None = None) -> tuple[Any, dict]:
        """(optimised ProceduralMaterial, report with loss before/after) via ``workers.recompose``."""
        t0 = time.perf_counter()
        opts = dict(options or {})
        if int(opts.get("iterations", 1)) == 0:
            proc = build_material(material, tree, noises, fits, seed, pieces)
            return proc, {"device": self.device, "iterations": 0, "seconds": time.perf_counter() - t0}
        cfg = RecomposeConfig.from_dict({"seed": seed, "device": self.device, **opts})
        band = tree.children and cut_is_band(tree.meta.get("structure"))
        thinner = (tree.children[0].id,) if band else ()        # the structural split's network
        proc, cells = choose_cells(lambda f: build_material(material, tree, noises, f, seed, pieces), fits,
                                   material, cfg, thinner=thinner)
        res = optimise(proc, material, cfg)
        report = res.report()
        report["cells"] = cells
        report["seconds_total"] = round(time.perf_counter() - t0, 3)
        return res.material, report
