"""``proceduralize run MANIFEST``: run a job on Ray (local unless --address)."""
from __future__ import annotations

import sys
from pathlib import Path

from service.commands.common import common_parser, print_table
from service.commands.jobs import load_manifest_or_report, remember_job
from workers.errors import InputError


def register(sub) -> None:
    p = sub.add_parser("run", parents=[common_parser()], help="run a job manifest on Ray (local unless --address)",
                       description="Validate MANIFEST (TOML/JSON/YAML), then run every material through the "
                                   "pipeline stages on Ray: a local Ray instance by default, or the cluster at "
                                   "--address. Progress is printed per material and stage; the record of the job "
                                   "is the SQLite file in its output folder. Rerunning resumes: finished stages "
                                   "whose files are intact are skipped. Exit 0 all done, 1 some materials "
                                   "failed, 2 bad manifest.")
    p.add_argument("manifest", type=Path, metavar="MANIFEST")
    p.add_argument("--out", type=Path, default=None, metavar="DIR", help="override the manifest's job.output folder")
    p.add_argument("--address", default=None, help="Ray address to join (e.g. auto, ray://host:10001); "
                                                   "default: start a local Ray")
    p.add_argument("--num-cpus", type=int, default=None, help="CPUs of the local Ray (default: all)")
    p.add_argument("--pptbf-db", default=None, metavar="DIR", help="PPTBF database folder (default: bundled)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(handler=handle)


def _check_before_ray(man, pptbf_db: str | None) -> None:
    """What would fail every material is checked before Ray starts: the job database (opened, and migrated
    when older) and the PPTBF database folder."""
    from service.store import Store

    for label, folder in (("--pptbf-db", pptbf_db), ("job.pptbf_database", man.pptbf_database)):
        if folder is not None and not (Path(folder) / "meta.json").is_file():
            raise InputError(f"{label} {folder}: not a PPTBF database folder (no meta.json); build one with "
                             "`proceduralize db rebuild --out DIR` or drop the option to use the bundled one")
    # an empty file is a database another job sharing it has just created: SQLite initialises it
    Store(man.database).close()


def handle(args) -> int:
    from service.scheduler import run_job

    man = load_manifest_or_report(args.manifest, output=args.out)
    if man is None:
        return 2
    _check_before_ray(man, args.pptbf_db)
    remember_job(man.name, man.database)
    print(f"job {man.name}: {len(man.materials)} material(s) -> {man.output}", file=sys.stderr)
    report = run_job(man, address=args.address, num_cpus=args.num_cpus, progress=not args.quiet,
                     mask_database=args.pptbf_db)
    print_table([(n, s, report.errors.get(n, "")) for n, s in report.materials.items()],
                header=("material", "status", "error"))
    done = sum(s == "done" for s in report.materials.values())
    print(f"job {report.job}: {done}/{len(report.materials)} materials done in {report.seconds:.1f} s "
          f"({report.executed} stage items run, {report.reused} reused); record: {report.database}")
    return report.exit_code
