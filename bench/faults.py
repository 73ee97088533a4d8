"""`make bench parts=faults`: faults injected into real runs, one table row each: how the fault was made, what the
user saw, and what was lost. Every run is the command line a user types (`python -m pipeline run ...`) in its own
process, so what the user saw is its exit code and its last line on stderr.

- memory: a cgroup memory limit (v2's memory.max, or v1's memory.limit_in_bytes) around a lego `default` run;
- disk: the output folder on a tmpfs of about half what the run writes, then the same command with room again;
- cache: each stage's files cut short at a random offset or edited in place, then the same command;
- kill: the run SIGKILLed at random moments, then the same command;
- outputs: the user's files in a stage's folder (before its first run, and saved beside its output before a re-run), and
  another scene of the same name run into the same output folder;
- hostile inputs: the fuzz corpus of the test suite, through ingest and poses;
- viewer: dozens of websocket clients on loopback connecting, moving, dropping and sending malformed messages.
The cgroup and tmpfs rows need root (mount, cgroup folders); where this process may not make them the row says so.
Results: bench/results/faults.json."""
from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from bench.common import recorded
from bench.fit import machine
from pipeline.disk import damaged_file, folder_bytes
from pipeline.runner import read_manifest
from stages.common.layout import STAGE_ORDER

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "bench" / "results" / "faults.json"
# A small synthetic object and short settings: the disk, cache and kill rows run the whole pipeline many times.
SMALL = ["--preset", "fast", "--set", "fit.steps=[300,300]", "--set", "fit.resolutions=[32,64]",
         "--set", "evaluate.video_frames=0", "--set", "export.splat_seconds=5", "--set", "export.texture_size=256"]


def pipeline(scene: Path, out: Path, *args: str, timeout: float = 3600, cgroup: Path | None = None,
             kill_after: float | None = None) -> dict:
    """One `python -m pipeline run` as a user starts it: exit code, last stderr line, seconds; SIGKILLed after
    `kill_after` seconds where given; inside `cgroup` (its cgroup.procs) where given."""
    command = [sys.executable, "-m", "pipeline", "run", str(scene), "--out", str(out), "--quiet", *args]
    started = time.time()
    preexec = (lambda: (cgroup / "cgroup.procs").write_text(str(os.getpid()))) if cgroup else None
    process = subprocess.Popen(command, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                               preexec_fn=preexec)
    try:
        _, err = process.communicate(timeout=kill_after if kill_after is not None else timeout)
    except subprocess.TimeoutExpired:
        process.send_signal(signal.SIGKILL if kill_after is not None else signal.SIGTERM)
        _, err = process.communicate()
    lines = [line for line in err.splitlines() if line.strip()]
    tracebacks = sum(line.startswith("Traceback") for line in lines)
    return {"exit_code": process.returncode, "last_line": lines[-1] if lines else "", "tracebacks": tracebacks,
            "seconds": round(time.time() - started, 1)}


def complete_outputs(out: Path) -> dict[str, str]:
    """Each complete stage output: 'intact' when every file its manifest records is as written, else the damage."""
    found = {}
    for name in STAGE_ORDER:
        manifest = read_manifest(out / name)
        if manifest is not None:
            damaged = damaged_file(out / name, manifest)
            found[name] = "intact" if damaged is None else f"damaged: {damaged}"
    return found


def small_scene(root: Path) -> Path:
    """A synthetic object's photos (24 at 160x120) with their true poses beside them."""
    scene = root / "object"
    if not scene.exists():
        subprocess.run([sys.executable, "-m", "pipeline", "synth", "object", str(scene), "--views", "24", "--width",
                        "160", "--height", "120"], cwd=REPO, check=True, stdout=subprocess.DEVNULL)
    return scene / "images"


# ---- memory ------------------------------------------------------------------------------------------------------
def make_cgroup(name: str, limit: int) -> tuple[Path, str] | str:
    """A cgroup limited to `limit` bytes and the file that limits it, or why none could be made."""
    v2 = Path("/sys/fs/cgroup")
    try:
        if (v2 / "cgroup.controllers").is_file():
            folder = v2 / name
            folder.mkdir(exist_ok=True)
            (folder / "memory.max").write_text(str(limit))
            (folder / "memory.swap.max").write_text("0") if (folder / "memory.swap.max").exists() else None
            return folder, "memory.max"
        folder = v2 / "memory" / name
        folder.mkdir(exist_ok=True)
        (folder / "memory.limit_in_bytes").write_text(str(limit))
        return folder, "memory.limit_in_bytes"
    except OSError as e:
        return f"no cgroup could be made here ({e.strerror}); run as root on a machine with cgroups"


def peak_and_oom(folder: Path) -> tuple[int | None, bool]:
    for peak_file in ("memory.peak", "memory.max_usage_in_bytes"):
        if (folder / peak_file).is_file():
            peak = int((folder / peak_file).read_text().split()[0])
            break
    else:
        peak = None
    oom = False
    if (folder / "memory.events").is_file():
        oom = any(line.startswith("oom_kill ") and int(line.split()[1]) > 0
                  for line in (folder / "memory.events").read_text().splitlines())
    elif (folder / "memory.oom_control").is_file():
        oom = any(line.startswith("oom_kill ") and int(line.split()[1]) > 0
                  for line in (folder / "memory.oom_control").read_text().splitlines())
    return peak, oom


def memory_rows(data: Path, work: Path) -> list[dict]:
    rows = []
    for gib in (1, 2):
        cgroup = make_cgroup(f"voxfield-bench-{gib}g", gib << 30)
        if isinstance(cgroup, str):
            rows.append({"fault": f"memory limited to {gib} GiB", "injected": "cgroup", "user_saw": cgroup,
                         "lost": "not run"})
            continue
        folder, limit_file = cgroup
        out = work / f"lego-{gib}g"
        shutil.rmtree(out, ignore_errors=True)
        run = pipeline(data / "lego", out, "--preset", "default", cgroup=folder)
        peak, oom = peak_and_oom(folder)
        killed = oom or run["exit_code"] in (-9, 137)
        rows.append({"fault": f"memory limited to {gib} GiB, lego `default`", "injected": f"cgroup {limit_file}",
                     "user_saw": f"exit {run['exit_code']}: {run['last_line']}", "tracebacks": run["tracebacks"],
                     "oom_killed": killed, "peak_gib": round(peak / 2**30, 2) if peak else None,
                     "seconds": run["seconds"], "outputs": complete_outputs(out),
                     "lost": "the run (OOM-killed)" if killed else "nothing"})
        shutil.rmtree(out, ignore_errors=True)
        try:
            folder.rmdir()  # empty once its one process has ended
        except OSError:
            pass
    return rows


# ---- disk --------------------------------------------------------------------------------------------------------
def disk_rows(scene: Path, work: Path) -> list[dict]:
    full = work / "disk-full-size"
    shutil.rmtree(full, ignore_errors=True)
    pipeline(scene, full, *SMALL)
    needed = folder_bytes(full)
    shutil.rmtree(full, ignore_errors=True)
    mount = work / "tmpfs"
    mount.mkdir(exist_ok=True)
    size_mib = max(2, needed // 2 // (1 << 20))
    try:
        subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_mib}m", "tmpfs", str(mount)], check=True,
                       capture_output=True)
    except (subprocess.CalledProcessError, FileNotFoundError) as e:
        return [{"fault": "a full disk", "injected": "tmpfs", "lost": "not run",
                 "user_saw": f"no tmpfs could be mounted here ({e}); run as root"}]
    try:
        out = mount / "out"
        first = pipeline(scene, out, *SMALL)
        before = complete_outputs(out)
        subprocess.run(["mount", "-o", f"remount,size={needed * 3 // (1 << 20) + 64}m", str(mount)], check=True)
        again = pipeline(scene, out, *SMALL)
        after = complete_outputs(out)
        kept = all(after.get(name) == "intact" for name in before)
        return [{"fault": f"the disk fills during a run (it writes {needed / 2**20:.0f} MiB)",
                 "injected": f"tmpfs of {size_mib} MiB, then remounted larger",
                 "user_saw": f"exit {first['exit_code']}: {first['last_line']}", "tracebacks": first["tracebacks"],
                 "complete_before": before, "rerun": f"exit {again['exit_code']}, {len(after)} stages complete",
                 "lost": "nothing" if kept and again["exit_code"] == 0 else f"outputs after the rerun: {after}"}]
    finally:
        subprocess.run(["umount", str(mount)], capture_output=True)


# ---- cache -------------------------------------------------------------------------------------------------------
def cache_rows(scene: Path, work: Path, rng: random.Random) -> list[dict]:
    out = work / "cache"
    shutil.rmtree(out, ignore_errors=True)
    pipeline(scene, out, *SMALL)
    reference = json.loads((out / "evaluate" / "metrics.json").read_text())["mean"]["psnr"]
    rows = []
    for name in STAGE_ORDER:
        files = sorted((out / name).rglob("*"))
        files = [p for p in files if p.is_file() and p.name != "manifest.json" and p.stat().st_size > 0]
        if not files:
            continue
        target = rng.choice(files)
        size = target.stat().st_size
        how = rng.choice(["truncate", "edit"])
        data = target.read_bytes()
        if how == "truncate":
            offset = rng.randrange(size)
            target.write_bytes(data[:offset])
            injected = f"{target.relative_to(out)} cut at byte {offset} of {size}"
        else:
            offset = rng.randrange(size)
            target.write_bytes(data[:offset] + bytes([data[offset] ^ 0x55]) + data[offset + 1:])
            injected = f"{target.relative_to(out)}: byte {offset} of {size} changed"
        run = pipeline(scene, out, *SMALL)
        psnr = json.loads((out / "evaluate" / "metrics.json").read_text())["mean"]["psnr"]
        outputs = complete_outputs(out)
        rows.append({"fault": f"a damaged {name} output", "injected": injected,
                     "user_saw": f"exit {run['exit_code']}; {name} ran again", "tracebacks": run["tracebacks"],
                     "psnr_before_after": [reference, psnr],
                     "lost": "nothing" if run["exit_code"] == 0 and all(v == "intact" for v in outputs.values())
                     else f"{outputs}"})
    return rows


# ---- kill --------------------------------------------------------------------------------------------------------
def kill_rows(scene: Path, work: Path, rng: random.Random, kills: int) -> list[dict]:
    out = work / "kill"
    shutil.rmtree(out, ignore_errors=True)
    whole = pipeline(scene, out, *SMALL)["seconds"]  # how long a whole run takes, to kill within it
    shutil.rmtree(out, ignore_errors=True)
    moments = []
    # Within the first half of a whole run's time, so that each killed run is cut off again somewhere (resumed runs
    # skip the stages already complete, and get further each time).
    for _ in range(kills):
        moment = round(rng.uniform(0.5, whole / 2), 1)
        run = pipeline(scene, out, *SMALL, kill_after=moment)
        moments.append((moment, run["exit_code"], sorted(complete_outputs(out))))
    final = pipeline(scene, out, *SMALL)
    outputs = complete_outputs(out)
    reached = [len(done) for _, _, done in moments]
    return [{"fault": "the run SIGKILLed at random moments",
             "injected": f"SIGKILL after {[m for m, _, _ in moments]} s (stages complete after each: {reached})",
             "user_saw": f"the same command finished: exit {final['exit_code']}", "tracebacks": final["tracebacks"],
             "lost": "nothing" if final["exit_code"] == 0 and len(outputs) == len(STAGE_ORDER)
             and all(v == "intact" for v in outputs.values()) else f"{outputs}"}]


# ---- the user's files in the output folder -------------------------------------------------------------------------
def output_rows(scene: Path, work: Path) -> list[dict]:
    out, other = work / "outputs", work / "other-object" / "images"
    shutil.rmtree(out, ignore_errors=True)
    notes, blend = out / "fit" / "notes.txt", out / "export" / "scene.blend"
    yours = {notes: "made before any run", blend: "saved beside the mesh"}
    notes.parent.mkdir(parents=True)
    notes.write_text(yours[notes])
    first = pipeline(scene, out, *SMALL)
    blend.write_text(yours[blend])
    again = pipeline(scene, out, *SMALL, "--set", "export.texture_size=128")
    before = {name: (read_manifest(out / name) or {}).get("run_id") for name in STAGE_ORDER}
    if not other.exists():
        shutil.copytree(scene, other)
    refused = pipeline(other, out, *SMALL)
    after = {name: (read_manifest(out / name) or {}).get("run_id") for name in STAGE_ORDER}
    kept = all(path.is_file() and path.read_text() == text for path, text in yours.items())
    outputs = complete_outputs(out)
    return [{"fault": "the user's files in the output folder, and another scene of the same name",
             "injected": "a file in fit/ before the first run; a file saved in export/ and the export's settings "
                         "changed; then another scene's photos run into the same folder",
             "user_saw": f"exit {first['exit_code']}, {again['exit_code']} (export made again), then exit "
                         f"{refused['exit_code']}: `{refused['last_line'][:90]}...`",
             "tracebacks": first["tracebacks"] + again["tracebacks"] + refused["tracebacks"],
             "lost": "nothing" if kept and before == after and len(outputs) == len(STAGE_ORDER)
             and all(v == "intact" for v in outputs.values()) else f"files kept: {kept}; outputs: {outputs}"}]


# ---- hostile inputs ------------------------------------------------------------------------------------------------
def hostile_rows() -> list[dict]:
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                          "tests/stages/test_hostile_inputs.py"], cwd=REPO, capture_output=True, text=True)
    summary = run.stdout.strip().splitlines()[-1] if run.stdout.strip() else run.stderr.strip()[-200:]
    return [{"fault": "hostile photos, videos, masks, pose files and folders", "injected": "the fuzz corpus "
             "(tests/stages/fuzz_corpus.py), each kind under a time limit", "user_saw": summary,
             "lost": "nothing" if run.returncode == 0 else "see the failed kinds"}]


# ---- viewer --------------------------------------------------------------------------------------------------------
def viewer_rows() -> list[dict]:
    started = time.monotonic()
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                          "tests/pipeline/test_viewer_load.py"], cwd=REPO, capture_output=True, text=True)
    summary = run.stdout.strip().splitlines()[-1] if run.stdout.strip() else run.stderr.strip()[-200:]
    return [{"fault": "the viewer under load", "injected": "40 websocket clients on loopback connect, move their "
             "cameras and drop (half without a close frame); every 5th sends a malformed message "
             "(tests/pipeline/test_viewer_load.py)",
             "user_saw": f"{summary}: each malformed client closed alone, the rest and a client that stayed rendered "
             f"({time.monotonic() - started:.0f} s)" if run.returncode == 0 else summary,
             "lost": "nothing" if run.returncode == 0 else "see the failed assertion"}]


def table(rows: list[dict]) -> str:
    lines = ["| fault | how it was injected | what the user saw | lost |", "|---|---|---|---|"]
    lines += [f"| {r['fault']} | {r['injected']} | {r['user_saw']} | {r['lost']} |" for r in rows]
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.faults", description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data", help="the folder holding lego/")
    parser.add_argument("--work", type=Path, default=Path("/tmp/voxfield-bench-faults"), help="scratch folder")
    parser.add_argument("--only", nargs="*",
                        default=["memory", "disk", "cache", "kill", "outputs", "hostile", "viewer"],
                        help="which rows to run")
    parser.add_argument("--kills", type=int, default=6, help="SIGKILLs at random moments before the last run")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    rng = random.Random(args.seed)
    earlier = json.loads(RESULTS.read_text())["rows"] if RESULTS.is_file() else []
    rows = [r for r in earlier if r.get("part") not in args.only]
    scene = small_scene(args.work)
    for part, make in (("memory", lambda: memory_rows(args.data, args.work)), ("disk", lambda: disk_rows(scene, args.work)),
                       ("cache", lambda: cache_rows(scene, args.work, rng)),
                       ("kill", lambda: kill_rows(scene, args.work, rng, args.kills)),
                       ("outputs", lambda: output_rows(scene, args.work)), ("hostile", hostile_rows),
                       ("viewer", viewer_rows)):
        if part in args.only:
            made = [{"part": part, "recorded": recorded(), **row} for row in make()]
            print(table(made), flush=True)
            rows += made
    RESULTS.write_text(json.dumps({"recorded": recorded(), "machine": machine(), "rows": rows}, indent=1) + "\n")
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
