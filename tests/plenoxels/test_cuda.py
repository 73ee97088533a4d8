"""The CUDA core: compiles wherever nvcc exists, and on a GPU matches the CPU core.

Three kinds of test:
- compile-only (any machine with nvcc, CI included): every csrc/*.cu builds for sm_90 with warnings
  as errors, and the torch glue of the CUDA build passes a syntax check against this torch's headers;
- device choice (everywhere): fit.device=cuda without a GPU and CUDA build is a one-line UserError;
- parity (a machine with an NVIDIA GPU and a CUDA build of plenoxels._C): each operator of
  torch.ops.voxfield gives on CUDA tensors the values and gradients it gives on CPU tensors, including
  the numerical extremes.
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest
import torch
import torch.utils.cpp_extension

from plenoxels.core import native
from plenoxels.core.background import BackgroundOptimiser, MultiSphereBackground
from plenoxels.core.errors import UserError
from plenoxels.core.grid import SparseGrid
from plenoxels.core.native import CUDA_MISSING, cuda_ready, resolve_device
from plenoxels.core.optim import GridGrad, SparseRMSProp
from plenoxels.core.regularizers import tv_loss_and_grad
from plenoxels.core.render import RenderOptions, loss_and_grad, max_weights, render

REPO = Path(__file__).resolve().parents[2]
CSRC = REPO / "csrc"
NVCC = shutil.which("nvcc")
needs_nvcc = pytest.mark.skipif(NVCC is None, reason="compile-only check needs nvcc (the CUDA toolkit) on PATH")
needs_gpu = pytest.mark.skipif(not cuda_ready(), reason="needs an NVIDIA GPU and a CUDA build")


# ---- compile-only -------------------------------------------------------------------------------
@needs_nvcc
@pytest.mark.parametrize("source", sorted(p.name for p in CSRC.glob("*.cu")))
def test_cuda_source_compiles(source, tmp_path):
    cmd = [NVCC, "-c", "-std=c++20", "-O3", f"-I{CSRC}", "-gencode=arch=compute_90,code=sm_90",
           "-Xcompiler", "-Wall,-Wextra", "--Werror", "all-warnings",
           str(CSRC / source), "-o", str(tmp_path / "kernels.o")]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "kernels.o").stat().st_size > 0


def test_cuda_sources_exist_for_every_launcher():
    """Each launcher declared for the glue is defined in a .cu file."""
    header = (CSRC / "cuda_kernels.h").read_text()
    sources = "".join(p.read_text() for p in CSRC.glob("*.cu"))
    declared = [line.split("(")[0].split()[-1] for line in header.splitlines() if line.startswith("cudaError_t ")]
    assert declared, "no launchers found in cuda_kernels.h"
    for name in declared:
        assert f"cudaError_t {name}(" in sources, f"launcher {name} is declared but not defined"


def _cuda_include_dir() -> Path:
    """The toolkit's include folder; nvcc on PATH may be a wrapper script outside the toolkit."""
    homes = [os.environ.get("CUDA_HOME"), os.environ.get("CUDA_PATH"), torch.utils.cpp_extension.CUDA_HOME,
             str(Path(NVCC).resolve().parent.parent), "/usr/local/cuda"]
    for home in filter(None, homes):
        if (Path(home) / "include" / "cuda_runtime.h").is_file():
            return Path(home) / "include"
    result = subprocess.run([NVCC, "--dryrun", "-c", "-x", "cu", "/dev/null"], capture_output=True, text=True)
    for token in (t.strip('"') for t in result.stderr.split()):
        if token.startswith("-I") and (Path(token[2:]) / "cuda_runtime.h").is_file():
            return Path(token[2:])
    pytest.fail(f"nvcc is at {NVCC} but no CUDA include folder with cuda_runtime.h was found; set CUDA_HOME")


@needs_nvcc
def test_cuda_glue_syntax(tmp_path):
    """bindings_cuda.cpp against this torch's headers with PLX_WITH_CUDA defined, as the CUDA build sees it."""
    include = Path(torch.utils.cpp_extension.include_paths()[0])
    cuda_include = _cuda_include_dir()
    # CPU wheels of torch ship the c10/cuda headers but not this generated one; an empty stand-in
    # is enough for a syntax check.
    if not (include / "c10/cuda/impl/cuda_cmake_macros.h").exists():
        stub = tmp_path / "c10/cuda/impl"
        stub.mkdir(parents=True)
        (stub / "cuda_cmake_macros.h").write_text("#pragma once\n")
    cxx = os.environ.get("CXX", "g++")
    cmd = [cxx, "-std=c++20", "-fsyntax-only", "-DPLX_WITH_CUDA", f"-I{CSRC}", f"-I{tmp_path}",
           "-isystem", str(include), "-isystem", str(include / "torch/csrc/api/include"),
           "-isystem", str(cuda_include), "-Wall", "-Wextra", "-Werror", str(CSRC / "bindings_cuda.cpp")]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-4000:]


# Operators with one kernel for every device, and the CPU-only ones: one advises host memory; the grid's loss that draws
# the background spheres in its own pass (a GPU draws them all beforehand); a batch's rays (a GPU makes them with torch's
# operators on the ray set's tables); the splats are distilled and scored on the CPU (their compositing and row Adam).
DEVICE_FREE_OPS = {"padded_stride", "num_threads"}
CPU_ONLY_OPS = {"advise_huge_pages", "loss_and_grad_spheres", "pixel_rays", "splat_composite",
                "splat_composite_backward", "adam_rows"}


def _declared_ops() -> set[str]:
    return set(re.findall(r'm\.def\("(\w+)\(', (CSRC / "ops.cpp").read_text()))


def test_every_op_has_a_cpu_and_a_cuda_implementation():
    """One schema (csrc/ops.cpp) for every operator; the CPU build registers each device-bound one and the
    CUDA glue registers the same set (checked in its source, as this build may be CPU-only)."""
    declared = _declared_ops()
    assert {"render", "loss_and_grad", "sample", "rmsprop_step", "tv_loss_and_grad"} <= declared
    device_bound = declared - DEVICE_FREE_OPS
    for name in sorted(device_bound):
        assert torch._C._dispatch_has_kernel_for_dispatch_key(f"voxfield::{name}", "CPU"), f"{name}: no CPU kernel"
    # Both backends register the list in ops.h (the CPU's through the build above, the CUDA glue by its source).
    listed = set(re.findall(r'^ +PLX_IMPL\(library, (\w+)\)', (CSRC / "ops.h").read_text(), re.M))
    assert listed == device_bound - CPU_ONLY_OPS
    assert "PLX_IMPL_DEVICE_OPS(m);" in (CSRC / "bindings_cuda.cpp").read_text()
    for name in sorted(DEVICE_FREE_OPS):
        getattr(native.ops, name)  # resolvable with no tensor to dispatch on
    assert [native.row_stride(d) for d in range(4)] == [4, 16, 32, 64]


# ---- device choice ------------------------------------------------------------------------------
def test_resolve_device_cpu_and_auto():
    assert resolve_device("cpu") == torch.device("cpu")
    expected = "cuda" if cuda_ready() else "cpu"
    assert resolve_device("auto").type == expected


def test_resolve_device_cuda():
    if cuda_ready():
        assert resolve_device("cuda").type == "cuda"
    else:
        with pytest.raises(UserError) as info:
            resolve_device("cuda")
        assert str(info.value) == CUDA_MISSING
        assert "\n" not in str(info.value)


def test_resolve_device_rejects_unknown_value():
    with pytest.raises(UserError, match="fit.device must be one of auto, cpu, cuda"):
        resolve_device("gpu")


# ---- parity with the CPU core (GPU only) --------------------------------------------------------
BLOCK = 4
BMIN = [-1.2, -1.0, -0.9]
BMAX = [1.0, 1.1, 0.8]
MARCH = dict(step=0.5, stop_transmittance=1e-4, near=0.0, sigma_threshold=0.0, max_samples=4096)


def _native():
    """The operators twice, for readability at the call sites: the device comes from the tensors."""
    return native.ops, native.ops


def _grid(degree, res=(13, 11, 12), fill=0.6, seed=0, density_scale=4.0):
    """A random sparse grid: links with about `fill` of the vertices allocated, random values."""
    gen = torch.Generator().manual_seed(seed)
    alive = torch.rand(res, generator=gen) < fill
    links = torch.full(res, -1, dtype=torch.int32)
    n = int(alive.sum())
    links[alive] = torch.randperm(n, generator=gen).to(torch.int32)
    columns = 1 + 3 * (degree + 1) ** 2
    stride = native.row_stride(degree)
    data = torch.zeros(n, stride)
    data[:, 0] = (torch.rand(n, generator=gen) - 0.3) * density_scale
    data[:, 1:columns] = torch.randn(n, columns - 1, generator=gen) * 0.4
    return links, data


def _rays(count, seed=1):
    """Rays from a sphere around the box towards random points in and around it."""
    gen = torch.Generator().manual_seed(seed)
    origins = torch.nn.functional.normalize(torch.randn(count, 3, generator=gen), dim=1) * 3.0
    aims = (torch.rand(count, 3, generator=gen) - 0.5) * 2.4
    dirs = (aims - origins) * (0.5 + torch.rand(count, 1, generator=gen))  # lengths need not be 1
    return origins.contiguous(), dirs.contiguous()


def _special_rays():
    """Misses, grazing rays along faces and edges, axis-aligned rays, origins inside the box."""
    o = [[5.0, 5.0, 5.0], [-3.0, -1.0, 0.0], [-3.0, 0.2, 0.8], [-1.2, -3.0, -0.9], [0.0, 0.0, 0.0],
         [0.3, -0.2, 0.1], [-1.19, 1.09, 0.79], [0.0, 0.0, -3.0], [1.0, 1.1, 0.8]]
    d = [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.3, -0.5, 0.8],
         [-1.0, 0.0, 0.0], [1.0, -1.0, -1.0], [0.0, 0.0, 1.0], [-1.0, -1.0, -1.0]]
    return torch.tensor(o), torch.tensor(d)


def _lattice(links, box=(BMIN, BMAX), knots=None) -> list[float]:
    """The map to grid coordinates as the operators take it: per axis [k, k positions, k grid coordinates] (grid.py's
    knots: per axis (position, share of the lattice))."""
    flat = []
    for a, r in enumerate(links.shape):
        inner = knots[a] if knots else ()
        xs = [box[0][a]] + [x for x, _ in inner] + [box[1][a]]
        gs = [0.0] + [f * (r - 1) for _, f in inner] + [float(r - 1)]
        flat += [float(len(xs))] + xs + gs
    return flat


def _cuda(values):
    return [v.cuda() if isinstance(v, torch.Tensor) else v for v in values]


def _march_args(march):
    return [march["step"], march["stop_transmittance"], march["near"], march["sigma_threshold"], march["max_samples"],
            march.get("contract", False)]


def _close(gpu, cpu, rtol=1e-4, atol=1e-5):
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=rtol, atol=atol)


def _render_both(links, data, degree, origins, dirs, background, march=MARCH, box=(BMIN, BMAX), knots=None,
                 past_grid_only=False):
    C, G = _native()
    cells, blocks = C.build_occupancy(links, BLOCK)
    args = [data, links, cells, blocks, BLOCK, _lattice(links, box, knots), degree, origins, dirs, background,
            past_grid_only, *_march_args(march)]
    return C.render(*args), G.render(*_cuda(args))


def _loss_grad_both(links, data, degree, origins, dirs, targets, background, march=MARCH, box=(BMIN, BMAX),
                    knots=None, near_gradient=0.0, past_grid_only=False):
    C, G = _native()
    cells, blocks = C.build_occupancy(links, BLOCK)
    n, stride = data.shape
    grads = {}
    for name, core, move in (("cpu", C, lambda v: v), ("cuda", G, _cuda)):
        grad = torch.zeros(n, stride)
        mask = torch.zeros(n, dtype=torch.uint8)
        rows = torch.zeros(n, dtype=torch.int32)
        args = [data, links, cells, blocks, BLOCK, _lattice(links, box, knots), degree, origins, dirs, targets, background,
                past_grid_only, *_march_args(march), near_gradient, grad, mask, rows, 0]
        moved = move(args)
        grad_out, mask_out, rows_out = moved[-4:-1]  # counted from the end: the march's arguments vary
        sse, grad_background, count = core.loss_and_grad(*moved, *native.ops.grad_scratch(grad_out, 64))
        grads[name] = (sse, grad_background.cpu(), grad_out.cpu(), mask_out.cpu(),
                       set(rows_out[:count].cpu().tolist()))
    return grads["cpu"], grads["cuda"]


@needs_gpu
def test_occupancy_and_row_coords_match():
    C, G = _native()
    links, _ = _grid(1, fill=0.05)
    for got, want in zip(G.build_occupancy(links.cuda(), BLOCK), C.build_occupancy(links, BLOCK)):
        assert torch.equal(got.cpu(), want)
    n = int((links >= 0).sum())
    assert torch.equal(G.row_coords(links.cuda(), n).cpu(), C.row_coords(links, n))


@needs_gpu
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_render_matches_cpu(degree):
    links, data = _grid(degree)
    origins, dirs = _rays(3000)
    background = torch.rand(origins.shape[0], 3)
    cpu, gpu = _render_both(links, data, degree, origins, dirs, background)
    for g, c in zip(gpu, cpu):
        _close(g, c)
    assert (cpu[2] > 0.5).any() and (cpu[2] < 0.5).any(), "the scene should give opaque and clear rays"


@needs_gpu
@pytest.mark.parametrize("knots", [None, (((-1.0, 0.1), (1.0, 0.9)), ((-0.4, 0.35),), ((1.5, 0.8),))],
                         ids=["one cell size", "knots"])
def test_contracted_grid_renders_and_differentiates_as_on_cpu(knots):
    """Bent rays through a contracted grid (unbounded scenes): from inside the inner cube, from the shell and from far
    away, on both devices; with one cell size, and with knots (a coarser shell)."""
    links, data = _grid(1, res=(17, 17, 17), density_scale=1.5)
    gen = torch.Generator().manual_seed(8)
    origins = torch.cat([torch.randn(1500, 3, generator=gen) * 2.0, torch.randn(500, 3, generator=gen) * 40.0])
    dirs = torch.randn(2000, 3, generator=gen)
    background, targets = torch.rand(2000, 3, generator=gen), torch.rand(2000, 3, generator=gen)
    march, box = {**MARCH, "contract": True}, ([-2.0] * 3, [2.0] * 3)
    cpu, gpu = _render_both(links, data, 1, origins, dirs, background, march, box, knots)
    for g, c in zip(gpu, cpu):
        _close(g, c)
    assert (cpu[2] > 0.5).any() and (cpu[2] < 0.5).any()
    cpu, gpu = _loss_grad_both(links, data, 1, origins, dirs, targets, background, march, box, knots)
    assert gpu[0] == pytest.approx(cpu[0], rel=1e-5)
    scale = float(cpu[2].abs().max())
    _close(gpu[2], cpu[2], rtol=1e-3, atol=1e-5 * scale)
    assert gpu[4] == cpu[4] and len(cpu[4]) > 0


@needs_gpu
def test_grid_with_knots_renders_counts_and_differentiates_as_on_cpu():
    """Rays cut into pieces at knot planes (cells fine in the middle of the box, coarse around it) meet the same
    samples on both devices."""
    knots = (((-0.5, 0.2), (0.4, 0.8)), ((0.0, 0.6),), ((-0.4, 0.1), (0.3, 0.9)))
    links, data = _grid(2, density_scale=1.5)
    origins, dirs = _all_rays()
    gen = torch.Generator().manual_seed(5)
    background, targets = torch.rand(origins.shape[0], 3, generator=gen), torch.rand(origins.shape[0], 3, generator=gen)
    cpu, gpu = _render_both(links, data, 2, origins, dirs, background, knots=knots)
    for g, c in zip(gpu, cpu):
        _close(g, c)
    cpu, gpu = _loss_grad_both(links, data, 2, origins, dirs, targets, background, knots=knots)
    assert gpu[0] == pytest.approx(cpu[0], rel=1e-5)
    scale = float(cpu[2].abs().max())
    _close(gpu[2], cpu[2], rtol=1e-3, atol=1e-5 * scale)
    assert gpu[4] == cpu[4] and len(cpu[4]) > 0
    C, G = _native()
    cells, blocks = C.build_occupancy(links, BLOCK)
    args = [data, links, cells, blocks, BLOCK, _lattice(links, knots=knots), 2, origins, dirs, *_march_args(MARCH)]
    assert G.sample_counts(*_cuda(args))[0] == C.sample_counts(*args)[0]


@needs_gpu
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_loss_and_grad_match_cpu(degree):
    links, data = _grid(degree, density_scale=1.5)
    origins, dirs = _rays(2000, seed=degree + 3)
    targets = torch.rand(origins.shape[0], 3)
    targets = torch.where(torch.rand(origins.shape[0], 3) < 0.3, -targets, targets)  # a share of floors
    background = torch.rand(origins.shape[0], 3)
    cpu, gpu = _loss_grad_both(links, data, degree, origins, dirs, targets, background)
    assert gpu[0] == pytest.approx(cpu[0], rel=1e-5)
    _close(gpu[1], cpu[1])
    scale = float(cpu[2].abs().max())
    assert scale > 0
    _close(gpu[2], cpu[2], rtol=1e-3, atol=1e-5 * scale)
    assert torch.equal(gpu[3], cpu[3])
    assert gpu[4] == cpu[4] and len(cpu[4]) > 0


@needs_gpu
def test_a_background_past_the_grid_only_matches_cpu():
    """The spheres' rule (none behind a stopped ray, the ramp above the stop) in the render and the loss, on a march
    that stops many rays."""
    links, data = _grid(2, density_scale=16.0)  # dense enough to stop about half the rays, a tenth in the ramp
    origins, dirs = _rays(2000, seed=11)
    targets, background = torch.rand(origins.shape[0], 3), torch.rand(origins.shape[0], 3)
    march = {**MARCH, "stop_transmittance": 0.05}
    cpu, gpu = _render_both(links, data, 2, origins, dirs, background, march, past_grid_only=True)
    for g, c in zip(gpu, cpu):
        _close(g, c)
    everywhere, _ = _render_both(links, data, 2, origins, dirs, background, march)
    stopped = 1 - cpu[2] < 0.05
    ramp = ~stopped & (1 - cpu[2] < 0.1)
    assert bool(stopped.any()) and bool(ramp.any())
    assert bool((everywhere[0][stopped] > cpu[0][stopped]).any())
    cpu, gpu = _loss_grad_both(links, data, 2, origins, dirs, targets, background, march, past_grid_only=True)
    assert gpu[0] == pytest.approx(cpu[0], rel=1e-5)
    _close(gpu[1], cpu[1])
    assert not bool(cpu[1][stopped].any())
    scale = float(cpu[2].abs().max())
    _close(gpu[2], cpu[2], rtol=1e-3, atol=1e-5 * scale)
    assert gpu[4] == cpu[4] and len(cpu[4]) > 0


@needs_gpu
def test_near_gradient_scaling_matches_cpu():
    links, data = _grid(2, density_scale=1.5)
    origins, dirs = _rays(2000, seed=7)
    targets, background = torch.rand(origins.shape[0], 3), torch.rand(origins.shape[0], 3)
    whole, _ = _loss_grad_both(links, data, 2, origins, dirs, targets, background)
    cpu, gpu = _loss_grad_both(links, data, 2, origins, dirs, targets, background, near_gradient=3.5)
    scale = float(cpu[2].abs().max())
    _close(gpu[2], cpu[2], rtol=1e-3, atol=1e-5 * scale)
    assert gpu[4] == cpu[4] and len(cpu[4]) > 0
    assert float(cpu[2].abs().sum()) < float(whole[2].abs().sum())  # it scaled something


@needs_gpu
def test_max_weights_match_cpu():
    C, G = _native()
    links, data = _grid(2)
    origins, dirs = _rays(3000)
    cells, blocks = C.build_occupancy(links, BLOCK)
    args = [data, links, cells, blocks, BLOCK, _lattice(links), 2, origins, dirs, *_march_args(MARCH)]
    cpu, gpu = torch.zeros(data.shape[0]), torch.zeros(data.shape[0], device="cuda")
    C.max_weights(*args, cpu)
    G.max_weights(*_cuda(args), gpu)
    assert cpu.max() > 0.1
    _close(gpu, cpu)


@needs_gpu
@pytest.mark.parametrize("weights", [(1e-3, 1e-4), (0.0, 1e-2), (5e-2, 0.0)])
def test_tv_matches_cpu(weights):
    C, G = _native()
    degree = 2
    links, data = _grid(degree, fill=0.7)
    n, stride = data.shape
    coords = C.row_coords(links, n)
    sample_rows = torch.randint(0, n, (n // 2,), generator=torch.Generator().manual_seed(5))
    out = {}
    for name, core in (("cpu", C), ("cuda", G)):
        grad = torch.zeros(n, stride)
        mask = torch.zeros(n, dtype=torch.uint8)
        rows = torch.zeros(n, dtype=torch.int32)
        args = [data, links, coords, sample_rows, *weights, degree, grad, mask, rows, 0]
        if name == "cpu":
            loss, count = C.tv_loss_and_grad(*args, *native.ops.grad_scratch(grad, 64))
        else:
            args = _cuda(args)
            loss, count = G.tv_loss_and_grad(*args, *native.ops.grad_scratch(args[7], 64))
            grad, mask, rows = args[7], args[8], args[9]
        out[name] = (loss, grad.cpu(), mask.cpu(), set(rows[:count].cpu().tolist()))
    assert out["cpu"][0] > 0
    assert out["cuda"][0] == pytest.approx(out["cpu"][0], rel=1e-5)
    scale = float(out["cpu"][1].abs().max())
    _close(out["cuda"][1], out["cpu"][1], rtol=1e-3, atol=1e-5 * scale)
    assert torch.equal(out["cuda"][2], out["cpu"][2])
    assert out["cuda"][3] == out["cpu"][3]


@needs_gpu
def test_rmsprop_matches_cpu():
    C, G = _native()
    gen = torch.Generator().manual_seed(7)
    n, stride, columns = 500, 16, 13
    data = torch.randn(n, stride, generator=gen)
    second = torch.rand(n, stride, generator=gen)
    touched = torch.randperm(n, generator=gen)[:200].to(torch.int32)
    grad = torch.zeros(n, stride)
    grad[touched.long(), :columns] = torch.randn(200, columns, generator=gen)
    mask = torch.zeros(n, dtype=torch.uint8)
    mask[touched.long()] = 1
    rows = torch.zeros(n, dtype=torch.int32)
    rows[:200] = touched
    results = {}
    for name, core in (("cpu", C), ("cuda", G)):
        tensors = [t.clone() for t in (data, second, grad, mask, rows)]
        if name == "cuda":
            tensors = _cuda(tensors)
        core.rmsprop_step(*tensors, 200, columns, 0.5, 0.01, 0.9, 1e-8, None, BLOCK, None, None)
        results[name] = [t.cpu() for t in tensors]
    for got, want in zip(results["cuda"][:4], results["cpu"][:4]):
        _close(got, want, rtol=1e-5, atol=1e-6)
    assert not torch.equal(results["cpu"][0], data), "the step should move the touched rows"
    assert int(results["cuda"][3].sum()) == 0 and float(results["cuda"][2].abs().sum()) == 0.0


@needs_gpu
def test_sample_matches_cpu():
    links, data = _grid(3)
    points = (torch.rand(5000, 3, generator=torch.Generator().manual_seed(2)) * 1.2 - 0.1) * torch.tensor(
        [s - 1.0 for s in links.shape])  # a tenth outside the box on each side
    cpu = native.ops.sample(data, links, points)
    gpu = native.ops.sample(data.cuda(), links.cuda(), points.cuda())
    assert bool((cpu == 0).all(dim=1).any()) and bool((cpu != 0).any(dim=1).any())
    _close(gpu, cpu, rtol=1e-6, atol=1e-6)
    grid = SparseGrid(links, data, BMIN, BMAX, 3)
    world = torch.rand(3000, 3, generator=torch.Generator().manual_seed(3)) * 3 - 1.5
    for got, want in zip(grid.to("cuda").sample(world.cuda()), grid.sample(world)):
        _close(got, want, rtol=1e-6, atol=1e-6)


@needs_gpu
def test_sample_counts_match_cpu():
    C, G = _native()
    links, data = _grid(1)
    origins, dirs = _all_rays()
    cells, blocks = C.build_occupancy(links, BLOCK)
    args = [data, links, cells, blocks, BLOCK, _lattice(links), 1, origins, dirs, *_march_args(MARCH)]
    cpu = C.sample_counts(*args)
    gpu = G.sample_counts(*_cuda(args))
    assert cpu[0] > cpu[1] > 0
    assert gpu[0] == cpu[0]
    assert gpu[1] == pytest.approx(cpu[1], rel=1e-4)


def _live_state(links, data, block):
    coords = native.ops.row_coords(links, data.shape[0])
    shape = [-(-(r - 1) // block) for r in links.shape]
    return coords, torch.zeros(shape, dtype=torch.int32), torch.zeros(shape, dtype=torch.uint8)


@needs_gpu
def test_live_blocks_match_cpu_and_follow_rmsprop():
    C, G = _native()
    links, data = _grid(1, fill=0.3, res=(21, 17, 19))
    coords, counts, flags = _live_state(links, data, BLOCK)
    data[coords[:, 0] < 10, 0] = -1.0  # no live vertex in the first blocks along x
    C.count_live_blocks(data, coords, BLOCK, counts, flags)
    gpu_args = _cuda([data, coords, BLOCK, counts.clone(), flags.clone()])
    G.count_live_blocks(*gpu_args)
    assert torch.equal(gpu_args[3].cpu(), counts) and torch.equal(gpu_args[4].cpu(), flags)
    assert 0 < int(flags.sum()) < flags.numel()
    # A step that flips the sign of many densities keeps counts and flags in step on both devices.
    n, stride = data.shape
    gen = torch.Generator().manual_seed(3)
    grad = torch.zeros(n, stride)
    grad[:, 0] = torch.randn(n, generator=gen) * 10
    rows = torch.randperm(n, generator=gen).to(torch.int32)
    mask = torch.ones(n, dtype=torch.uint8)
    state = {}
    for name in ("cpu", "cuda"):
        tensors = [data.clone(), torch.zeros(n, stride), grad.clone(), mask.clone(), rows.clone()]
        live = [coords, counts.clone(), flags.clone()]
        if name == "cuda":
            tensors, live = _cuda(tensors), _cuda(live)
        native.ops.rmsprop_step(*tensors, n, 4, 2.0, 0.01, 0.9, 1e-8, live[0], BLOCK, live[1], live[2])
        state[name] = [t.cpu() for t in (tensors[0], live[1], live[2])]
    _close(state["cuda"][0], state["cpu"][0], rtol=1e-5, atol=1e-6)
    assert not torch.equal(state["cpu"][1], counts), "the step should change some counts"
    assert torch.equal(state["cuda"][1], state["cpu"][1]) and torch.equal(state["cuda"][2], state["cpu"][2])
    recount = _live_state(links, state["cpu"][0], BLOCK)
    C.count_live_blocks(state["cpu"][0], *recount[:1], BLOCK, *recount[1:])
    assert torch.equal(state["cuda"][1], recount[1]) and torch.equal(state["cuda"][2], recount[2])


# ---- numerical extremes on CUDA -----------------------------------------------------------------
def _all_rays():
    origins, dirs = _rays(500, seed=11)
    special_o, special_d = _special_rays()
    return torch.cat([origins, special_o]), torch.cat([dirs, special_d])


@needs_gpu
@pytest.mark.parametrize("density", [0.0, 1e6])
def test_extreme_density(density):
    degree = 1
    links, data = _grid(degree)
    data[:, 0] = density
    origins, dirs = _all_rays()
    background = torch.rand(origins.shape[0], 3)
    targets = torch.rand(origins.shape[0], 3)
    cpu, gpu = _render_both(links, data, degree, origins, dirs, background)
    for g, c in zip(gpu, cpu):
        assert torch.isfinite(g).all()
        _close(g, c)
    if density == 0.0:
        _close(gpu[0], background)
    else:
        assert (gpu[2] == 1.0).any(), "infinite-ish density must make some rays fully opaque"
    cpu_grads, gpu_grads = _loss_grad_both(links, data, degree, origins, dirs, targets, background)
    assert torch.isfinite(gpu_grads[2]).all()
    scale = max(float(cpu_grads[2].abs().max()), 1e-12)
    _close(gpu_grads[2], cpu_grads[2], rtol=1e-3, atol=1e-5 * scale)
    assert gpu_grads[4] == cpu_grads[4]


@needs_gpu
@pytest.mark.parametrize("march", [dict(MARCH, step=1e-3, max_samples=300), dict(MARCH, step=50.0),
                                   dict(MARCH, near=1.5), dict(MARCH, stop_transmittance=0.5)],
                         ids=["tiny-step-capped", "huge-step", "near-plane", "early-stop"])
def test_extreme_steps_and_cutoffs(march):
    degree = 2
    links, data = _grid(degree)
    origins, dirs = _all_rays()
    background = torch.rand(origins.shape[0], 3)
    targets = torch.rand(origins.shape[0], 3)
    cpu, gpu = _render_both(links, data, degree, origins, dirs, background, march)
    for g, c in zip(gpu, cpu):
        assert torch.isfinite(g).all()
        _close(g, c, rtol=1e-4, atol=2e-5)
    cpu_grads, gpu_grads = _loss_grad_both(links, data, degree, origins, dirs, targets, background, march)
    scale = max(float(cpu_grads[2].abs().max()), 1e-12)
    _close(gpu_grads[2], cpu_grads[2], rtol=1e-3, atol=1e-5 * scale)
    assert gpu_grads[4] == cpu_grads[4]


@needs_gpu
def test_special_rays_behave():
    """Misses and grazing rays see only the background; an origin inside the box sees the grid."""
    degree = 0
    links, data = _grid(degree, fill=1.0)
    origins, dirs = _special_rays()
    background = torch.full((origins.shape[0], 3), 0.25)
    _, gpu = _render_both(links, data, degree, origins, dirs, background)
    rgb, _, opacity = (t.cpu() for t in gpu)
    assert opacity[0] == 0.0 and torch.equal(rgb[0], background[0])  # misses the box
    assert opacity[4] > 0.0 and opacity[5] > 0.0  # origins inside the box


# ---- dispatch through the public API ------------------------------------------------------------
@pytest.mark.skipif(cuda_ready(), reason="this machine has the CUDA core; the missing-build message cannot be provoked here")
def test_cuda_tensors_without_cuda_build_fail_with_one_line():
    grid = SparseGrid.dense((3, 3, 3), (0, 0, 0), (1, 1, 1), 0)
    with pytest.raises(UserError) as info:
        grid.to("cuda")
    assert str(info.value) == CUDA_MISSING


@needs_gpu
def test_training_steps_on_cuda_follow_cpu():
    """render / loss_and_grad / TV / RMSProp / max_weights / prune through plenoxels' Python API, on a
    grid moved to the GPU, track the same steps on the CPU."""
    degree = 2
    links, data = _grid(degree, density_scale=1.0)
    opts = RenderOptions(step_size=0.5)
    runs = {}
    for device in ("cpu", "cuda"):
        grid = SparseGrid(links, data.clone(), BMIN, BMAX, degree).to(device)
        grad, optim = GridGrad(grid), SparseRMSProp(grid, lr_density=0.5, lr_sh=0.005)
        generator = torch.Generator().manual_seed(0)
        losses = []
        for step in range(4):
            origins, dirs = _rays(1500, seed=20 + step)
            targets = torch.rand(origins.shape[0], 3, generator=generator)
            mse, _ = loss_and_grad(grid, origins, dirs, targets, torch.ones(origins.shape[0], 3), opts, grad)
            tv_loss_and_grad(grid, grad, 1e-3, 1e-3, 0.5, generator)
            optim.step(grad)
            losses.append(mse)
        assert grid.data.device.type == device and grad.touched_mask.device.type == device
        origins, dirs = _rays(800, seed=99)
        result = render(grid, origins, dirs, torch.zeros(origins.shape[0], 3), opts)
        weights = max_weights(grid, origins, dirs, opts)
        pruned, _ = grid.prune(weights > 0.01)
        runs[device] = (losses, result.rgb.cpu(), weights.cpu(), pruned.num_occupied)
    assert runs["cuda"][0] == pytest.approx(runs["cpu"][0], rel=1e-3)
    assert runs["cpu"][0][-1] < runs["cpu"][0][0], "the steps should lower the loss"
    _close(runs["cuda"][1], runs["cpu"][1], rtol=1e-2, atol=2e-3)
    _close(runs["cuda"][2], runs["cpu"][2], rtol=1e-2, atol=2e-3)
    assert abs(runs["cuda"][3] - runs["cpu"][3]) <= 0.01 * runs["cpu"][3]


@needs_gpu
@pytest.mark.parametrize("spread", [0.9, 8.0])
def test_background_matches_cpu(spread):
    g = torch.Generator().manual_seed(21)
    cpu = MultiSphereBackground(r_min=1.5, r_max=3e5, n_spheres=6, height=8, width=16)
    with torch.no_grad():
        cpu.texture.copy_(torch.randn(cpu.texture.shape, generator=g))
    gpu = MultiSphereBackground.from_config(cpu.config())
    gpu.load_state_dict(cpu.state_dict())
    gpu.to("cuda")
    o = (torch.rand(4096, 3, generator=g) * 2 - 1) * spread
    d = torch.randn(4096, 3, generator=g)
    grad_rgb = torch.randn(4096, 3, generator=g)
    torch.testing.assert_close(gpu(o.cuda(), d.cuda()).cpu(), cpu(o, d), atol=1e-5, rtol=1e-5)
    grads = []
    for model in (cpu, gpu):
        optimiser = BackgroundOptimiser(model, lr=0.0)
        optimiser.backward(o, d, model(o.to(model.texture.device), d.to(model.texture.device)), grad_rgb)
        rows = optimiser.touched_rows[: optimiser.num_touched].long()
        grads.append((optimiser.grad.cpu(), set(rows.cpu().tolist())))
    assert grads[0][1] == grads[1][1]
    torch.testing.assert_close(grads[1][0], grads[0][0], atol=1e-4, rtol=1e-4)
