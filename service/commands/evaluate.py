"""``proceduralize evaluate JOB``: the quality scorecard of a finished job (the scoring: :mod:`service.evaluate`)."""
from __future__ import annotations

import math
from pathlib import Path

from service.commands.common import common_parser, print_table
from service.commands.jobs import open_job
from service.evaluate import COLUMNS, METRICS, SEED_OFFSET, JobEvaluation, evaluate_job


def register(sub) -> None:
    p = sub.add_parser("evaluate", parents=[common_parser()], help="quality scorecard of a job vs baselines",
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
    p.set_defaults(handler=handle)


def _fmt(v: float) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.4g}"


def print_report(ev: JobEvaluation) -> None:
    """The scorecard table, the per-method summary with the ratio to the other-half floor, skipped materials."""
    print_table([(r.material, r.map, r.method, *(_fmt(getattr(r, k)) for k in METRICS)) for r in ev.rows],
                header=COLUMNS)
    summary = ev.summary()
    if summary:
        print()
        print_table([(s["method"], s["rows"], *(_fmt(s[k]) for k in METRICS),
                      *(_fmt(s[f"{k}_ratio_to_half"]) for k in METRICS)) for s in summary],
                    header=("method (mean)", "rows", *METRICS, *(f"{k}/half" for k in METRICS)))
    gram_rows, gram_sum = ev.gram()
    if gram_rows:
        print("\nVGG-19 Gram distance to the input, in units of the input's own left-to-right distance (1 = floor)")
        print_table([(d["material"], d["map"], *(_fmt(d.get(k, float("nan"))) for k in ("procedural", "rpn", "flat")),
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


def handle(args) -> int:
    from workers.evaluate import EvalConfig

    store, job = open_job(args.job)
    try:
        ev = evaluate_job(store, job, out=args.out, seed=args.seed, seed_offset=args.seed_offset,
                          config=EvalConfig(render=not args.no_render, lights=args.lights),
                          materials=args.material)
    finally:
        store.close()
    print_report(ev)
    return 1 if ev.skipped or not ev.rows else 0
