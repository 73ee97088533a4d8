"""Hostile inputs made on the fly: each kind is a photo folder (or a video) holding something a user may hand us.

A kind's maker writes into an empty folder and returns the path to give the pipeline; nothing here is committed data.
"""
import json
import os
import re
import shutil
import struct
import tempfile
import zlib
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from PIL import Image

from stages.capture.synthetic import write_panorama_video, write_scene


def textured(h=48, w=64, seed=0):
    rng = np.random.default_rng(seed)
    return cv2.resize(rng.integers(0, 256, (h // 4, w // 4, 3), dtype=np.uint8), (w, h), interpolation=cv2.INTER_CUBIC)


def good_photos(folder: Path, count=3):
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(count):
        Image.fromarray(textured(seed=i)).save(folder / f"p{i}.jpg", quality=92)
    return folder


def bomb_png(path: Path, side=40000):
    """A PNG whose header claims side x side pixels over a few bytes of data."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    header = struct.pack(">IIBBBBB", side, side, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"\0" * 64))
                     + chunk(b"IEND", b""))


def with_orientation(tag):
    def make(folder):
        exif = Image.Exif()
        exif[0x0112] = tag
        Image.fromarray(textured(seed=7)).save(good_photos(folder) / f"o{tag}.jpg", exif=exif, quality=92)
        return folder
    return make


def one(name, writer):
    def make(folder):
        writer(good_photos(folder) / name)
        return folder
    return make


def video(frames, truncate=False, picture=lambda frame: frame):
    def make(folder):
        folder.mkdir(parents=True)
        path = folder / "clip.mp4"
        out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10, (64, 48))
        for i in range(frames):
            out.write(picture(textured(seed=i)))
        out.release()
        if truncate and path.exists():
            path.write_bytes(path.read_bytes()[: max(1, path.stat().st_size // 2)])
        elif not path.exists():
            path.write_bytes(b"")
        return path
    return make


def mask_case(mask):
    def make(folder):
        good_photos(folder)
        (folder / "masks").mkdir()
        for i in range(3):
            Image.fromarray(mask(i)).save(folder / "masks" / f"p{i}.png")
        return folder
    return make


def symlink_loop(folder):
    good_photos(folder)
    os.symlink(folder / "loop", folder / "loop")
    os.symlink(folder, folder / "self")
    return folder


def folder_named_jpg(folder):
    (good_photos(folder) / "x.jpg").mkdir()
    return folder


def read_only(folder):
    good_photos(folder)
    folder.chmod(0o555)
    return folder


def mixed_sizes(folder):
    good_photos(folder)
    Image.fromarray(textured(96, 64, seed=5)).save(folder / "tall.jpg")
    Image.fromarray(textured(40, 120, seed=6)).save(folder / "wide.jpg")
    return folder


def mask_rotated(folder):
    good_photos(folder)
    (folder / "masks").mkdir()
    for i in range(3):
        exif = Image.Exif()
        exif[0x0112] = 6
        Image.fromarray(np.full((48, 64), 255, np.uint8)).save(folder / "masks" / f"p{i}.jpg", exif=exif)
    return folder


def photos_in_subfolders(folder):
    good_photos(folder / "day1")
    good_photos(folder / "day2")
    return folder


def two_videos(folder):
    video(12)(folder / "first").rename(folder / "first.mp4")
    video(12)(folder / "second").rename(folder / "second.mp4")
    return folder


def grey_among_colour(folder):
    good_photos(folder, count=4)
    Image.fromarray(textured(seed=9)[..., 0]).save(folder / "grey.jpg")
    return folder


def copied_photo(folder):
    good_photos(folder)
    shutil.copy(folder / "p0.jpg", folder / "p0 copy.jpg")
    return folder


def mask_turned_as_stored(folder):
    """Phone photos stored turned (EXIF 6), their masks made from the pixels as stored."""
    folder.mkdir(parents=True)
    (folder / "masks").mkdir()
    for i in range(3):
        exif = Image.Exif()
        exif[0x0112] = 6
        Image.fromarray(textured(seed=i)).save(folder / f"p{i}.jpg", exif=exif, quality=92)
        Image.fromarray(np.full((48, 64), 255, np.uint8)).save(folder / "masks" / f"p{i}.png")
    return folder


def pillarboxed(frame):
    """A frame's middle within black columns, as an editor pads a portrait clip."""
    padded = np.zeros_like(frame)
    padded[:, 16:48] = frame[:, 16:48]
    return padded


def watermarked(frame):
    """A frame with a caption burned in, as an app leaves on every frame."""
    frame = frame.copy()
    cv2.putText(frame, "@me", (4, 44), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return frame


def photos_like(edit):
    def make(folder):
        folder.mkdir(parents=True)
        for i in range(3):
            Image.fromarray(edit(textured(seed=i))).save(folder / f"p{i}.png")
        return folder
    return make


def video_360(folder):
    """A 360 camera's clip: cut into views around the horizon."""
    folder.mkdir(parents=True)
    write_panorama_video(folder / "walk.mp4", n_frames=8, width=256, fps=4)
    return folder / "walk.mp4"


def photos_360_flat(folder):
    """360 photos, marked so in their XMP, of one flat grey: every view repeats the first."""
    folder.mkdir(parents=True)
    xmp = b'<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:Description GPano:ProjectionType="equirectangular"/></x:xmpmeta>'
    for i in range(3):
        Image.fromarray(np.full((64, 128, 3), 128, np.uint8)).save(folder / f"theta{i}.jpg", xmp=xmp)
    return folder


def animated_gif(path):
    frames = [Image.fromarray(textured(seed=s)) for s in range(3)]
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=100, loop=0)


@lru_cache(maxsize=1)
def pose_template() -> Path:
    """A tiny synthetic scene with its transforms.json, made once per test process."""
    return write_scene("object", Path(tempfile.mkdtemp()) / "object", n_views=6, width=40, height=30, seed=3,
                       supersample=1)


def posed(edit):
    """A copy of the template scene whose pose files `edit` spoils (it gets the scene folder and its transforms)."""
    def make(folder):
        shutil.copytree(pose_template() / "images", folder / "images")
        meta = json.loads((pose_template() / "transforms.json").read_text())
        meta = edit(folder, meta)
        if meta is not None:
            (folder / "transforms.json").write_text(json.dumps(meta))
        return folder
    return make


def frame_matrix(value):
    def edit(folder, meta):
        meta["frames"][0]["transform_matrix"] = value(meta["frames"][0]["transform_matrix"])
        return meta
    return edit


def without(key, in_frame=False):
    def edit(folder, meta):
        (meta["frames"][0] if in_frame else meta).pop(key)
        return meta
    return edit


def llff(table):
    def edit(folder, meta):
        np.save(folder / "poses_bounds.npy", table)
    return edit


def colmap_no_images(folder, meta):
    (folder / "sparse" / "0").mkdir(parents=True)
    pycolmap.Reconstruction().write(str(folder / "sparse" / "0"))


def not_json(folder, meta):
    (folder / "transforms.json").write_text("{\"frames\": [")


def metashape(spoil):
    """Metashape's cameras.xml for the template's photos, spoiled by `spoil` (a function of its text)."""
    def edit(folder, meta):
        size = f'<resolution width="{meta["w"]}" height="{meta["h"]}"/>'
        cameras = "".join(
            f'<camera id="{n}" sensor_id="0" label="{Path(f["file_path"]).stem}"><transform>'
            f'{" ".join(map(repr, (np.array(f["transform_matrix"]) @ np.diag([1.0, -1, -1, 1])).ravel().tolist()))}'
            "</transform></camera>" for n, f in enumerate(meta["frames"]))
        text = (f'<?xml version="1.0"?><document version="2.0.0"><chunk><sensors><sensor id="0" type="frame">{size}'
                f'<calibration type="frame" class="adjusted">{size}<f>{meta["fl_x"]!r}</f><cx>0</cx><cy>0</cy>'
                f"</calibration></sensor></sensors><cameras>{cameras}</cameras></chunk></document>")
        (folder / "cameras.xml").write_text(spoil(text))
    return edit


def opensfm(spoil):
    """OpenSfM's reconstruction.json for the template's photos, spoiled by `spoil` (a function of its one
    reconstruction)."""
    def edit(folder, meta):
        shots = {}
        for f in meta["frames"]:
            w2c = np.linalg.inv(np.array(f["transform_matrix"]) @ np.diag([1.0, -1, -1, 1]))
            shots[Path(f["file_path"]).name] = {"rotation": cv2.Rodrigues(w2c[:3, :3])[0].ravel().tolist(),
                                                "translation": w2c[:3, 3].tolist(), "camera": "c"}
        camera = {"projection_type": "perspective", "width": meta["w"], "height": meta["h"],
                  "focal": meta["fl_x"] / max(meta["w"], meta["h"])}
        (folder / "opensfm").mkdir()
        (folder / "opensfm" / "reconstruction.json").write_text(json.dumps([spoil({"cameras": {"c": camera},
                                                                                   "shots": shots})]))
    return edit


def nsvf(spoil):
    """NSVF's pose/ folder and intrinsics.txt for the template's photos, spoiled by `spoil` (a function of the scene
    folder)."""
    def edit(folder, meta):
        (folder / "pose").mkdir()
        for f in meta["frames"]:
            c2w = np.array(f["transform_matrix"]) @ np.diag([1.0, -1, -1, 1])
            np.savetxt(folder / "pose" / f"{Path(f['file_path']).stem}.txt", c2w)
        k = np.array([[meta["fl_x"], 0, meta["cx"], 0], [0, meta["fl_y"], meta["cy"], 0], [0, 0, 1, 0], [0, 0, 0, 1]])
        np.savetxt(folder / "intrinsics.txt", k)
        spoil(folder)
    return edit


def polycam(spoil):
    """Polycam's cameras/ for the template's photos (in images/), the first camera's keys spoiled by `spoil`."""
    def edit(folder, meta):
        (folder / "cameras").mkdir()
        for n, f in enumerate(meta["frames"]):
            c2w = np.array(f["transform_matrix"])
            camera = {"fx": meta["fl_x"], "fy": meta["fl_y"], "cx": meta["cx"], "cy": meta["cy"], "width": meta["w"],
                      "height": meta["h"], **{f"t_{r}{c}": c2w[r, c] for r in range(3) for c in range(4)}}
            text = json.dumps(spoil(camera) if n == 0 else camera)
            (folder / "cameras" / f"{Path(f['file_path']).stem}.json").write_text(text)
    return edit


def record3d(spoil):
    """Record3D's metadata.json beside the template's photos (in images/, named by number), spoiled by `spoil`."""
    def edit(folder, meta):
        poses = []
        for f in sorted(meta["frames"], key=lambda f: int(Path(f["file_path"]).stem)):
            c2w = np.array(f["transform_matrix"])
            poses.append(list(pycolmap.Rotation3d(c2w[:3, :3]).quat) + c2w[:3, 3].tolist())
        k = [meta["fl_x"], 0, 0, 0, meta["fl_y"], 0, meta["cx"], meta["cy"], 1]
        data = spoil({"K": k, "w": meta["w"], "h": meta["h"], "poses": poses})
        (folder / "metadata.json").write_text(json.dumps(data))
    return edit


def mvsnet(spoil):
    """MVSNet's cams/ for the template's photos, the first camera file's text spoiled by `spoil`."""
    def edit(folder, meta):
        (folder / "cams").mkdir()
        k = np.array([[meta["fl_x"], 0, meta["cx"]], [0, meta["fl_y"], meta["cy"]], [0, 0, 1]])
        for n, f in enumerate(meta["frames"]):
            w2c = np.linalg.inv(np.array(f["transform_matrix"]) @ np.diag([1.0, -1, -1, 1]))
            rows = lambda m: "\n".join(" ".join(map(str, row)) for row in m)
            text = f"extrinsic\n{rows(w2c)}\n\nintrinsic\n{rows(k)}\n\n1 0.1\n"
            spoiled = spoil(text) if n == 0 else text
            path = folder / "cams" / f"{Path(f['file_path']).stem}_cam.txt"
            path.write_bytes(spoiled if isinstance(spoiled, bytes) else spoiled.encode())
    return edit


def realitycapture(spoil, first_only=True):
    """RealityCapture's XMP files beside the template's photos, the first one's text (every one's where not
    `first_only`) spoiled by `spoil`."""
    def edit(folder, meta):
        for n, f in enumerate(meta["frames"]):
            c2w = np.array(f["transform_matrix"])
            w2c = np.linalg.inv(c2w @ np.diag([1.0, -1, -1, 1]))
            side = max(meta["w"], meta["h"])
            text = ('<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-'
                    'ns#"><rdf:Description '
                    'xmlns:xcr="http://www.capturingreality.com/ns/xcr/1.1#" xcr:DistortionModel="brown3" '
                    f'xcr:FocalLength35mm="{meta["fl_x"] * 36 / side!r}" xcr:PrincipalPointU="0" '
                    f'xcr:PrincipalPointV="0"><xcr:Rotation>{" ".join(map(repr, w2c[:3, :3].ravel().tolist()))}'
                    f'</xcr:Rotation><xcr:Position>{" ".join(map(repr, c2w[:3, 3].tolist()))}</xcr:Position>'
                    "<xcr:DistortionCoeficients>0 0 0 0 0 0</xcr:DistortionCoeficients></rdf:Description></rdf:RDF>"
                    "</x:xmpmeta>")
            spoiled = spoil(text) if n == 0 or not first_only else text
            path = folder / "images" / f"{Path(f['file_path']).stem}.xmp"
            path.write_bytes(spoiled if isinstance(spoiled, bytes) else spoiled.encode())
    return edit


def realitycapture_csv(spoil):
    """RealityCapture's camera CSV beside images/ (every camera looking along -z), its text spoiled by `spoil`."""
    def edit(folder, meta):
        rows = ["#name,x,y,alt,heading,pitch,roll,f,px,py,k1,k2,k3,k4,t1,t2"]
        rows += [f"{Path(f['file_path']).name},0,0,{n},0,0,0,30,0,0,0,0,0,0,0,0" for n, f in enumerate(meta["frames"])]
        (folder / "cameras.csv").write_text(spoil("\n".join(rows) + "\n"))
    return edit


def meshroom(spoil):
    """Meshroom's cameras.sfm beside images/ for the template's photos (AliceVision 1.2.11: every value a string),
    spoiled by `spoil` (a function of its data; a string it returns is written as the file's text)."""
    def edit(folder, meta):
        views, poses = [], []
        for n, f in enumerate(meta["frames"]):
            w2c = np.linalg.inv(np.array(f["transform_matrix"]) @ np.diag([1.0, -1, -1, 1]))
            views.append({"viewId": str(n), "poseId": str(n), "intrinsicId": "7", "path": f["file_path"]})
            poses.append({"poseId": str(n), "pose": {"transform": {
                "rotation": [str(v) for v in w2c[:3, :3].T.ravel()],
                "center": [str(v) for v in np.array(f["transform_matrix"])[:3, 3]]}}})
        intrinsic = {"intrinsicId": "7", "width": str(meta["w"]), "height": str(meta["h"]), "sensorWidth": "36",
                     "type": "pinhole", "distortionType": "none", "undistortionType": "none",
                     "focalLength": str(meta["fl_y"] * 36 / max(meta["w"], meta["h"])),
                     "pixelRatio": str(meta["fl_y"] / meta["fl_x"]), "principalPoint": ["0", "0"]}
        data = spoil({"version": ["1", "2", "11"], "views": views, "intrinsics": [intrinsic], "poses": poses})
        (folder / "cameras.sfm").write_text(data if isinstance(data, str) else json.dumps(data))
    return edit


def bundler(spoil, with_list=True):
    """Bundler's bundle.out beside images/ for the template's photos, with its list.txt (where `with_list`), its
    text spoiled by `spoil`."""
    def edit(folder, meta):
        cameras = []
        for f in meta["frames"]:
            w2c = np.linalg.inv(np.array(f["transform_matrix"]))
            rows = [[meta["fl_x"], 0.0, 0.0], *w2c[:3, :3].tolist(), w2c[:3, 3].tolist()]
            cameras.append("\n".join(" ".join(map(repr, map(float, row))) for row in rows))
        text = f"# Bundle file v0.3\n{len(cameras)} 0\n" + "\n".join(cameras) + "\n"
        (folder / "bundle.out").write_text(spoil(text))
        if with_list:
            (folder / "list.txt").write_text("".join(f"{f['file_path']}\n" for f in meta["frames"]))
    return edit


def openmvg(spoil):
    """OpenMVG's sfm_data.json beside images/ for the template's photos (cereal's JSON: each view and intrinsic behind
    a pointer), spoiled by `spoil` (a function of its data; a string it returns is written as the file's text)."""
    def edit(folder, meta):
        views, poses = [], []
        for n, f in enumerate(meta["frames"]):
            c2w = np.array(f["transform_matrix"])
            view = {"filename": Path(f["file_path"]).name, "id_view": n, "id_intrinsic": 0, "id_pose": n}
            views.append({"key": n, "value": {"polymorphic_id": 1073741824,
                                              "ptr_wrapper": {"id": 2147483650 + n, "data": view}}})
            poses.append({"key": n, "value": {"rotation": (c2w[:3, :3] @ np.diag([1.0, -1, -1])).T.tolist(),
                                              "center": c2w[:3, 3].tolist()}})
        intrinsic = {"width": meta["w"], "height": meta["h"], "focal_length": meta["fl_x"],
                     "principal_point": [meta["cx"], meta["cy"]]}
        intrinsics = [{"key": 0, "value": {"polymorphic_id": 2147483649, "polymorphic_name": "pinhole",
                                           "ptr_wrapper": {"id": 2147483649, "data": intrinsic}}}]
        data = spoil({"sfm_data_version": "0.3", "views": views, "intrinsics": intrinsics, "extrinsics": poses})
        (folder / "sfm_data.json").write_text(data if isinstance(data, str) else json.dumps(data))
    return edit


def first_openmvg_intrinsic(**changed):
    """A spoiler of OpenMVG's scene that changes its intrinsic's keys (`polymorphic_name`) or data (the rest)."""
    def spoil(d):
        value = d["intrinsics"][0]["value"]
        name = {"polymorphic_name": changed.pop("polymorphic_name")} if "polymorphic_name" in changed else {}
        data = {**value["ptr_wrapper"]["data"], **changed}
        return {**d, "intrinsics": [{"key": 0, "value": {**value, **name, "ptr_wrapper": {"id": 2147483649,
                                                                                          "data": data}}}]}
    return spoil


def pix4d(spoil):
    """Pix4D's calibrated camera parameters beside images/ for the template's photos (its header, then a block of ten
    lines a photo), its text spoiled by `spoil`."""
    def edit(folder, meta):
        header = ("fileName imageWidth imageHeight\ncamera matrix K [3x3]\nradial distortion [3x1]\n"
                  "tangential distortion [2x1]\ncamera position t [3x1]\ncamera rotation R [3x3]\n"
                  "camera model m = K [R|-Rt] X\n\n")
        blocks = []
        for f in meta["frames"]:
            c2w = np.array(f["transform_matrix"]) @ np.diag([1.0, -1, -1, 1])
            k = [[meta["fl_x"], 0, meta["cx"]], [0, meta["fl_y"], meta["cy"]], [0, 0, 1]]
            rows = [*k, [0, 0, 0], [0, 0], c2w[:3, 3].tolist(), *c2w[:3, :3].T.tolist()]
            blocks.append(f"{Path(f['file_path']).name} {meta['w']} {meta['h']}\n" +
                          "".join(" ".join(map(repr, map(float, row))) + "\n" for row in rows))
        (folder / "p_calibrated_camera_parameters.txt").write_text(spoil(header + "".join(blocks)))
    return edit


def lines_set(lines: dict[int, str]):
    """A spoiler of a text file that sets the lines numbered (from 0) to the text given."""
    return lambda text: "\n".join(lines.get(n, line) for n, line in enumerate(text.split("\n")))


def first_pose(text):
    return lambda folder: sorted((folder / "pose").iterdir())[0].write_text(text)


POSE_KINDS = {
    "transforms_nan": posed(frame_matrix(lambda m: [[float("nan")] * 4] + m[1:])),
    "transforms_inf": posed(frame_matrix(lambda m: [[float("inf")] * 4] + m[1:])),
    "transforms_singular": posed(frame_matrix(lambda m: [[0.0] * 4] * 3 + [m[3]])),
    "transforms_non_rigid": posed(frame_matrix(lambda m: [[3 * v for v in m[0]]] + m[1:])),
    "transforms_short_matrix": posed(frame_matrix(lambda m: [row[:3] for row in m[:3]])),
    "transforms_matrix_text": posed(frame_matrix(lambda m: "identity")),
    "transforms_no_frames": posed(without("frames")),
    "transforms_no_matrix": posed(without("transform_matrix", in_frame=True)),
    "transforms_no_path": posed(without("file_path", in_frame=True)),
    "transforms_focal_text": posed(lambda folder, meta: {**meta, "fl_x": "long", "fl_y": None}),
    "transforms_frames_dict": posed(lambda folder, meta: {**meta, "frames": {"a": 1}}),
    "transforms_cut_short": posed(not_json),
    "llff_wrong_shape": posed(llff(np.zeros((6, 15)))),
    "llff_nan": posed(llff(np.full((6, 17), np.nan))),
    "llff_one_dim": posed(llff(np.zeros(17))),
    "colmap_no_images": posed(colmap_no_images),
    "metashape_cut_short": posed(metashape(lambda text: text[:len(text) // 2])),
    "metashape_focal_nan": posed(metashape(lambda text: re.sub("<f>[^<]*</f>", "<f>nan</f>", text))),
    "metashape_matrix_text": posed(metashape(lambda text: text.replace("<transform>", "<transform>identity ", 1))),
    "metashape_none_aligned": posed(metashape(lambda text: re.sub("<transform>[^<]*</transform>", "", text))),
    "metashape_spherical": posed(metashape(lambda text: text.replace('type="frame"', 'type="spherical"'))),
    "opensfm_rotation_nan": posed(opensfm(lambda r: {**r, "shots": {k: {**v, "rotation": [float("nan")] * 3}
                                                                     for k, v in r["shots"].items()}})),
    "opensfm_rotation_text": posed(opensfm(lambda r: {**r, "shots": {k: {**v, "rotation": "up"}
                                                                     for k, v in r["shots"].items()}})),
    "opensfm_camera_missing": posed(opensfm(lambda r: {**r, "cameras": {}})),
    "opensfm_focal_text": posed(opensfm(lambda r: {**r, "cameras": {"c": {**r["cameras"]["c"], "focal": "wide"}}})),
    "opensfm_projection_unknown": posed(opensfm(lambda r: {**r, "cameras": {"c": {**r["cameras"]["c"],
                                                                                 "projection_type": "dual"}}})),
    "opensfm_not_a_list": posed(opensfm(lambda r: 7)),
    "nsvf_pose_text": posed(nsvf(first_pose("identity\n"))),
    "nsvf_pose_nine_numbers": posed(nsvf(first_pose("1 0 0\n0 1 0\n0 0 1\n"))),
    "nsvf_pose_nan": posed(nsvf(first_pose("nan " * 16))),
    "nsvf_pose_singular": posed(nsvf(first_pose("0 0 0 1\n" * 3 + "0 0 0 1\n"))),
    "nsvf_no_intrinsics": posed(nsvf(lambda folder: (folder / "intrinsics.txt").unlink())),
    "nsvf_focal_zero": posed(nsvf(lambda folder: (folder / "intrinsics.txt").write_text("0 20 15 0\n0 0 0\n1\n"))),
    "nsvf_intrinsics_ragged": posed(nsvf(lambda folder: (folder / "intrinsics.txt").write_text("30 0\n0 30 15\n"))),
    "nsvf_intrinsics_binary": posed(nsvf(lambda folder: (folder / "intrinsics.txt").write_bytes(b"\xff\xfe\x00"))),
    "polycam_focal_text": posed(polycam(lambda c: {**c, "fx": "wide"})),
    "polycam_no_pose": posed(polycam(lambda c: {k: v for k, v in c.items() if not k.startswith("t_")})),
    "polycam_pose_nan": posed(polycam(lambda c: {**c, "t_00": float("nan")})),
    "polycam_width_zero": posed(polycam(lambda c: {**c, "width": 0})),
    "polycam_not_a_dict": posed(polycam(lambda c: [1, 2])),
    "record3d_k_text": posed(record3d(lambda m: {**m, "K": "pinhole"})),
    "record3d_poses_short_rows": posed(record3d(lambda m: {**m, "poses": [p[:6] for p in m["poses"]]})),
    "record3d_quaternion_zero": posed(record3d(lambda m: {**m, "poses": [[0.0] * 4 + p[4:] for p in m["poses"]]})),
    "record3d_pose_nan": posed(record3d(lambda m: {**m, "poses": [[float("nan")] * 7] + m["poses"][1:]})),
    "record3d_width_zero": posed(record3d(lambda m: {**m, "w": 0})),
    "record3d_per_frame_focal_nan": posed(record3d(lambda m: {**m, "perFrameIntrinsicCoeffs": [
        [float("nan"), m["K"][4], m["K"][6], m["K"][7]]] * len(m["poses"])})),
    "mvsnet_no_intrinsic": posed(mvsnet(lambda text: text.replace("intrinsic", "lens"))),
    "mvsnet_extrinsic_text": posed(mvsnet(lambda text: text.replace("extrinsic\n", "extrinsic\nR t\n"))),
    "mvsnet_extrinsic_singular": posed(mvsnet(lambda text: "extrinsic\n" + "0 0 0 1\n" * 4 + text.split("\n\n", 1)[1])),
    "mvsnet_focal_zero": posed(mvsnet(lambda text: text.split("intrinsic")[0] + "intrinsic\n0 0 1\n0 0 1\n0 0 1\n")),
    "mvsnet_binary": posed(mvsnet(lambda text: b"\xff\xfe\x00")),
    "realitycapture_rotation_nan": posed(realitycapture(lambda text: re.sub(
        "<xcr:Rotation>[^<]*", "<xcr:Rotation>" + "nan " * 9, text))),
    "realitycapture_rotation_short": posed(realitycapture(lambda text: re.sub(
        "<xcr:Rotation>[^<]*", "<xcr:Rotation>1 0 0 0 1 0", text))),
    "realitycapture_no_focal": posed(realitycapture(lambda text: re.sub('xcr:FocalLength35mm="[^"]*"', "", text))),
    "realitycapture_focal_text": posed(realitycapture(lambda text: re.sub(
        'xcr:FocalLength35mm="[^"]*"', 'xcr:FocalLength35mm="wide"', text))),
    "realitycapture_division_lens": posed(realitycapture(lambda text: text.replace("brown3", "division").replace(
        ">0 0 0 0 0 0<", ">-0.1 0 0 0 0 0<"), first_only=False)),
    "realitycapture_binary": posed(realitycapture(lambda text: text.encode()[:200] + b"\xff\xfe\x00")),
    "realitycapture_csv_pitch_text": posed(realitycapture_csv(lambda text: text.replace(",0,0,0,30,", ",0,level,0,30,",
                                                                                      1))),
    "realitycapture_csv_focal_zero": posed(realitycapture_csv(lambda text: text.replace(",30,", ",0,"))),
    "realitycapture_csv_cut_short": posed(realitycapture_csv(lambda text: text[:text.index("\n") + 12])),
    "meshroom_cut_short": posed(meshroom(lambda d: json.dumps(d)[:-40])),
    "meshroom_rotation_text": posed(meshroom(lambda d: {**d, "poses": [{**d["poses"][0], "pose": {"transform": {
        **d["poses"][0]["pose"]["transform"], "rotation": ["up"] * 9}}}] + d["poses"][1:]})),
    "meshroom_no_intrinsic": posed(meshroom(lambda d: {**d, "intrinsics": []})),
    "meshroom_fisheye1": posed(meshroom(lambda d: {**d, "intrinsics": [{**d["intrinsics"][0],
                                                                        "distortionType": "fisheye1"}]})),
    "meshroom_focal_nan": posed(meshroom(lambda d: {**d, "intrinsics": [{**d["intrinsics"][0],
                                                                         "focalLength": "nan"}]})),
    "meshroom_views_not_a_list": posed(meshroom(lambda d: {**d, "views": 7})),
    "bundler_no_list": posed(bundler(lambda text: text, with_list=False)),
    "bundler_count_wrong": posed(bundler(lines_set({1: "1000 0"}))),
    "bundler_focal_text": posed(bundler(lines_set({2: "wide 0 0"}))),
    "bundler_rotation_nan": posed(bundler(lines_set({3: "nan nan nan"}))),
    "bundler_rotation_singular": posed(bundler(lines_set({3: "0 0 0", 4: "0 0 0", 5: "0 0 0"}))),
    "openmvg_cut_short": posed(openmvg(lambda d: json.dumps(d)[:-30])),
    "openmvg_rotation_text": posed(openmvg(lambda d: {**d, "extrinsics": [{"key": 0, "value": {
        **d["extrinsics"][0]["value"], "rotation": [["up"] * 3] * 3}}] + d["extrinsics"][1:]})),
    "openmvg_rotation_short": posed(openmvg(lambda d: {**d, "extrinsics": [{"key": 0, "value": {
        **d["extrinsics"][0]["value"], "rotation": [[1, 0, 0], [0, 1, 0]]}}] + d["extrinsics"][1:]})),
    "openmvg_no_intrinsic": posed(openmvg(lambda d: {**d, "intrinsics": []})),
    "openmvg_focal_zero": posed(openmvg(first_openmvg_intrinsic(focal_length=0))),
    "openmvg_lens_unknown": posed(openmvg(first_openmvg_intrinsic(polymorphic_name="pinhole_division"))),
    "openmvg_lens_short": posed(openmvg(first_openmvg_intrinsic(polymorphic_name="pinhole_radial_k3",
                                                                disto_k3=[0.1]))),
    "openmvg_views_not_a_list": posed(openmvg(lambda d: {**d, "views": {"0": 1}})),
    "pix4d_cut_short": posed(pix4d(lambda text: text[:-60])),
    "pix4d_no_size": posed(pix4d(lines_set({8: "0000.png"}))),
    "pix4d_focal_text": posed(pix4d(lines_set({9: "wide 0 20"}))),
    "pix4d_focal_zero": posed(pix4d(lines_set({9: "0 0 20"}))),
    "pix4d_rotation_singular": posed(pix4d(lines_set({15: "0 0 0", 16: "0 0 0", 17: "0 0 0"}))),
    "pix4d_numbers_over": posed(pix4d(lines_set({17: "0 0 1 7"}))),
    "metashape_component_flat": posed(metashape(lambda text: text.replace(
        "<cameras>", '<components><component id="0"><transform><scale>0</scale></transform></component></components>'
        "<cameras>").replace('sensor_id="0"', 'sensor_id="0" component_id="0"'))),
}

KINDS = {
    "bomb_png": one("bomb.png", bomb_png),
    "zero_byte": one("empty.jpg", lambda p: p.write_bytes(b"")),
    "text_as_jpg": one("notes.jpg", lambda p: p.write_text("not a photo\n")),
    "truncated_jpg": one("cut.jpg", lambda p: (Image.fromarray(textured(seed=9)).save(p), p.write_bytes(p.read_bytes()[:200]))),
    "cmyk": one("cmyk.jpg", lambda p: Image.fromarray(textured(seed=4)).convert("CMYK").save(p)),
    "grey16": one("grey16.png", lambda p: cv2.imwrite(str(p), textured(seed=3)[..., 0].astype(np.uint16) * 257)),
    "palette": one("pal.png", lambda p: Image.fromarray(textured(seed=8)).convert("P").save(p)),
    "one_by_one": one("dot.png", lambda p: Image.fromarray(np.zeros((1, 1, 3), np.uint8)).save(p)),
    "huge_aspect": one("strip.png", lambda p: Image.fromarray(textured(4, 4000, seed=2)).save(p)),
    "animated_gif": one("anim.gif", animated_gif),
    "space_name": one("my photo 1.jpg", lambda p: Image.fromarray(textured(seed=11)).save(p)),
    "non_ascii_name": one("фото-é-写真.jpg", lambda p: Image.fromarray(textured(seed=12)).save(p)),
    "name_not_utf8": one(os.fsdecode(b"caf\xe9.png"), lambda p: Image.fromarray(textured(seed=13)).save(p)),
    "random_bytes_png": one("noise.png", lambda p: p.write_bytes(np.random.default_rng(0).bytes(4096))),
    "png_header_only": one("head.png", lambda p: p.write_bytes(b"\x89PNG\r\n\x1a\n")),
    "raw_random_bytes": one("IMG_9.CR2", lambda p: p.write_bytes(np.random.default_rng(1).bytes(8192))),
    "raw_tiff_header_only": one("IMG_8.dng", lambda p: p.write_bytes(b"II*\x00\x08\x00\x00\x00")),
    "folder_named_jpg": folder_named_jpg,
    "symlink_loop": symlink_loop,
    "read_only_folder": read_only,
    "mixed_sizes": mixed_sizes,
    **{f"orientation_{t}": with_orientation(t) for t in (2, 3, 4, 5, 7, 8, 0, 9, 65535)},
    "mask_other_size": mask_case(lambda i: np.full((10, 30), 255, np.uint8)),
    "mask_all_black": mask_case(lambda i: np.zeros((48, 64), np.uint8)),
    "mask_all_white": mask_case(lambda i: np.full((48, 64), 255, np.uint8)),
    "mask_rotated_exif": mask_rotated,
    "mask_turned_as_stored": mask_turned_as_stored,
    "photos_in_subfolders": photos_in_subfolders,
    "videos_two_in_folder": two_videos,
    "grey_among_colour": grey_among_colour,
    "copied_photo": copied_photo,
    "video_black_bars": video(20, picture=pillarboxed),
    "video_dark_throughout": video(20, picture=np.zeros_like),
    "video_watermarked": video(20, picture=watermarked),
    "photos_black_bars": photos_like(pillarboxed),
    "photos_dark_throughout": photos_like(np.zeros_like),
    "video_no_frames": video(0),
    "video_one_frame": video(1),
    "video_truncated": video(20, truncate=True),
    "video_360": video_360,
    "photos_360_flat": photos_360_flat,
}

# What the user must see for each kind: "skip" names the file among the skipped, "stop" is one UserError line,
# "keep" ingests every photo; a kind missing here is "keep".
EXPECT = {
    **{k: "skip" for k in ("bomb_png", "zero_byte", "text_as_jpg", "truncated_jpg", "animated_gif", "random_bytes_png",
                           "png_header_only", "raw_random_bytes", "raw_tiff_header_only")},
    **{k: "stop" for k in ("mask_other_size", "mask_rotated_exif", "video_no_frames", "video_one_frame",
                           "video_truncated", "photos_in_subfolders", "videos_two_in_folder", "video_dark_throughout",
                           "photos_dark_throughout", "photos_360_flat")},
}
