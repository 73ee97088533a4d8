"""How much memory this process may use, so a fit never asks for more than is there: a first level whose every vertex
would not fit stops before it starts, and later levels are held to as many voxels as fit (the tighter of this and
fit.voxel_budget).

What a process may use is the least of the machine's memory, what the kernel reports available (MemAvailable: other
jobs' memory is not ours) plus what this process already holds, and the limit of every cgroup it runs in (v2's
memory.max, v1's memory.limit_in_bytes: a container, a Slurm job, a systemd scope) less what the rest of that group
holds (its usage less the page cache the kernel would drop first, inactive_file, as `docker stats` counts it). A
machine's size alone lets a fit plan past what a container allows, and the kernel's OOM killer then ends it with
nothing said."""
from __future__ import annotations

import ctypes
import math
import os
from dataclasses import dataclass
from pathlib import Path

from plenoxels.core.errors import UserError

# The share of usable memory a fit's grid may take at its peak; the rest is the training photos' pixels and rays,
# the per-thread gradient tables (plenoxels/core/optim.py, at most a quarter), the renders and the system.
GRID_MEMORY_SHARE = 0.5
# Copies of a voxel's row a fit holds at its peak, as measured: the parameters, RMSProp's running mean square, the
# gradient tables, and during an upsampling the old grid's rows beside the new grid's with their optimiser state
# (lego at `paper`, 7.47 M voxels at 512^3 at SH degree 2, peaked at 10.0 GiB, about 1.2 kB a voxel past its photos:
# bench/README.md, "The papers' protocol").
ROW_COPIES = 10


@dataclass(frozen=True)
class MemoryLimit:
    bytes: int
    source: str
    """What sets it, for the line that stops a fit: "physical memory", "MemAvailable", "cgroup memory.max"."""


# A cgroup limit at or above this is "no limit" (v1 writes 2^63 rounded down to a page).
NO_LIMIT = 1 << 60


def _read_int(path: Path) -> int | None:
    try:
        text = path.read_text().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def _meminfo(proc: Path, key: str) -> int | None:
    try:
        for line in (proc / "meminfo").read_text().splitlines():
            name, _, value = line.partition(":")
            if name == key:
                return int(value.split()[0]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def _resident(proc: Path) -> int:
    """Bytes this process holds in memory now (its resident set)."""
    try:
        return int((proc / "self" / "statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


def _stat(path: Path, key: str) -> int:
    """A value of a cgroup's memory.stat, 0 if absent."""
    try:
        for line in path.read_text().splitlines():
            name, _, value = line.partition(" ")
            if name == key:
                return int(value)
    except (OSError, ValueError):
        return 0
    return 0


def _cgroup_limits(proc: Path, cgroups: Path) -> list[tuple[int, int, str]]:
    """(limit, usage, which file) of every cgroup this process is in and each of their parents that sets a limit."""
    try:
        lines = (proc / "self" / "cgroup").read_text().splitlines()
    except OSError:
        return []
    found = []
    for line in lines:
        _, controllers, path = line.split(":", 2)
        if controllers == "":  # v2: one unified hierarchy
            base, limit_file, usage_file, cache_key = cgroups, "memory.max", "memory.current", "inactive_file"
        elif "memory" in controllers.split(","):
            base, limit_file, usage_file, cache_key = (cgroups / "memory", "memory.limit_in_bytes",
                                                       "memory.usage_in_bytes", "total_inactive_file")
        else:
            continue
        folder = base / path.lstrip("/")
        while True:
            limit = _read_int(folder / limit_file)
            if limit is not None and limit < NO_LIMIT:
                usage = max((_read_int(folder / usage_file) or 0) - _stat(folder / "memory.stat", cache_key), 0)
                found.append((limit, usage, f"cgroup {limit_file}"))
            if folder == base or base not in folder.parents:
                break
            folder = folder.parent
    return found


def memory_limit(proc: Path = Path("/proc"), cgroups: Path = Path("/sys/fs/cgroup")) -> MemoryLimit:
    """The most memory this process may hold in all, and what sets it (module docstring)."""
    held = _resident(proc)
    candidates = [MemoryLimit(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"), "physical memory")]
    available = _meminfo(proc, "MemAvailable")
    if available is not None:
        candidates.append(MemoryLimit(available + held, "MemAvailable"))
    for limit, usage, which in _cgroup_limits(proc, cgroups):
        candidates.append(MemoryLimit(max(limit - max(usage - held, 0), 0), which))
    return min(candidates, key=lambda c: c.bytes)


def usable_memory() -> int:
    """Bytes this process may hold in all (memory_limit)."""
    return memory_limit().bytes


def resident_memory() -> int:
    """Bytes this process holds now, the libraries' mapped code included: a cgroup charges it too."""
    return _resident(Path("/proc"))


def release_freed() -> None:
    """Hands the heap's freed pages back to the system where the C library can (glibc's malloc_trim): glibc keeps them
    for reuse, a cgroup counts them as this process's, and a phase's large temporaries would otherwise stay charged
    to the phases after it."""
    try:
        ctypes.CDLL(None).malloc_trim(0)
    except (OSError, AttributeError):  # not glibc
        pass


def check_fits(need: int, what: str, advice: str, limit: MemoryLimit | None = None) -> None:
    """Stops with one line when `need` bytes in all (for `what`, in words: the work and what it holds) would not fit in
    what this process may use; `advice`: the settings that make it smaller."""
    limit = memory_limit() if limit is None else limit
    if need > limit.bytes:
        raise UserError(f"{what} needs about {need / 2**30:.1f} GiB, more than the {limit.bytes / 2**30:.1f} GiB this "
                        f"process may use (set by {limit.source}); {advice}, or give the job more memory")


def fit_bytes_per_voxel(sh_degree: int) -> int:
    """A voxel's bytes at a fit's peak: its row of density and SH coefficients (float32) in ROW_COPIES copies, and its
    index entries."""
    return (1 + 3 * (sh_degree + 1) ** 2) * 4 * ROW_COPIES + 8


def voxels_that_fit(sh_degree: int, memory: int | None = None) -> int:
    """The most voxels a fit's grid may hold in `memory` bytes (default: what this process may use)."""
    memory = usable_memory() if memory is None else memory
    return int(GRID_MEMORY_SHARE * memory // fit_bytes_per_voxel(sh_degree))


def check_dense_level(shape: tuple[int, ...], sh_degree: int, memory: int | None = None) -> None:
    """Stops with what to do when a first level of `shape` (every vertex allocated) would not fit in memory."""
    voxels = math.prod(shape)
    limit = voxels_that_fit(sh_degree, memory)
    if voxels > limit:
        source = "the memory given" if memory is not None else memory_limit().source
        memory = usable_memory() if memory is None else memory
        raise UserError(f"a first level of {'x'.join(map(str, shape))} vertices ({voxels / 1e6:.1f} M, every one "
                        f"allocated until the first prune) needs about {voxels * fit_bytes_per_voxel(sh_degree) / 2**30:.1f} "
                        f"GiB, more than the {GRID_MEMORY_SHARE * memory / 2**30:.1f} GiB a grid may take of the "
                        f"{memory / 2**30:.1f} GiB this process may use (set by {source}); "
                        f"start coarser (fit.resolutions beginning at 128, as the presets do) and let later levels grow "
                        f"where the scene is, or give the job more memory")
