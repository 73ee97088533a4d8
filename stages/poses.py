"""Poses: camera poses and pinhole intrinsics for every ingested image, by COLMAP SfM through pycolmap
(stages/sfm/reconstruct.py) or imported from pose files the user already has (stages/sfm/pose_import.py).

Writes poses/transforms.json (nerfstudio layout, OpenGL camera-to-world in the frame the poses came
in), poses/images/ (undistorted pinhole PNGs, the ingested names), poses/masks/ (when ingest kept
masks), poses/sparse/ (the undistorted COLMAP model, binary) and poses/points.npz (points triangulated
between nearby photos at the final poses, and their observations). SfM and imports both end as a distorted COLMAP
model at the ingested image size, and one path (stages/sfm/outputs.py) undistorts and writes it, so later stages
never know where the poses came from.
"""
from __future__ import annotations

import time
from pathlib import Path

import pycolmap

from stages.common.json_files import read_json
from stages.capture.photos import is_video, photo_folder
from stages.capture.panorama import at_pole
from stages.sfm import gimbal, gps, pose_import
from stages.sfm.pole_views import add_pole_views
from stages.sfm.imported_model import turned_upright
from stages.sfm.pose_files import unread
from stages.sfm.outputs import write_poses
from stages.common.text import short_list
from stages.sfm.reconstruct import colmap_logging, reconstruct
from stages.sfm.video_again import denser_frames, rescale_model
from plenoxels.core.errors import UserError
from stages.settings.poses import Settings
from stages.common.layout import IMAGES_JSON



def _check_registered(reconstruction: pycolmap.Reconstruction, records: list[dict], share: float, how: str) -> list[str]:
    posed = {Path(im.name).stem for im in reconstruction.images.values() if im.has_pose}
    left_out = [r["name"] for r in records if r["name"] not in posed]
    if len(posed) < share * len(records):
        raise UserError(f"{how} posed only {len(posed)}/{len(records)} images (below poses.min_registered_share="
                        f"{share:g}); left out: {short_list(left_out)}. Take more overlapping photos or lower the share")
    return left_out


def _sfm(ctx, s: Settings, folder: Path, records: list[dict]) -> tuple[pycolmap.Reconstruction, dict, list[str]]:
    """SfM's model of the images (a 360 frame's views at the poles posed from its others: pole_views.py), what
    happened on the way, and the images it leaves out."""
    around = [r for r in records if not at_pole(r)]
    reconstruction, info = reconstruct(around, folder / "images", photo_folder(ctx.scene), is_video(ctx.scene),
                                       ctx.scratch / f"sfm_{folder.name}", s, ctx.report, s.min_registered_share)
    left_out = _check_registered(reconstruction, around, s.min_registered_share, "SfM")
    return reconstruction, info, left_out + add_pole_views(reconstruction, records)


def georeference(found: dict | None, above_take_off: bool = False) -> dict | None:
    """transforms.json's `georeference`, where the model's frame is metres east, north and up of a place
    (`in_metres_of`: gps.gravity's for a held model, gps.into_metres's for a pose file's); its altitude above where
    the drone took off where its heights were (a flight log's barometer)."""
    if not found or "in_metres_of" not in found:
        return None
    altitude = "altitude (metres above the take-off)" if above_take_off else "altitude (metres)"
    return {"origin": found["in_metres_of"], "origin_is": f"latitude, longitude (degrees), {altitude}, WGS 84",
            "axes": "metres east, north and up of the origin", "within_m": found["fit_m"]}


def run(ctx) -> dict:
    s: Settings = ctx.settings
    ingest = ctx.upstream["ingest"]
    ingested = read_json(ingest / IMAGES_JSON)
    records = ingested["images"]
    started = time.perf_counter()
    with colmap_logging(s.colmap_log):
        pycolmap.set_random_seed(s.seed)
        found = pose_import.find(s.source, s.path, records, ctx.scene)
        if found is None:
            source, source_path, bounds, gravity = "sfm", None, {}, None
            for binary, what, command in unread(ctx.scene) if s.source == "auto" else []:
                ctx.report.warn(f"{binary} is {what}, which is not read, so SfM poses the photos; to take its poses, "
                                f"write it as a file that is read beside it ({command})")
            try:
                reconstruction, info, left_out = _sfm(ctx, s, ingest, records)
            except UserError as refused:
                clip = ingested.get("video")
                if clip is None or "max_per_second" not in clip:
                    raise
                ctx.report.warn(f"{refused}; reading the clip again with frames closer together")
                full, full_records, ingest, retried, denser = denser_frames(ctx.scene, clip, records, ctx.scratch,
                                                                             ctx.report)
                try:
                    reconstruction, info, left_out = _sfm(ctx, s, full, full_records)
                except UserError as again:
                    # The first read's refusal is the warning above: repeated here, the line doubles.
                    raise UserError(f"{again} (the clip read again at full size with frames twice as close, "
                                    f"{len(records)} -> {len(retried)} frames; the first read's refusal is "
                                    "above)") from None
                rescale_model(reconstruction, retried[0]["width"], retried[0]["height"])
                info["denser"] = {"first_frames": len(records), "first_refusal": str(refused), "frames": len(retried),
                                  "motion": denser["motion"],
                                  "posed_at": [full_records[0]["width"], full_records[0]["height"]]}
                records = retried
        else:
            source, imported = found
            reconstruction, turned = turned_upright(imported.reconstruction, records, half_turns=source == "colmap")
            info = {"seconds": {}, **({"turned_upright": turned} if turned else {})}
            source_path, bounds, gravity = imported.path, imported.bounds, imported.gravity
            ctx.report.info(f"importing {source} poses from {imported.path}")
            left_out = _check_registered(reconstruction, records, s.min_registered_share, f"{imported.path}")
        if gravity is None and not is_video(ctx.scene):  # a drone's photos say which way is up, whoever posed them
            pitches = {f"{r['name']}.png": pitch for r in records if "panorama" not in r  # 360 views are cut level
                       and (pitch := gimbal.pitch(photo_folder(ctx.scene) / r["source"])) is not None}
            gravity, info["gimbal"] = gimbal.gravity(reconstruction, pitches) if pitches else (None, None)
            if gravity is not None:
                info["gimbal"]["taken"] = True
        held = (info.get("gps_priors") or {}).get("origin")
        imported_frame = source != "sfm"
        located = (gps.photo_positions(records, photo_folder(ctx.scene)) if gravity is None or held or imported_frame
                   else {})
        if imported_frame and located:  # a pose file's frame, moved into the photos' GPS metres where it fits them
            given = gravity
            gravity, info["gps"], scale = gps.into_metres(reconstruction, located, gravity)
            bounds = {name: (near * scale, far * scale) for name, (near, far) in bounds.items()}
            if given is None and "in_metres_of" in info["gps"]:
                info["gps"]["taken"] = True
        elif gravity is None or held:
            # A survey's GPS says up too; where SfM held the cameras near it, whether the model's frame is its metres
            up, info["gps"] = gps.gravity(reconstruction, located, held) if located else (None, None)
            if gravity is None and up is not None:
                gravity, info["gps"]["taken"] = up, True
        step = time.perf_counter()
        written = write_poses(ctx.work, ctx.scratch, ingest, reconstruction, records, source, source_path, bounds,
                              ctx.report, gravity, check_matches=source != "sfm",  # SfM's model was checked already
                              georeference=georeference(info.get("gps"), gps.above_take_off(records)))
        if written.get("contradicted"):
            info["pose_file_contradicted"] = written["contradicted"]
        info["seconds"]["undistort_and_triangulate"] = time.perf_counter() - step

    registered = written["frames"]
    points = reconstruction.num_points3D()
    error = reconstruction.compute_mean_reprojection_error() if points else None
    track = reconstruction.compute_mean_track_length() if points else None
    if left_out:
        ctx.report.warn(f"{len(left_out)} image(s) have no pose and are left out: {short_list(left_out)}")
    how = "registered" if source == "sfm" else f"imported ({source}) for"
    line = f"{how} {registered}/{len(records)} images ({registered / len(records):.0%}) at {written['width']}x{written['height']}"
    if left_out:
        line += f" (no pose: {short_list(left_out)})"
    if points:
        line += f", {points} points, mean reprojection error {error:.2f} px, mean track length {track:.1f}"
    if source == "sfm":
        line += f" ({info['matching']} matching: {info['pairs_verified']}/{info['pairs_matched']} pairs verified)"
        if info.get("masked_images"):
            line += f", features only inside the masks of {info['masked_images']} images"
    if written.get("triangulated"):
        line += (f"{';' if points else ','} {written['triangulated']['points']} points triangulated from "
                 f"{written['triangulated']['pairs']} pairs of nearby photos")
        points = points or written["triangulated"]["points"]
    if info.get("denser"):
        line += (f"; the ingested {info['denser']['first_frames']} frames did not hold together, so these poses come "
                 f"from the clip read again with a frame each {info['denser']['motion']:.1%} of the view's diagonal, "
                 f"posed at {info['denser']['posed_at'][0]}x{info['denser']['posed_at'][1]}")
    if info.get("pose_file_contradicted"):
        line += (f"; {len(info['pose_file_contradicted'])} photo(s) whose imported poses contradict their own matches "
                 f"left out: {short_list(info['pose_file_contradicted'])}")
    if info.get("turned_upright"):
        line += (f"; the pose file describes {info['turned_upright']} photos as stored, turned from upright (their "
                 "EXIF orientation), so their cameras are turned with them")
    if info.get("other_scene"):
        line += f"; {len(info['other_scene'])} photos share no match with the rest (something else), left out"
    if info.get("gimbal"):
        found = info["gimbal"]
        line += (f"; up from the gimbal pitch of {found['photos']} photos" if found.get("taken") else
                 f"; the gimbal pitch of {found['photos']}/{found['of']} photos not taken for up"
                 + (f" (their ups {found['spread_deg']:.1f} deg apart)" if "spread_deg" in found else ""))
    if info.get("gps_priors"):
        line += f"; the cameras held near the GPS of {info['gps_priors']['photos']} photos in bundle adjustment"
        if "stated" in info["gps_priors"]:
            stated, across = info["gps_priors"]["stated"]
            line += f" ({stated} at the error their source gives, median {across:.2f} m across)"
    found = info.get("gps") or {}
    if found.get("taken"):
        line += (f"; up from the GPS of {found['photos']} photos ({found['span_m']:.0f} m across, the cameras fitted "
                 f"to it within {found['fit_m']:.1f} m)")
    elif "fit_m" in found and "in_metres_of" not in found and not (info.get("gimbal") or {}).get("taken"):
        line += (f"; the GPS of {found['photos']} photos ({found['span_m']:.0f} m across, the cameras fitted to it "
                 f"within {found['fit_m']:.1f} m) not taken for up (past {gps.MAX_TILT_DEG:g} deg)")
    if "in_metres_of" in found:
        latitude, longitude, altitude = found["in_metres_of"]
        line += (f"; the poses in metres east, north and up of {latitude:.6f}, {longitude:.6f}, {altitude:.1f} m (the "
                 "first photo's GPS: transforms.json's georeference)")
    if info.get("lens_probe"):
        line += "; the images mapped first showed a fisheye's lens, so the camera is OPENCV_FISHEYE"
    if info.get("attempt_why"):
        line += f"; as set, {info['attempt_why']}, so these poses come from the attempt with {info['attempt']}"
    if info.get("mapper_fallback"):
        line += f"; {info['mapper_fallback']}, so the incremental mapper made these poses"
    info["seconds"] = {k: round(v, 2) for k, v in info["seconds"].items()}
    return {"line": line, "source": source, "registered": registered, "images": len(records), "left_out": left_out,
            "points": points, "mean_reprojection_error": error, "mean_track_length": track,
            "seconds_total": round(time.perf_counter() - started, 2), **info}
