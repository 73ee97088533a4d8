"""Captures as a user hands them over, posed by SfM: each scene's photos (or a video) through the whole pipeline at a
preset, ingest to evaluate, with the pose files that come with it ignored (`poses.source=sfm`). What the other parts
measure from a scene's own poses, this one measures as a new user meets it.

Scenes: fox, cup, ball and fern (their photo folders; fern's images_4), apple (its 5 s clip), ball_video (ball's 127
frames written as an 8 fps MP4 under bench/out/sfm_captures/, a 16 s phone video), cup_video (cup's 77 photos in
the order taken, a 10 s video), room_360 (a 360 camera's equirectangular video of the synthetic room kind, 48
frames at 960x480 carried once around its still life: `write_panorama_video`), room_fisheye (an action camera's
clip of it: `write_fisheye_video`) and drone_video (a drone's mapping flight over the unbounded kind with its flight
log: `write_drone_video`; its poses also against where it flew). Each run records the evaluate stage's
held-out PSNR, SSIM and LPIPS (every 8th frame held out, at the fit's image scale), the fit's seconds and grid, the
poses' points and the foreground box in units of the cameras' distance (what sets the cells' size); a run the
pipeline refuses, its one-line reason and how long it took to give it. Writes bench/results/sfm_captures.json (a run
replaces the one of the same scene, preset and label).

    .venv/bin/python -m bench.sfm_captures [--scenes fox cup ball fern apple ball_video cup_video room_360 room_fisheye
        drone_video]
        [--preset fast] [--label L] [--set SECTION.KEY=VALUE ...]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from bench.common import recorded, write_runs
from bench.fit import machine

REPO = Path(__file__).resolve().parent.parent
OUT = REPO / "bench" / "out" / "sfm_captures"
RESULTS = REPO / "bench" / "results" / "sfm_captures.json"
SCENES = ("fox", "cup", "ball", "fern", "apple", "ball_video", "cup_video", "room_360", "room_fisheye", "drone_video")
DRONE_TRUTH = OUT / "drone_video" / "truth.npy"  # each frame's camera-to-world, the scene's units as 100 m
VIDEO_FPS = 8


def scene_input(name: str, data: Path) -> Path:
    if name == "apple":
        return data / "apple" / "apple.mp4"
    if name == "fern":
        return data / "fern" / "images_4"
    if name == "room_360":
        video = OUT / "room_360.mp4"
        if not video.is_file():
            from stages.capture.synthetic import write_panorama_video
            OUT.mkdir(parents=True, exist_ok=True)
            write_panorama_video(video, n_frames=48, width=960)
        return video
    if name == "room_fisheye":  # an action camera's wide mode: 150 degrees across the diagonal, no EXIF
        video = OUT / "room_fisheye.mp4"
        if not video.is_file():
            from stages.capture.synthetic import write_fisheye_video
            OUT.mkdir(parents=True, exist_ok=True)
            write_fisheye_video(video, n_frames=60)
        return video
    if name == "drone_video":  # a mapping flight's clip with its flight log beside it
        video = OUT / "drone_video" / "DJI_0001.MP4"
        if not DRONE_TRUTH.is_file():
            from stages.capture.synthetic import write_drone_video
            video.parent.mkdir(parents=True, exist_ok=True)
            np.save(DRONE_TRUTH, write_drone_video(video))
        return video
    if not name.endswith("_video"):
        return data / name / "images"
    video = OUT / f"{name}.mp4"
    if not video.is_file():
        import cv2
        # in the order they were taken: cup's photos are numbered 1..77
        frames = sorted((data / name.removesuffix("_video") / "images").glob("*.jpg"),
                        key=lambda p: (len(p.stem), p.stem))
        height, width = cv2.imread(str(frames[0])).shape[:2]
        OUT.mkdir(parents=True, exist_ok=True)
        writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), VIDEO_FPS, (width, height))
        for frame in frames:
            writer.write(cv2.imread(str(frame)))
        writer.release()
    return video


def summary(out: Path, stage: str) -> dict:
    return json.loads((out / stage / "manifest.json").read_text())["summary"]


def flight_errors(out: Path) -> dict:
    """The drone video's poses against where it flew: the cameras' distance (metres, rms and most) from a similarity
    fitted to the flight, how far (degrees) the poses' up is from each camera's true up, and the focal length found
    (pixels at 320x240; the truth's 277)."""
    import pycolmap
    truth, transforms = np.load(DRONE_TRUTH), json.loads((out / "poses" / "transforms.json").read_text())
    up = np.asarray(transforms.get("up", [0.0, 0.0, 1.0]))
    frames = transforms["frames"]
    flown = np.stack([truth[int(f["name"].split("_")[1])] for f in frames])
    posed = np.stack([np.asarray(f["transform_matrix"]) for f in frames])
    similarity = pycolmap.estimate_sim3d(posed[:, :3, 3], 100.0 * flown[:, :3, 3])
    off = np.linalg.norm(np.stack([similarity * c for c in posed[:, :3, 3]]) - 100.0 * flown[:, :3, 3], axis=1)
    seen = np.einsum("nji,j->ni", posed[:, :3, :3], up / np.linalg.norm(up))  # up in each camera's axes
    true = flown[:, 2, :3]  # the world's +z in each true camera's axes
    angle = np.degrees(np.arccos(np.clip(np.sum(seen * true, axis=1), -1.0, 1.0)))
    return {"off_flight_m": {"rms": round(float(np.sqrt(np.mean(off ** 2))), 3), "max": round(float(off.max()), 3)},
            "up_off_deg": {"median": round(float(np.median(angle)), 2), "max": round(float(angle.max()), 2)},
            "focal_px": round(float(transforms["fl_x"]), 1), "georeference": transforms.get("georeference")}


def one_run(name: str, data: Path, preset: str, label: str, overrides: list[str]) -> dict:
    out = OUT / f"{name}-{preset}-{label.replace(' ', '_')}"
    command = [sys.executable, "-m", "pipeline", "run", str(scene_input(name, data)), "--out", str(out), "--preset",
               preset, "--set", "poses.source=sfm", "--until", "evaluate"]
    command += [arg for override in overrides for arg in ("--set", override)]
    started = time.monotonic()
    done = subprocess.run(command, cwd=REPO, stderr=subprocess.PIPE, text=True)
    sys.stderr.write(done.stderr[-4000:])
    if done.returncode:
        reason = [line for line in done.stderr.splitlines() if line.strip()][-1:] or ["(no message)"]
        return {"scene": name, "preset": preset, "label": label, "set": overrides, "recorded": recorded(),
                "machine": machine(), "refused": reason[0].strip(), "seconds": round(time.monotonic() - started, 1)}
    scene = json.loads((out / "normalize" / "scene.json").read_text())
    fit = json.loads((out / "fit" / "fit.json").read_text())
    metrics = json.loads((out / "evaluate" / "metrics.json").read_text())
    box = scene["foreground"]
    poses = summary(out, "poses")
    return {"scene": name, "preset": preset, "label": label, "set": overrides, "recorded": recorded(),
            "machine": machine(), "mean": metrics["mean"], "views": metrics["count"], "fit_seconds": fit["seconds"],
            "train_psnr": fit["train_psnr"], "grid": fit["model"]["resolution"], "voxels": fit["model"]["occupied"],
            "scene_model": fit.get("scene_model"), "type": scene["type"],
            "poses": {"registered": poses["registered"], "images": poses["images"], "points": poses["points"],
                      "seconds": poses["seconds_total"], "line": poses["line"]},
            "foreground_in_camera_distances": (np.subtract(box["max"], box["min"])
                                               / scene["measured"]["camera_distance"]).round(3).tolist(),
            "surroundings_growth": scene["measured"].get("surroundings_growth"),
            **({"flight": flight_errors(out)} if name == "drone_video" else {})}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--label", default="", help="names a variant (default: the date and commit)")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="a setting for every run, as the pipeline takes it (repeatable)")
    args = parser.parse_args()
    label = args.label or recorded()
    results = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {"runs": []}
    for name in args.scenes:
        run = one_run(name, args.data, args.preset, label, args.set)
        if "refused" in run:
            print(f"{name} {args.preset} {label}: refused after {run['seconds']:.0f} s: {run['refused']}")
        else:
            print(f"{name} {args.preset} {label}: {run['mean']['psnr']:.2f} dB in {run['fit_seconds']:.0f} s of "
                  f"fitting, box {run['foreground_in_camera_distances']} camera distances")
        same = (name, args.preset, label)
        results["runs"] = [r for r in results["runs"] if (r["scene"], r["preset"], r["label"]) != same]
        results["runs"].append(run)
        results["machine"] = run["machine"]
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        write_runs(RESULTS, results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
