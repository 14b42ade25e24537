"""``proceduralize report JOB``: a static HTML report of a job (the pages: :mod:`service.report`)."""
from __future__ import annotations

import time
from pathlib import Path

from service.commands.common import common_parser
from service.commands.jobs import open_job
from service.report import ReportOptions, build_report
from workers.errors import InputError


def register(sub) -> None:
    p = sub.add_parser("report", parents=[common_parser()], help="write a static HTML report of a job",
                       description="Write index.html (job summary) and one page per material: input vs "
                                   "procedural maps and renders, the decomposition tree with masks, PPTBF fits, "
                                   "recomposition loss, metrics (from 'proceduralize evaluate'), timings, errors "
                                   "and editing examples (super-resolution, extension, pattern scale, new seed, "
                                   "a parameter edit). Open index.html in a browser; no server needed.")
    p.add_argument("job", metavar="JOB", help="job name, manifest, output folder or database file")
    p.add_argument("--out", type=Path, default=None, metavar="DIR", help="report folder (default <job output>/report)")
    p.add_argument("--edit-size", type=int, default=ReportOptions.edit_size, metavar="PX",
                   help=f"largest side of the editing previews (default {ReportOptions.edit_size}; doubled "
                        f"for super-resolution and extension)")
    p.add_argument("--no-editing", action="store_true", help="skip the editing section (faster)")
    p.set_defaults(handler=handle)


def handle(args) -> int:
    if args.edit_size < 8:
        raise InputError(f"--edit-size {args.edit_size}: must be >= 8")
    store, name = open_job(args.job)
    t0 = time.perf_counter()
    with store:
        index = build_report(store, name, args.out, ReportOptions(edit_size=args.edit_size,
                                                                  editing=not args.no_editing), job_ref=args.job)
    print(f"report of job {name} written in {time.perf_counter() - t0:.1f} s: {index}")
    return 0
