"""``proceduralize demo``: the normal -> height -> normal round trip on a real material."""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from service.commands.common import common_parser, print_table, write_preview
from workers.errors import InputError
from workers.height import angular_error, height_to_normal

REPO = Path(__file__).resolve().parents[2]
DEMO_MATERIAL = "castle_brick_broken_06"


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


def register(sub) -> None:
    p = sub.add_parser("demo", parents=[common_parser()], help="round-trip demo on a real material",
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
    p.set_defaults(handler=handle)


def handle(args) -> int:
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
    p_in = write_preview(maps_in, out / "preview_input.png")
    p_back = write_preview(maps_back, out / "preview.png")
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
    print_table([
        ("height scale (px units)", f"{mat.height_scale:.3f}"),
        ("normal tilt (dx, drow)", f"{mat.normal_tilt[0]:+.4f}, {mat.normal_tilt[1]:+.4f}"),
        ("angular error mean (deg)", f"{e['mean']:.2f}"),
        ("angular error median (deg)", f"{e['median']:.2f}"),
        ("angular error p95 (deg)", f"{e['p95']:.2f}"),
        ("angular error max (deg)", f"{e['max']:.2f}"),
        ("load + integrate (s)", f"{t_load:.2f}"),
        ("height -> normal (s)", f"{t_back:.3f}"),
    ], header=("normal -> height -> normal", "value"))
    print(f"outputs in {out}: {', '.join(report['outputs'])}")
    return 0


