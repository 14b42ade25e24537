"""The pipeline's stages, each declared once: what it needs, how its work items are listed, where it runs, which
options it takes and the function that runs one item.

The scheduler plans, places and records stages from :data:`STAGES`; the manifest validates stage lists and
option tables against it; the report and the store order stages by it. A new stage is one :class:`Stage`
below, its body (a ``stage_*`` function of :mod:`service.pipeline`) and its test.

:func:`run_stage` runs one item of a stage where the scheduler placed it (a Ray task or actor, or in-process):
the body writes its files under the material's :class:`~service.folder.MaterialFolder` and returns
``{"files": [...], "info": {...}}``; the result record adds the artefacts (path relative to the job output,
kind, checksum, bytes), the worker and the timing. No Ray and no SQLite here.
"""
from __future__ import annotations

import copy
import enum
import importlib
import os
import socket
import time
from dataclasses import KW_ONLY, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from service import pipeline
from service.folder import MaterialFolder

if TYPE_CHECKING:
    from service.manifest import MaterialSpec


class Placement(enum.Enum):
    """Where the items of a stage run on Ray (the values name the actor kinds of :mod:`service.scheduler`)."""

    TASK = "task"                  # a plain task: 1 CPU reserved, 1 thread
    MASK_ACTOR = "masks"           # a CPU actor holding the PPTBF index (workers.actors.MaskFitter)
    RECOMPOSE_ACTOR = "recompose"  # a GPU or CPU recomposition actor (workers.actors.Recomposer; service.placement)


#: the info a finished single-item stage recorded, by stage name ({} when it has not run)
InfoLookup = Callable[[str], dict]
#: the maps the noise stage models: one item per decomposition leaf and each of these maps the material has
NOISE_MAPS = ("albedo", "height", "roughness", "metallic")


def one_item(spec: MaterialSpec, info: InfoLookup) -> list[str]:
    """A stage with one work item per material (its id is the empty string)."""
    return [""]


def noise_items(spec: MaterialSpec, info: InfoLookup) -> list[str]:
    """``leaf/map`` for every leaf of the decomposition tree and every map of :data:`NOISE_MAPS` the material has."""
    tree = info("decompose")
    maps = info("load").get("maps", [])
    return [f"{leaf}/{mp}" for leaf in tree.get("leaves", []) for mp in NOISE_MAPS if mp in maps]


def mask_items(spec: MaterialSpec, info: InfoLookup) -> list[str]:
    """The tree nodes whose mask is fitted (every child of a matting split but the last)."""
    tree = info("decompose")
    return list(tree.get("fit_masks", tree.get("nodes", [])[1:]))


def render_items(spec: MaterialSpec, info: InfoLookup) -> list[str]:
    """One render tag per output size x seed x scale (:func:`service.pipeline.output_renders`)."""
    return pipeline.output_renders(spec)


@dataclass(frozen=True)
class Stage:
    """One stage of the pipeline.

    ``needs``: stages whose results it reads (they run first; a result recomputed in a run makes it stale).
    ``items(spec, info)``: its work items for a material, given the info its predecessors recorded.
    ``placement``: a plain Ray task, a mask-fitting actor or a recomposition actor.
    ``config``: the dataclass its options table must fit (the manifest key named like the stage, in a material
    or in [defaults]); None for a stage without options. Given as (module, class name) when its module is heavy
    to import (scipy, torch): it is imported when options are checked, not when the registry is.
    ``run(call, holder)``: the body; ``holder`` is the actor's MaskFitter / Recomposer (None in a task).
    """

    name: str
    _: KW_ONLY
    needs: tuple[str, ...] = ()
    items: Callable[[MaterialSpec, InfoLookup], list[str]] = one_item
    placement: Placement = Placement.TASK
    config: tuple[str, str] | type | None = None
    run: Callable[[StageCall, Any], dict]

    def config_class(self) -> type | None:
        """The options dataclass (imported on first use when declared as (module, class name))."""
        if self.config is None or isinstance(self.config, type):
            return self.config
        module, name = self.config
        return getattr(importlib.import_module(module), name)

    def config_fields(self) -> set[str]:
        """Option names the stage accepts (none without a config)."""
        cls = self.config_class()
        return set(cls.__dataclass_fields__) if cls is not None else set()


#: every stage, in pipeline order
STAGES: tuple[Stage, ...] = (
    Stage("load", run=pipeline.stage_load),
    Stage("decompose", needs=("load",), run=pipeline.stage_decompose),
    Stage("noise", needs=("decompose",), items=noise_items, config=("workers.noise", "NoiseConfig"),
          run=pipeline.stage_noise),
    Stage("masks", needs=("decompose",), items=mask_items, placement=Placement.MASK_ACTOR,
          config=("workers.masks", "MaskFitConfig"), run=pipeline.stage_masks),
    Stage("recompose", needs=("noise", "masks"), placement=Placement.RECOMPOSE_ACTOR,
          config=("workers.recompose", "RecomposeConfig"), run=pipeline.stage_recompose),
    Stage("output", needs=("recompose",), items=render_items, run=pipeline.stage_output),
)
#: stage names in pipeline order
STAGE_NAMES: tuple[str, ...] = tuple(s.name for s in STAGES)
_BY_NAME = {s.name: s for s in STAGES}


def _check_order(stages: tuple[Stage, ...]) -> None:
    """Names are unique and a stage needs only stages declared before it (the order is the pipeline's)."""
    seen: set[str] = set()
    for s in stages:
        later = [d for d in s.needs if d not in seen]
        if s.name in seen or later:
            raise ValueError(f"stage {s.name!r}: declared twice or needs {later}, which are not declared before it")
        seen.add(s.name)


_check_order(STAGES)


def stage(name: str) -> Stage:
    """The stage called ``name`` (KeyError naming the known stages)."""
    try:
        return _BY_NAME[name]
    except KeyError:
        raise KeyError(f"no stage {name!r}; stages are {list(STAGE_NAMES)}") from None


# ----------------------------------------------------------------------------- running one item


@dataclass
class StageCall:
    """Everything a worker needs for one stage item (picklable: plain fields and the material's spec)."""

    job: str
    root: str
    spec: MaterialSpec
    stage: str
    item: str = ""
    debug: dict = field(default_factory=dict)
    timeout: float | None = None
    memory_budget: int | None = None   # bytes; None: the worker's default (half its machine's memory)

    @property
    def folder(self) -> MaterialFolder:
        """The material's folder inside the job output."""
        return MaterialFolder(Path(self.root) / self.spec.output)

    @property
    def options(self) -> dict:
        """A copy of the material's options table of this call's stage ({} when it has none)."""
        return copy.deepcopy(self.spec.stage_options(self.stage))


def run_stage(call: StageCall, holder: Any = None) -> dict:
    """Run one stage item and return its result record (artefacts with checksums, info, timing, worker)."""
    started = time.time()
    t0, c0 = time.perf_counter(), time.process_time()
    what = f"stage {call.stage}" + (f"[{call.item}]" if call.item else "")
    with pipeline.time_limit(call.timeout, what):
        pipeline.debug_hooks(call)
        res = stage(call.stage).run(call, holder)
    arts = [artefact(call.root, Path(p), kind=f"{call.stage}:{Path(p).suffix.lstrip('.')}") for p in res["files"]]
    info = dict(res.get("info", {}))
    # CPU seconds of this process (all its threads) and its thread count: a stage busier than its reservation
    # (cpu_s > duration) or starved by its neighbours (cpu_s well under duration) shows here
    info.update(cpu_s=round(time.process_time() - c0, 3), threads=_thread_count())
    return {"artefacts": arts, "info": info, "worker": f"{socket.gethostname()}:{os.getpid()}",
            "started": started, "finished": time.time(), "duration": time.perf_counter() - t0}


def artefact(root: str | Path, path: Path, kind: str) -> dict:
    """Artefact record of a written file: path relative to the job output, checksum, size."""
    from service.store import file_checksum  # sqlite_utils: not imported by `proceduralize --help`

    return {"path": str(Path(path).resolve().relative_to(Path(root).resolve())), "kind": kind,
            "checksum": file_checksum(path), "bytes": Path(path).stat().st_size}


def _thread_count() -> int | None:
    """OS threads of this process (Linux /proc), None where that is not readable."""
    try:
        return len(os.listdir("/proc/self/task"))
    except OSError:
        return None
