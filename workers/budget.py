"""Memory budget: estimate the bytes a render, a load or the fitting stages need and refuse, before
allocating, what would not fit.

The budget is, in order: an explicit value (``--memory-budget``, ``job.memory_budget``), the environment
variable PROCEDURALIZE_MEMORY_BUDGET, else half of this machine's memory (its cgroup limit when lower).
Sizes are written as bytes or with a unit: ``512M``, ``8G``, ``1.5GiB``.

The estimates are deliberately simple and on the safe side: they count the float32 arrays a stage holds at
once per pixel (measured on real materials, see bench/speed.py), not Python's own overhead.
"""
from __future__ import annotations

import os
import re
from pathlib import Path

from .errors import InputError

ENV = "PROCEDURALIZE_MEMORY_BUDGET"
#: evaluating a graph keeps every node's output (float32, up to 3 channels) plus temporaries; measured:
#: 11 nodes at 1024x1024 add ~190 MB of RSS
RENDER_BYTES_PER_PX_NODE = 24
#: maps written, preview render and normal integration on top of the node outputs
RENDER_BYTES_PER_PX = 96
#: decomposition, noise, mask and recomposition stages per working-size pixel (features, KNN graphs,
#: spectra, torch tensors with gradients)
FIT_BYTES_PER_PX = 1024
#: reading a map: the decoded float32 image, its resized copy and the float64 temporaries of the checks
LOAD_BYTES_PER_PX_CHANNEL = 12

_UNITS = {"": 1, "b": 1, "k": 2**10, "kb": 10**3, "kib": 2**10, "m": 2**20, "mb": 10**6, "mib": 2**20,
          "g": 2**30, "gb": 10**9, "gib": 2**30, "t": 2**40, "tb": 10**12, "tib": 2**40}


class MemoryBudgetError(InputError):
    """A request would need more memory than the budget allows (refused before allocating)."""


def parse_bytes(value: str | int | float, where: str = "memory budget") -> int:
    """``8G``, ``512MiB``, ``1e9`` or a number of bytes -> bytes (InputError naming ``where`` otherwise)."""
    if isinstance(value, bool):
        raise InputError(f"{where}: must be a size such as 8G or 512M, got {value!r}")
    if isinstance(value, (int, float)):
        n = float(value)
    else:
        m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:e[0-9]+)?)\s*([a-zA-Z]*)\s*", str(value))
        if not m or m.group(2).lower() not in _UNITS:
            raise InputError(f"{where}: must be a size such as 8G, 512M or a number of bytes, got {value!r}")
        n = float(m.group(1)) * _UNITS[m.group(2).lower()]
    if not 2**24 <= n <= 2**50:
        raise InputError(f"{where}: {value!r} is outside 16 MiB .. 1 PiB")
    return int(n)


def machine_memory() -> int:
    """Physical memory of this machine, or its cgroup (container) limit when that is lower."""
    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    for f in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = Path(f).read_text().strip()
        except OSError:
            continue
        if text.isdigit() and 0 < int(text) < total:
            total = int(text)
    return int(total)


def budget(explicit: str | int | None = None) -> int:
    """The budget in bytes: ``explicit``, else $PROCEDURALIZE_MEMORY_BUDGET, else half the machine's memory."""
    if explicit is not None:
        return parse_bytes(explicit)
    env = os.environ.get(ENV)
    if env:
        return parse_bytes(env, ENV)
    return machine_memory() // 2


def gib(n: float) -> str:
    return f"{n / 2**30:.2f} GiB"


def check(what: str, need: int, limit: int | None = None) -> None:
    """Raise MemoryBudgetError when ``need`` bytes exceed the budget (``limit`` or :func:`budget`)."""
    limit = budget() if limit is None else int(limit)
    if need > limit:
        raise MemoryBudgetError(f"{what} needs about {gib(need)}, more than the memory budget of {gib(limit)}; "
                                f"ask for less, or raise the budget (--memory-budget, job.memory_budget or "
                                f"${ENV})")


def render_bytes(nodes: int, width: int, height: int) -> int:
    """Bytes to evaluate a graph of ``nodes`` nodes at width x height and write its maps and preview."""
    return int(width) * int(height) * (RENDER_BYTES_PER_PX_NODE * max(1, int(nodes)) + RENDER_BYTES_PER_PX)


def fit_bytes(width: int, height: int) -> int:
    """Bytes the fitting stages need at a working size of width x height."""
    return int(width) * int(height) * FIT_BYTES_PER_PX


def load_bytes(sizes: list[tuple[int, int, int]], working: tuple[int, int]) -> int:
    """Bytes to read maps of (width, height, channels) and resample them to ``working``."""
    tw, th = working
    return sum(w * h * max(c, 3) * LOAD_BYTES_PER_PX_CHANNEL + tw * th * max(c, 3) * LOAD_BYTES_PER_PX_CHANNEL
               for w, h, c in sizes)
