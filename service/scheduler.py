"""Run every material of a job on Ray: per-stage tasks, actor pools, retries, resume.

The driver (this module) is the only writer to the job database. It submits the first stage of every
material at once and, as results come back, records them and submits what became ready:

    load -> decompose -> { noise (one task per leaf x map), masks (one call per tree node, on a pool of
    CPU actors holding the PPTBF index) } -> recompose (GPU or CPU actors, see service.placement) -> output

Stages, what they need, their work items and where they run (a task, a mask actor, a recomposition actor)
are read from their declarations in :mod:`service.stages`.

Worker crashes (WorkerCrashedError, RayActorError, ...) are retried up to ``max_attempts``; an
exception inside a stage fails only its material. A stage item whose row is done and whose artefacts are
on disk with the recorded checksums is skipped on a rerun (resume).

Reservations are honest: tasks reserve 1 CPU and run 1 torch thread; a mask actor reserves 1 CPU; a CPU
recomposition actor reserves ``job.recompose_cpus`` CPUs and runs that many threads; a GPU one reserves 1 GPU
and 1 CPU. Actor stages queue in the driver and go to an idle actor of their pool, one call per actor at a time,
so recomposition of one material overlaps mask fitting of others, bounded by the pools' sizes (GPUs the cluster
has or can reach; CPUs / reservation), and the time an item waits for a slot is measured (``stages.wait``).
Pools grow with their queue up to that bound, first by taking over idle actors of the same shape from another
pool (an actor runs mask fits and recompositions alike), and an idle actor whose queue is empty is retired when the
work in flight needs its CPUs, so idle actors never starve the tasks they wait for on a small cluster.

GPU actors are requested at job start when some material routes to them, so a GPU group that scales from zero
sees the demand (pending actors) while the first stages run. When no GPU actor has started after
``job.gpu_wait_s``, "auto" materials recompose on CPU (warning logged, ``materials.device_note`` says why) and
"cuda" materials fail with that reason.
"""
from __future__ import annotations

import json
import logging
import os
import sys
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import ray
import ray.exceptions as rex
from tqdm import tqdm

from service import claims, placement
from service.manifest import JobManifest, MaterialSpec, _Problems
from service.manifest import parse_faults as _parse_faults
from service.stages import STAGE_NAMES, Placement, StageCall, run_stage, stage
from service.store import Store
from workers.errors import InputError, ManifestError

logger = logging.getLogger(__name__)

MASK_RESOURCE = placement.MASK_RESOURCE
#: actor pools: mask fitting, recomposition on CPU, recomposition on GPU
POOLS = ("masks", "cpu", "gpu")
#: a pool whose actors fail to start this many times in a row gives up and fails the materials it holds
MAX_START_FAILURES = 3
#: seconds between two reads of the cluster's capacity while a job runs
CAPACITY_REFRESH_S = 5.0
#: environment variable with fault-injection hooks for tests (JSON, see parse_faults)
FAULTS_ENV = "PROCEDURALIZE_FAULTS"
#: the address every listener of a local Ray binds to: nothing of a local run is reachable from the network
LOCAL_IP = "127.0.0.1"


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
    actor: Any = None        # the _Slot running it (actor stages)
    queued: float = 0.0      # wall time the item became ready (its wait for a slot is measured from here)


@dataclass
class _Slot:
    """One actor of a pool: starting (``ready`` False), idle, or running one call (``busy``)."""

    handle: Any
    ready_ref: Any
    ready: bool = False
    busy: Any = None
    started: float = 0.0     # monotonic time the actor was requested
    node: str = ""
    device: str = "cpu"
    note: str | None = None
    options: dict = field(default_factory=dict)   # the Ray options it was started with (its shape)


@dataclass
class _Pool:
    """Actors of one kind and the driver-side queue of the items waiting for one of them."""

    kind: str
    limit: int
    cpus: float                      # CPUs each actor reserves
    queue: deque = field(default_factory=deque)   # (material, stage, item, attempt, queued wall time)
    slots: list = field(default_factory=list)
    start_failures: int = 0


def _retryable_errors() -> tuple[type, ...]:
    """Ray errors that mean "the worker/actor/node went away", not "the stage raised"."""
    names = ("WorkerCrashedError", "RayActorError", "ActorDiedError", "ActorUnavailableError", "ObjectLostError",
             "OwnerDiedError", "NodeDiedError", "LocalRayletDiedError", "TaskUnschedulableError")
    # OutOfMemoryError is not among them: the same item on the same inputs would run out of memory again
    return tuple(getattr(rex, n) for n in names if hasattr(rex, n))


def parse_faults(doc: dict, where: str = "faults") -> dict:
    """Validated fault-injection hooks (tests only): {crash_once: {stage, marker, material}, sleep: {stage,
    seconds, material}}."""
    probs = _Problems()
    out = _parse_faults(doc, Path.cwd(), probs)
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
    result["worker"] = f"{result.get('worker')}@{ray.get_runtime_context().get_node_id()[:8]}"
    return result


def run_stage_task(call: StageCall) -> dict:
    """Body of the per-stage Ray task (1 CPU reserved, 1 thread)."""
    placement.use_threads(1)
    return _on_node(run_stage(call))


class _StageActor:
    """Ray actor body: runs mask fits (a MaskFitter, PPTBF index loaded on the first fit) and recompositions (a
    Recomposer), whichever its calls ask for, so an idle actor of one CPU pool can serve another of the same shape.

    Its torch threads follow its CPU reservation; an actor placed for CUDA checks that torch sees a device and
    otherwise runs on CPU (logged, and noted in each recomposition's info)."""

    def __init__(self, device: str = "cpu", database: str | None = None, threads: int = 1):
        from workers.actors import MaskFitter  # loaded in the actor, not in the driver

        placement.use_threads(threads, load_torch=device == "cuda")
        self.threads = threads
        self.device, self.note = placement.pick_torch_device(device)
        self.fitter = MaskFitter(database)
        self.recomposer = None

    def _holder(self, call: StageCall) -> Any:
        if stage(call.stage).placement is not Placement.RECOMPOSE_ACTOR:
            return self.fitter
        if self.recomposer is None:
            from workers.actors import Recomposer  # torch: imported on the first recomposition

            placement.use_threads(self.threads, load_torch=True)
            self.recomposer = Recomposer(self.device)
        # the actor's device wins over the material's option (which chose the pool)
        call.spec = call.spec.with_options(call.stage, device=self.device)
        return self.recomposer

    def run(self, call: StageCall) -> dict:
        holder = self._holder(call)
        result = _on_node(run_stage(call, holder))
        if holder is self.recomposer and self.note:
            result["info"]["placement_note"] = self.note
        return result

    def ready(self) -> dict:
        return {"pid": os.getpid(), "node": ray.get_runtime_context().get_node_id()[:8], "device": self.device,
                "note": self.note, "threads": _torch_threads()}


def _torch_threads() -> int | None:
    torch = sys.modules.get("torch")
    return torch.get_num_threads() if torch is not None else None


class Scheduler:
    """Drives one job to completion on the connected Ray cluster."""

    def __init__(self, manifest: JobManifest, store: Store | None = None, progress: bool = True,
                 mask_database: str | None = None, faults: dict | None = None):
        self.manifest = manifest
        self.faults = parse_faults(faults) if faults is not None else faults_from_env()
        self.store = store or Store(manifest.database)
        self._own_store = store is None
        self.progress = progress
        self.mask_database = mask_database or (str(manifest.pptbf_database) if manifest.pptbf_database else None)
        self.capacity = placement.read_capacity()
        self._capacity_at = time.monotonic()
        self._task = ray.remote(num_cpus=1, max_retries=0)(run_stage_task)
        self._pools: dict[str, _Pool] = {}
        self._starting: dict[Any, tuple[_Pool, _Slot]] = {}   # actor ready() ref -> its slot
        self._gpu_deadline: float | None = None
        self._gpu_gave_up: str | None = None   # why GPU recomposition was abandoned in this run
        self._notes: dict[str, str] = {}       # material -> why it was recomposed on another device than asked
        self.inflight: dict[Any, _Flight] = {}
        self.mats: dict[str, _Material] = {}
        self.executed = 0
        self.reused = 0
        self._retryable = _retryable_errors()
        self._tries: dict[tuple[str, str, str], int] = {}
        self._bar = None

    @property
    def cpus(self) -> float:
        return self.capacity.cpus

    @property
    def gpus(self) -> int:
        return self.capacity.gpus

    # -- planning

    def _plan(self, spec: MaterialSpec) -> tuple[list[str], str | None]:
        """Stages to run for a material and an error if the plan cannot work."""
        plan = list(spec.stages or self.manifest.stages or STAGE_NAMES)
        for s in plan:
            for d in stage(s).needs:
                if d not in plan and not self._stage_done_before(spec.name, d):
                    return plan, (f"stage {s!r} needs stage {d!r}, which is neither in this job's stages nor "
                                  "finished by an earlier run")
        return plan, None

    def _stage_done_before(self, material: str, name: str) -> bool:
        rows = self.store.items(self.manifest.name, material, name)
        return bool(rows) and all(self.store.is_done(self.manifest.name, material, name, r["item"],
                                                     self.manifest.output) for r in rows)

    def _items(self, m: _Material, name: str) -> list[str]:
        """Work items of a stage for ``m``, planned from what its predecessors recorded."""
        return stage(name).items(m.spec, lambda s: m.info.get(s) or self.store.done_info(self.manifest.name,
                                                                                      m.spec.name, s))

    # -- submission

    def _call(self, m: _Material, name: str, item: str) -> StageCall:
        return StageCall(job=self.manifest.name, root=str(self.manifest.output), spec=m.spec, stage=name,
                         item=item, debug=self.faults, timeout=self.manifest.stage_timeout,
                         memory_budget=self.manifest.memory_budget)

    # -- actor pools

    def _refresh_capacity(self) -> None:
        """Re-read the cluster (nodes join and leave while a job runs) and re-bound the pools."""
        if time.monotonic() - self._capacity_at < CAPACITY_REFRESH_S:
            return
        self.capacity = placement.read_capacity()
        self._capacity_at = time.monotonic()
        for pool in self._pools.values():
            pool.limit = self._limit(pool.kind)

    def _recompose_threads(self) -> int:
        return placement.cpu_threads(self.manifest.recompose_cpus, self.capacity)

    def _limit(self, kind: str) -> int:
        """Most actors of a pool: masks CPUs/2, or every CPU where no node holds a mask actor beside a CPU
        recomposition actor of more than one thread (job.mask_actors overrides; within ``mask_fitter`` slots);
        CPU recomposition CPUs / its reservation; GPU recomposition the GPUs the cluster has or can reach.
        On a 2-CPU machine with 2-thread recompositions, half the CPUs for masks left the other one idle through
        the whole mask phase: the recomposition it was kept for cannot start beside a mask actor anyway."""
        cap = self.capacity
        if kind == "masks":
            threads = self._recompose_threads()
            alone = threads > 1 and cap.node_cpus < 1 + threads
            n = self.manifest.mask_actors or max(1, int(cap.cpus) // (1 if alone else 2))
            return min(n, cap.mask_slots) if cap.mask_slots else n
        if kind == "gpu":
            return max(1, cap.max_gpus)
        return max(1, int(cap.cpus // self._recompose_threads()))

    def _pool(self, kind: str) -> _Pool:
        if kind not in self._pools:
            cpus = float(self._recompose_threads()) if kind == "cpu" else 1.0
            self._pools[kind] = _Pool(kind=kind, limit=self._limit(kind), cpus=cpus)
        return self._pools[kind]

    def _start_actor(self, pool: _Pool) -> None:
        """Request one more actor for ``pool`` (pending until Ray, or the autoscaler, finds it a node)."""
        threads = int(pool.cpus)
        opts = self._actor_options(pool)
        args = ("cuda" if pool.kind == "gpu" else "cpu", self.mask_database, threads)
        handle = ray.remote(max_restarts=0, max_task_retries=0, **opts)(_StageActor).remote(*args)
        slot = _Slot(handle=handle, ready_ref=handle.ready.remote(), started=time.monotonic(), options=opts)
        pool.slots.append(slot)
        self._starting[slot.ready_ref] = (pool, slot)
        logger.info("requested a %s actor %s (%d in the pool, at most %d)", pool.kind, opts, len(pool.slots),
                    pool.limit)

    def _drop_slot(self, pool: _Pool, slot: _Slot) -> None:
        """Kill an actor and forget it (a retired idle one, a dead one, a pending one no longer wanted)."""
        if slot in pool.slots:
            pool.slots.remove(slot)
        self._starting.pop(slot.ready_ref, None)
        try:
            ray.kill(slot.handle, no_restart=True)
        except Exception:  # noqa: BLE001 - already gone
            pass

    def _on_actor_ready(self, ref: Any) -> None:
        pool, slot = self._starting.pop(ref)
        try:
            info = ray.get(ref)
        except Exception as exc:  # noqa: BLE001 - the actor could not start (constructor raised, node lost)
            self._drop_slot(pool, slot)
            pool.start_failures += 1
            msg = f"a {pool.kind} actor failed to start: {type(exc).__name__}: {' '.join(str(exc).split())[:300]}"
            logger.warning("%s", msg)
            if pool.start_failures >= MAX_START_FAILURES:
                self._pool_broken(pool, msg)
            return
        slot.ready, slot.node, slot.device, slot.note = True, info["node"], info["device"], info["note"]
        pool.start_failures = 0
        log = logger.warning if slot.note else logger.info
        log("%s actor pid %s ready on node %s: torch on %s, %s thread(s)%s", pool.kind, info["pid"], info["node"],
            info["device"], info["threads"], f" ({slot.note})" if slot.note else "")

    def _pool_broken(self, pool: _Pool, why: str) -> None:
        """Actors of ``pool`` keep failing to start: GPU work falls back like a GPU that never came; else the
        queued materials fail with the reason."""
        if pool.kind == "gpu":
            self._give_up_gpu(f"GPU actors failed to start {pool.start_failures} times ({why})")
            return
        for name, *_ in list(pool.queue):
            self._fail_material(self.mats[name], f"{pool.kind} actors failed to start {pool.start_failures} "
                                                 f"times: {why}")
        pool.queue.clear()

    @staticmethod
    def _device(m: _Material, name: str) -> str:
        """The ``device`` option of a recomposition-actor stage of ``m``: auto, cuda or cpu."""
        return m.spec.stage_options(name).get("device", "auto")

    def _recompose_kind(self, m: _Material, name: str) -> str | None:
        """The pool that runs stage ``name`` of ``m`` on a recomposition actor ("gpu" or "cpu"), or None when it
        cannot run (material failed)."""
        device = self._device(m, name)
        kind = placement.recompose_route(device, self.capacity)
        if kind == "gpu" and self._gpu_gave_up:
            if device == "cuda":
                self._fail_material(m, f"{name}: {name}.device = 'cuda' but {self._gpu_gave_up}")
                return None
            self._notes[m.spec.name] = f"{self._gpu_gave_up}; recomposed on CPU ({name}.device = 'auto')"
            return "cpu"
        return kind

    def _wants_gpu(self, m: _Material) -> bool:
        """True when ``m`` will recompose on a GPU in this run (not failed, not finished by an earlier run)."""
        return m.error is None and any(
            stage(s).placement is Placement.RECOMPOSE_ACTOR
            and placement.recompose_route(self._device(m, s), self.capacity) == "gpu"
            and not self._stage_done_before(m.spec.name, s) for s in m.plan)

    def _give_up_gpu(self, why: str) -> None:
        """Stop waiting for GPUs: withdraw the pending GPU actors and move the GPU queue to CPU ("auto")."""
        self._gpu_gave_up = why
        logger.warning("%s; 'auto' recompositions run on CPU, 'cuda' ones fail", why)
        pool = self._pools.get("gpu")
        if pool is None:
            return
        for slot in [s for s in pool.slots if not s.ready]:
            self._drop_slot(pool, slot)
        queued, pool.queue = list(pool.queue), deque()
        for entry in queued:
            m = self.mats[entry[0]]
            if m.error is None:
                kind = self._recompose_kind(m, entry[1])
                if kind is not None:
                    self._pool(kind).queue.append(entry)

    def _check_gpu_wait(self) -> None:
        """The wait for GPUs starts whenever the GPU pool has no running actor (at job start, or after its node
        was lost) and ends when one runs; past ``job.gpu_wait_s`` GPU work gives up."""
        pool = self._pools.get("gpu")
        if pool is None or self._gpu_gave_up:
            return
        if any(s.ready for s in pool.slots):
            self._gpu_deadline = None
        elif self._gpu_deadline is None:
            self._gpu_deadline = time.monotonic() + self.manifest.gpu_wait_s
        elif time.monotonic() >= self._gpu_deadline:
            self._give_up_gpu(f"no GPU actor started within job.gpu_wait_s = {self.manifest.gpu_wait_s:g} s "
                              f"(cluster: {placement.describe(self.capacity)})")

    def _enqueue(self, m: _Material, name: str, item: str, attempt: int) -> None:
        """Queue an actor-stage item in the driver; ``_pump`` hands it to an idle actor of its pool."""
        kind = "masks" if stage(name).placement is Placement.MASK_ACTOR else self._recompose_kind(m, name)
        if kind is None:
            return
        self.store.mark_item(self.manifest.name, m.spec.name, name, item, "queued")
        self._pool(kind).queue.append((m.spec.name, name, item, attempt, time.time()))

    def _dispatch(self, slot: _Slot, entry: tuple) -> None:
        material, name, item, attempt, queued = entry
        m = self.mats[material]
        self.store.start_item(self.manifest.name, material, name, item)
        ref = slot.handle.run.remote(self._call(m, name, item))
        slot.busy = ref
        self.inflight[ref] = _Flight(material, name, item, attempt, slot, queued)

    def _pump(self) -> None:
        """Hand queued items to idle actors, grow pools to their queue (within their bound), retire idle actors
        whose CPUs the work in flight needs, and give up on GPUs after the wait."""
        self._refresh_capacity()
        self._check_gpu_wait()
        for pool in list(self._pools.values()):
            pool.queue = deque(e for e in pool.queue if self.mats[e[0]].error is None)
            self._adopt(pool)
            for slot in pool.slots:
                if not pool.queue:
                    break
                if slot.ready and slot.busy is None:
                    self._dispatch(slot, pool.queue.popleft())
            if pool.kind == "gpu" and self._gpu_gave_up:
                continue
            busy = sum(s.busy is not None for s in pool.slots)
            while len(pool.slots) < min(pool.limit, busy + len(pool.queue)):
                self._start_actor(pool)
        self._retire_idle()

    def _actor_options(self, pool: _Pool) -> dict[str, Any]:
        """The Ray options (the shape) of an actor of ``pool``."""
        return placement.actor_options(pool.kind, int(pool.cpus), self.capacity)

    def _adopt(self, pool: _Pool) -> None:
        """Give ``pool`` the idle actors of other pools that have nothing queued and the shape ``pool`` would start
        (same Ray options: a one-CPU recomposition actor and a mask actor without ``mask_fitter`` pinning), instead
        of retiring them for new processes (a few seconds of a core each time the work moves between mask fitting
        and recomposition). An actor of ``pool`` still waiting for a node is withdrawn for one adopted."""
        idle = sum(s.ready and s.busy is None for s in pool.slots)
        pending = [s for s in pool.slots if not s.ready]
        needed = len(pool.queue) - idle
        if needed <= 0:
            return
        shape = self._actor_options(pool)
        for other in self._pools.values():
            if other is pool or other.queue:
                continue
            for slot in [s for s in other.slots if s.ready and s.busy is None and s.options == shape]:
                if needed <= 0:
                    return
                if len(pool.slots) >= pool.limit:
                    if not pending:
                        return
                    self._drop_slot(pool, pending.pop())
                other.slots.remove(slot)
                pool.slots.append(slot)
                needed -= 1
                logger.info("an idle %s actor on node %s now serves the %s pool", other.kind, slot.node, pool.kind)

    def _retire_idle(self) -> None:
        """Kill idle CPU actors with nothing queued while the CPUs reserved by the work in flight exceed the
        cluster's (tasks are waiting for them), or while an actor has waited long for a node (fragmentation)."""
        pools = [p for p in self._pools.values() if p.kind != "gpu"]
        idle = [(p, s) for p in pools if not p.queue for s in p.slots if s.ready and s.busy is None]
        if not idle:
            return
        tasks = sum(fl.actor is None for fl in self.inflight.values())
        gpu_held = sum(s.ready for s in self._pools["gpu"].slots) if "gpu" in self._pools else 0
        held = sum(p.cpus * len(p.slots) for p in pools) + gpu_held
        excess = tasks + held - self.capacity.cpus
        stuck = any(not s.ready and time.monotonic() - s.started > 30.0 for p in pools for s in p.slots)
        for pool, slot in idle:
            if excess <= 0 and not stuck:
                break
            logger.info("retiring an idle %s actor on node %s (its CPUs are needed)", pool.kind, slot.node)
            self._drop_slot(pool, slot)
            excess -= pool.cpus
            stuck = False

    def _queued(self) -> int:
        return sum(len(p.queue) for p in self._pools.values())

    def _submit(self, m: _Material, name: str, item: str) -> None:
        key = (m.spec.name, name, item)
        attempt = self._tries[key] = self._tries.get(key, 0) + 1  # attempts in this run decide retries
        if stage(name).placement is not Placement.TASK:
            self._enqueue(m, name, item, attempt)
            return
        self.store.start_item(self.manifest.name, m.spec.name, name, item)
        call = self._call(m, name, item)
        ref = self._task.options(name=f"{m.spec.name}:{name}:{item}"[:100]).remote(call)
        self.inflight[ref] = _Flight(m.spec.name, name, item, attempt, None, time.time())

    def _advance(self, m: _Material) -> None:
        """Submit every stage of ``m`` whose prerequisites are done; reuse finished items (resume)."""
        progressed = True
        while progressed and m.error is None:
            progressed = False
            for name in m.plan:
                needs = stage(name).needs
                if name in m.submitted or any(d in m.plan and d not in m.done for d in needs):
                    continue
                m.submitted.add(name)
                items = self._items(m, name)
                stale = any(d in m.fresh for d in needs)  # an input was recomputed in this run
                todo = set()
                for item in items:
                    if not stale and self.store.is_done(self.manifest.name, m.spec.name, name, item,
                                                        self.manifest.output):
                        self.reused += 1
                        if item == "":  # what the next stages plan their items from
                            m.info[name] = self.store.done_info(self.manifest.name, m.spec.name, name)
                    else:
                        todo.add(item)
                if not items and (stale or not self.store.is_done(self.manifest.name, m.spec.name, name, "",
                                                                  self.manifest.output)):
                    self.store.finish_item(self.manifest.name, m.spec.name, name, "", {"info": {"items": 0}})
                self._bar_total(len(todo))
                if not todo:
                    m.done.add(name)
                    self._say(m.spec.name, name, f"reused ({len(items)} item(s))" if items else "nothing to do")
                    progressed = True
                    continue
                m.waiting[name] = todo
                m.fresh.add(name)
                for item in sorted(todo):
                    self._submit(m, name, item)

    # -- results

    def _on_result(self, fl: _Flight, result: dict) -> None:
        m = self.mats[fl.material]
        wait = max(0.0, float(result.get("started", fl.queued)) - fl.queued) if fl.queued else None
        self.store.finish_item(self.manifest.name, fl.material, fl.stage, fl.item, result, wait=wait)
        if stage(fl.stage).placement is Placement.RECOMPOSE_ACTOR:  # the device it really ran on
            info = result.get("info", {})
            self.store.set_device(self.manifest.name, fl.material, str(info.get("device", "cpu")),
                                  info.get("placement_note") or self._notes.get(fl.material))
        self.executed += 1
        self._bar_step()
        if fl.item == "":  # what the next stages plan their items from
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
        if m.error is not None:
            return
        m.error = message
        self.store.set_material(self.manifest.name, m.spec.name, "failed", message)
        self._say(m.spec.name, "-", f"FAILED: {message}")
        for ref, fl in list(self.inflight.items()):
            if fl.material == m.spec.name:
                ray.cancel(ref, force=False)

    def _on_error(self, fl: _Flight, exc: BaseException) -> None:
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
            if fl.actor is not None:  # the actor is gone: drop it, the pool starts another on demand
                for pool in self._pools.values():
                    if fl.actor in pool.slots:
                        self._drop_slot(pool, fl.actor)
                logger.warning("dropped a dead %s actor", fl.stage)
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

    def _say(self, material: str, name: str, text: str) -> None:
        logger.info("%s %s %s", material, name, text)
        if self.progress:
            tqdm.write(f"{material:<28} {name:<9} {text}", file=sys.stderr)

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
        logger.info("job %s run %d: %d materials on %s", job.name, runs, len(job.materials),
                    placement.describe(self.capacity))
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
            gpu_work = sum(self._wants_gpu(m) for m in self.mats.values())
            if gpu_work:  # request GPU actors now: a GPU group scaling from zero boots while the CPU stages run
                pool = self._pool("gpu")
                for _ in range(min(pool.limit, gpu_work)):
                    self._start_actor(pool)
            for m in self.mats.values():
                if m.error is None:
                    self._advance(m)
                    self._maybe_finish(m)
            self._pump()
            while self.inflight or self._queued():
                refs = list(self.inflight) + list(self._starting)
                if not refs:  # queued work but no actor can be started for it
                    for pool in self._pools.values():
                        self._pool_broken(pool, "no actor could be started")
                    break
                ready, _ = ray.wait(refs, num_returns=1, timeout=2.0)
                for ref in ready:
                    if ref in self._starting:
                        self._on_actor_ready(ref)
                        continue
                    fl = self.inflight.pop(ref)
                    if fl.actor is not None and fl.actor.busy is ref:
                        fl.actor.busy = None
                    try:
                        result = ray.get(ref)
                    except Exception as exc:  # noqa: BLE001 - classified in _on_error
                        self._on_error(fl, exc)
                        continue
                    if self.mats[fl.material].error is not None:
                        self.store.finish_item(job.name, fl.material, fl.stage, fl.item, result)
                        continue
                    self._on_result(fl, result)
                self._pump()
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
                for slot in list(pool.slots):
                    self._drop_slot(pool, slot)
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
    started = ensure_ray(address, num_cpus)
    try:
        return Scheduler(manifest, progress=progress, mask_database=mask_database).run()
    finally:
        if started:
            ray.shutdown()
