"""Many scenes in one command: each scene is a whole `pipeline run` in its own process, with its own output folder.

A scene's run is already idempotent and resumable (content-keyed stages, atomic outputs), so the batch only spreads
runs and collects what they did: it never schedules stages itself. A crash or a kill of one scene's process loses
nothing that scene finished, the other scenes go on, and running the same batch again resumes it. What each scene did
is read from its stage manifests, not from what it prints; its one-line error is the last line its process wrote to
stderr (the command line prints a UserError as one line).

Under the batch's output folder:
    <scene-name>/          that scene's pipeline output (as `python -m pipeline run SCENE --out DIR/<scene-name>`)
    <scene-name>/batch.log, batch.err.log   the scene process's stdout and stderr of the last batch run
    batch.json, batch.csv  one record per scene: stages, photos, scene type, PSNR/SSIM, mesh, time, peak memory, error

Local workers (`LocalWorkers`) run N scenes at a time on this machine; `pipeline.batch_ray.RayCluster` runs the same
scene processes as Ray tasks on a cluster.
"""
from __future__ import annotations

import csv
import ctypes
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Protocol

from pipeline import config
from stages.common.json_files import read_json, write_json
from stages.common.text import format_bytes, format_duration
from pipeline.runner import read_manifest
from pipeline.scenes import output_names
from pipeline.stage import STAGE_ORDER
from plenoxels.core.errors import UserError
from stages.common.layout import EXPORT_JSON, MESH_PLY, METRICS_JSON, scene_json, stage_file

PR_SET_PDEATHSIG = 1
RECORD_FIELDS = ("name", "status", "stages_done", "stages_ran", "registered", "images", "scene_type", "psnr", "ssim",
                 "mesh_faces", "mesh_bytes", "stage_seconds", "wall_seconds", "peak_memory_bytes", "host", "error",
                 "scene", "out")


@dataclass
class BatchOptions:
    """What every scene's `pipeline run` is given."""
    preset: str = "default"
    overrides: list[str] = field(default_factory=list)
    until: str | None = None

    def check(self) -> None:
        """A bad preset or override is one error now, not the same failure in every scene."""
        unknown = set(config.parse_overrides(self.overrides)) - set(STAGE_ORDER)
        config.load_preset(self.preset)
        if unknown:
            raise UserError(f"unknown settings section '{sorted(unknown)[0]}'; sections are: {', '.join(STAGE_ORDER)}")

    def stages(self) -> list[str]:
        return list(STAGE_ORDER[: STAGE_ORDER.index(self.until or STAGE_ORDER[-1]) + 1])


@dataclass(frozen=True)
class SceneJob:
    """One scene of the batch: its photos (or video) and its output folder."""
    name: str
    scene: Path
    out: Path

    def command(self, options: BatchOptions) -> list[str]:
        cmd = [sys.executable, "-m", "pipeline", "run", str(self.scene), "--out", str(self.out),
               "--preset", options.preset, "--quiet"]
        for pair in options.overrides:
            cmd += ["--set", pair]
        if options.until:
            cmd += ["--until", options.until]
        return cmd


def plan_jobs(scenes: list[Path], out_root: Path) -> list[SceneJob]:
    out_root = out_root.resolve()
    return [SceneJob(name, scene.resolve(), out_root / name) for name, scene in zip(output_names(scenes), scenes)]


# Looked up once here: the scene process calls it between fork and exec, where it should do as little as it can.
_prctl = ctypes.CDLL(None, use_errno=True).prctl


def _die_with(parent: int):
    """For the scene process, before exec: be killed when the worker that started it dies, so a killed worker (or
    batch) leaves no run behind holding the scene's lock, and a retry can take the scene over."""
    def arm() -> None:
        _prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
        if os.getppid() != parent:  # the worker died before the signal was armed
            os._exit(1)
    return arm


def run_scene(job: SceneJob, options: BatchOptions, threads: int) -> dict:
    """Runs one scene's pipeline in a child process and returns its record (see `scene_record`).
    Peak memory is the child's own maximum resident set (its rusage, not the worker's)."""
    job.out.mkdir(parents=True, exist_ok=True)
    before = stage_run_ids(job.out)
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    started = time.monotonic()
    with open(job.out / "batch.log", "w") as log, open(job.out / "batch.err.log", "w") as err:
        child = subprocess.Popen(job.command(options), stdin=subprocess.DEVNULL, stdout=log, stderr=err, env=env,
                                 preexec_fn=_die_with(os.getpid()))
        _, status, usage = os.wait4(child.pid, 0)
        child.returncode = os.waitstatus_to_exitcode(status)
    wall = time.monotonic() - started
    error = None
    if child.returncode != 0:
        lines = [line for line in (job.out / "batch.err.log").read_text(errors="replace").splitlines() if line.strip()]
        error = lines[-1].strip() if lines else f"exited with code {child.returncode}"
        if child.returncode < 0:
            error = f"killed by signal {-child.returncode} ({error})" if lines else f"killed by signal {-child.returncode}"
    return scene_record(job, options, before, error=error, wall_seconds=wall, peak_memory_bytes=usage.ru_maxrss * 1024)


def stage_run_ids(out: Path) -> dict[str, str | None]:
    """Each stage's current output, by the id its run gave it: a stage whose id changes has re-run."""
    return {name: (read_manifest(out / name) or {}).get("run_id") for name in STAGE_ORDER}


def _read(path: Path) -> dict:
    try:
        return read_json(path)
    except (FileNotFoundError, ValueError):
        return {}


def scene_record(job: SceneJob, options: BatchOptions, run_ids_before: dict[str, str | None], error: str | None,
                 wall_seconds: float, peak_memory_bytes: int) -> dict:
    """What a scene's output folder holds now, from its stage manifests and their small JSON outputs."""
    manifests = {name: read_manifest(job.out / name) for name in STAGE_ORDER}
    done = [name for name in options.stages() if manifests[name]]
    ran = [name for name in done if manifests[name].get("run_id") != run_ids_before.get(name)]
    poses = (manifests["poses"] or {}).get("summary", {})
    mean = _read(stage_file(job.out, "evaluate", METRICS_JSON)).get("mean") or {}
    mesh = stage_file(job.out, "export", MESH_PLY)
    return {
        "name": job.name, "scene": str(job.scene), "out": str(job.out),
        "status": "failed" if error else "done", "error": error,
        "stages_done": done, "stages_ran": ran,
        "registered": poses.get("registered"), "images": poses.get("images"),
        "scene_type": _read(scene_json(job.out)).get("type"),
        "psnr": mean.get("psnr"), "ssim": mean.get("ssim"),
        "mesh_faces": (_read(stage_file(job.out, "export", EXPORT_JSON)).get("mesh") or {}).get("faces"),
        "mesh_bytes": mesh.stat().st_size if manifests["export"] and mesh.is_file() else None,
        "stage_seconds": round(sum(manifests[n].get("seconds", 0.0) for n in done), 2),
        "wall_seconds": round(wall_seconds, 2), "peak_memory_bytes": peak_memory_bytes,
        "host": socket.gethostname(),
    }


class Workers(Protocol):
    """Where the scene processes run: `start` them all, then `wait` returns the records finished since it was last
    called (waiting at most `timeout` seconds for one), until none is `pending`."""
    def start(self, jobs: list[SceneJob], options: BatchOptions) -> None: ...
    def wait(self, timeout: float) -> list[dict]: ...
    def pending(self) -> int: ...
    def running(self) -> int: ...
    def close(self) -> None: ...


class LocalWorkers:
    """`workers` scenes at a time on this machine, each with an equal share of its threads."""

    def __init__(self, workers: int = 1):
        self.workers = max(1, workers)
        cores = int(os.environ.get("OMP_NUM_THREADS") or os.cpu_count() or 1)
        self.threads = max(1, cores // self.workers)
        self.pool = ThreadPoolExecutor(self.workers)
        self.futures: set[Future] = set()
        self._running = 0
        self._lock = threading.Lock()

    def _run(self, job: SceneJob, options: BatchOptions) -> dict:
        with self._lock:
            self._running += 1
        try:
            return run_scene(job, options, self.threads)
        finally:
            with self._lock:
                self._running -= 1

    def start(self, jobs: list[SceneJob], options: BatchOptions) -> None:
        self.futures = {self.pool.submit(self._run, job, options) for job in jobs}

    def wait(self, timeout: float) -> list[dict]:
        finished, self.futures = wait(self.futures, timeout=timeout, return_when=FIRST_COMPLETED)
        return [f.result() for f in finished]

    def pending(self) -> int:
        return len(self.futures)

    def running(self) -> int:
        return self._running

    def close(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)


def run_batch(jobs: list[SceneJob], options: BatchOptions, workers: Workers, out_root: Path,
              quiet: bool = False) -> list[dict]:
    """Runs every job on `workers`, printing a line per finished scene and a progress line; writes batch.json and
    batch.csv under `out_root` as scenes finish (so a killed batch still leaves them) and returns the records."""
    out_root = out_root.resolve()
    out_root.mkdir(parents=True, exist_ok=True)
    previous = {r["name"]: r for r in _read(out_root / "batch.json").get("scenes", [])}
    records: dict[str, dict] = {}
    started = time.monotonic()
    progress = Progress(len(jobs), quiet)
    workers.start(jobs, options)
    try:
        while workers.pending():
            for record in workers.wait(timeout=1.0):
                old = previous.get(record["name"])
                if not record["stages_ran"] and old and old.get("peak_memory_bytes"):
                    # Nothing was recomputed: the memory that made these outputs is the last run's.
                    record["peak_memory_bytes"] = max(record["peak_memory_bytes"], old["peak_memory_bytes"])
                records[record["name"]] = record
                progress.finished(record)
                write_results(out_root, [records[j.name] for j in jobs if j.name in records], options,
                              time.monotonic() - started)
            progress.show(workers.running(), time.monotonic() - started)
    finally:
        workers.close()
        progress.end()
    return [records[j.name] for j in jobs if j.name in records]


class Progress:
    """One line: scenes done, running and failed, and an ETA from the rate scenes have finished at so far."""

    def __init__(self, total: int, quiet: bool):
        self.total, self.quiet = total, quiet
        self.done = self.failed = 0
        self.last = ""
        self.tty = sys.stderr.isatty()

    def finished(self, record: dict) -> None:
        if record["status"] == "done":
            self.done += 1
        else:
            self.failed += 1
        self._clear()
        print(f"[batch] {record['name']}: {describe(record)}", flush=True)
        self.last = ""

    def show(self, running: int, elapsed: float) -> None:
        if self.quiet:
            return
        finished = self.done + self.failed
        counts = f"  batch: {self.done}/{self.total} done, {running} running, {self.failed} failed"
        eta = format_duration(elapsed / finished * (self.total - finished)) if finished else "?"
        if self.tty:
            print(f"\r{counts}, {format_duration(elapsed)} elapsed, ETA {eta}\x1b[K", end="", file=sys.stderr, flush=True)
            self.last = counts
        elif counts != self.last:  # a log gets a line when the counts change, not every second
            print(f"{counts}, {format_duration(elapsed)} elapsed, ETA {eta}", file=sys.stderr, flush=True)
            self.last = counts

    def _clear(self) -> None:
        if self.tty and self.last and not self.quiet:
            print("\r\x1b[K", end="", file=sys.stderr, flush=True)

    def end(self) -> None:
        self._clear()


def describe(record: dict) -> str:
    if record["status"] != "done":
        return f"FAILED: {record['error']}"
    ran = record["stages_ran"]
    what = f"ran {', '.join(ran)}" if ran else "every stage up to date"
    scores = f", PSNR {record['psnr']:.2f} dB" if record["psnr"] is not None else ""
    return f"{what}{scores} in {format_duration(record['wall_seconds'])}"


def write_results(out_root: Path, records: list[dict], options: BatchOptions, seconds: float) -> None:
    write_json(out_root / "batch.json", {"options": asdict(options), "seconds": round(seconds, 2), "scenes": records})
    tmp = out_root / "batch.csv.tmp"
    with open(tmp, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=RECORD_FIELDS, extrasaction="ignore")
        writer.writeheader()
        for record in records:
            writer.writerow({**record, "stages_done": " ".join(record["stages_done"]),
                             "stages_ran": " ".join(record["stages_ran"])})
    os.replace(tmp, out_root / "batch.csv")


def format_table(records: list[dict]) -> str:
    """The batch's results as a text table, then each failure with its reason."""
    header = ("scene", "status", "stages", "photos", "type", "PSNR", "SSIM", "mesh faces", "mesh", "time", "peak mem")
    rows = [header]
    for r in records:
        rows.append((
            r["name"], r["status"], f"{len(r['stages_done'])} ({len(r['stages_ran'])} ran)",
            f"{r['registered']}/{r['images']}" if r["registered"] is not None else "-",
            r["scene_type"] or "-",
            f"{r['psnr']:.2f}" if r["psnr"] is not None else "-",
            f"{r['ssim']:.3f}" if r["ssim"] is not None else "-",
            f"{r['mesh_faces']}" if r["mesh_faces"] is not None else "-",
            format_bytes(r["mesh_bytes"]) if r["mesh_bytes"] is not None else "-",
            format_duration(r["stage_seconds"]),
            f"{r['peak_memory_bytes'] / 2**30:.2f} GiB",
        ))
    widths = [max(len(str(row[i])) for row in rows) for i in range(len(header))]
    lines = ["  ".join(str(v).ljust(w) for v, w in zip(row, widths)).rstrip() for row in rows]
    lines += [f"failed: {r['name']}: {r['error']}" for r in records if r["status"] != "done"]
    return "\n".join(lines)
