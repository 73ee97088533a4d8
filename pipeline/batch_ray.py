"""The batch on a Ray cluster: each scene's process (`pipeline.batch.run_scene`) runs as a Ray task.

Ray is an optional extra (`make install extras=cluster`): without it this module still imports, and a RayCluster
says how to install it.
Every machine of the cluster needs this project installed and the scenes and the output folder at the same paths (a
shared filesystem): a task writes the scene's outputs where the driver and any retry will look for them. A task asks
for `cpus_per_scene` CPUs, and one GPU when the fit runs on one; when the worker running it dies, Ray runs the task
again elsewhere and the scene's pipeline resumes from what it had finished.
"""
from __future__ import annotations

import math

from pipeline import config
from pipeline.batch import BatchOptions, SceneJob, run_scene, scene_record, stage_run_ids
from plenoxels.core.errors import UserError

try:
    import ray
except ImportError:
    ray = None
NO_RAY = "--ray needs Ray, an optional extra: make install extras=cluster (or pip install '.[cluster]')"

# Retries after a worker dies (a lost machine, an OOM kill); a scene that fails on its own is reported, not retried.
MAX_RETRIES = 3


def wants_gpu(options: BatchOptions, cluster_gpus: float) -> bool:
    """Whether a scene's task should hold a GPU: its fit runs (within --until) and `fit.device` lets it use one."""
    if "fit" not in options.stages():
        return False
    layers = config.merge(config.load_preset(options.preset), config.parse_overrides(options.overrides))
    device = layers.get("fit", {}).get("device", "auto")
    if device == "cuda" and not cluster_gpus:
        raise UserError("fit.device=cuda but the Ray cluster has no GPU; use fit.device=auto or add GPU workers")
    return device != "cpu" and cluster_gpus > 0


class RayCluster:
    """Runs the batch's scenes as Ray tasks on the cluster at `address` ('auto', 'ray://host:10001', 'host:6379'),
    or, with none, on the cluster `ray start` made on this machine, else on a new local one. A Ray session the
    caller already started is used as it is."""

    def __init__(self, address: str | None = None, cpus_per_scene: float = 1.0, max_retries: int = MAX_RETRIES):
        if ray is None:
            raise UserError(NO_RAY)
        self.owns_session = not ray.is_initialized()
        if self.owns_session:
            try:
                ray.init(address=address, include_dashboard=False, log_to_driver=False)
            except ConnectionError as e:
                raise UserError(f"cannot reach the Ray cluster at {address}: {e}") from None
        self.cpus_per_scene = cpus_per_scene
        self.max_retries = max_retries
        self.refs: dict = {}

    def start(self, jobs: list[SceneJob], options: BatchOptions) -> None:
        self.options = options
        resources = ray.cluster_resources()
        gpus = 1 if wants_gpu(options, resources.get("GPU", 0)) else 0
        self.slots = max(1, int(resources.get("CPU", 1) // self.cpus_per_scene))
        if gpus:
            self.slots = min(self.slots, int(resources["GPU"]))
        task = ray.remote(run_scene).options(num_cpus=self.cpus_per_scene, num_gpus=gpus,
                                             max_retries=self.max_retries, name="voxfield-scene")
        threads = max(1, math.ceil(self.cpus_per_scene))
        self.refs = {task.remote(job, options, threads): job for job in jobs}

    def wait(self, timeout: float) -> list[dict]:
        ready, _ = ray.wait(list(self.refs), num_returns=len(self.refs), timeout=timeout)
        records = []
        for ref in ready:
            job = self.refs.pop(ref)
            try:
                records.append(ray.get(ref))
            except ray.exceptions.RayError as e:
                # Ray gave up on the task (its workers kept dying): report the scene with what its folder holds.
                reason = (str(e).strip().splitlines() or [type(e).__name__])[0]
                records.append(scene_record(job, self.options, stage_run_ids(job.out), error=f"Ray task lost: {reason}",
                                            wall_seconds=0.0, peak_memory_bytes=0))
        return records

    def pending(self) -> int:
        return len(self.refs)

    def running(self) -> int:
        return min(len(self.refs), self.slots)

    def close(self) -> None:
        if self.owns_session:
            ray.shutdown()

