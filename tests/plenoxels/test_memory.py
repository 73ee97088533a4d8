"""What a process may use: the least of the machine, MemAvailable and every cgroup limit above it (v1 and v2), read
from fake /proc and /sys/fs/cgroup trees; a fit planned under a small limit stops with the line that says so."""
import os

import numpy as np
import pytest

from plenoxels.core import memory
from plenoxels.core.errors import UserError
from plenoxels.core.ray_set import RaySet
from plenoxels.core.cameras import Intrinsics

GIB = 1 << 30
PAGE = os.sysconf("SC_PAGE_SIZE")


def fake_proc(root, cgroup_lines: str, available: int | None, resident: int = 0):
    proc = root / "proc"
    (proc / "self").mkdir(parents=True)
    (proc / "self" / "cgroup").write_text(cgroup_lines)
    (proc / "self" / "statm").write_text(f"{resident // PAGE * 4} {resident // PAGE} 0 0 0 0 0\n")
    meminfo = "MemTotal:       999999999 kB\n"
    if available is not None:
        meminfo += f"MemAvailable:   {available // 1024} kB\n"
    (proc / "meminfo").write_text(meminfo)
    return proc


def write(path, text):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def test_a_cgroup_v2_limit_binds_from_the_group_or_any_parent(tmp_path):
    proc = fake_proc(tmp_path, "0::/job/step\n", available=100 * GIB, resident=GIB // 4)
    cgroups = tmp_path / "cgroup"
    write(cgroups / "job" / "step" / "memory.max", "max\n")
    write(cgroups / "job" / "step" / "memory.current", "0\n")
    write(cgroups / "job" / "memory.max", f"{2 * GIB}\n")
    write(cgroups / "job" / "memory.current", f"{GIB // 2}\n")  # this process's quarter and another quarter
    limit = memory.memory_limit(proc, cgroups)
    assert limit.source == "cgroup memory.max"
    assert limit.bytes == 2 * GIB - GIB // 4  # the limit less what the rest of the group holds


def test_a_cgroup_v1_memory_limit_binds(tmp_path):
    proc = fake_proc(tmp_path, "5:cpu,cpuacct:/\n4:memory:/slurm/job_7\n0::/\n", available=100 * GIB)
    cgroups = tmp_path / "cgroup"
    write(cgroups / "memory" / "slurm" / "job_7" / "memory.limit_in_bytes", f"{GIB}\n")
    write(cgroups / "memory" / "slurm" / "job_7" / "memory.usage_in_bytes", "0\n")
    write(cgroups / "memory" / "memory.limit_in_bytes", "9223372036854771712\n")  # v1's "no limit"
    limit = memory.memory_limit(proc, cgroups)
    assert (limit.bytes, limit.source) == (GIB, "cgroup memory.limit_in_bytes")



def test_the_page_cache_a_group_could_drop_does_not_count_against_it(tmp_path):
    proc = fake_proc(tmp_path, "4:memory:/job\n", available=100 * GIB, resident=GIB // 4)
    for version, (limit_file, usage_file, key) in {"v1": ("memory.limit_in_bytes", "memory.usage_in_bytes",
                                                          "total_inactive_file"),
                                                   "v2": ("memory.max", "memory.current", "inactive_file")}.items():
        cgroups = tmp_path / version
        group = cgroups / "memory" / "job" if version == "v1" else cgroups / "job"
        if version == "v2":
            (proc / "self" / "cgroup").write_text("0::/job\n")
        write(group / limit_file, f"{2 * GIB}\n")
        write(group / usage_file, f"{GIB + GIB // 4}\n")  # this process's quarter, and a GiB of files read
        write(group / "memory.stat", f"cache {GIB}\nactive_file {GIB // 4}\n{key} {3 * GIB // 4}\n")
        # What another process holds is the usage less this one's and the inactive file pages: a quarter GiB.
        assert memory.memory_limit(proc, cgroups).bytes == 2 * GIB - GIB // 4, version

def test_without_a_cgroup_limit_what_is_available_binds_not_the_machine(tmp_path):
    proc = fake_proc(tmp_path, "0::/\n", available=GIB, resident=GIB // 2)
    write(tmp_path / "cgroup" / "memory.max", "max\n")
    limit = memory.memory_limit(proc, tmp_path / "cgroup")
    assert (limit.bytes, limit.source) == (GIB + GIB // 2, "MemAvailable")  # what is free plus what this holds


def test_unreadable_files_leave_the_machine_s_size(tmp_path):
    limit = memory.memory_limit(tmp_path / "no-proc", tmp_path / "no-cgroup")
    assert limit.source == "physical memory" and limit.bytes == PAGE * os.sysconf("SC_PHYS_PAGES")


def test_a_first_level_past_the_limit_stops_with_what_it_needs_and_what_sets_the_limit(monkeypatch):
    monkeypatch.setattr(memory, "memory_limit", lambda: memory.MemoryLimit(GIB, "cgroup memory.max"))
    with pytest.raises(UserError) as stopped:
        memory.check_dense_level((128, 128, 128), sh_degree=2)
    line = str(stopped.value)
    assert "\n" not in line and "0.5 GiB a grid may take of the 1.0 GiB this process may use (set by cgroup " \
                                 "memory.max)" in line
    assert f"{128 ** 3 * memory.fit_bytes_per_voxel(2) / GIB:.1f} GiB" in line and "fit.resolutions" in line
    memory.check_dense_level((64, 64, 64), sh_degree=2)  # 0.3 GiB of a 0.5 GiB share: goes ahead


def test_photos_are_held_as_bytes_whether_given_as_floats_or_bytes():
    rng = np.random.default_rng(0)
    floats = rng.random((6, 5, 3)).astype(np.float32)
    k = Intrinsics(5.0, 5.0, 2.5, 3.0, 5, 6)
    from_floats = RaySet([floats], [np.eye(4)], [k])
    from_bytes = RaySet([np.round(floats * 255).astype(np.uint8)], [np.eye(4)], [k])
    assert from_floats.pixels.dtype == from_bytes.pixels.dtype and from_floats.pixels.equal(from_bytes.pixels)
    np.testing.assert_allclose(from_floats.image(0).numpy(), floats, atol=0.5 / 255 + 1e-6)


def test_freed_heap_pages_go_back_to_the_system():
    memory.release_freed()  # what earlier tests left free on the heap would otherwise be reused, not grown
    chunks = [np.ones(1000) for _ in range(50_000)]  # 400 MB in 8 kB arrays: under glibc's mmap threshold, on the heap
    pin = np.ones(10)  # allocated last, it keeps the heap's top in use, so free() alone returns nothing
    grown = memory.resident_memory()
    del chunks
    memory.release_freed()
    assert grown - memory.resident_memory() > 300 << 20 and pin.sum() == 10
