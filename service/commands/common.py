"""Helpers shared by the command modules: the common parent parser, argument types, the memory budget option,
output folders, the render memory check, text tables and map/preview files.

Light at import time (``proceduralize --help`` imports it): numpy and the small ``workers`` modules only.
"""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

from workers import budget
from workers.errors import InputError

logger = logging.getLogger("proceduralize")

# workers.graph.MIN_SCALE, MAX_SCALE (not imported: workers.graph pulls scipy, --help stays light)
MIN_SCALE, MAX_SCALE = 1.0 / 64.0, 64.0


def common_parser() -> argparse.ArgumentParser:
    """Options every subcommand accepts (``-v`` may come before or after the subcommand)."""
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("-v", "--verbose", action="count", default=argparse.SUPPRESS,
                   help="more logging (-v info, -vv debug)")
    return p


def parse_size(text: str) -> tuple[int, int]:
    """Parse ``WxH`` (or a single ``N`` for a square) into (width, height) (argparse type)."""
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


def positive_float(text: str) -> float:
    """A float > 0 (argparse type)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not v > 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be > 0")
    return v


def parse_scale(text: str) -> float:
    """A pattern scale within graph.MIN_SCALE .. graph.MAX_SCALE (argparse type)."""
    v = positive_float(text)
    if not MIN_SCALE <= v <= MAX_SCALE:
        raise argparse.ArgumentTypeError(f"{text!r} must be from {MIN_SCALE:g} to {MAX_SCALE:g}")
    return v


def parse_seed(text: str) -> int:
    """A realisation seed 0 .. 2**63-1 (argparse type)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if not 0 <= v < 2**63:
        raise argparse.ArgumentTypeError(f"{text!r} must be from 0 to 2**63-1")
    return v


def add_budget_option(p: argparse.ArgumentParser) -> None:
    """``--memory-budget SIZE`` (read by :func:`check_render_memory`)."""
    p.add_argument("--memory-budget", default=None, metavar="SIZE",
                   help="refuse a request estimated to need more memory (e.g. 4G; default "
                        "$PROCEDURALIZE_MEMORY_BUDGET, else half of this machine's memory)")


def output_folder(path: Path, flag: str = "--out") -> Path:
    """Create the output folder ``path``; InputError naming ``flag`` when it is a file or cannot be made."""
    if path.exists() and not path.is_dir():
        raise InputError(f"{flag} {path}: exists and is not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{flag} {path}: cannot create the folder ({exc.strerror or exc})") from None
    return path


def check_render_memory(mat, w: int, h: int, budget_text: str | None) -> None:
    """Refuse (MemoryBudgetError, exit 2) a render estimated to exceed the memory budget, before allocating."""
    budget.check(f"rendering {w}x{h} ({len(mat.nodes)} graph nodes)", budget.render_bytes(len(mat.nodes), w, h),
                 budget.budget(budget_text))


def print_table(rows: list[tuple], header: tuple) -> None:
    """Print a left-aligned text table."""
    cells = [tuple(str(c) for c in header)] + [tuple(str(c) for c in r) for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    for j, r in enumerate(cells):
        print("  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip())
        if j == 0:
            print("  ".join("-" * w for w in widths))


def write_preview(maps: dict, path: Path) -> Path:
    """Write ``workers.render.preview_image(maps)`` (a GGX render of the maps) to ``path``."""
    from workers.maps import write_image
    from workers.render import preview_image

    return write_image(path, preview_image(maps), bits=8)


def write_maps(maps: dict, out: Path, bits: int = 8) -> dict[str, Path]:
    """Write evaluated maps as PNG (:func:`workers.maps.write_maps`)."""
    from workers.maps import write_maps as write

    return write(maps, out, bits)
