"""Run every material of a job on Ray: per-stage tasks, actor pools, retries, resume.

The driver (this module) is the only writer to the job database. It submits the first stage of every
material at once and, as results come back, records them and submits what became ready:

    load -> decompose -> { noise (one task per leaf x map), masks (one call per tree node, on a pool of
    CPU actors holding the PPTBF index) } -> recompose (GPU actor when the cluster has GPUs, else CPU)
    -> output

Worker crashes (WorkerCrashedError, RayActorError, ...) are retried up to ``max_attempts``; an
exception inside a stage fails only its material. A stage item whose row is done and whose artefacts are
on disk with the recorded checksums is skipped on a rerun (resume).

Actors request no CPU (``num_cpus=0``): a 2-CPU cluster holding two idle actors that each reserved a CPU
would starve the tasks they wait for. GPUs are requested only when ``ray.cluster_resources()`` has them, and
the custom resource ``mask_fitter`` only when some node advertises it (deploy/ puts it on the CPU group, so
mask actors stay off a zero-CPU head node).
"""
from __future__ import annotations

import json
import logging
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from service import claims, pipeline
from service.manifest import JobManifest, MaterialSpec
from service.pipeline import DEPENDS, NOISE_MAPS, STAGES, StageCall
from service.store import Store
from workers.errors import InputError, ManifestError

logger = logging.getLogger(__name__)

#: environment variable with fault-injection hooks for tests (JSON, see parse_faults)
FAULTS_ENV = "PROCEDURALIZE_FAULTS"
#: the address every listener of a local Ray binds to: nothing of a local run is reachable from the network
LOCAL_IP = "127.0.0.1"
#: custom Ray resource that pins mask-fitting actors to the CPU worker group when a cluster advertises it
MASK_RESOURCE = "mask_fitter"


@dataclass
class JobReport:
    """Outcome of one driver run."""

    job: str
    database: Path
    output: Path
    materials: dict[str, str]
    errors: dict[str, str]
    executed: int = 0
    reused: int = 0
    seconds: float = 0.0

    @property
    def exit_code(self) -> int:
        """0 when every material is done, 1 when some failed."""
        return 0 if all(s == "done" for s in self.materials.values()) else 1


@dataclass
class _Material:
    """Driver-side state of one material."""

    spec: MaterialSpec
    plan: list[str]
    done: set = field(default_factory=set)
    submitted: set = field(default_factory=set)
    waiting: dict = field(default_factory=dict)  # stage -> set of items not finished yet
    info: dict = field(default_factory=dict)  # stage -> info dict
    fresh: set = field(default_factory=set)  # stages executed in this run: their dependants cannot be reused
    error: str | None = None


@dataclass
class _Flight:
    material: str
    stage: str
    item: str
    attempt: int
    actor: Any = None


def _retryable_errors() -> tuple[type, ...]:
    """Ray errors that mean "the worker/actor/node went away", not "the stage raised"."""
    import ray.exceptions as rex

    names = ("WorkerCrashedError", "RayActorError", "ActorDiedError", "ActorUnavailableError", "ObjectLostError",
             "OwnerDiedError", "NodeDiedError", "LocalRayletDiedError", "TaskUnschedulableError")
    # OutOfMemoryError is not among them: the same item on the same inputs would run out of memory again
    return tuple(getattr(rex, n) for n in names if hasattr(rex, n))


def parse_faults(doc: dict, where: str = "faults") -> dict:
    """Validated fault-injection hooks (tests only): {crash_once: {stage, marker, material}, sleep: {stage,
    seconds, material}}."""
    from service.manifest import _Problems, parse_faults as parse

    probs = _Problems()
    out = parse(doc, Path.cwd(), probs)
    if probs:
        raise ManifestError(list(probs), where)
    return out


def faults_from_env() -> dict:
    """Fault hooks from the environment variable PROCEDURALIZE_FAULTS (JSON); a manifest cannot carry them."""
    raw = os.environ.get(FAULTS_ENV)
    if not raw:
        return {}
    try:
        doc = json.loads(raw)
    except ValueError as exc:
        raise ManifestError(f"not valid JSON ({exc})", FAULTS_ENV) from None
    return parse_faults(doc, FAULTS_ENV)


def ensure_ray(address: str | None = None, num_cpus: int | None = None) -> bool:
    """Connect to ``address`` or start a new local Ray bound to loopback; True when this call started/connected
    it."""
    import ray

    if ray.is_initialized():
        return False
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    kw: dict[str, Any] = {"include_dashboard": False, "logging_level": "WARNING"}
    if address:
        kw["address"] = address
    else:  # a fresh local instance (never someone's `ray start` found on this host), reachable from here only
        kw.update(address="local", _node_ip_address=LOCAL_IP, dashboard_host=LOCAL_IP)
        if num_cpus:
            kw["num_cpus"] = int(num_cpus)
    ray.init(**kw)
    return True


def _on_node(result: dict) -> dict:
    """Tag a stage result's worker with the Ray node it ran on (``host:pid@node``)."""
    import ray

    result["worker"] = f"{result.get('worker')}@{ray.get_runtime_context().get_node_id()[:8]}"
    return result


def run_stage_task(call: dict) -> dict:
    """Body of the per-stage Ray task."""
    return _on_node(pipeline.run_stage(call))


class _StageActor:
    """Ray actor body: holds a MaskFitter (PPTBF index loaded once) or a Recomposer and runs stage calls."""

    def __init__(self, kind: str, device: str = "cpu", database: str | None = None, threads: int = 2):
        from workers.actors import MaskFitter, Recomposer

        if kind == "recompose" and device == "cpu":  # a 0-CPU actor would otherwise use every core
            import torch

            torch.set_num_threads(threads)
        self.kind = kind
        self.resources = MaskFitter(database) if kind == "masks" else Recomposer(device)

    def run(self, call: dict) -> dict:
        return _on_node(pipeline.run_stage(call, self.resources))

    def ready(self) -> str:
        return f"{self.kind} actor pid {os.getpid()}"


class Scheduler:
    """Drives one job to completion on the connected Ray cluster."""

    def __init__(self, manifest: JobManifest, store: Store | None = None, progress: bool = True,
                 mask_database: str | None = None, faults: dict | None = None):
        import ray

        self.manifest = manifest
        self.faults = parse_faults(faults) if faults is not None else faults_from_env()
        self.store = store or Store(manifest.database)
        self._own_store = store is None
        self.progress = progress
        self.mask_database = mask_database or (str(manifest.pptbf_database) if manifest.pptbf_database else None)
        res = ray.cluster_resources()
        self.cpus = float(res.get("CPU", 1.0))
        self.gpus = int(res.get("GPU", 0))
        self.mask_slots = int(res.get(MASK_RESOURCE, 0))
        self._task = ray.remote(num_cpus=1, max_retries=0)(run_stage_task)
        self._pools: dict[str, list] = {}
        self._rr: dict[str, int] = {}
        self.inflight: dict[Any, _Flight] = {}
        self.mats: dict[str, _Material] = {}
        self.executed = 0
        self.reused = 0
        self._retryable = _retryable_errors()
        self._tries: dict[tuple[str, str, str], int] = {}
        self._bar = None

    # -- planning

    def _plan(self, spec: MaterialSpec) -> tuple[list[str], str | None]:
        """Stages to run for a material and an error if the plan cannot work."""
        mdict = spec.to_json()
        explicit = spec.stages or self.manifest.stages
        if explicit:
            plan = list(explicit)
        else:
            plan = []
            for s in STAGES:
                missing = pipeline.missing_modules(s, mdict)
                if missing:
                    self.store.mark_item(self.manifest.name, spec.name, s, "", "unavailable",
                                         f"module(s) {', '.join(missing)} not available; stage not run")
                    logger.warning("%s: stage %s not run: module(s) %s not available", spec.name, s,
                                   ", ".join(missing))
                elif all(d in plan for d in DEPENDS[s]):
                    plan.append(s)
        for s in plan:
            for d in DEPENDS[s]:
                if d not in plan and not self._stage_done_before(spec.name, d):
                    return plan, (f"stage {s!r} needs stage {d!r}, which is neither in this job's stages nor "
                                  "finished by an earlier run")
        return plan, None

    def _stage_done_before(self, material: str, stage: str) -> bool:
        rows = self.store.items(self.manifest.name, material, stage)
        return bool(rows) and all(self.store.is_done(self.manifest.name, material, stage, r["item"],
                                                     self.manifest.output) for r in rows)

    def _items(self, m: _Material, stage: str) -> list[str]:
        """Work items of a stage (noise: leaf/map; masks: fitted tree nodes; output: renders; else one)."""
        if stage == "output":
            return pipeline.output_renders(m.spec.to_json())
        if stage not in ("noise", "masks"):
            return [""]
        tree = m.info.get("decompose") or self.store.done_info(self.manifest.name, m.spec.name, "decompose")
        if stage == "noise":
            maps = (m.info.get("load") or self.store.done_info(self.manifest.name, m.spec.name, "load")).get("maps", [])
            return [f"{leaf}/{mp}" for leaf in tree.get("leaves", []) for mp in NOISE_MAPS if mp in maps]
        return list(tree.get("fit_masks", tree.get("nodes", [])[1:]))

    # -- submission

    def _call(self, m: _Material, stage: str, item: str) -> dict:
        return StageCall(job=self.manifest.name, root=str(self.manifest.output), material=m.spec.to_json(),
                         stage=stage, item=item, debug=self.faults, timeout=self.manifest.stage_timeout,
                         memory_budget=self.manifest.memory_budget).to_dict()

    def _new_actor(self, kind: str) -> Any:
        """One stage actor: 'masks' (CPU, PPTBF index) or 'recompose' (a GPU when the cluster has them)."""
        import ray

        if kind == "masks":
            opts: dict[str, Any] = {"num_cpus": 0}
            if self.mask_slots:  # deploy configs advertise this resource on the CPU worker group
                opts["resources"] = {MASK_RESOURCE: 1}
            args = ("masks", "cpu", self.mask_database)
        else:
            opts = {"num_cpus": 0, "num_gpus": 1} if self.gpus else {"num_cpus": 0}
            args = ("recompose", "cuda" if self.gpus else "cpu", None)
        return ray.remote(max_restarts=0, max_task_retries=0, **opts)(_StageActor).remote(*args)

    def _pool(self, kind: str) -> list:
        """The actor pool of a kind, created on first use (masks: CPUs/2 or job.mask_actors; recompose: 1 per GPU)."""
        if kind not in self._pools:
            if kind == "masks":
                n = self.manifest.mask_actors or max(1, int(self.cpus) // 2)
                n = min(n, self.mask_slots) if self.mask_slots else n
            else:  # one per GPU; on CPU clusters one per 2 CPUs (each actor's torch uses 2 threads)
                n = self.gpus if self.gpus else max(1, int(self.cpus) // 2)
            self._pools[kind] = [self._new_actor(kind) for _ in range(n)]
            self._rr[kind] = 0
            logger.info("started %d %s actor(s) (%d GPU in the cluster)", n, kind, self.gpus)
        return self._pools[kind]

    def _replace_actor(self, kind: str, dead: Any) -> None:
        """Swap a dead actor for a fresh one (once per dead handle; later failures of it find it gone)."""
        import ray

        pool = self._pools.get(kind, [])
        for i, a in enumerate(pool):
            if a is dead:
                try:
                    ray.kill(a, no_restart=True)
                except Exception:  # noqa: BLE001 - already gone
                    pass
                pool[i] = self._new_actor(kind)
                logger.warning("replaced a dead %s actor", kind)
                return

    def _submit(self, m: _Material, stage: str, item: str) -> None:
        self.store.start_item(self.manifest.name, m.spec.name, stage, item)
        key = (m.spec.name, stage, item)
        attempt = self._tries[key] = self._tries.get(key, 0) + 1  # attempts in this run decide retries
        call = self._call(m, stage, item)
        actor = None
        if stage in ("masks", "recompose"):
            pool = self._pool(stage)
            actor = pool[self._rr[stage] % len(pool)]
            self._rr[stage] += 1
            ref = actor.run.remote(call)
        else:
            ref = self._task.options(name=f"{m.spec.name}:{stage}:{item}"[:100]).remote(call)
        self.inflight[ref] = _Flight(m.spec.name, stage, item, attempt, actor)

    def _advance(self, m: _Material) -> None:
        """Submit every stage of ``m`` whose prerequisites are done; reuse finished items (resume)."""
        progressed = True
        while progressed and m.error is None:
            progressed = False
            for stage in m.plan:
                if stage in m.submitted or any(d in m.plan and d not in m.done for d in DEPENDS[stage]):
                    continue
                m.submitted.add(stage)
                missing = pipeline.missing_modules(stage, m.spec.to_json())
                if missing:
                    msg = (f"StageUnavailable: stage {stage!r} needs module(s) {', '.join(missing)}, which are "
                           "not installed; drop it from the stages list or install it")
                    self.store.fail_item(self.manifest.name, m.spec.name, stage, "", msg, "StageUnavailable")
                    self._fail_material(m, f"{stage}: {msg}")
                    return
                items = self._items(m, stage)
                stale = any(d in m.fresh for d in DEPENDS[stage])  # an input was recomputed in this run
                todo = set()
                for item in items:
                    if not stale and self.store.is_done(self.manifest.name, m.spec.name, stage, item,
                                                        self.manifest.output):
                        self.reused += 1
                        if item == "" and stage in ("load", "decompose"):
                            m.info[stage] = self.store.done_info(self.manifest.name, m.spec.name, stage)
                    else:
                        todo.add(item)
                if not items and (stale or not self.store.is_done(self.manifest.name, m.spec.name, stage, "",
                                                                  self.manifest.output)):
                    self.store.finish_item(self.manifest.name, m.spec.name, stage, "", {"info": {"items": 0}})
                self._bar_total(len(todo))
                if not todo:
                    m.done.add(stage)
                    self._say(m.spec.name, stage, f"reused ({len(items)} item(s))" if items else "nothing to do")
                    progressed = True
                    continue
                m.waiting[stage] = todo
                m.fresh.add(stage)
                for item in sorted(todo):
                    self._submit(m, stage, item)

    # -- results

    def _on_result(self, fl: _Flight, result: dict) -> None:
        m = self.mats[fl.material]
        self.store.finish_item(self.manifest.name, fl.material, fl.stage, fl.item, result)
        self.executed += 1
        self._bar_step()
        if fl.item == "" and fl.stage in ("load", "decompose"):
            m.info[fl.stage] = result.get("info", {})
        waiting = m.waiting.get(fl.stage, set())
        waiting.discard(fl.item)
        if not waiting and m.error is None:
            m.done.add(fl.stage)
            secs = sum(r["duration"] or 0 for r in self.store.items(self.manifest.name, fl.material, fl.stage))
            self._say(fl.material, fl.stage, f"done ({len(self._items(m, fl.stage))} item(s), {secs:.1f} s)")
            self._advance(m)
        self._maybe_finish(m)

    def _fail_material(self, m: _Material, message: str) -> None:
        import ray

        if m.error is not None:
            return
        m.error = message
        self.store.set_material(self.manifest.name, m.spec.name, "failed", message)
        self._say(m.spec.name, "-", f"FAILED: {message}")
        for ref, fl in list(self.inflight.items()):
            if fl.material == m.spec.name:
                ray.cancel(ref, force=False)

    def _on_error(self, fl: _Flight, exc: BaseException) -> None:
        import ray

        m = self.mats[fl.material]
        if m.error is not None:
            self.store.mark_item(self.manifest.name, fl.material, fl.stage, fl.item, "cancelled", m.error)
            return
        where = f"{fl.stage}" + (f"[{fl.item}]" if fl.item else "")
        if isinstance(exc, self._retryable) and not isinstance(exc, ray.exceptions.RayTaskError):
            final = fl.attempt >= self.manifest.max_attempts
            msg = f"{type(exc).__name__} (attempt {fl.attempt}/{self.manifest.max_attempts}): " + \
                  " ".join(str(exc).split())[:500]
            self.store.fail_item(self.manifest.name, fl.material, fl.stage, fl.item, msg, type(exc).__name__,
                                 final=final)
            if fl.actor is not None:
                self._replace_actor(fl.stage, fl.actor)
            if final:
                self._fail_material(m, f"{where}: worker lost {fl.attempt} times: {msg}")
            else:
                logger.warning("%s %s: %s; retrying", fl.material, where, msg)
                self._say(fl.material, fl.stage, f"worker lost ({type(exc).__name__}), retrying")
                self._submit(m, fl.stage, fl.item)
            return
        cause = getattr(exc, "cause", None) or exc
        text = str(cause) if not isinstance(cause, ray.exceptions.RayTaskError) else str(cause).splitlines()[-1]
        msg = f"{type(cause).__name__}: {' '.join(text.split())}"
        detail = str(exc) if isinstance(exc, ray.exceptions.RayTaskError) else msg  # remote traceback
        self.store.fail_item(self.manifest.name, fl.material, fl.stage, fl.item, msg, type(cause).__name__,
                             final=True, detail=detail)
        self._fail_material(m, f"{where}: {msg}")

    def _maybe_finish(self, m: _Material) -> None:
        if m.error is None and all(s in m.done for s in m.plan):
            if not any(fl.material == m.spec.name for fl in self.inflight.values()):
                self.store.set_material(self.manifest.name, m.spec.name, "done")

    # -- progress

    def _say(self, material: str, stage: str, text: str) -> None:
        logger.info("%s %s %s", material, stage, text)
        if self.progress:
            from tqdm import tqdm

            tqdm.write(f"{material:<28} {stage:<9} {text}", file=sys.stderr)

    def _bar_total(self, n: int) -> None:
        if self._bar is not None and n:
            self._bar.total += n
            self._bar.refresh()

    def _bar_step(self) -> None:
        if self._bar is not None:
            self._bar.update(1)

    # -- main loop

    def run(self) -> JobReport:
        """Run (or resume) the job; returns the per-material outcome."""
        import ray
        from tqdm import tqdm

        t0 = time.perf_counter()
        job = self.manifest
        self.manifest.output.mkdir(parents=True, exist_ok=True)
        runs = self.store.register_job(job.name, str(job.source) if job.source else None, str(job.output),
                                       job.to_json())
        reset = self.store.sync_materials(job.name, [
            {"name": m.name, "output": m.output, "spec_hash": m.spec_hash(), "spec": m.to_json()}
            for m in job.materials])
        if reset:
            logger.warning("materials changed since the last run, recomputed from scratch: %s", ", ".join(reset))
        logger.info("job %s run %d: %d materials, %.0f CPU, %d GPU", job.name, runs, len(job.materials),
                    self.cpus, self.gpus)
        self._bar = tqdm(total=0, unit="item", desc=job.name, file=sys.stderr, leave=False,
                         disable=not (self.progress and sys.stderr.isatty()))
        try:
            for spec in job.materials:
                try:  # before anything is written for it: the folder must be this job's
                    claims.claim(job.material_dir(spec), job.name, self.store.path)
                except InputError as exc:
                    m = self.mats[spec.name] = _Material(spec=spec, plan=[])
                    self._fail_material(m, str(exc))
                    continue
                plan, err = self._plan(spec)
                m = self.mats[spec.name] = _Material(spec=spec, plan=plan)
                self.store.set_material(job.name, spec.name, "running")
                if err:
                    self._fail_material(m, err)
                    continue
                self._advance(m)
                self._maybe_finish(m)
            while self.inflight:
                ready, _ = ray.wait(list(self.inflight), num_returns=1, timeout=2.0)
                for ref in ready:
                    fl = self.inflight.pop(ref)
                    try:
                        result = ray.get(ref)
                    except Exception as exc:  # noqa: BLE001 - classified in _on_error
                        self._on_error(fl, exc)
                        continue
                    if self.mats[fl.material].error is not None:
                        self.store.finish_item(job.name, fl.material, fl.stage, fl.item, result)
                        continue
                    self._on_result(fl, result)
            for m in self.mats.values():
                if m.error is None:
                    missing = [s for s in m.plan if s not in m.done]
                    if missing:
                        self._fail_material(m, f"stages {missing} did not finish")
                    else:
                        self._maybe_finish(m)
        except BaseException:
            self.store.finish_job(job.name, "interrupted")
            for ref in self.inflight:
                ray.cancel(ref, force=True)
            raise
        finally:
            if self._bar is not None:
                self._bar.close()
            for pool in self._pools.values():
                for a in pool:
                    ray.kill(a, no_restart=True)
            self._pools.clear()
        statuses = {m.spec.name: ("failed" if m.error else "done") for m in self.mats.values()}
        report = JobReport(job=job.name, database=self.store.path, output=job.output, materials=statuses,
                           errors={n: m.error for n, m in self.mats.items() if m.error}, executed=self.executed,
                           reused=self.reused, seconds=time.perf_counter() - t0)
        self.store.finish_job(job.name, "done" if report.exit_code == 0 else "failed")
        if self._own_store:
            self.store.close()
        return report


def run_job(manifest: JobManifest, address: str | None = None, num_cpus: int | None = None,
            progress: bool = True, mask_database: str | None = None) -> JobReport:
    """Run a validated job on Ray (local unless ``address``); shuts Ray down only if this call started it."""
    import ray

    started = ensure_ray(address, num_cpus)
    try:
        return Scheduler(manifest, progress=progress, mask_database=mask_database).run()
    finally:
        if started:
            ray.shutdown()
