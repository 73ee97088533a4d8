"""Benchmark of the poses stage: SfM through pycolmap against the poses each scene comes with, side by
side with Debian's `colmap automatic_reconstructor` (COLMAP 3.8 CLI) on the same photos in the same run.

Scenes: fox (against its transforms.json), cup (against sparse/0), fern (against poses_bounds.npy) and
synthetic object and forward scenes (against their true poses). For each: images registered, camera
centre error as a share of the camera spread and rotation error after a similarity alignment, time per
step and peak memory; the stage's poses are also compared with the CLI's. Every run is a child process,
measured by GNU time. Writes bench/results/poses.json.

    .venv/bin/python -m bench.poses [--data ../shared/data] [--scenes fox,cup] [--no-cli | --cli-scenes fox]
                                    [--variants exhaustive,global | none] [--max-side 480]
                                    [--cli-variants cli,cli_single_camera] [--reuse-cli]

A CLI variant that is not run this time (not in --cli-variants, or --no-cli) but whose model an earlier run
left in the scene's folder is compared again from that model, with its recorded time, and marked "reused".

The CLI gets the photos the stage works on (ingest's output, at its longest side), so both solve the same
problem; the stage's time is compared without ingest (resizing), which the CLI is spared.

The CLI runs with its defaults except `--use_gpu 0` (and, as `cli_single_camera`, with one shared camera
as the stage has for photos from one camera): this build of COLMAP has no CUDA, and its default
OpenGL SIFT needs a display, so it aborts on a headless machine.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pycolmap

from stages.common.json_files import write_json
from stages.sfm.compare import compare_poses
from stages.capture.synthetic import write_scene
from plenoxels.core.cameras import opengl_c2w_from_colmap_w2c

REPO = Path(__file__).resolve().parent.parent
# The CLI's exhaustive matching of fox at full size ran past 30 minutes on the loaded 2-core machine; it now gets the
# ingested (960 px) photos, but keep the margin.
CHILD_TIMEOUT_S = 3600
VIDEO_HOLD = 3
# Settings measured per scene (--variants picks some). fox: matching both ways, the global mapper (which falls back to
# incremental when its model misplaces images), and a refined principal point, to test whether the rotation offset
# against fox's own COLMAP model comes from the principal point.
VARIANTS = {
    "fox": {"exhaustive": ["poses.matching=exhaustive"], "sequential": ["poses.matching=sequential"],
            "global": ["poses.mapper=global"], "principal_point": ["poses.refine_principal_point=true"],
            # the CLI's default camera set-up (a camera per photo), to see how much of the gap to it that explains
            "per_image_camera": ["poses.shared_camera=no"]},
    "fern": {"default": [], "principal_point": ["poses.refine_principal_point=true"]},
    # cup's own model gives each photo its own focal length (529-632 px, no distortion)
    "cup": {"default": [], "per_image_camera": ["poses.shared_camera=no"]},
    # a 64-view orbit in capture order, matched sequentially with and without the loop-closing pairs
    "synthetic_orbit": {"sequential": ["poses.matching=sequential"],
                        "sequential_no_loop": ["poses.matching=sequential", "poses.loop_neighbours=0"]},
    # square crops whose EXIF keeps the uncropped photo's focal length: with the size the camera recorded (which tells
    # the stage to ignore the focal), and without it (so the wrong focal is used, and only the model checks can help)
    "synthetic_cropped": {"default": []},
    # the orbit as a video through ingest (frames kept by motion), then SfM as video gets it (sequential + loops)
    "synthetic_video": {"default": []},
    "synthetic_cropped_no_size": {"default": []},
}


def timed_child(command: list[str], log: Path, env: dict | None = None) -> dict:
    """Runs a command; wall seconds, exit code and its peak resident memory. GNU time measures the memory,
    because a child forked from this (large) Python process would otherwise report this process's peak."""
    peak_file = log.with_suffix(".peak_kb")
    peak_file.unlink(missing_ok=True)
    started = time.perf_counter()
    with open(log, "w") as out:
        # Its own session, so a timeout ends the measured command too, not only GNU time.
        process = subprocess.Popen(["/usr/bin/time", "-f", "%M", "-o", str(peak_file), *command], stdout=out,
                                   stderr=subprocess.STDOUT, cwd=REPO, env={**os.environ, **(env or {})},
                                   start_new_session=True)
        try:
            code = process.wait(timeout=CHILD_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
            code = "timeout"
    lines = peak_file.read_text().split() if peak_file.is_file() else []
    return {"seconds": round(time.perf_counter() - started, 1), "exit_code": code,
            "peak_rss_mb": round(int(lines[-1]) / 1024, 1) if lines and lines[-1].isdigit() else None}


def poses_from_transforms(path: Path) -> dict[str, np.ndarray]:
    data = json.loads(path.read_text())
    return {f["name"]: np.asarray(f["transform_matrix"]) for f in data["frames"]}


def poses_from_colmap_workspace(sparse: Path) -> tuple[dict[str, np.ndarray], int]:
    """The largest of the CLI's models, as our camera-to-world by image stem; and how many models it made."""
    models = [pycolmap.Reconstruction(d) for d in sorted(sparse.iterdir()) if d.is_dir()] if sparse.is_dir() else []
    if not models:
        return {}, 0
    best = max(models, key=lambda m: m.num_reg_images())
    poses = {}
    for image in best.images.values():
        if image.has_pose:
            pose = image.cam_from_world()
            poses[Path(image.name).stem] = opengl_c2w_from_colmap_w2c(pose.rotation.matrix(), pose.translation)
    return poses, len(models)


def compare(estimate: dict[str, np.ndarray], reference: dict[str, np.ndarray]) -> dict:
    common = sorted(set(estimate) & set(reference))
    if len(common) < 3:
        return {"compared": len(common)}
    errors = compare_poses(np.stack([estimate[n] for n in common]), np.stack([reference[n] for n in common]))
    return {"compared": len(common), **{k: round(v, 5) for k, v in errors.items() if isinstance(v, float)}}


def run_stage(images: Path, out: Path, overrides: list[str], log: Path) -> dict:
    command = [sys.executable, "-m", "pipeline", "poses", str(images), "--out", str(out)]
    for override in overrides:
        command += ["--set", override]
    child = timed_child(command, log, env={"OMP_NUM_THREADS": "2"})
    manifest_path = out / "poses" / "manifest.json"
    if child["exit_code"] != 0 or not manifest_path.is_file():
        return {**child, "error": log.read_text().strip().splitlines()[-1:] if log.is_file() else None}
    manifest = json.loads(manifest_path.read_text())
    ingest = json.loads((out / "ingest" / "manifest.json").read_text())
    summary = manifest["summary"]
    return {**child, "stage_seconds": manifest["seconds"], "ingest_seconds": ingest["seconds"],
            "steps": summary.get("seconds", {}), "registered": summary["registered"], "images": summary["images"],
            "points": summary["points"], "mean_reprojection_error": summary["mean_reprojection_error"],
            "matching": summary.get("matching"), "pairs_verified": summary.get("pairs_verified"),
            "models": summary.get("models"), "mapper": summary.get("mapper"),
            "mapper_fallback": summary.get("mapper_fallback"), "attempts": summary.get("attempts"),
            "attempt": summary.get("attempt"), "focal_prior": summary.get("focal_prior"), "line": summary["line"]}


# The CLI runs: its defaults, and one shared camera as the stage uses for photos from one camera (the CLI's
# default gives every photo its own), so that both solve the same problem.
CLI_VARIANTS = {"cli": [], "cli_single_camera": ["--single_camera", "1"]}


def run_cli(images: Path, workspace: Path, log: Path, options: list[str]) -> dict:
    shutil.rmtree(workspace, ignore_errors=True)
    workspace.mkdir(parents=True)
    child = timed_child(["colmap", "automatic_reconstructor", "--workspace_path", str(workspace),
                         "--image_path", str(images), "--use_gpu", "0", *options], log)
    poses, models = poses_from_colmap_workspace(workspace / "sparse")
    return {**child, "registered": len(poses), "models": models, "poses": poses}


def scenes(data: Path, work: Path, wanted: list[str]) -> dict[str, Path]:
    """Photo folder per scene; each scene's own pose file sits beside it (or in its parent)."""
    found = {"fox": data / "fox" / "images", "cup": data / "cup" / "images", "fern": data / "fern" / "images_4"}
    for kind, views in (("object", 40), ("forward", 30)):
        name = f"synthetic_{kind}"
        if name in wanted:
            if not (work / name / "transforms.json").is_file():
                write_scene(kind, work / name, n_views=views, width=640, height=480, seed=0, supersample=1)
            found[name] = work / name / "images"
    if "synthetic_orbit" in wanted:
        if not (work / "synthetic_orbit" / "transforms.json").is_file():
            write_scene("object", work / "synthetic_orbit", n_views=64, width=480, height=360, seed=1, supersample=1)
        found["synthetic_orbit"] = work / "synthetic_orbit" / "images"
    if "synthetic_video" in wanted:
        found["synthetic_video"] = orbit_video(work / "synthetic_orbit", work / "synthetic_video" / "video" / "orbit.avi")
    for name, record_size in (("synthetic_cropped", True), ("synthetic_cropped_no_size", False)):
        if name in wanted:
            found[name] = cropped_with_exif(work / "synthetic_object", work / name, record_size)
    return {k: v for k, v in found.items() if k in wanted}


def orbit_video(scene: Path, video: Path) -> Path:
    """The 64-view synthetic orbit as a 24 fps video, each view held VIDEO_HOLD frames (a slow walk around it)."""
    import cv2

    if not (scene / "transforms.json").is_file():
        write_scene("object", scene, n_views=64, width=480, height=360, seed=1, supersample=1)
    video.parent.mkdir(parents=True, exist_ok=True)
    photos = sorted((scene / "images").glob("*.png"))
    first = cv2.imread(str(photos[0]))
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 24, first.shape[1::-1])
    for photo in photos:
        for _ in range(VIDEO_HOLD):
            writer.write(cv2.imread(str(photo)))
    writer.release()
    shutil.copy(scene / "transforms.json", video.parent.parent / "transforms.json")  # the truth, beside the video's folder
    return video


def cropped_with_exif(scene: Path, out: Path, record_size: bool) -> Path:
    """The synthetic object's photos cropped to a centred square, as JPEGs whose EXIF gives the uncropped photo's
    35 mm equivalent focal (so it reads 1.18x too short for what is left: the diagonal shrank from 800 to 679 px), with a transforms.json of the true
    cameras of the crops beside them."""
    from PIL import Image

    if not (scene / "transforms.json").is_file():
        write_scene("object", scene, n_views=40, width=640, height=480, seed=0, supersample=1)
    truth = json.loads((scene / "transforms.json").read_text())
    w, h = truth["w"], truth["h"]
    focal_35mm = round(truth["fl_x"] / np.hypot(w, h) * np.hypot(36.0, 24.0))
    left = (w - h) // 2
    (out / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for frame in truth["frames"]:
        stem = Path(frame["file_path"]).stem
        photo = Image.open(scene / frame["file_path"]).convert("RGB").crop((left, 0, left + h, h))
        exif = Image.Exif()
        exif[0x0110] = "Synthetic"
        tags = {0xA405: focal_35mm, **({0xA002: w, 0xA003: h} if record_size else {})}
        exif.get_ifd(0x8769).update(tags)
        photo.save(out / "images" / f"{stem}.jpg", quality=95, exif=exif)
        frames.append({"file_path": f"images/{stem}.jpg", "transform_matrix": frame["transform_matrix"]})
    write_json(out / "transforms.json", {"fl_x": truth["fl_x"], "fl_y": truth["fl_y"], "cx": truth["cx"] - left,
                                         "cy": truth["cy"], "w": h, "h": h, "frames": frames})
    return out / "images"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    parser.add_argument("--work", type=Path, default=REPO / "bench" / "out" / "poses")
    parser.add_argument("--scenes", default="fox,cup,fern,synthetic_object,synthetic_forward")
    parser.add_argument("--no-cli", action="store_true")
    parser.add_argument("--cli-scenes", default=None, help="scenes to run the CLI on (default: all of --scenes)")
    parser.add_argument("--cli-variants", default="cli", help=f"CLI runs: {', '.join(CLI_VARIANTS)}")
    parser.add_argument("--reuse-cli", action="store_true",
                        help="compare with the CLI models and times of the scene's last runs instead of running them again")
    parser.add_argument("--variants", default=None, help="variants to run (default: all of each scene's)")
    parser.add_argument("--max-side", type=int, default=0,
                        help="ingest photos at this longest side (0: ingest's default); results go under <scene>_<side>px")
    parser.add_argument("--results", type=Path, default=REPO / "bench" / "results" / "poses.json")
    args = parser.parse_args()
    size = [f"ingest.max_side={args.max_side}"] if args.max_side else []
    cli_scenes = set((args.cli_scenes if args.cli_scenes is not None else args.scenes).split(","))
    args.work.mkdir(parents=True, exist_ok=True)
    use_cli = not args.no_cli and shutil.which("colmap") is not None
    results_path = args.results
    # Scenes run separately accumulate: each run replaces the entries of the scenes it ran.
    earlier = json.loads(results_path.read_text()) if results_path.is_file() else {}
    machine = {"cpus": os.cpu_count(), "pycolmap": pycolmap.__version__, "has_cuda": pycolmap.has_cuda}
    if use_cli:
        machine["colmap_cli"] = "COLMAP 3.8 (Debian), automatic_reconstructor defaults + --use_gpu 0"
    results = {**earlier, "machine": {**earlier.get("machine", {}), **machine}, "scenes": earlier.get("scenes", {})}
    for name, images in scenes(args.data, args.work, args.scenes.split(",")).items():
        print(f"[poses bench] {name}: {images}", flush=True)
        key = f"{name}_{args.max_side}px" if args.max_side else name
        folder = args.work / key
        folder.mkdir(exist_ok=True)
        entry: dict = {"photos": str(images), "settings": size}
        if images.is_file():  # a video: its frames are named by index, each synthetic view held VIDEO_HOLD frames
            truth = json.loads((images.parent.parent / "transforms.json").read_text())
            views = sorted(truth["frames"], key=lambda f: f["file_path"])
            ref_poses = {f"frame_{i:06d}": np.asarray(views[i // VIDEO_HOLD]["transform_matrix"])
                         for i in range(VIDEO_HOLD * len(views))}
            entry["reference"] = {"line": f"the true poses of the {len(views)} views"}
        else:
            reference = run_stage(images, folder / "reference", size, folder / "reference.log")
            ref_poses = poses_from_transforms(folder / "reference" / "poses" / "transforms.json") if "line" in reference else {}
            entry["reference"] = {"line": reference.get("line"), "error": reference.get("error")}
        variants = VARIANTS.get(name, {"default": []})
        if args.variants:
            variants = {k: v for k, v in variants.items() if k in args.variants.split(",")}
        # Picking some variants keeps the others' results from the scene's last run.
        entry["stage"] = dict(earlier.get("scenes", {}).get(key, {}).get("stage", {})) if args.variants else {}
        for variant, overrides in variants.items():
            result = run_stage(images, folder / f"stage_{variant}", ["poses.source=sfm", *size, *overrides],
                               folder / f"stage_{variant}.log")
            if "line" in result:
                poses = poses_from_transforms(folder / f"stage_{variant}" / "poses" / "transforms.json")
                result["vs_reference"] = compare(poses, ref_poses)
                result["settings"] = overrides
            entry["stage"][variant] = result
            print(f"  stage {variant}: {json.dumps({k: result.get(k) for k in ('registered', 'stage_seconds', 'peak_rss_mb', 'vs_reference')})}", flush=True)
        earlier_entry = earlier.get("scenes", {}).get(key, {})
        for cli_name, options in CLI_VARIANTS.items():
            workspace = folder / cli_name
            earlier_cli = earlier_entry.get(cli_name)
            wanted = use_cli and name in cli_scenes and cli_name in args.cli_variants.split(",")
            if earlier_cli and earlier_cli.get("exit_code") == 0 and (args.reuse_cli or not wanted):
                # An earlier run's model and time, compared again with whatever the stage gave this time.
                cli = {**earlier_cli, "reused": True, "poses": poses_from_colmap_workspace(workspace / "sparse")[0]}
            elif wanted:
                # The ingested photos: the same pixels the stage matched, whatever --max-side says.
                cli = run_cli(folder / "reference" / "ingest" / "images", workspace, folder / f"{cli_name}.log", options)
            else:
                continue
            cli_poses = cli.pop("poses")
            cli["options"] = options
            cli["vs_reference"] = compare(cli_poses, ref_poses)
            entry[cli_name] = cli
            for variant, result in entry["stage"].items():
                if "line" in result:
                    poses = poses_from_transforms(folder / f"stage_{variant}" / "poses" / "transforms.json")
                    result[f"vs_{cli_name}"] = compare(poses, cli_poses)
                    result[f"time_vs_{cli_name}"] = round(result["stage_seconds"] / cli["seconds"], 3) if cli["seconds"] else None
            print(f"  {cli_name}: {json.dumps({k: cli.get(k) for k in ('registered', 'seconds', 'peak_rss_mb', 'vs_reference')})}", flush=True)
        entry["load_average"] = os.getloadavg()
        results["scenes"][key] = entry
        write_json(results_path, results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
