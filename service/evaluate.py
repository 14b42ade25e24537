"""``proceduralize evaluate JOB``: the quality scorecard of a finished job (issue 9 part 1).

For every material of the job: read the working-size input maps (``load/maps.npz``) and the published graph
(``material.json``), regenerate the procedural maps from the graph alone at the reference size (the left half
of the input, see :mod:`workers.evaluate` for the protocol) with seed = the graph's seed + ``seed_offset``, and
score them and the baselines. Writes ``<job output>/evaluation/{metrics.csv, metrics.json, summary.csv}`` and
``<material>/evaluation.json``. Materials that failed or have no graph are listed with the reason.
"""
from __future__ import annotations

import csv
import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

from typing import TYPE_CHECKING

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


def _atomic_text(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(path)
    return path


def _write_csv(path: Path, rows: list[dict], columns: tuple[str, ...]) -> Path:
    """Rows as CSV (missing values empty)."""
    import io

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(columns), extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: "" if _clean(r.get(k)) is None else _clean(r.get(k)) for k in columns})
    return _atomic_text(path, buf.getvalue())


def _write_json(path: Path, doc: dict) -> Path:
    def walk(x):
        if isinstance(x, dict):
            return {k: walk(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [walk(v) for v in x]
        return _clean(x)

    return _atomic_text(path, json.dumps(walk(doc), indent=1))


def evaluate_material_dir(mdir: Path, name: str, seed: int = 0, seed_offset: int = SEED_OFFSET,
                          config: "EvalConfig | None" = None) -> tuple[list["MetricRow"], dict]:
    """Scorecard rows of one material folder and the per-material document (InputError if files are missing)."""
    from service.pipeline import read_npz
    from workers import graph
    from workers.errors import InputError
    from workers.evaluate import (EvalConfig, evaluate_material, gram_ratios, gram_summary, reference_size,
                                  summarise)

    graph_file, maps_file = mdir / "material.json", mdir / "load" / "maps.npz"
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
        raise InputError(f"{mdir}: {exc}") from None
    doc = {"material": name, "graph": str(graph_file), "inputs": str(maps_file),
           "input_size": [int(inputs["albedo"].shape[1]), int(inputs["albedo"].shape[0])],
           "reference_size": [w, h], "graph_seed": int(mat.seed), "evaluation_seed": eval_seed,
           "metric_seed": seed, "graph_seconds": round(t_graph, 3), "protocol": PROTOCOL,
           "rows": [r.to_dict() for r in rows], "summary": summarise(rows),
           "gram_ratios": gram_ratios(rows), "gram_summary": gram_summary(rows)}
    return rows, doc


def _skip_reason(m: dict, mdir: Path) -> str | None:
    """Why a material cannot be scored (None if it can be tried)."""
    if m.get("status") == "failed":
        return f"material failed: {m.get('error') or 'see proceduralize status'}"
    if not (mdir / "material.json").is_file():
        return f"no material.json in {mdir} (status {m.get('status')}: the output stage did not finish)"
    return None


def evaluate_job(store, job: str, out: Path | None = None, seed: int = 0, seed_offset: int = SEED_OFFSET,
                 config: "EvalConfig | None" = None, materials: list[str] | None = None) -> JobEvaluation:
    """Score every material of ``job`` in ``store``; write the CSV/JSON files; never stop at a bad material."""
    from workers.errors import InputError, ProceduralizeError

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
        mdir = root / m["output"]
        reason = _skip_reason(m, mdir)
        if reason is None:
            try:
                rows, doc = evaluate_material_dir(mdir, m["name"], seed, seed_offset, config)
            except (ProceduralizeError, OSError, ValueError, KeyError) as exc:
                reason = f"{type(exc).__name__}: {exc}"
            else:
                ev.rows += rows
                ev.files.append(_write_json(mdir / "evaluation.json", doc))
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


def _fmt(v: float) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.4g}"


def print_report(ev: JobEvaluation) -> None:
    """The scorecard table, the per-method summary with the ratio to the other-half floor, skipped materials."""
    from service.cli import _print_table

    _print_table([(r.material, r.map, r.method, *(_fmt(getattr(r, k)) for k in METRICS)) for r in ev.rows],
                 header=COLUMNS)
    summary = ev.summary()
    if summary:
        print()
        _print_table([(s["method"], s["rows"], *(_fmt(s[k]) for k in METRICS),
                       *(_fmt(s[f"{k}_ratio_to_half"]) for k in METRICS)) for s in summary],
                     header=("method (mean)", "rows", *METRICS, *(f"{k}/half" for k in METRICS)))
    gram_rows, gram_sum = ev.gram()
    if gram_rows:
        print("\nVGG-19 Gram distance to the input, in units of the input's own left-to-right distance (1 = floor)")
        _print_table([(d["material"], d["map"], *(_fmt(d.get(k, float("nan"))) for k in ("procedural", "rpn", "flat")),
                       "yes" if d.get("procedural", math.inf) < d.get("rpn", -math.inf) else "no")
                      for d in gram_rows], header=("material", "map", "procedural", "random-phase", "flat",
                                                   "beats random-phase"))
        for scope, d in gram_sum.items():
            if d["pairs"]:
                print(f"{scope}: {d['pairs']} pairs, median procedural/floor {_fmt(d['median_procedural'])} "
                      f"(random-phase {_fmt(d['median_rpn'])}, flat {_fmt(d['median_flat'])}), procedural "
                      f"beats random-phase on {100 * d['beats_rpn']:.0f} %")
    for name, reason in ev.skipped:
        print(f"not evaluated: {name}: {reason}")
    print(f"{len({r.material for r in ev.rows})} material(s) evaluated, {len(ev.skipped)} not, "
          f"in {ev.seconds:.1f} s -> {ev.output}")


def add_command(sub) -> None:
    """Register ``proceduralize evaluate``."""
    from service.cli import _common

    p = sub.add_parser("evaluate", parents=[_common()], help="quality scorecard of a job vs baselines",
                       description="For each material of a finished job, compare the input maps and renders "
                                   "with the procedural output regenerated from material.json alone (other "
                                   "seed), next to three baselines: random phase noise, the input's other half "
                                   "(the floor) and a flat mean material. Metrics: multi-scale patch sliced "
                                   "Wasserstein, radial power spectrum, histogram, pretrained VGG-19 Gram distance "
                                   "(also in units of the input's own left-to-right distance) (lower is better). "
                                   "Prints the "
                                   "table and writes <job output>/evaluation/metrics.{csv,json}. Exit 0 all "
                                   "materials scored, 1 some could not be, 2 bad job reference.")
    p.add_argument("job", metavar="JOB", help="job name, manifest, output folder or database file")
    p.add_argument("--out", type=Path, default=None, metavar="DIR",
                   help="folder for metrics.csv/json (default: <job output>/evaluation)")
    p.add_argument("--material", action="append", default=None, metavar="NAME",
                   help="score only this material (repeatable)")
    p.add_argument("--seed", type=int, default=0, help="seed of the metrics' sampling and the RPN baseline")
    p.add_argument("--seed-offset", type=int, default=SEED_OFFSET,
                   help=f"procedural seed = graph seed + this (default {SEED_OFFSET})")
    p.add_argument("--lights", type=int, default=16, choices=range(1, 17), metavar="1..16",
                   help="how many of the paper's 16 lights to render (default 16)")
    p.add_argument("--no-render", action="store_true", help="skip the render rows (maps only)")
    p.set_defaults(handler=_cmd_evaluate)


def _cmd_evaluate(args) -> int:
    from service.cli import _open_job
    from workers.evaluate import EvalConfig

    store, job = _open_job(args.job)
    try:
        ev = evaluate_job(store, job, out=args.out, seed=args.seed, seed_offset=args.seed_offset,
                          config=EvalConfig(render=not args.no_render, lights=args.lights),
                          materials=args.material)
    finally:
        store.close()
    print_report(ev)
    return 1 if ev.skipped or not ev.rows else 0
