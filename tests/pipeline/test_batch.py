"""The batch command: many scenes, each a whole `pipeline run` in its own process, on local workers or on a Ray
cluster; failures reported, re-runs skip what is done, and killed runs (or Ray workers) resume."""
import contextlib
import json
import os
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from pipeline.batch import BatchOptions, format_table, plan_jobs, run_batch, stage_run_ids
from pipeline.scenes import output_names, read_scene_list
from pipeline.stage import STAGE_ORDER
from stages.capture.synthetic import write_scene
from plenoxels.core.errors import UserError

REPO = Path(__file__).resolve().parents[2]
GOOD = ("vase", "bowl", "cup")
# Every stage on 12 photos of 48x36 with a one-level 16^3 fit: seconds per scene, mostly process start-up.
QUICK = ["fit.resolutions=[16]", "fit.steps=[40]", "fit.batch_size=1024", "fit.tile_size=16", "fit.image_scale=1.0",
         "fit.eval_every=0", "evaluate.video_frames=0", "export.points=500", "export.splat_seconds=0",
         "export.texture_size=128"]
OPTIONS = BatchOptions(preset="fast", overrides=QUICK)
NO_RAY = "Ray is an optional extra: install it with `make install extras=cluster`"


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """Three small synthetic object scenes, a folder with no photos in it, and a list file naming all four."""
    root = tmp_path_factory.mktemp("batch_scenes")
    for seed, name in enumerate(GOOD):
        write_scene("object", root / name, n_views=12, width=48, height=36, seed=seed, supersample=1)
    (root / "broken" / "images").mkdir(parents=True)
    (root / "broken" / "images" / "notes.txt").write_text("not a photo")
    listing = root / "scenes.txt"
    listing.write_text("# the shelf\n" + "".join(f"{name}/images\n" for name in (*GOOD, "broken")))
    return root, listing


def batch_command(*args) -> list[str]:
    cmd = [sys.executable, "-m", "pipeline", "batch", *map(str, args), "--preset", "fast"]
    for pair in QUICK:
        cmd += ["--set", pair]
    return cmd


def records_by_name(out: Path) -> dict[str, dict]:
    return {r["name"]: r for r in json.loads((out / "batch.json").read_text())["scenes"]}


def assert_good_and_broken(records: dict[str, dict]) -> None:
    assert set(records) == {*GOOD, "broken"}
    for name in GOOD:
        r = records[name]
        assert r["status"] == "done" and r["error"] is None, r
        assert r["stages_done"] == list(STAGE_ORDER) and r["registered"] == r["images"] == 12
        assert r["scene_type"] == "object" and r["psnr"] > 10 and 0 < r["ssim"] <= 1
        assert r["mesh_faces"] > 0 and r["mesh_bytes"] > 0 and r["peak_memory_bytes"] > 50e6
    broken = records["broken"]
    assert broken["status"] == "failed" and broken["stages_done"] == []
    assert "usable image" in broken["error"] and "\n" not in broken["error"]


def assert_nothing_ran(records: dict[str, dict], out: Path) -> None:
    for name in GOOD:
        assert records[name]["stages_ran"] == [], records[name]
        log = (out / name / "batch.log").read_text()
        assert log.count("up to date") == len(STAGE_ORDER), log


def pipeline_processes(marker: str) -> list[tuple[int, int]]:
    """(pid, parent pid) of every `pipeline run` process whose command line mentions `marker`."""
    found = []
    for entry in Path("/proc").iterdir():
        try:
            argv = (entry / "cmdline").read_bytes().split(b"\0")
            parent = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        if b"run" in argv and any(marker.encode() in a for a in argv) and any(a.endswith(b"pipeline") for a in argv):
            found.append((int(entry.name), parent))
    return found


def wait_for(predicate, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)


def test_scene_lists_and_names(scenes):
    root, listing = scenes
    listed = read_scene_list([listing, root / "vase" / "images"])
    assert listed == [(root / n / "images").resolve() for n in (*GOOD, "broken")]  # the repeat is dropped
    assert output_names([Path("a/fox/images"), Path("b/fox/images"), Path("fern/images_4")]) == ["fox", "fox-2", "fern"]


def test_local_workers_run_every_scene_report_the_broken_one_and_skip_everything_the_second_time(scenes, tmp_path):
    root, listing = scenes
    out = tmp_path / "out"
    first = subprocess.run(batch_command(listing, "--out", out, "--workers", "2"), capture_output=True, text=True,
                           cwd=REPO, env={**os.environ, "OMP_NUM_THREADS": "2"})
    assert first.returncode == 1, first.stderr  # a scene failed
    records = records_by_name(out)
    assert_good_and_broken(records)
    assert all(records[n]["stages_ran"] == list(STAGE_ORDER) for n in GOOD)
    assert "failed: broken: error: only 0 usable image(s)" in first.stdout and "batch: 4/4" not in first.stderr
    assert "3/4 done, 0 running, 1 failed" in first.stderr
    csv_lines = (out / "batch.csv").read_text().splitlines()
    assert csv_lines[0].startswith("name,status,stages_done") and len(csv_lines) == 5

    again = subprocess.run(batch_command(listing, "--out", out, "--workers", "2"), capture_output=True, text=True,
                           cwd=REPO, env={**os.environ, "OMP_NUM_THREADS": "2"})
    assert again.returncode == 1
    records_again = records_by_name(out)
    assert_nothing_ran(records_again, out)
    for name in GOOD:  # the memory that made the outputs is kept, not the memory of skipping them
        assert records_again[name]["peak_memory_bytes"] >= records[name]["peak_memory_bytes"]


def test_a_batch_killed_mid_scene_resumes_where_it_stopped(scenes, tmp_path):
    root, _ = scenes
    out = tmp_path / "out"
    paths = [root / name / "images" for name in GOOD[:2]]
    first, second = (out / name for name in GOOD[:2])
    batch = subprocess.Popen(batch_command(*paths, "--out", out, "--workers", "1"), cwd=REPO,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_for(lambda: (second / "ingest" / "manifest.json").exists(), 120, "the second scene's ingest")
    finally:
        batch.kill()
        batch.wait()
    # The scene's process dies with the batch: nothing is left holding its output folder.
    wait_for(lambda: not pipeline_processes(str(second)), 10, "the scene process to die with its batch")
    assert (first / "export" / "manifest.json").exists() and not (second / "export" / "manifest.json").exists()
    before = stage_run_ids(second)

    resumed = subprocess.run(batch_command(*paths, "--out", out, "--workers", "1"), capture_output=True, text=True,
                             cwd=REPO)
    assert resumed.returncode == 0, resumed.stderr
    records = records_by_name(out)
    assert records[GOOD[0]]["stages_ran"] == []
    assert records[GOOD[1]]["status"] == "done" and records[GOOD[1]]["stages_done"] == list(STAGE_ORDER)
    assert "ingest" not in records[GOOD[1]]["stages_ran"] and stage_run_ids(second)["ingest"] == before["ingest"]
    assert "every stage up to date" in resumed.stdout and GOOD[1] in format_table(list(records.values()))



@pytest.mark.parametrize("seed", [7])
def test_a_batch_whose_scene_processes_are_killed_at_random_moments_finishes_every_scene_on_a_rerun(scenes, tmp_path,
                                                                                                   seed):
    """SIGKILL at seeded random moments to whichever scene process is running: the batch reports those scenes as
    killed and goes on; the rerun finishes every scene, and no stage that had finished runs again."""
    root, _ = scenes
    out = tmp_path / "out"
    rng = random.Random(seed)
    paths = [root / name / "images" for name in GOOD]
    batch = subprocess.Popen(batch_command(*paths, "--out", out, "--workers", "2"), cwd=REPO,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    killed = []
    try:
        while batch.poll() is None and len(killed) < len(GOOD):
            time.sleep(rng.uniform(0.5, 4.0))
            running = sorted(pid for pid, _ in pipeline_processes(str(out)))
            if running:
                pid = rng.choice(running)
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
                    killed.append(pid)
        assert batch.wait(timeout=300) in (0, 1)
    finally:
        batch.kill()
    assert killed, "no scene process was running to be killed"
    first = records_by_name(out)
    assert any("killed by signal 9" in (r["error"] or "") for r in first.values()), first
    finished_before = {name: {stage: run for stage, run in stage_run_ids(out / name).items() if run}
                       for name in GOOD}

    rerun = subprocess.run(batch_command(*paths, "--out", out, "--workers", "2"), capture_output=True, text=True,
                           cwd=REPO)
    assert rerun.returncode == 0, rerun.stderr
    records = records_by_name(out)
    for name in GOOD:
        assert records[name]["status"] == "done" and records[name]["stages_done"] == list(STAGE_ORDER), records[name]
        after = stage_run_ids(out / name)
        assert {stage: after[stage] for stage in finished_before[name]} == finished_before[name], name
        assert set(records[name]["stages_ran"]).isdisjoint(finished_before[name]), records[name]


# ---- on a Ray cluster ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def ray_cluster():
    ray = pytest.importorskip("ray", reason=NO_RAY)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


def test_ray_batch_runs_every_scene_reports_the_broken_one_and_skips_everything_the_second_time(scenes, tmp_path,
                                                                                               ray_cluster):
    from pipeline.batch_ray import RayCluster

    root, listing = scenes
    out = tmp_path / "out"
    jobs = plan_jobs(read_scene_list([listing]), out)
    run_batch(jobs, OPTIONS, RayCluster(), out, quiet=True)
    records = records_by_name(out)
    assert_good_and_broken(records)
    run_batch(jobs, OPTIONS, RayCluster(), out, quiet=True)
    assert_nothing_ran(records_by_name(out), out)


def test_ray_retries_a_scene_whose_worker_is_killed_mid_scene(scenes, tmp_path, ray_cluster):
    from pipeline.batch_ray import RayCluster

    root, _ = scenes
    out = tmp_path / "out"
    jobs = plan_jobs([root / "cup" / "images"], out)
    options = BatchOptions(preset="fast", overrides=[*QUICK, "fit.steps=[400]"])
    results = []
    driver = threading.Thread(target=lambda: results.extend(run_batch(jobs, options, RayCluster(), out, quiet=True)))
    driver.start()
    wait_for(lambda: (jobs[0].out / "normalize" / "manifest.json").exists(), 120, "the scene to reach its fit")
    [(scene_process, ray_worker)] = pipeline_processes(str(jobs[0].out))
    kept = stage_run_ids(jobs[0].out)
    os.kill(ray_worker, signal.SIGKILL)
    wait_for(lambda: not Path(f"/proc/{scene_process}").exists(), 10, "the scene process to die with its worker")
    driver.join(timeout=120)
    assert not driver.is_alive()
    [record] = results
    assert record["status"] == "done" and record["stages_done"] == list(STAGE_ORDER), record
    # The retry kept what the killed attempt had finished.
    assert all(stage_run_ids(jobs[0].out)[s] == kept[s] for s in ("ingest", "poses", "normalize"))
    assert "ingest" not in record["stages_ran"] and "export" in record["stages_ran"]


def test_ray_path_without_ray_is_a_one_line_error(tmp_path):
    code = ("import sys; sys.modules['ray'] = None\n"
            "from pipeline.cli import main\n"
            f"sys.exit(main(['batch', {str(tmp_path)!r}, '--ray']))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO)
    assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr
    assert "make install extras=cluster" in result.stderr


def test_a_scene_task_holds_a_gpu_only_when_its_fit_can_use_one():
    pytest.importorskip("ray", reason=NO_RAY)
    from pipeline.batch_ray import wants_gpu
    assert wants_gpu(BatchOptions(), cluster_gpus=2) and not wants_gpu(BatchOptions(), cluster_gpus=0)
    assert not wants_gpu(BatchOptions(overrides=["fit.device=cpu"]), cluster_gpus=2)
    assert not wants_gpu(BatchOptions(until="normalize"), cluster_gpus=2)
    with pytest.raises(UserError, match="no GPU"):
        wants_gpu(BatchOptions(overrides=["fit.device=cuda"]), cluster_gpus=0)
