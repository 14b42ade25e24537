"""Where stage work runs on Ray: what the cluster has or can grow to, what each stage reserves, which torch device.

Placement is decided from configuration and demand, never from a one-off snapshot:

- ``recompose.device`` of a material is ``"auto"`` (default), ``"cuda"`` or ``"cpu"``. ``"cuda"``, and ``"auto"``
  on a cluster that has GPUs or declares GPU node types (autoscaler node groups, or ``PROCEDURALIZE_MAX_GPUS``
  for a cluster whose GPU group scales from zero), send the material to GPU actors that request ``num_gpus=1``:
  while no GPU node is up the request stays pending, which is the demand an autoscaler acts on.
- Every task and actor reserves the CPUs its threads use (``num_cpus`` = torch threads), and sets its torch
  thread count to that reservation, so Ray's accounting matches what runs.
- Inside a GPU actor the torch device is checked, not assumed: a node that advertises ``GPU`` but whose torch
  cannot see CUDA runs on CPU, with a warning and a note recorded with the material.
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from typing import Any

logger = logging.getLogger(__name__)

#: custom Ray resource that pins mask-fitting actors to the CPU worker group when a cluster advertises it
MASK_RESOURCE = "mask_fitter"
#: environment variable naming how many GPUs the cluster can scale to (deploy configs set it on the head)
MAX_GPUS_ENV = "PROCEDURALIZE_MAX_GPUS"
DEVICES = ("auto", "cuda", "cpu")


@dataclass
class Capacity:
    """What the cluster has now and what it may grow to (refreshed by the scheduler while a job runs)."""

    cpus: float = 1.0            # CPUs of the live nodes, all together
    node_cpus: float = 1.0       # the most CPUs one live node has (bound for a single actor's reservation)
    gpus: int = 0                # GPUs of the live nodes
    max_gpus: int = 0            # GPUs the cluster can reach: live ones or declared node types, whichever is more
    mask_slots: int = 0          # ``mask_fitter`` resource units (0: the resource is not used)

    @property
    def gpu_capable(self) -> bool:
        """True when GPU work can be placed now or once the autoscaler adds a declared GPU node."""
        return self.max_gpus > 0


def declared_gpus() -> int:
    """GPUs the cluster declares it can scale to: the autoscaler's node groups (when it reports them to the GCS)
    or ``PROCEDURALIZE_MAX_GPUS``; 0 when neither says anything."""
    env = os.environ.get(MAX_GPUS_ENV, "").strip()
    if env:
        try:
            return max(0, int(env))
        except ValueError:
            logger.warning("%s=%r is not an integer; ignored", MAX_GPUS_ENV, env)
    try:
        import ray._private.state as rstate

        limits = rstate.state.get_max_resources_from_cluster_config() or {}
        return int(min(limits.get("GPU", 0) or 0, 1 << 16))
    except Exception:  # noqa: BLE001 - older Ray, no autoscaler config: nothing declared
        return 0


def read_capacity() -> Capacity:
    """The connected cluster's capacity (live nodes plus declared GPU node types)."""
    import ray

    alive = [n for n in ray.nodes() if n.get("Alive")]
    res = [n.get("Resources", {}) for n in alive]
    cpus = sum(float(r.get("CPU", 0)) for r in res)
    gpus = int(sum(float(r.get("GPU", 0)) for r in res))
    return Capacity(cpus=max(cpus, 0.0), node_cpus=max([float(r.get("CPU", 0)) for r in res] or [0.0]),
                    gpus=gpus, max_gpus=max(gpus, declared_gpus()),
                    mask_slots=int(sum(float(r.get(MASK_RESOURCE, 0)) for r in res)))


def recompose_route(device: str, capacity: Capacity) -> str:
    """Which actor pool recomposes a material: ``"gpu"`` or ``"cpu"``."""
    if device == "cpu":
        return "cpu"
    if device == "cuda":
        return "gpu"
    return "gpu" if capacity.gpu_capable else "cpu"


def cpu_threads(wanted: int, capacity: Capacity) -> int:
    """CPUs one CPU recomposition actor reserves (= its torch threads): ``wanted``, bounded by the largest node so
    the actor stays placeable."""
    return max(1, min(int(wanted), int(capacity.node_cpus) or 1))


def use_threads(n: int, load_torch: bool = False) -> None:
    """Make this process's torch and OpenMP use ``n`` threads: a stage's threads follow its reservation.

    Sets ``OMP_NUM_THREADS`` for a torch imported later and the thread count of a torch already imported."""
    import sys

    n = max(1, int(n))
    os.environ["OMP_NUM_THREADS"] = str(n)
    if load_torch:
        import torch  # noqa: F401
    torch = sys.modules.get("torch")  # noqa: F811 - set the threads of a torch someone loaded
    if torch is not None and torch.get_num_threads() != n:
        torch.set_num_threads(n)


def pick_torch_device(requested: str) -> tuple[str, str | None]:
    """The torch device an actor placed for ``requested`` really uses, and a note when it differs.

    ``"cuda"``: the first visible CUDA device when torch sees one; otherwise CPU, with the reason (a node may
    advertise a ``GPU`` resource that this torch build or driver cannot use)."""
    if requested != "cuda":
        return "cpu", None
    import torch

    if torch.cuda.is_available():
        return "cuda", None
    visible = os.environ.get("CUDA_VISIBLE_DEVICES", "<unset>")
    note = (f"placed on a node with a GPU resource (CUDA_VISIBLE_DEVICES={visible}) but torch "
            f"{torch.__version__} sees no CUDA device; recomposition ran on CPU")
    logger.warning("%s", note)
    return "cpu", note


def pending_gpu_demand(address: str | None = None) -> float:
    """GPUs requested by pending tasks/actors, as the autoscaler sees them (0.0 when nothing waits for a GPU)."""
    import ray
    from ray.autoscaler.v2.sdk import get_cluster_status

    status = get_cluster_status(address or ray.get_runtime_context().gcs_address)
    total = 0.0
    for demand in status.resource_demands.ray_task_actor_demand:
        for b in demand.bundles_by_count:
            total += float(b.bundle.get("GPU", 0.0)) * b.count
    return total


def node_of(worker: str | None) -> str:
    """The node-id prefix of a stage result's ``worker`` field (``host:pid@node``)."""
    return (worker or "").rpartition("@")[2]


def describe(capacity: Capacity) -> str:
    """One line for the log."""
    return (f"{capacity.cpus:g} CPU (largest node {capacity.node_cpus:g}), {capacity.gpus} GPU up, "
            f"{capacity.max_gpus} GPU reachable")


def actor_options(kind: str, threads: int, capacity: Capacity) -> dict[str, Any]:
    """Ray options of a stage actor: ``masks`` (1 CPU, pinned by ``mask_fitter`` when advertised), ``cpu``
    recomposition (``threads`` CPUs) or ``gpu`` recomposition (1 GPU and 1 CPU feeding it)."""
    if kind == "masks":
        opts: dict[str, Any] = {"num_cpus": 1}
        if capacity.mask_slots:
            opts["resources"] = {MASK_RESOURCE: 1}
        return opts
    if kind == "gpu":
        return {"num_cpus": 1, "num_gpus": 1}
    return {"num_cpus": threads}
