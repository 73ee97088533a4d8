"""The poses stage's output from a distorted COLMAP model (SfM's or an import's): undistorted pinhole images and
masks, the undistorted model, transforms.json (nerfstudio layout, OpenGL camera-to-world) and points.npz (points
triangulated between nearby photos, and their observations), so later stages never know where the poses came from."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pycolmap
from PIL import Image

from stages.common.media import write_png
from stages.common.json_files import write_json
from stages.common.text import short_list
from stages.sfm.model_checks import MAX_CONTRADICTED_SHARE, disagreeing_frames, drop_images
from stages.sfm.triangulate import triangulate
from plenoxels.core.cameras import Intrinsics, opengl_c2w_from_colmap_w2c
from stages.common.layout import POINTS_NPZ, TRANSFORMS_JSON
from plenoxels.core.errors import UserError


# The first distortion coefficient a fisheye without any is given (a radius 1e-7 further at one radian off the axis).
FISHEYE_NUDGE = 1e-7


def _camera_dict(camera: pycolmap.Camera) -> dict:
    return {"model": camera.model_name, "width": camera.width, "height": camera.height,
            "params": [float(v) for v in camera.params], "param_names": camera.params_info.split(", ")}


def _pinhole(camera: pycolmap.Camera) -> dict:
    return {"fl_x": float(camera.focal_length_x), "fl_y": float(camera.focal_length_y),
            "cx": float(camera.principal_point_x), "cy": float(camera.principal_point_y),
            "w": camera.width, "h": camera.height}


def _undistort_mask(mask: np.ndarray, camera: pycolmap.Camera) -> np.ndarray:
    """The same warp `undistort_images` applies to the photo, so mask and image stay aligned."""
    bitmap, _ = pycolmap.undistort_image(pycolmap.UndistortCameraOptions(), pycolmap.Bitmap.from_array(mask), camera)
    return np.asarray(bitmap.to_array()).reshape(bitmap.height, bitmap.width)


def write_poses(out: Path, scratch: Path, ingest_dir: Path, distorted: pycolmap.Reconstruction, records: list[dict],
                source: str, source_path: Path | None, bounds: dict, report, gravity=None,
                check_matches: bool = False, georeference: dict | None = None) -> dict:
    """Undistorts the posed images of `distorted` (a model of the ingested PNGs in `ingest_dir`) and writes the poses
    output into `out`: images/, masks/, sparse/, transforms.json and points.npz. `bounds` maps image names to LLFF
    (near, far); `gravity` is the world's up where the poses' source fixes it, `georeference` where the frame is
    metres east, north and up of a place (stages/sfm/gps.py); `scratch` holds the intermediate models. With
    `check_matches` (a pose file's poses), the photos whose matches with their neighbours contradict their poses are
    left out and it is all written again, or where there are too many of them the file is refused."""
    written = _write_poses(out, scratch, ingest_dir, distorted, records, source, source_path, bounds, report, gravity,
                           georeference)
    disagreeing = disagreeing_frames(written["agreement"], written["frames"]) \
        if check_matches and "agreement" in written else {}
    if not disagreeing:
        return written
    names = [written["names"][i] for i in disagreeing]
    if len(names) > MAX_CONTRADICTED_SHARE * written["frames"]:
        raise UserError(f"the poses in {source_path} contradict the photos' own matches: for {len(names)} of "
                        f"{written['frames']} photos at most {max(disagreeing.values()):.0%} of their matches with "
                        "nearby photos agree with their poses, where poses that fit agree with most; the pose file may "
                        "be another capture's or in another convention: set poses.source=sfm to pose them anew")
    report.warn(f"{len(names)} photo(s) whose imported poses contradict their own matches are left out: "
                f"{short_list(names)}")
    drop_images(distorted, names)
    clear_poses(out)
    written = _write_poses(out, scratch, ingest_dir, distorted, records, source, source_path, bounds, report, gravity,
                           georeference)
    return {**written, "contradicted": names}


def _write_poses(out: Path, scratch: Path, ingest_dir: Path, distorted: pycolmap.Reconstruction, records: list[dict],
                 source: str, source_path: Path | None, bounds: dict, report, gravity,
                 georeference: dict | None = None) -> dict:
    model_dir, undistorted_dir = scratch / "distorted", scratch / "undistorted"
    for folder in (model_dir, undistorted_dir):
        shutil.rmtree(folder, ignore_errors=True)
    model_dir.mkdir(parents=True)
    distorted.write_binary(model_dir)
    # COLMAP copies an image whose camera has no distortion coefficients as it is, a fisheye's too: its equidistant
    # projection alone is no pinhole, so a coefficient far below a pixel's worth makes it undistort.
    written = pycolmap.Reconstruction(model_dir)
    unbent = [c for c in written.cameras.values()
              if "FISHEYE" in c.model_name and not np.any(c.params[c.extra_params_idxs()])]
    for camera in unbent:
        params = camera.params.copy()
        params[camera.extra_params_idxs()[0]] = FISHEYE_NUDGE
        camera.params = params
    if unbent:
        written.write_binary(model_dir)
    posed = {Path(im.name).stem: im for im in distorted.images.values() if im.has_pose}
    report.info(f"undistorting {len(posed)} images to pinhole")
    pycolmap.undistort_images(undistorted_dir, model_dir, ingest_dir / "images", output_type="COLMAP")
    shutil.move(undistorted_dir / "images", out / "images")
    undistorted = pycolmap.Reconstruction(undistorted_dir / "sparse")
    (out / "sparse").mkdir()
    undistorted.write_binary(out / "sparse")

    by_name = {Path(im.name).stem: im for im in undistorted.images.values()}
    frames, frame_index, cameras = [], {}, []
    for record in records:
        image = by_name.get(record["name"])
        if image is None or record["name"] not in posed:
            continue
        pose = image.cam_from_world()
        frame = {"name": record["name"], "file_path": f"images/{record['name']}.png",
                 "transform_matrix": opengl_c2w_from_colmap_w2c(pose.rotation.matrix(), pose.translation).tolist()}
        if record.get("mask"):
            mask = np.asarray(Image.open(ingest_dir / record["mask"]).convert("L"))
            (out / "masks").mkdir(exist_ok=True)
            write_png(out / "masks" / f"{record['name']}.png",
                      _undistort_mask(mask, distorted.cameras[posed[record["name"]].camera_id]))
            frame["mask_path"] = f"masks/{record['name']}.png"
            if record.get("cutout"):
                frame["cutout"] = True
        if record.get("split"):
            frame["split"] = record["split"]
        if record.get("colourless"):
            frame["colourless"] = True
        if record.get("panorama"):  # a view of a 360 frame: held out, or not, with the frame's other views
            frame["panorama_frame"] = record["panorama"]["frame"]
        if record["name"] in bounds:
            frame["near"], frame["far"] = bounds[record["name"]]
        frame_index[image.image_id] = len(frames)
        frames.append(frame)
        cameras.append((undistorted.cameras[image.camera_id], distorted.cameras[posed[record["name"]].camera_id]))

    shared = _pinhole(cameras[0][0])
    per_frame = any(_pinhole(c) != shared for c, _ in cameras)
    originals = [_camera_dict(o) for _, o in cameras]
    for frame, (camera, _), original in zip(frames, cameras, originals):
        if per_frame:
            frame.update(_pinhole(camera))
        if originals.count(original) != len(originals):
            frame["original_camera"] = original
    write_json(out / TRANSFORMS_JSON, {
        "camera_model": "PINHOLE", **shared, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        "original_camera": originals[0], "source": source,
        "source_path": str(source_path) if source_path else None,
        **({"up": [float(v) for v in gravity]} if gravity is not None else {}),
        **({"georeference": georeference} if georeference else {}), "frames": frames})
    written = {"frames": len(frames), "width": shared["w"], "height": shared["h"]}
    # Points from pairs of nearby photos at the final poses, whatever the poses came from. SfM's points are one a
    # track, spread over whatever textured surface it matched (a wooden floor around a ball); pairs count a surface
    # once for each pair of nearby photos that sees it, so the bulk normalize boxes is what the photos are about, and
    # the box does not depend on where the poses came from (bench/README.md, "How normalize boxes a room"). The SfM
    # model's own points stay in sparse/. The pairs' matches also say how far the poses agree with the photos.
    report.info("triangulating points between nearby photos for the scene's box and depths" if not bounds else
                "matching nearby photos to check their poses")
    points = triangulate((np.asarray(Image.open(out / f["file_path"]).convert("RGB")) for f in frames),
                         np.stack([np.asarray(f["transform_matrix"]) for f in frames]),
                         [Intrinsics.from_frame({**shared, **f}) for f in frames])
    written["names"], written["agreement"] = [f["name"] for f in frames], points.agreement
    if bounds:
        # LLFF's poses bring each photo's depth range, which is all normalize would take from points.
        write_points(out / POINTS_NPZ, undistorted, frame_index)
        return written
    np.savez(out / POINTS_NPZ, **points.arrays())
    written["triangulated"] = {"points": len(points.xyz), "pairs": points.pairs}
    return written


def clear_poses(out: Path) -> None:
    """Everything write_poses wrote into `out`, removed (to write it again)."""
    for folder in ("images", "masks", "sparse"):
        shutil.rmtree(out / folder, ignore_errors=True)
    for name in (TRANSFORMS_JSON, POINTS_NPZ):
        (out / name).unlink(missing_ok=True)


def write_points(path: Path, reconstruction: pycolmap.Reconstruction, frame_index: dict[int, int]) -> None:
    """points.npz: the points seen by the written frames (`frame_index`: COLMAP image id -> frame), their colour,
    error and track length, and one (frame, point) row per observation."""
    xyz, rgb, error, track_length, obs_frame, obs_point = [], [], [], [], [], []
    for point in reconstruction.points3D.values():
        elements = [e for e in point.track.elements if e.image_id in frame_index]
        if not elements:
            continue
        for element in elements:
            obs_frame.append(frame_index[element.image_id])
            obs_point.append(len(xyz))
        xyz.append(point.xyz)
        rgb.append(point.color)
        error.append(point.error)
        track_length.append(len(elements))
    np.savez(path, xyz=np.asarray(xyz, dtype=np.float64).reshape(-1, 3), rgb=np.asarray(rgb, dtype=np.uint8).reshape(-1, 3),
             error=np.asarray(error, dtype=np.float64), track_length=np.asarray(track_length, dtype=np.int32),
             obs_frame=np.asarray(obs_frame, dtype=np.int32), obs_point=np.asarray(obs_point, dtype=np.int32))
