"""Kernel benchmark: forward+backward samples per second, native C++ core vs its PyTorch twin.

SH degree 2 at 128^3 (dense, as the coarse stage starts) and 256^3 (the occupied region only, as
after pruning), on a synthetic density field, with random-ray batches (random pixels of random
cameras), the same in the fit's coherent order (sorted random), tile batches (32x32-pixel tiles), and cached random
rays (64 random rays repeated, so their rows stay in cache: what random rays would reach if memory cost nothing).
Samples/s counts the samples that contribute (density above threshold, before early termination); marching empty
space is part of the time.
Both backends run in the same process on the same batches; medians of repeats.

    python bench/kernels.py [--repeats 5] [--rays 8192] [--twin-rays 256] [--sizes 128 256] [--threads 1 2 4 8 16]
        [--out bench/results/kernels.json]

The thread scaling runs every count from 1 to the machine's threads unless --threads names the counts.

Writes bench/results/kernels.json and prints a table.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from plenoxels.core import native, reference  # noqa: E402
from plenoxels.planning.fit_cost import processor_name  # noqa: E402
from plenoxels.core.grid import SparseGrid  # noqa: E402
from plenoxels.core.optim import GridGrad  # noqa: E402
from plenoxels.core.render import RenderOptions  # noqa: E402
from plenoxels.core.render import loss_and_grad, sample_counts  # noqa: E402
from plenoxels.core.ray_set import coherent_order  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "kernels.json"
TILE = 32
# Batches run before the timed ones (caches, the thread pool).
WARMUP = 2
IMAGE = 512
FOCAL = 600.0


def synthetic_field(points: torch.Tensor) -> torch.Tensor:
    """Density of a lumpy object inside [-1, 1]^3: a thick shell plus a few solid blobs."""
    r = points.norm(dim=-1)
    shell = torch.exp(-((r - 0.6) / 0.12) ** 2)
    blobs = torch.zeros_like(r)
    for centre in ((0.3, 0.2, -0.1), (-0.35, -0.2, 0.25), (0.05, -0.4, -0.3)):
        blobs = blobs + torch.exp(-((points - torch.tensor(centre)).norm(dim=-1) / 0.15) ** 2)
    return 12.0 * (shell + blobs) - 2.0


def make_grid(resolution: int, sparse: bool, sh_degree: int = 2, seed: int = 0) -> SparseGrid:
    """The synthetic field on a grid: every vertex (dense) or only those within 2 voxels of positive
    density (sparse, built without ever allocating the dense table)."""
    gen = torch.Generator().manual_seed(seed)
    axis = torch.linspace(-1, 1, resolution)
    density = torch.empty((resolution,) * 3)
    for x in range(resolution):
        yy, zz = torch.meshgrid(axis, axis, indexing="ij")
        density[x] = synthetic_field(torch.stack([torch.full_like(yy, float(axis[x])), yy, zz], dim=-1))
    if sparse:
        keep = density > 0
        for _ in range(2):  # grow by 2 voxels, axis by axis
            for a in range(3):
                src = keep.clone()
                keep.narrow(a, 1, resolution - 1).logical_or_(src.narrow(a, 0, resolution - 1))
                keep.narrow(a, 0, resolution - 1).logical_or_(src.narrow(a, 1, resolution - 1))
    else:
        keep = torch.ones_like(density, dtype=torch.bool)
    links = torch.full((resolution,) * 3, -1, dtype=torch.int32)
    links[keep] = torch.arange(int(keep.sum()), dtype=torch.int32)
    sh = torch.randn(int(keep.sum()), 3 * (sh_degree + 1) ** 2, generator=gen) * 0.3
    return SparseGrid.from_values(links, density[keep], sh, (-1, -1, -1), (1, 1, 1), sh_degree)


def camera(gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """A random camera on a sphere of radius 3 looking at the origin: (centre, 3x3 rotation)."""
    v = torch.randn(3, generator=gen)
    centre = v / v.norm() * 3.0
    back = centre / centre.norm()
    right = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0]), back)
    right = right / right.norm()
    up = torch.linalg.cross(back, right)
    return centre, torch.stack([right, up, back], dim=1)


def pixel_rays(centre, rot, u, v) -> tuple[torch.Tensor, torch.Tensor]:
    d_cam = torch.stack([(u + 0.5 - IMAGE / 2) / FOCAL, -(v + 0.5 - IMAGE / 2) / FOCAL, -torch.ones_like(u)], dim=1)
    dirs = d_cam @ rot.T
    return centre.expand_as(dirs).contiguous(), dirs.contiguous()


def random_batch(n: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Each ray from its own random camera through a random pixel."""
    origins, dirs = [], []
    for _ in range(n // 64):  # 64 cameras' worth per call keeps set-up cheap, rays are still shuffled
        centre, rot = camera(gen)
        u = torch.randint(0, IMAGE, (64,), generator=gen).float()
        v = torch.randint(0, IMAGE, (64,), generator=gen).float()
        o, d = pixel_rays(centre, rot, u, v)
        origins.append(o)
        dirs.append(d)
    origins, dirs = torch.cat(origins), torch.cat(dirs)
    perm = torch.randperm(origins.shape[0], generator=gen)
    return origins[perm].contiguous(), dirs[perm].contiguous()


def sorted_batch(n: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """random_batch's rays in the fit's coherent order (plenoxels.core.train.coherent_order)."""
    origins, dirs = random_batch(n, gen)
    order = coherent_order(origins, dirs)
    return origins[order].contiguous(), dirs[order].contiguous()


def cached_batch(n: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """64 random rays repeated to n: random rays' mix of misses, hits and samples per ray, with every row they touch
    in cache after its first use."""
    origins, dirs = (t[:64] for t in random_batch(max(n, 64), gen))  # rays of many cameras, as random_batch's
    repeats = max(1, n // 64)
    return origins.repeat(repeats, 1).contiguous(), dirs.repeat(repeats, 1).contiguous()


def tile_batch(n: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """32x32-pixel tiles of random cameras, tiles kept contiguous; tiles overlap the object."""
    origins, dirs = [], []
    jj, ii = torch.meshgrid(torch.arange(TILE), torch.arange(TILE), indexing="ij")
    for _ in range(max(1, n // (TILE * TILE))):
        centre, rot = camera(gen)
        u0, v0 = torch.randint(IMAGE // 4, 3 * IMAGE // 4 - TILE, (2,), generator=gen).tolist()
        o, d = pixel_rays(centre, rot, (ii.reshape(-1) + u0).float(), (jj.reshape(-1) + v0).float())
        origins.append(o)
        dirs.append(d)
    return torch.cat(origins).contiguous(), torch.cat(dirs).contiguous()


def time_backend(grid, batches, backend: str, opts: RenderOptions) -> tuple[list[float], list[float]]:
    """Wall-clock and process CPU seconds of each batch's loss_and_grad: the product's native core or the twin's."""
    step = loss_and_grad if backend == "native" else reference.loss_and_grad
    grad = GridGrad(grid)
    if backend == "native":
        # Map the per-thread tables' pages before timing: on this virtual machine a page's first touch costs about
        # 1.7 ms per 2 MiB, which a fit pays once per level and random batches would otherwise pay over the first few.
        for table in grad.scratch():
            table.zero_()
    wall, cpu = [], []
    for origins, dirs, targets, background in batches:
        start, start_cpu = time.perf_counter(), time.process_time()
        step(grid, origins, dirs, targets, background, opts, grad)
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
        grad.clear()
    return wall, cpu


def thread_scaling(grid, make, seed: int, repeats: int, rays: int, opts: RenderOptions,
                   thread_counts: list[int]) -> dict:
    """Native samples/s at each of `thread_counts` (the same batches for each count), and each count's speed-up over
    the first count's."""
    most = torch.get_num_threads()
    gen = torch.Generator().manual_seed(seed + 1)
    batches = []
    for _ in range(repeats + WARMUP):
        origins, dirs = make(rays, gen)
        batches.append((origins, dirs, torch.rand(origins.shape[0], 3, generator=gen), torch.ones(origins.shape[0], 3)))
    counts = [sample_counts(grid, b[0], b[1], opts)[1] for b in batches[WARMUP:]]
    by_threads = {}
    try:
        for threads in thread_counts:
            torch.set_num_threads(threads)  # also the native core's OpenMP team
            wall, _ = time_backend(grid, batches, "native", opts)
            by_threads[threads] = statistics.median(c / t for c, t in zip(counts, wall[WARMUP:]))
    finally:
        torch.set_num_threads(most)
    first = by_threads[thread_counts[0]]
    return {str(t): {"samples_per_s": v, "speedup": v / first} for t, v in by_threads.items()}


def run(sizes, repeats: int, rays: int, twin_rays: int, thread_counts: list[int]) -> dict:
    opts = RenderOptions(step_size=0.5)
    rows = []
    for size in sizes:
        sparse = size > 128
        t0 = time.perf_counter()
        grid = make_grid(size, sparse)
        grid.occupancy()
        build_s = time.perf_counter() - t0
        for kind, make in (("random", random_batch), ("sorted random", sorted_batch), ("tiles", tile_batch),
                           ("cached random", cached_batch)):
            gen = torch.Generator().manual_seed(size)
            result = {"resolution": size, "grid": "occupied region" if sparse else "dense", "batch": kind,
                      "occupied_vertices": grid.num_occupied, "grid_mb": round(grid.memory_bytes() / 2**20, 1),
                      "grid_build_s": round(build_s, 2)}
            for backend, n in (("native", rays), ("torch", twin_rays)):
                batches = []
                for _ in range(repeats + WARMUP):
                    origins, dirs = make(n, gen)
                    targets = torch.rand(origins.shape[0], 3, generator=gen)
                    batches.append((origins, dirs, targets, torch.ones(origins.shape[0], 3)))
                wall, cpu = time_backend(grid, batches, backend, opts)
                wall, cpu = wall[WARMUP:], cpu[WARMUP:]
                counts = [sample_counts(grid, b[0], b[1], opts) for b in batches[WARMUP:]]
                threads = native.num_threads() if backend == "native" else torch.get_num_threads()
                result[backend] = {
                    "rays_per_batch": batches[WARMUP][0].shape[0],
                    "samples_per_batch": int(statistics.median(c[1] for c in counts)),
                    "lattice_samples_per_batch": int(statistics.median(c[0] for c in counts)),
                    "seconds_per_batch": statistics.median(wall),
                    "samples_per_s": statistics.median(c[1] / t for c, t in zip(counts, wall)),
                    # What the threads would do with the cores to themselves: samples per CPU-second
                    # times the thread count (the machine is shared; wall time includes waiting).
                    "samples_per_s_cpu_time_based": statistics.median(threads * c[1] / t for c, t in zip(counts, cpu)),
                }
            result["speedup"] = result["native"]["samples_per_s"] / result["torch"]["samples_per_s"]
            result["native_by_threads"] = thread_scaling(grid, make, size, repeats, rays, opts, thread_counts)
            rows.append(result)
            print_row(result)
        del grid
    return {
        "what": "forward+backward (fused MSE loss and gradient), SH degree 2, step 0.5 voxel; samples/s counts "
                "contributing samples; median over repeats",
        "machine": {"cpu": processor_name(), "threads": native.num_threads(), "torch": torch.__version__,
                    "load_average_at_end": os.getloadavg()[0]},
        "repeats": repeats,
        "results": rows,
    }


def print_row(r: dict) -> None:
    if print_row.first:
        print(f"{'grid':>18} {'batch':>13} {'native M/s':>11} {'(cpu-time)':>10} {'twin M/s':>9} {'ratio':>6} "
              f"{'samples/ray':>11}")
        print_row.first = False
    n, t = r["native"], r["torch"]
    spr = n["samples_per_batch"] / n["rays_per_batch"]
    print(f"{r['resolution']:>4}^3 {r['grid']:>13} {r['batch']:>13} {n['samples_per_s'] / 1e6:>11.2f} "
          f"{n['samples_per_s_cpu_time_based'] / 1e6:>10.2f} {t['samples_per_s'] / 1e6:>9.3f} {r['speedup']:>6.0f} "
          f"{spr:>11.1f}  threads: " + ", ".join(f"{t}: {v['samples_per_s'] / 1e6:.2f} ({v['speedup']:.2f}x)"
                                              for t, v in r["native_by_threads"].items()), flush=True)


print_row.first = True


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--rays", type=int, default=8192, help="rays per native batch")
    parser.add_argument("--twin-rays", type=int, default=256, help="rays per PyTorch-twin batch")
    parser.add_argument("--threads", type=int, nargs="+", default=None,
                        help="thread counts of the scaling columns (default: 1 up to the machine's threads)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    if math.prod(args.sizes) <= 0 or args.repeats < 1 or min(args.threads or [1]) < 1:
        parser.error("sizes, repeats and thread counts must be positive")
    os.environ.setdefault("OMP_NUM_THREADS", str(os.cpu_count()))
    thread_counts = sorted(set(args.threads or range(1, torch.get_num_threads() + 1)))
    report = run(args.sizes, args.repeats, args.rays, args.twin_rays, thread_counts)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
