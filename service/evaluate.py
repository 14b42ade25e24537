"""The quality scorecard of a finished job (the command: :mod:`service.commands.evaluate`).

For every material of the job: read the working-size input maps (``load/maps.npz``) and the published graph
(``material.json``), regenerate the procedural maps from the graph alone at the reference size (the left half
of the input, see :mod:`workers.evaluate` for the protocol) with seed = the graph's seed + ``seed_offset``, and
score them and the baselines. Writes ``<job output>/evaluation/{metrics.csv, metrics.json, summary.csv}`` and
``<material>/evaluation.json``. Materials that failed or have no graph are listed with the reason.
"""
from __future__ import annotations

import csv
import io
import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from pptbf_db.errors import ProceduralizeError
from pptbf_db.files import write_text
from service.folder import MaterialFolder
from service.pipeline import read_npz
from workers.errors import InputError

if TYPE_CHECKING:  # workers.evaluate pulls numpy/scipy/torch: imported inside functions so --help stays light
    from workers.evaluate import EvalConfig, MetricRow

logger = logging.getLogger(__name__)

SEED_OFFSET = 1000
METRICS = ("swd", "spectrum", "histogram", "gram")  # == workers.evaluate.METRICS (checked in tests)
COLUMNS = ("material", "map", "method", *METRICS)
PROTOCOL = ("reference = left half of each working-size input map; procedural = graph re-evaluated at the "
            "reference size with seed = graph seed + seed_offset; half = right half of the input (the floor); "
            "rpn = random phase noise of the whole input map, left-half crop (normal: RPN of the normal's xyz, "
            "renormalised); flat = mean of the whole input map; render = GGX under the paper's 16 lights, "
            "tonemapped, metrics averaged over lights; gram = pretrained VGG-19 Gram distance (relu1_1..relu4_1) "
            "of the map as an image, gram ratios in units of the half row (the input's own left-to-right "
            "distance); lower is better")


@dataclass
class JobEvaluation:
    """Scorecard of a job: rows of every evaluated material, skipped materials with the reason, files written."""

    job: str
    output: Path
    rows: list["MetricRow"] = field(default_factory=list)
    skipped: list[tuple[str, str]] = field(default_factory=list)
    files: list[Path] = field(default_factory=list)
    seconds: float = 0.0

    def summary(self) -> list[dict]:
        from workers.evaluate import summarise

        return summarise(self.rows)

    def gram(self) -> tuple[list[dict], dict]:
        """VGG-19 Gram ratios to the floor per (material, map), and their summary (workers.evaluate)."""
        from workers.evaluate import gram_ratios, gram_summary

        return gram_ratios(self.rows), gram_summary(self.rows)


def _clean(v):
    """NaN -> None (JSON null); floats rounded to 6 significant digits."""
    if isinstance(v, float):
        return None if math.isnan(v) else float(f"{v:.6g}")
    return v





def _write_csv(path: Path, rows: list[dict], columns: tuple[str, ...]) -> Path:
    """Rows as CSV (missing values empty)."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(columns), extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: "" if _clean(r.get(k)) is None else _clean(r.get(k)) for k in columns})
    return write_text(path, buf.getvalue())


def _write_json(path: Path, doc: dict) -> Path:
    def walk(x):
        if isinstance(x, dict):
            return {k: walk(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [walk(v) for v in x]
        return _clean(x)

    return write_text(path, json.dumps(walk(doc), indent=1))


def evaluate_material_dir(mdir: MaterialFolder | Path, name: str, seed: int = 0,
                          seed_offset: int = SEED_OFFSET,
                          config: "EvalConfig | None" = None) -> tuple[list["MetricRow"], dict]:
    """Scorecard rows of one material folder and the per-material document (InputError if files are missing)."""
    from workers import graph
    from workers.evaluate import EvalConfig, evaluate_material, gram_ratios, gram_summary, reference_size, summarise

    folder = MaterialFolder.of(mdir)
    graph_file, maps_file = folder.published, folder.working_maps
    if not graph_file.is_file():
        raise InputError(f"{graph_file}: no published graph (the output stage did not finish)")
    if not maps_file.is_file():
        raise InputError(f"{maps_file}: no working-size input maps (the load stage did not finish)")
    try:
        inputs = read_npz(maps_file)
    except (OSError, ValueError) as exc:
        raise InputError(f"{maps_file}: unreadable ({exc})") from None
    mat = graph.load(graph_file)
    w, h = reference_size(inputs)
    eval_seed = int(mat.seed) + seed_offset
    t0 = time.perf_counter()
    procedural = graph.evaluate(mat, w, h, scale=mat.working_scale, seed=eval_seed)  # the inputs' pattern size
    t_graph = time.perf_counter() - t0
    try:
        rows = evaluate_material(inputs, procedural, seed=seed, material=name, config=config or EvalConfig())
    except ValueError as exc:
        raise InputError(f"{folder.path}: {exc}") from None
    doc = {"material": name, "graph": str(graph_file), "inputs": str(maps_file),
           "input_size": [int(inputs["albedo"].shape[1]), int(inputs["albedo"].shape[0])],
           "reference_size": [w, h], "graph_seed": int(mat.seed), "evaluation_seed": eval_seed,
           "metric_seed": seed, "graph_seconds": round(t_graph, 3), "protocol": PROTOCOL,
           "rows": [r.to_dict() for r in rows], "summary": summarise(rows),
           "gram_ratios": gram_ratios(rows), "gram_summary": gram_summary(rows)}
    return rows, doc


def _skip_reason(m: dict, folder: MaterialFolder) -> str | None:
    """Why a material cannot be scored (None if it can be tried)."""
    if m.get("status") == "failed":
        return f"material failed: {m.get('error') or 'see proceduralize status'}"
    if not folder.published.is_file():
        return f"no material.json in {folder.path} (status {m.get('status')}: the output stage did not finish)"
    return None


def evaluate_job(store, job: str, out: Path | None = None, seed: int = 0, seed_offset: int = SEED_OFFSET,
                 config: "EvalConfig | None" = None, materials: list[str] | None = None) -> JobEvaluation:
    """Score every material of ``job`` in ``store``; write the CSV/JSON files; never stop at a bad material."""
    t0 = time.perf_counter()
    root = store.output_root(job)   # where the files are now (a moved or copied job folder too)
    ev = JobEvaluation(job=job, output=Path(out) if out else root / "evaluation")
    known = [m["name"] for m in store.materials(job)]
    unknown = sorted(set(materials or ()) - set(known))
    if unknown:
        raise InputError(f"job {job!r} has no material(s) {', '.join(unknown)} (has: {', '.join(known)})")
    for m in store.materials(job):
        if materials and m["name"] not in materials:
            continue
        folder = MaterialFolder(root / m["output"])
        reason = _skip_reason(m, folder)
        if reason is None:
            try:
                rows, doc = evaluate_material_dir(folder, m["name"], seed, seed_offset, config)
            except (ProceduralizeError, OSError, ValueError, KeyError) as exc:
                reason = f"{type(exc).__name__}: {exc}"
            else:
                ev.rows += rows
                ev.files.append(_write_json(folder.evaluation, doc))
        if reason is not None:
            logger.warning("%s: not evaluated: %s", m["name"], reason)
            ev.skipped.append((m["name"], reason))
    ev.seconds = time.perf_counter() - t0
    ev.files += write_results(ev, seed, seed_offset)
    return ev


def write_results(ev: JobEvaluation, seed: int, seed_offset: int) -> list[Path]:
    """metrics.csv (every row), summary.csv (per method), gram.csv (VGG-19 Gram ratios to the floor per material
    and map) and metrics.json (all of them + skipped) in ``ev.output``."""
    rows = [r.to_dict() for r in ev.rows]
    summary = ev.summary()
    scols = tuple(summary[0]) if summary else ("method",)
    gram_rows, gram_sum = ev.gram()
    doc = {"job": ev.job, "protocol": PROTOCOL, "metric_seed": seed, "seed_offset": seed_offset,
           "columns": list(COLUMNS), "rows": rows, "summary": summary, "gram_ratios": gram_rows,
           "gram_summary": gram_sum,
           "skipped": [{"material": n, "reason": r} for n, r in ev.skipped], "seconds": round(ev.seconds, 3)}
    return [_write_csv(ev.output / "metrics.csv", rows, COLUMNS),
            _write_csv(ev.output / "summary.csv", summary, scols),
            _write_csv(ev.output / "gram.csv", gram_rows, ("material", "map", "procedural", "rpn", "flat")),
            _write_json(ev.output / "metrics.json", doc)]
