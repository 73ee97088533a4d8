"""Folders with a camera file a photo: NSVF's and NeRF++'s (svox2's Tanks and Temples and its own captures: a text
file of OpenCV camera-to-world, beside a pinhole's K; their splits held out as the folder says) and Polycam's raw
export (a JSON file a photo), MVSNet's cams/ (world-to-camera and K in one text file a photo); and Record3D's
export (one metadata file for its numbered frames)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from stages.common.json_files import read_json
from pipeline.report import Reporter
from pipeline.runner import Pipeline
from stages.capture.synthetic import write_scene

N_VIEWS = 8
FLIP_YZ = np.diag([1.0, -1.0, -1.0, 1.0])


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory) -> Path:
    return write_scene("object", tmp_path_factory.mktemp("nsvf") / "object", n_views=N_VIEWS, width=120, height=90,
                       seed=5, supersample=1)


@pytest.fixture(scope="module")
def truth(synthetic) -> dict:
    return read_json(synthetic / "transforms.json")


def run(scene: Path, out: Path, *overrides: str) -> dict:
    return Pipeline(scene, out, overrides=list(overrides), reporter=Reporter(quiet=True)).run(
        ["ingest", "poses", "normalize"])


def k_matrix(truth: dict, scale: float = 1.0) -> np.ndarray:
    fx, fy, cx, cy = (truth[key] * scale for key in ("fl_x", "fl_y", "cx", "cy"))
    return np.array([[fx, 0, cx, 0], [0, fy, cy, 0], [0, 0, 1, 0], [0, 0, 0, 1]])


def write_photo(synthetic: Path, frame: dict, path: Path, scale: int = 1) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    photo = Image.open(synthetic / frame["file_path"]).convert("RGB")
    photo.resize((photo.width * scale, photo.height * scale), Image.LANCZOS).save(path)


def nsvf_folder(synthetic: Path, truth: dict, folder: Path, prefixes: list[str], world_to_camera: bool = False,
                older_intrinsics: bool = False) -> dict[str, str]:
    """NSVF's layout: rgb/<prefix><i>.png at twice the truth's size, pose/ (or extrinsic/) <same>.txt, intrinsics.txt.
    Returns the poses stage's image name -> the truth's stem."""
    frames = sorted(truth["frames"], key=lambda f: f["file_path"])
    names = {}
    (folder / ("extrinsic" if world_to_camera else "pose")).mkdir(parents=True)
    for i, (prefix, frame) in enumerate(zip(prefixes, frames)):
        name = f"{prefix}{i:04d}"
        write_photo(synthetic, frame, folder / "rgb" / f"{name}.png", scale=2)
        c2w = np.asarray(frame["transform_matrix"]) @ FLIP_YZ
        if world_to_camera:
            np.savetxt(folder / "extrinsic" / f"{name}.txt", np.linalg.inv(c2w))
        else:
            np.savetxt(folder / "pose" / f"{name}.txt", c2w)
        names[name] = Path(frame["file_path"]).stem
    k = k_matrix(truth, 2.0)
    if older_intrinsics:  # NSVF's synthetic scenes: f cx cy 0, then lines that are not the matrix, then the size
        (folder / "intrinsics.txt").write_text(f"{k[0, 0]:.9f} {k[0, 2]:.9f} {k[1, 2]:.9f} 0.\n0. 0. 0.\n1.\n"
                                               f"{2 * truth['w']} {2 * truth['h']}\n")
    else:
        np.savetxt(folder / "intrinsics.txt", k)
    return names


def assert_poses(out: Path, truth: dict, names: dict[str, str], world: np.ndarray = np.eye(4)) -> dict:
    """The poses stage's cameras and pinhole equal the truth's (at the ingested size, the truth's own), the
    cameras moved by `world`."""
    poses = read_json(out / "poses" / "transforms.json")
    want = {Path(f["file_path"]).stem: world @ np.asarray(f["transform_matrix"]) for f in truth["frames"]}
    got = {f["name"]: np.asarray(f["transform_matrix"]) for f in poses["frames"]}
    assert sorted(got) == sorted(names)
    for name, c2w in got.items():
        np.testing.assert_allclose(c2w, want[names[name]], atol=1e-6)
    for key in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
        assert poses[key] == pytest.approx(truth[key], rel=1e-6), key
    return poses


def splits(out: Path) -> dict[str, str]:
    return {f["name"]: f["split"] for f in read_json(out / "normalize" / "scene.json")["frames"]}


@pytest.mark.parametrize("variant", ["pose", "extrinsic", "older_intrinsics"])
def test_nsvf_folder_is_posed_as_written_and_holds_out_its_val_photos(synthetic, truth, tmp_path, variant):
    folder = tmp_path / "nsvf"
    prefixes = ["0_"] * 5 + ["1_"] * 2 + ["2_"]
    names = nsvf_folder(synthetic, truth, folder, prefixes, world_to_camera=variant == "extrinsic",
                        older_intrinsics=variant == "older_intrinsics")
    run(folder, tmp_path / "out", f"ingest.max_side={truth['w']}")
    poses = assert_poses(tmp_path / "out", truth, {n: s for n, s in names.items() if not n.startswith("2_")})
    assert poses["source"] == "nsvf"
    assert splits(tmp_path / "out") == {n: "test" if n.startswith("1_") else "train"
                                        for n in names if not n.startswith("2_")}


def test_nsvf_test_split_and_a_split_it_lacks(synthetic, truth, tmp_path):
    folder = tmp_path / "nsvf"
    names = nsvf_folder(synthetic, truth, folder, ["0_"] * 6 + ["2_"] * 2)
    run(folder, tmp_path / "out", f"ingest.max_side={truth['w']}", "ingest.holdout_split=test")
    assert splits(tmp_path / "out") == {n: "test" if n.startswith("2_") else "train" for n in names}
    from plenoxels.core.errors import UserError
    with pytest.raises(UserError, match=r"no val photos to hold out.*ingest.holdout_split to one it has \(test\)"):
        run(folder, tmp_path / "val", f"ingest.max_side={truth['w']}")


def test_nsvf_photos_of_every_split_key_the_ingest(synthetic, truth, tmp_path):
    from stages.settings.ingest import fingerprint

    folder = tmp_path / "nsvf"
    nsvf_folder(synthetic, truth, folder, ["0_"] * 5 + ["1_"] * 2 + ["2_"])
    before = fingerprint(folder)
    for name in ("1_0005.png", "2_0007.png"):  # a held-out photo replaced, whichever split is held out
        with open(folder / "rgb" / name, "ab") as photo:
            photo.write(b"\0")
        assert fingerprint(folder) != before
        before = fingerprint(folder)


def test_a_folder_of_notes_beside_the_photos_is_no_pose_folder(synthetic, truth, tmp_path):
    from stages.sfm.pose_files import candidates

    frames = sorted(truth["frames"], key=lambda f: f["file_path"])[:3]
    for frame in frames:
        write_photo(synthetic, frame, tmp_path / "capture" / "images" / Path(frame["file_path"]).name)
    for folder in ("poses", "cams"):
        (tmp_path / "capture" / folder).mkdir()
        (tmp_path / "capture" / folder / "notes.txt").write_text("shot on a cloudy day\n")
    found = candidates(tmp_path / "capture")
    assert found["nsvf"] == [] and found["mvsnet"] == []  # SfM poses this capture
    stem = Path(frames[0]["file_path"]).stem
    (tmp_path / "capture" / "poses" / f"{stem}.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\n")
    (tmp_path / "capture" / "cams" / f"{stem}_cam.txt").write_text("extrinsic\n")
    found = candidates(tmp_path / "capture")
    assert found["nsvf"] == [tmp_path / "capture" / "poses"] and found["mvsnet"] == [tmp_path / "capture" / "cams"]


def nerfpp_folder(synthetic: Path, truth: dict, folder: Path, splits_of: dict[str, list[int]]) -> dict[str, str]:
    """NeRF++'s layout: <split>/rgb/<i>.png, <split>/pose/<i>.txt and <split>/intrinsics/<i>.txt, 16 numbers on one
    line each; file names repeat across splits, as its Tanks and Temples' do."""
    frames = sorted(truth["frames"], key=lambda f: f["file_path"])
    names = {}
    for split, indices in splits_of.items():
        for i, index in enumerate(indices):
            write_photo(synthetic, frames[index], folder / split / "rgb" / f"{i:06d}.png")
            for part, matrix in (("pose", np.asarray(frames[index]["transform_matrix"]) @ FLIP_YZ),
                                 ("intrinsics", k_matrix(truth))):
                (folder / split / part).mkdir(exist_ok=True)
                (folder / split / part / f"{i:06d}.txt").write_text(" ".join(map(repr, matrix.ravel().tolist())))
            names[f"{split}_rgb_{i:06d}"] = Path(frames[index]["file_path"]).stem
    return names


def test_nerfpp_folder_poses_every_split_with_its_own_files(synthetic, truth, tmp_path):
    folder = tmp_path / "tat"
    names = nerfpp_folder(synthetic, truth, folder, {"train": [0, 1, 2, 3, 4], "validation": [5], "test": [6, 7]})
    run(folder, tmp_path / "out", "ingest.holdout_split=test")
    assert_poses(tmp_path / "out", truth, {n: s for n, s in names.items() if not n.startswith("validation")})
    assert splits(tmp_path / "out") == {n: "test" if n.startswith("test") else "train"
                                        for n in names if not n.startswith("validation")}
    run(folder, tmp_path / "val", "poses.path=train/pose")  # named: that folder's photos are posed, the others named
    poses = read_json(tmp_path / "val" / "poses" / "transforms.json")
    assert sorted(f["name"] for f in poses["frames"]) == sorted(n for n in names if n.startswith("train"))


def turned_about_x(angle: float) -> np.ndarray:
    turned = np.eye(4)
    turned[1:3, 1:3] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
    return turned


def polycam_cameras(synthetic: Path, truth: dict, keyframes: Path, photos: str, cameras: str, world: np.ndarray):
    """Polycam's photos (at twice the truth's size, as JPEGs) and a camera JSON file each, its pose moved by
    `world`."""
    (keyframes / cameras).mkdir(parents=True)
    for frame in truth["frames"]:
        stem = Path(frame["file_path"]).stem
        write_photo(synthetic, frame, keyframes / photos / f"{stem}.jpg", scale=2)
        c2w = world @ np.asarray(frame["transform_matrix"])
        camera = {"fx": 2 * truth["fl_x"], "fy": 2 * truth["fl_y"], "cx": 2 * truth["cx"], "cy": 2 * truth["cy"],
                  "width": 2 * truth["w"], "height": 2 * truth["h"], "blur_score": 80.0,
                  **{f"t_{r}{c}": float(c2w[r, c]) for r in range(3) for c in range(4)}}
        (keyframes / cameras / f"{stem}.json").write_text(json.dumps(camera))


def test_polycam_export_is_posed_from_its_undistorted_photos_cameras(synthetic, truth, tmp_path):
    export = tmp_path / "polycam"
    polycam_cameras(synthetic, truth, export / "keyframes", "corrected_images", "corrected_cameras", np.eye(4))
    # The raw photos' cameras are in another frame: the undistorted photos and their own cameras are the ones read.
    polycam_cameras(synthetic, truth, export / "keyframes", "images", "cameras", turned_about_x(0.3))
    (export / "mesh_info.json").write_text("{}")
    names = {Path(f["file_path"]).stem: Path(f["file_path"]).stem for f in truth["frames"]}
    run(export, tmp_path / "out", f"ingest.max_side={truth['w']}")
    assert assert_poses(tmp_path / "out", truth, names)["source"] == "polycam"
    # Given the raw photos' folder, their own cameras are read.
    run(export / "keyframes" / "images", tmp_path / "raw", f"ingest.max_side={truth['w']}")
    assert_poses(tmp_path / "raw", truth, names, turned_about_x(0.3))


def quaternion_xyzw(rotation: np.ndarray) -> list[float]:
    """A rotation matrix's unit quaternion, (x, y, z, w)."""
    w = np.sqrt(max(0.0, 1.0 + np.trace(rotation))) / 2
    x, y, z = (np.sqrt(max(0.0, 1.0 + 2 * rotation[i, i] - np.trace(rotation))) / 2 for i in range(3))
    signs = (rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0], rotation[1, 0] - rotation[0, 1])
    x, y, z = (np.copysign(v, sign) for v, sign in zip((x, y, z), signs))
    return [float(x), float(y), float(z), float(w)]


@pytest.mark.parametrize("per_frame", [False, True])
def test_record3d_export_poses_each_numbered_frame_from_its_row(synthetic, truth, tmp_path, per_frame):
    """Record3D's metadata: K shared by every frame, or (newer exports) each frame's own fx, fy, cx, cy beside a K
    that is no longer the frames' (the focus moved after the first)."""
    export = tmp_path / "record3d"
    frames = sorted(truth["frames"], key=lambda f: f["file_path"])
    poses, names = [], {}
    for i, frame in enumerate(frames):
        write_photo(synthetic, frame, export / "rgb" / f"{i}.jpg", scale=2)
        c2w = np.asarray(frame["transform_matrix"])
        poses.append(quaternion_xyzw(c2w[:3, :3]) + c2w[:3, 3].tolist())
        names[str(i)] = Path(frame["file_path"]).stem
    k = k_matrix(truth, 2.0)[:3, :3]
    metadata = {"K": k.T.ravel().tolist(), "w": 2 * truth["w"], "h": 2 * truth["h"], "fps": 60, "poses": poses}
    if per_frame:
        metadata["perFrameIntrinsicCoeffs"] = [[k[0, 0], k[1, 1], k[0, 2], k[1, 2]]] * len(poses)
        metadata["K"] = (k * [[1.2], [1.2], [1]]).T.ravel().tolist()
    (export / "metadata.json").write_text(json.dumps(metadata))
    (export / "rgb" / "3(1).jpg").write_bytes((export / "rgb" / "3.jpg").read_bytes())  # a copy the phone made
    run(export, tmp_path / "out", f"ingest.max_side={truth['w']}")
    assert assert_poses(tmp_path / "out", truth, names)["source"] == "record3d"


def mvsnet_cam(c2w: np.ndarray, k: np.ndarray) -> str:
    """A camera file as MVSNet writes them: world-to-camera (OpenCV axes), K, then the depth range."""
    rows = lambda m: "\n".join(" ".join(f"{v:.12g}" for v in row) for row in m)
    return f"extrinsic\n{rows(np.linalg.inv(c2w @ FLIP_YZ))}\n\nintrinsic\n{rows(k)}\n\n425.0 2.5 192 905.0\n"


@pytest.mark.parametrize("layout", ["mvsnet", "blendedmvs"])
def test_mvsnet_cams_pose_the_photos_beside_them(synthetic, truth, tmp_path, layout):
    """MVSNet's images/ beside cams/; BlendedMVS's blended_images/ beside cams/, where each photo has a masked copy
    (blacked out where its reconstruction saw nothing) that is no photo of the scene."""
    folder, photos = tmp_path / "Family", "images" if layout == "mvsnet" else "blended_images"
    (folder / "cams").mkdir(parents=True)
    names = {}
    for i, frame in enumerate(sorted(truth["frames"], key=lambda f: f["file_path"])):
        write_photo(synthetic, frame, folder / photos / f"{i:08d}.jpg", scale=2)
        if layout == "blendedmvs":
            masked = np.asarray(Image.open(folder / photos / f"{i:08d}.jpg")).copy()
            masked[: masked.shape[0] // 2] = 0
            Image.fromarray(masked).save(folder / photos / f"{i:08d}_masked.jpg")
        text = mvsnet_cam(np.asarray(frame["transform_matrix"]), k_matrix(truth, 2.0)[:3, :3])
        (folder / "cams" / f"{i:08d}_cam.txt").write_text(text)
        names[f"{i:08d}"] = Path(frame["file_path"]).stem
    (folder / ("pair.txt" if layout == "mvsnet" else "cams/pair.txt")).write_text(f"{len(names)}\n")
    run(folder, tmp_path / "out", f"ingest.max_side={truth['w']}")
    assert assert_poses(tmp_path / "out", truth, names)["source"] == "mvsnet"
    if layout == "blendedmvs":
        line = read_json(tmp_path / "out" / "ingest" / "manifest.json")["summary"]["line"]
        assert line == f"{len(names)} images at {truth['w']}x{truth['h']}, {len(names)} masked copies left for the " \
                       "photos of their names"


def realitycapture_xmp(c2w: np.ndarray, k: np.ndarray, width: int, height: int, as_attributes: bool,
                       model: str = "brown3", coefficients: tuple = (0.0,) * 6) -> str:
    """An XMP file as RealityCapture writes one beside a photo it aligned: world-to-camera rotation (OpenCV axes),
    the camera's centre, a 35 mm focal length and a principal point off the centre in units of the longer side;
    its pose as elements or (RealityScan's newer files) attributes."""
    w2c = np.linalg.inv(c2w @ FLIP_YZ)
    side = max(width, height)
    rotation, position = " ".join(f"{v:.15g}" for v in w2c[:3, :3].ravel()), " ".join(f"{v:.15g}" for v in c2w[:3, 3])
    pose = (f'xcr:Rotation="{rotation}" xcr:Position="{position}"', "") if as_attributes else \
        ("", f"<xcr:Rotation>{rotation}</xcr:Rotation><xcr:Position>{position}</xcr:Position>")
    return (f'<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
            f'<rdf:Description xmlns:xcr="http://www.capturingreality.com/ns/xcr/1.1#" xcr:Version="3" '
            f'xcr:PosePrior="locked" xcr:Coordinates="absolute" xcr:DistortionModel="{model}" '
            f'xcr:FocalLength35mm="{k[0, 0] * 36 / side:.15g}" xcr:Skew="0" xcr:AspectRatio="1" '
            f'xcr:PrincipalPointU="{(k[0, 2] - width / 2) / side:.15g}" '
            f'xcr:PrincipalPointV="{(k[1, 2] - height / 2) / side:.15g}" {pose[0]}>{pose[1]}'
            f'<xcr:DistortionCoeficients>{" ".join(map(str, coefficients))}</xcr:DistortionCoeficients>'
            "</rdf:Description></rdf:RDF></x:xmpmeta>")


def test_realitycapture_xmp_files_pose_the_photos_they_stand_beside(synthetic, truth, tmp_path):
    """Photos padded on the right (their principal point left of centre), each with RealityCapture's XMP file, its
    pose an element or an attribute; one photo RealityCapture did not align (its file holds no pose), and a photo
    editor's sidecar of another's name that is no pose file."""
    folder, pad = tmp_path / "aligned", 40
    names = {}
    for i, frame in enumerate(sorted(truth["frames"], key=lambda f: f["file_path"])):
        write_photo(synthetic, frame, folder / f"IMG_{i:04d}.jpg", scale=2)
        photo = np.asarray(Image.open(folder / f"IMG_{i:04d}.jpg"))
        Image.fromarray(np.pad(photo, ((0, 0), (0, pad), (0, 0)))).save(folder / f"IMG_{i:04d}.jpg", quality=95)
        height, width = photo.shape[0], photo.shape[1] + pad
        text = realitycapture_xmp(np.asarray(frame["transform_matrix"]), k_matrix(truth, 2.0), width, height, i % 2)
        if i == 2:  # not aligned: calibration alone
            text = text.replace("<xcr:Rotation>", "<xcr:Unused>").replace("</xcr:Rotation>", "</xcr:Unused>")
        (folder / f"IMG_{i:04d}.xmp").write_text(text)
        if i != 2:
            names[f"IMG_{i:04d}"] = Path(frame["file_path"]).stem
    run(folder, tmp_path / "out", f"ingest.max_side={2 * truth['w'] + pad}")
    poses = read_json(tmp_path / "out" / "poses" / "transforms.json")
    want = {Path(f["file_path"]).stem: np.asarray(f["transform_matrix"]) for f in truth["frames"]}
    assert poses["source"] == "realitycapture" and sorted(f["name"] for f in poses["frames"]) == sorted(names)
    for frame in poses["frames"]:
        np.testing.assert_allclose(frame["transform_matrix"], want[names[frame["name"]]], atol=1e-6)
    for key, value in {"fl_x": 2 * truth["fl_x"], "cx": 2 * truth["cx"], "cy": 2 * truth["cy"],
                       "w": 2 * truth["w"] + pad, "h": 2 * truth["h"]}.items():
        assert poses[key] == pytest.approx(value, rel=1e-6), key

    exported = tmp_path / "exported"  # the XMP files exported to a folder of their own, which poses.path names
    (exported / "photos").mkdir(parents=True)
    (exported / "xmp").mkdir()
    for photo in folder.glob("*.jpg"):
        (exported / "photos" / photo.name).write_bytes(photo.read_bytes())
        (exported / "xmp" / f"{photo.stem}.xmp").write_text(photo.with_suffix(".xmp").read_text())
    run(exported / "photos", tmp_path / "out_exported", f"ingest.max_side={2 * truth['w'] + pad}",
        "ingest.crop_bars=false", f"poses.path={exported / 'xmp'}")  # the padding's black is no video's bars
    exported_poses = read_json(tmp_path / "out_exported" / "poses" / "transforms.json")
    assert exported_poses["source"] == "realitycapture" and len(exported_poses["frames"]) == len(names)

    from stages.sfm import pose_files
    edited = tmp_path / "edited"  # Lightroom's sidecars: the same names, no pose
    for i in range(3):
        write_photo(synthetic, truth["frames"][i], edited / f"IMG_{i:04d}.jpg")
        (edited / f"IMG_{i:04d}.xmp").write_text('<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF><rdf:Description '
                                                  'crs:Exposure2012="+0.50"/></rdf:RDF></x:xmpmeta>')
    assert pose_files.candidates(edited)["realitycapture"] == []


def test_realitycapture_lens_projects_as_the_opencv_lens_it_names(synthetic, truth, tmp_path):
    """A Brown lens with three radial and two tangential terms (OpenCV's k1, k2, p1, p2, k3), written in
    RealityCapture's order (k1, k2, k3, k4, t1, t2: t1 OpenCV's p2, as AliceVision reads them): the imported camera
    projects points where OpenCV's lens does. A fourth radial term (brown4), which COLMAP's model lacks, is folded
    into the others within a tenth of a pixel."""
    import cv2
    import pycolmap
    k = k_matrix(truth)[:3, :3]
    w, h = truth["w"], truth["h"]
    points = np.random.default_rng(0).uniform([-w / 2, -h / 2], [w / 2, h / 2], (200, 2)) / truth["fl_x"]
    points = np.concatenate([points, np.ones((len(points), 1))], axis=1)
    r2 = (points[:, :2] ** 2).sum(axis=1, keepdims=True)
    fourth_radial = points[:, :2] * (1 - 0.2 * r2 + 0.05 * r2 ** 2 + 0.02 * r2 ** 3 + 0.5 * r2 ** 4) * truth["fl_x"] \
        + [truth["cx"], truth["cy"]]
    opencv = cv2.projectPoints(points, np.zeros(3), np.zeros(3), k, np.array([-0.2, 0.05, 0.004, -0.003, 0.02]))[0]
    for model, ours, want, within in [("brown3t2", (-0.2, 0.05, 0.02, 0, -0.003, 0.004), opencv.reshape(-1, 2), 1e-6),
                                      ("brown4", (-0.2, 0.05, 0.02, 0.5, 0, 0), fourth_radial, 0.1)]:
        folder = tmp_path / model
        for i, frame in enumerate(sorted(truth["frames"], key=lambda f: f["file_path"])):
            write_photo(synthetic, frame, folder / f"{i:03d}.png")
            (folder / f"{i:03d}.xmp").write_text(realitycapture_xmp(np.asarray(frame["transform_matrix"]), k, w, h,
                                                                    False, model, ours))
        Pipeline(folder, tmp_path / f"out_{model}", overrides=[f"ingest.max_side={w}"],
                 reporter=Reporter(quiet=True)).run(["ingest", "poses"])
        original = read_json(tmp_path / f"out_{model}" / "poses" / "transforms.json")["original_camera"]
        camera = pycolmap.Camera(model=original["model"], width=w, height=h, params=original["params"])
        np.testing.assert_allclose(camera.img_from_cam(points), want, atol=within)


@pytest.mark.parametrize("geographic", [False, True])
def test_realitycapture_csv_poses_the_photos_it_names(synthetic, truth, tmp_path, geographic):
    """RealityCapture's camera CSV beside images/ (as nerfstudio's `ns-process-data realitycapture` reads it): each
    row's position, heading, pitch and roll (OpenGL's camera turned about z by -heading, x by pitch and y by roll),
    35 mm focal length and principal point. With `geographic`, exported in WGS 84: x and y are longitude and latitude
    (the truth's metres east, north and up of a place in Zurich), alt metres above the sea; the poses come in metres
    east, north and up of the first camera, and z is the world's up."""
    import pycolmap
    folder = tmp_path / "capture"
    rows = ["#name,x,y,alt,heading,pitch,roll,f,px,py,k1,k2,k3,k4,t1,t2"]
    frames = sorted(truth["frames"], key=lambda f: f["file_path"])
    centres = np.array([np.asarray(frame["transform_matrix"])[:3, 3] for frame in frames])
    world = np.eye(4)
    if geographic:
        latitude, longitude, altitude = pycolmap.GPSTransform().enu_to_ellipsoid(
            centres - centres[0], 47.3769, 8.5417, 408.0).T
        positions = np.stack([longitude, latitude, altitude], axis=1)
        world[:3, 3] = -centres[0]
    names = {}
    for i, frame in enumerate(frames):
        write_photo(synthetic, frame, folder / "images" / f"IMG_{i:04d}.JPG", scale=2)
        c2w = np.asarray(frame["transform_matrix"])
        rotation = c2w[:3, :3]
        pitch, roll = np.arcsin(rotation[2, 1]), np.arctan2(-rotation[2, 0], rotation[2, 2])
        about_x = np.array([[1, 0, 0], [0, np.cos(pitch), -np.sin(pitch)], [0, np.sin(pitch), np.cos(pitch)]])
        about_y = np.array([[np.cos(roll), 0, np.sin(roll)], [0, 1, 0], [-np.sin(roll), 0, np.cos(roll)]])
        about_z = rotation @ about_y.T @ about_x.T
        heading = -np.arctan2(about_z[1, 0], about_z[0, 0])
        side = 2 * max(truth["w"], truth["h"])
        values = [*(positions[i] if geographic else c2w[:3, 3]), *np.degrees([heading, pitch, roll]),
                  truth["fl_x"] * 2 * 36 / side, (2 * truth["cx"] - truth["w"]) / side,
                  (2 * truth["cy"] - truth["h"]) / side, 0, 0, 0, 0, 0, 0]
        rows.append(",".join([f"IMG_{i:04d}.JPG"] + [repr(float(v)) for v in values]))
        names[f"IMG_{i:04d}"] = Path(frame["file_path"]).stem
    (folder / "cameras.csv").write_text("\n".join(rows) + "\n")
    (folder / "notes.csv").write_text("photo,comment\nIMG_0000.JPG,first\n")  # no camera export
    run(folder, tmp_path / "out", f"ingest.max_side={truth['w']}")
    poses = assert_poses(tmp_path / "out", truth, names, world)
    assert poses["source"] == "realitycapture"
    assert poses.get("up") == ([0.0, 0.0, 1.0] if geographic else None)


def test_a_realitycapture_csv_is_read_in_degrees_only_where_its_numbers_cannot_be_metres():
    """Longitude and latitude where the cameras spread over far fewer of them than metres of altitude, or over less
    than a hundredth away from the origin (a survey flown level); metres otherwise (a crane's shot, rising ten metres
    over half a metre across, around the origin)."""
    from stages.sfm.realitycapture import in_metres

    def rows(positions):
        return {str(n): {"#name": f"{n}.jpg", "x": repr(float(x)), "y": repr(float(y)), "alt": repr(float(z))}
                for n, (x, y, z) in enumerate(positions)}
    level = rows([(8.5417 + 0.002 * (n % 3), 47.3769 + 0.001 * (n // 3), 508.0) for n in range(9)])
    assert in_metres(level, "cameras.csv")
    east = [float(row["x"]) for row in level.values()]
    assert max(east) - min(east) == pytest.approx(0.004 * 6_378_137 * np.pi / 180 * np.cos(np.radians(47.38)),
                                                  rel=0.01)  # 0.004 degrees of longitude, in metres
    rising = rows([(0.25 * np.cos(a), 0.25 * np.sin(a), 10.0 * a / 6) for a in np.linspace(0, 6, 9)])
    assert not in_metres(rising, "cameras.csv") and rising["1"]["alt"] == repr(10.0 * 0.75 / 6)
    walked = rows([(3.0 * np.cos(a), 3.0 * np.sin(a), 1.5) for a in np.linspace(0, 6, 9)])
    assert not in_metres(walked, "cameras.csv")


def meshroom_intrinsic(truth: dict, version: tuple[int, int, int], scale: float) -> dict:
    """A camera as the AliceVision of `version` writes it (every value a string), for photos at `scale` x the truth's
    size, on a phone's sensor 6.17 mm wide."""
    fx, fy, cx, cy = (truth[key] * scale for key in ("fl_x", "fl_y", "cx", "cy"))
    w, h, sensor = truth["w"] * scale, truth["h"] * scale, 6.17
    camera = {"intrinsicId": "1052", "width": str(w), "height": str(h), "sensorWidth": str(sensor),
              "sensorHeight": "4.55", "serialNumber": "phone", "type": "pinhole",
              "distortionType": "radialk3", "distortionParams": ["0", "0", "0"], "undistortionType": "none"}
    if version < (1, 2, 0):
        camera["pxFocalLength"] = str(fx)
    elif version < (1, 2, 2):
        camera["pxFocalLength"] = [str(fx), str(fy)]
    elif version < (1, 2, 5):
        camera.update(focalLength=str(fx * sensor / w), pixelRatio=str(fx / fy))
    elif version < (1, 2, 11):
        camera.update(focalLength=str(fx * sensor / w), pixelRatio=str(fy / fx))
    else:
        camera.update(focalLength=str(fy * sensor / max(w, h)), pixelRatio=str(fy / fx))
    camera["principalPoint"] = [str(cx), str(cy)] if version < (1, 2, 1) else [str(cx - w / 2), str(cy - h / 2)]
    if version < (1, 2, 8):
        camera["type"] = "radial3"
    return camera


def meshroom_transform(w2c: np.ndarray) -> dict:
    return {"rotation": [repr(float(v)) for v in w2c[:3, :3].T.ravel()],  # column by column
            "center": [repr(float(v)) for v in -w2c[:3, :3].T @ w2c[:3, 3]]}


@pytest.mark.parametrize("version, rig, lensless", [((1, 2, 11), False, False), ((1, 2, 6), False, False),
                                                    ((1, 2, 4), False, False), ((1, 2, 0), False, False),
                                                    ((1, 0, 0), False, False), ((1, 2, 11), True, False),
                                                    ((1, 2, 11), False, True)])
def test_meshroom_cameras_pose_the_photos_they_name(synthetic, truth, tmp_path, version, rig, lensless):
    """A Meshroom project's cameras.sfm (its cache beside the photos; the photos' paths those of the machine it ran
    on), in each of the file's versions whose focal length and principal point differ; one photo SfM did not place.
    With `rig`, each camera is one of a rig posed as one: the rig's pose, moved by the camera's sub-pose. With
    `lensless`, the camera has no lens, and the coefficients a writer left beside it are not read (AliceVision's
    loader passes them over too)."""
    folder = tmp_path / "capture"
    views, poses, names = [], [], {}
    sub_pose = np.eye(4)
    sub_pose[:3, :3], sub_pose[:3, 3] = turned_about_x(0.3)[:3, :3], [0.2, -0.1, 0.05]
    for i, frame in enumerate(sorted(truth["frames"], key=lambda f: f["file_path"])):
        write_photo(synthetic, frame, folder / "images" / f"IMG_{i:04d}.JPG", scale=2)
        views.append({"viewId": str(9000 + i), "poseId": str(9000 + i), "intrinsicId": "1052",
                      "path": f"C:/Users/someone/shots/IMG_{i:04d}.JPG", "width": str(2 * truth["w"]),
                      "height": str(2 * truth["h"])})
        if i == 5:
            continue
        w2c = np.linalg.inv(np.asarray(frame["transform_matrix"]) @ FLIP_YZ)
        if rig:
            views[-1].update(rigId="0", subPoseId="0", isPoseIndependant="false")
            w2c = np.linalg.inv(sub_pose) @ w2c
        poses.append({"poseId": str(9000 + i), "pose": {"transform": meshroom_transform(w2c), "locked": "0"}})
        names[f"IMG_{i:04d}"] = Path(frame["file_path"]).stem
    intrinsic = meshroom_intrinsic(truth, version, 2.0)
    if lensless:
        intrinsic.update(distortionType="none", distortionParams=["0", "0", "0"])
    data = {"version": [str(v) for v in version], "featuresFolders": [], "matchesFolders": [], "views": views,
            "intrinsics": [intrinsic], "poses": poses,
            "rigs": [{"rigId": "0", "subPoses": [{"status": "constant", "pose": meshroom_transform(sub_pose)}]}]}
    cache = folder / "MeshroomCache" / "StructureFromMotion" / "3f5a0c"
    cache.mkdir(parents=True)
    (cache / "cameras.sfm").write_text(json.dumps(data, indent=4))
    run(folder, tmp_path / "out", f"ingest.max_side={truth['w']}")
    assert assert_poses(tmp_path / "out", truth, names)["source"] == "meshroom"


@pytest.mark.parametrize("orientation", [6, 8, 3])
def test_a_colmap_model_of_photos_as_stored_is_turned_upright_with_them(synthetic, truth, tmp_path, orientation):
    """A phone's photos stored turned from upright (a quarter or a half), with the EXIF orientation that shows them
    upright, posed by COLMAP, which reads the stored pixels: each camera turns with its photo, and the poses are the
    truth's."""
    import pycolmap
    from plenoxels.core.cameras import colmap_w2c_from_opengl_c2w
    from stages.sfm.imported_model import TURNS

    folder, turn = tmp_path / "phone", TURNS[orientation]  # stored camera axes -> upright
    (folder / "images").mkdir(parents=True)
    w, h, fx, fy, cx, cy = (truth[key] for key in ("w", "h", "fl_x", "fl_y", "cx", "cy"))
    stored = {6: (h, w, fy, fx, cy, w - cx), 8: (h, w, fy, fx, h - cy, cx), 3: (w, h, fx, fy, w - cx, h - cy)}
    width, height, *pinhole = stored[orientation]
    model = pycolmap.Reconstruction()
    model.add_camera_with_trivial_rig(pycolmap.Camera(model="OPENCV", width=width, height=height, camera_id=1,
                                                      params=[*pinhole, 0, 0, 0, 0]))
    names, points = {}, np.random.default_rng(2).uniform(-0.3, 0.3, (12, 3))
    for i, frame in enumerate(sorted(truth["frames"], key=lambda f: f["file_path"])):
        upright = np.asarray(Image.open(synthetic / frame["file_path"]).convert("RGB"))
        exif = Image.Exif()
        exif[0x0112] = orientation
        Image.fromarray(np.rot90(upright, {6: 1, 8: -1, 3: 2}[orientation]).copy()).save(
            folder / "images" / f"IMG_{i:04d}.jpg", quality=95, exif=exif)
        rotation, translation = colmap_w2c_from_opengl_c2w(np.asarray(frame["transform_matrix"]))
        rotation, translation = turn.T @ rotation, turn.T @ translation
        seen = model.cameras[1].img_from_cam(points @ rotation.T + translation)  # COLMAP's matches: exact
        model.add_image_with_trivial_frame(pycolmap.Image(name=f"IMG_{i:04d}.jpg", camera_id=1, image_id=i + 1,
                                                          keypoints=seen),
                                           pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), translation))
        names[f"IMG_{i:04d}"] = Path(frame["file_path"]).stem
    for n, xyz in enumerate(points):
        model.add_point3D(xyz, pycolmap.Track([pycolmap.TrackElement(i + 1, n) for i in range(len(names))]),
                          np.zeros(3, np.uint8))
    (folder / "sparse" / "0").mkdir(parents=True)
    model.write(folder / "sparse" / "0")
    run(folder, tmp_path / "out", f"ingest.max_side={w}")
    assert assert_poses(tmp_path / "out", truth, names)["source"] == "colmap"
    summary = read_json(tmp_path / "out" / "poses" / "manifest.json")["summary"]
    assert f"describes {len(names)} photos as stored, turned from upright" in summary["line"]
    assert summary["points"] == len(points) and summary["mean_reprojection_error"] < 1e-6  # its matches turned too


@pytest.mark.parametrize("orientation", [6, 8, 3])
def test_a_turned_camera_projects_as_its_photo_turned(orientation):
    """The camera of a photo's stored pixels, turned: a point it sees lands where the stored camera puts it, moved
    as the photo's pixels move when it is shown upright (its lens's radial and tangential terms too)."""
    import pycolmap
    from stages.sfm.imported_model import TURNS, turned_camera

    stored = pycolmap.Camera(model="FULL_OPENCV", width=160, height=120, camera_id=1,
                             params=[150, 140, 83, 57, -0.2, 0.05, 0.004, -0.003, 0.02, 0, 0, 0])
    turned = turned_camera(stored, orientation, 2)
    assert (turned.width, turned.height) == ((160, 120) if orientation == 3 else (120, 160))
    points = np.random.default_rng(1).uniform([-0.5, -0.4, 1.0], [0.5, 0.4, 1.0], (100, 3))
    u, v = stored.img_from_cam(points).T
    want = np.stack({6: [120 - v, u], 8: [v, 160 - u], 3: [160 - u, 120 - v]}[orientation], axis=1)
    np.testing.assert_allclose(turned.img_from_cam(points @ TURNS[orientation].T), want, atol=1e-9)


def test_bundler_cameras_pose_the_photos_their_list_names(synthetic, truth, tmp_path):
    """Bundler's layout: list.txt beside images/, bundle/bundle.out (world-to-camera in OpenGL's axes, a focal length
    in pixels and two radial terms a camera, the principal point at the photo's centre); a camera the reconstruction
    left out has a focal length of 0."""
    folder = tmp_path / "bundler"
    (folder / "bundle").mkdir(parents=True)
    cameras, listing, names = [], [], {}
    for i, frame in enumerate(sorted(truth["frames"], key=lambda f: f["file_path"])):
        write_photo(synthetic, frame, folder / "images" / f"IMG_{i:04d}.jpg", scale=2)
        w2c = np.linalg.inv(np.asarray(frame["transform_matrix"]))
        focal = 0.0 if i == 4 else 2 * truth["fl_x"]
        rows = [[focal, 0.0, 0.0], *w2c[:3, :3], w2c[:3, 3]]
        cameras.append("\n".join(" ".join(f"{v:.15g}" for v in row) for row in rows))
        listing.append(f"images/IMG_{i:04d}.jpg 0 {focal:.6f}")
        if i != 4:
            names[f"IMG_{i:04d}"] = Path(frame["file_path"]).stem
    (folder / "bundle" / "bundle.out").write_text(f"# Bundle file v0.3\n{len(cameras)} 0\n" + "\n".join(cameras) + "\n")
    (folder / "list.txt").write_text("\n".join(listing) + "\n")
    run(folder, tmp_path / "out", f"ingest.max_side={truth['w']}")
    assert assert_poses(tmp_path / "out", truth, names)["source"] == "bundler"


def cereal_objects(values: list[tuple[int, str | None, dict]]) -> list[dict]:
    """A list of {key, value} as cereal writes OpenMVG's pointers: a type's name the first time it comes, its number
    alone after (the first with the high bit set), a new pointer's id with the high bit set too."""
    numbers: dict[str, int] = {}
    entries = []
    for pointer, (key, name, data) in enumerate(values, start=1):
        value = {"polymorphic_id": 1073741824}  # the base type, not a polymorphic one
        if name is not None and name not in numbers:
            numbers[name] = len(numbers) + 1
            value = {"polymorphic_id": 0x80000000 | numbers[name], "polymorphic_name": name}
        elif name is not None:
            value = {"polymorphic_id": numbers[name]}
        entries.append({"key": key, "value": {**value, "ptr_wrapper": {"id": 0x80000000 | pointer, "data": data}}})
    return entries


@pytest.mark.parametrize("lens", ["pinhole", "pinhole_radial_k3", "pinhole_brown_t2"])
def test_openmvg_scene_poses_the_photos_it_names(synthetic, truth, tmp_path, lens):
    """OpenMVG's layout: images/ beside reconstruction_sequential/sfm_data.json (converted from its .bin) and
    matches/sfm_data.json, the listing made before SfM (views and intrinsics, no pose), which poses nothing. Two
    intrinsics of one type (the second named by its number alone, as cereal writes it); a view SfM did not pose."""
    folder = tmp_path / "openmvg"
    frames = sorted(truth["frames"], key=lambda f: f["file_path"])
    views, extrinsics, names = [], [], {}
    for i, frame in enumerate(frames):
        write_photo(synthetic, frame, folder / "images" / f"DSC_{i:04d}.JPG", scale=2)
        views.append((i, None, {"local_path": "/home/someone/images/", "filename": f"DSC_{i:04d}.JPG",
                                "width": 2 * truth["w"], "height": 2 * truth["h"], "id_view": i,
                                "id_intrinsic": i % 2, "id_pose": 4294967295 if i == 2 else i}))
        if i != 2:
            w2c = np.linalg.inv(np.asarray(frame["transform_matrix"]) @ FLIP_YZ)
            extrinsics.append({"key": i, "value": {"rotation": w2c[:3, :3].tolist(),
                                                   "center": (-w2c[:3, :3].T @ w2c[:3, 3]).tolist()}})
            names[f"DSC_{i:04d}"] = Path(frame["file_path"]).stem
    assert truth["fl_x"] == pytest.approx(truth["fl_y"])  # OpenMVG's pinhole has one focal length
    intrinsic = {"width": 2 * truth["w"], "height": 2 * truth["h"], "focal_length": 2 * truth["fl_x"],
                 "principal_point": [2 * truth["cx"], 2 * truth["cy"]]}
    from stages.sfm.openmvg import LENSES
    key, _, order = LENSES[lens]
    if key:
        intrinsic[key] = [0.0] * len(set(order) - {None})
    intrinsics = cereal_objects([(0, lens, intrinsic), (1, lens, dict(intrinsic))])
    listing = {"sfm_data_version": "0.3", "root_path": "/home/someone/images", "views": cereal_objects(views),
               "intrinsics": intrinsics, "extrinsics": [], "structure": [], "control_points": []}
    for place, data in (("matches", listing), ("reconstruction_sequential", {**listing, "extrinsics": extrinsics})):
        (folder / place).mkdir()
        (folder / place / "sfm_data.json").write_text(json.dumps(data, indent=4))
    run(folder, tmp_path / "out", f"ingest.max_side={truth['w']}")
    assert assert_poses(tmp_path / "out", truth, names)["source"] == "openmvg"


@pytest.mark.parametrize("binary, command", [
    ("reconstruction_sequential/sfm_data.bin", "openMVG_main_ConvertSfM_DataFormat -i sfm_data.bin -o sfm_data.json"),
    ("MeshroomCache/StructureFromMotion/3f5a0c/sfm.abc", "aliceVision_convertSfMFormat -i sfm.abc -o cameras.sfm")])
def test_a_binary_pose_file_is_named_with_how_to_convert_it(synthetic, truth, tmp_path, monkeypatch, capsys, binary,
                                                            command):
    """OpenMVG's SfM writes its scene in binary (sfm_data.bin), Meshroom's as Alembic (sfm.abc): neither is read, so
    SfM poses the photos, and a warning names the file and the command that writes one that is read. OpenMVG's image
    listing beside them (matches/sfm_data.json) poses nothing, and is passed over."""
    import stages.poses
    from plenoxels.core.errors import UserError

    folder = tmp_path / "capture"
    for i, frame in enumerate(sorted(truth["frames"], key=lambda f: f["file_path"])):
        write_photo(synthetic, frame, folder / "images" / f"DSC_{i:04d}.JPG")
    (folder / binary).parent.mkdir(parents=True)
    (folder / binary).write_bytes(bytes(range(256)) * 4)
    (folder / "matches").mkdir()  # OpenMVG's image listing, made before its SfM: views, no poses
    (folder / "matches" / "sfm_data.json").write_text(json.dumps({"sfm_data_version": "0.3", "views": [],
                                                                  "intrinsics": [], "extrinsics": []}))

    def sfm(*args, **kwargs):
        raise UserError("SfM ran")

    monkeypatch.setattr(stages.poses, "reconstruct", sfm)
    with pytest.raises(UserError, match="SfM ran"):
        run(folder, tmp_path / "out")
    warnings = [line for line in capsys.readouterr().err.splitlines() if Path(binary).name in line]
    assert len(warnings) == 1 and command in warnings[0]
    with pytest.raises(UserError, match="SfM ran"):
        run(folder, tmp_path / "sfm", "poses.source=sfm")  # SfM asked for: nothing to say
    assert Path(binary).name not in capsys.readouterr().err


@pytest.mark.parametrize("lens", ["pinhole_radial_k1", "pinhole_radial_k3", "pinhole_brown_t2", "fisheye"])
def test_an_openmvg_lens_projects_as_openmvg_projects(lens):
    """Each of OpenMVG's lenses read as a COLMAP camera puts a point where OpenMVG's own model puts it (its
    formulas, from its cameras' source): radial terms, Brown's tangential pair and the fisheye's angle terms in
    order."""
    import pycolmap
    from stages.sfm.openmvg import LENSES, camera

    given = {"pinhole_radial_k1": [-0.21], "pinhole_radial_k3": [-0.2, 0.06, -0.01],
             "pinhole_brown_t2": [-0.2, 0.06, -0.01, 0.004, -0.003], "fisheye": [0.05, -0.02, 0.01, -0.004]}[lens]
    intrinsic = {"width": 640, "height": 480, "focal_length": 500.0, "principal_point": [322.0, 236.0],
                 LENSES[lens][0]: given}
    k, (model, coefficients) = camera(lens, intrinsic, "test")
    colmap = pycolmap.Camera(model=model, width=k.w, height=k.h, params=[k.fl_x, k.fl_y, k.cx, k.cy, *coefficients])
    x, y = np.random.default_rng(4).uniform(-0.5, 0.5, (2, 200))
    r2 = x * x + y * y
    if lens == "fisheye":
        theta = np.arctan(np.sqrt(r2))
        bent = theta * (1 + sum(c * theta ** (2 * n + 2) for n, c in enumerate(given))) / np.sqrt(r2)
        dx, dy = x * bent, y * bent
    else:
        k1, k2, k3, t1, t2 = (given + [0.0] * 5)[:5]
        radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
        dx = x * radial + t2 * (r2 + 2 * x * x) + 2 * t1 * x * y
        dy = y * radial + t1 * (r2 + 2 * y * y) + 2 * t2 * x * y
    want = np.stack([500.0 * dx + 322.0, 500.0 * dy + 236.0], axis=1)
    got = colmap.img_from_cam(np.stack([x, y, np.ones_like(x)], axis=1))
    np.testing.assert_allclose(got, want, atol=1e-9)


PIX4D_HEADER = ("fileName imageWidth imageHeight \ncamera matrix K [3x3] \nradial distortion [3x1] \n"
                "tangential distortion [2x1] \ncamera position t [3x1] \ncamera rotation R [3x3] \n"
                "camera model m = K [R|-Rt] X \n\n")


def test_pix4d_calibrated_cameras_pose_the_photos_they_name(synthetic, truth, tmp_path):
    """Pix4D's project beside the photos (`survey/1_initial/params/survey_calibrated_camera_parameters.txt`): a block
    a calibrated photo, one after the other (name and size, K, radial and tangential terms, position, world-to-camera
    rotation in OpenCV's axes); a photo Pix4D did not calibrate has none. Its world's z is up."""
    folder = tmp_path / "capture"
    blocks, names = [], {}
    for i, frame in enumerate(sorted(truth["frames"], key=lambda f: f["file_path"])):
        write_photo(synthetic, frame, folder / "images" / f"DJI_{i:04d}.JPG", scale=2)
        if i == 6:
            continue
        c2w = np.asarray(frame["transform_matrix"]) @ FLIP_YZ
        rows = [*k_matrix(truth, 2.0)[:3, :3], [0, 0, 0], [0, 0], c2w[:3, 3], *c2w[:3, :3].T]
        blocks.append(f"DJI_{i:04d}.JPG {2 * truth['w']} {2 * truth['h']}\n" +
                      "".join(" ".join(f"{float(v):.20f}" for v in row) + " \n" for row in rows))
        names[f"DJI_{i:04d}"] = Path(frame["file_path"]).stem
    params = folder / "survey" / "1_initial" / "params"
    params.mkdir(parents=True)
    (params / "survey_calibrated_camera_parameters.txt").write_text(PIX4D_HEADER + "".join(blocks))
    run(folder, tmp_path / "out", f"ingest.max_side={truth['w']}")
    poses = assert_poses(tmp_path / "out", truth, names)
    assert poses["source"] == "pix4d" and poses["up"] == [0.0, 0.0, 1.0]


def test_a_pix4d_lens_projects_as_pix4d_defines_it():
    """Pix4D's lens read as a COLMAP camera puts a point where Pix4D's own definition of it does (its radial terms,
    and T1, T2 as OpenCV's p1, p2)."""
    import pycolmap
    from stages.sfm.pix4d import camera

    radial, tangential = [-0.12, 0.05, -0.01], [0.0024, -0.0029]
    numbers = np.array([500.0, 0, 322, 0, 500, 236, 0, 0, 1, *radial, *tangential, 0, 0, 0, *np.eye(3).ravel()])
    k, (model, coefficients), _ = camera(640, 480, numbers, "test")
    colmap = pycolmap.Camera(model=model, width=k.w, height=k.h, params=[k.fl_x, k.fl_y, k.cx, k.cy, *coefficients])
    x, y = np.random.default_rng(5).uniform(-0.5, 0.5, (2, 200))
    r2 = x * x + y * y
    scale = 1 + radial[0] * r2 + radial[1] * r2 ** 2 + radial[2] * r2 ** 3
    (t1, t2) = tangential
    dx, dy = x * scale + 2 * t1 * x * y + t2 * (r2 + 2 * x * x), y * scale + 2 * t2 * x * y + t1 * (r2 + 2 * y * y)
    got = colmap.img_from_cam(np.stack([x, y, np.ones_like(x)], axis=1))
    np.testing.assert_allclose(got, np.stack([500 * dx + 322, 500 * dy + 236], axis=1), atol=1e-9)


def write_pose_file(scene: Path, meta: dict, kind: str) -> None:
    """The poses of `meta` (a transforms.json's) as a transforms.json, or as LLFF's poses_bounds.npy in its place."""
    if kind == "transforms":
        (scene / "transforms.json").write_text(json.dumps(meta))
        return
    (scene / "transforms.json").unlink(missing_ok=True)
    rows = []
    for frame in sorted(meta["frames"], key=lambda f: f["file_path"]):
        c2w = np.asarray(frame["transform_matrix"])
        llff = np.stack([-c2w[:3, 1], c2w[:3, 0], c2w[:3, 2], c2w[:3, 3]], 1)  # LLFF's [down, right, back]
        hwf = np.array([[meta["h"]], [meta["w"]], [meta["fl_x"]]])
        rows.append(np.concatenate([np.concatenate([llff, hwf], 1).ravel(), [0.5, 20.0]]))
    np.save(scene / "poses_bounds.npy", np.array(rows))


@pytest.mark.parametrize("kind", ["transforms", "llff"])
def test_a_pose_file_that_contradicts_its_photos_matches_is_refused_and_a_photo_that_does_left_out(tmp_path, kind):
    """A pose file checked against the photos' own matches: a pose turned 10 degrees leaves its photo out; poses
    shuffled among the photos (a file of another capture, or read in another convention) stop the poses stage with
    one line that says so. LLFF's poses too, though their depth ranges leave nothing to triangulate."""
    import cv2
    from plenoxels.core.errors import UserError

    scene = write_scene("room", tmp_path / "room", n_views=10, width=320, height=240, seed=3, supersample=1)
    truth = read_json(scene / "transforms.json")
    turned = json.loads(json.dumps(truth))
    c2w = np.asarray(turned["frames"][3]["transform_matrix"])
    c2w[:3, :3] = cv2.Rodrigues(np.array([0.17, 0.0, 0.0]))[0] @ c2w[:3, :3]
    turned["frames"][3]["transform_matrix"] = c2w.tolist()
    write_pose_file(scene, turned, kind)
    summary = Pipeline(scene, tmp_path / "turned", reporter=Reporter(quiet=True)).run(["poses"])["poses"]["summary"]
    assert summary["source"] == kind
    assert summary["pose_file_contradicted"] == [Path(truth["frames"][3]["file_path"]).stem]
    assert summary["registered"] == 9
    assert "1 photo(s) whose imported poses contradict their own matches left out" in summary["line"]

    shuffled = json.loads(json.dumps(truth))
    matrices = [frame["transform_matrix"] for frame in shuffled["frames"]]
    for frame, n in zip(shuffled["frames"], np.random.default_rng(0).permutation(len(matrices))):
        frame["transform_matrix"] = matrices[n]
    write_pose_file(scene, shuffled, kind)
    with pytest.raises(UserError, match="contradict the photos' own matches.*set poses.source=sfm"):
        Pipeline(scene, tmp_path / "shuffled", reporter=Reporter(quiet=True)).run(["poses"])
    assert not (tmp_path / "shuffled" / "poses").exists()
    write_pose_file(scene, truth, kind)  # the file as it was: every photo posed
    assert Pipeline(scene, tmp_path / "true", reporter=Reporter(quiet=True)).run(["poses"])["poses"]["summary"][
        "registered"] == 10


def turn_taking(direction: np.ndarray, to: np.ndarray) -> np.ndarray:
    """A 4x4 rotation taking the unit `direction` to the unit `to` (about their common normal)."""
    axis = np.cross(direction, to)
    sine, cosine = np.linalg.norm(axis), direction @ to
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]]) / max(sine, 1e-12)
    turn = np.eye(4)
    turn[:3, :3] = np.eye(3) + sine * k + (1 - cosine) * k @ k
    return turn


def test_a_phones_gravity_is_up_even_where_the_cameras_look_down_along_it(tmp_path):
    # A capture whose cameras look along gravity (a survey, a scan of a table from above): the cameras cannot say
    # which way is up, the phone's world (ARKit's, y up) can. The forward scene is turned so that its cameras look
    # down ARKit's y.
    scene = write_scene("forward", tmp_path / "forward", n_views=8, width=120, height=90, seed=2, supersample=1)
    truth = read_json(scene / "transforms.json")
    c2ws = np.stack([np.asarray(f["transform_matrix"]) for f in truth["frames"]])
    looking = -c2ws[:, :3, 2].mean(axis=0)
    turn = turn_taking(looking / np.linalg.norm(looking), np.array([0.0, -1.0, 0.0]))
    export = tmp_path / "record3d"
    poses = []
    for i, (frame, c2w) in enumerate(zip(truth["frames"], c2ws)):
        write_photo(scene, frame, export / "rgb" / f"{i}.jpg")
        turned = turn @ c2w
        poses.append(quaternion_xyzw(turned[:3, :3]) + turned[:3, 3].tolist())
    k = k_matrix(truth)[:3, :3]
    (export / "metadata.json").write_text(json.dumps({"K": k.T.ravel().tolist(), "w": truth["w"], "h": truth["h"],
                                                      "poses": poses}))
    run(export, tmp_path / "out")
    normalized = read_json(tmp_path / "out" / "normalize" / "scene.json")
    assert normalized["measured"]["up_from"] == "gravity, as the poses' source gives it (transforms.json's up)"
    assert normalized["measured"]["cameras_up_from_gravity_deg"] > 60   # what the cameras alone would have taken
    world = np.asarray(normalized["world_from_input"])
    np.testing.assert_allclose(world[:3, :3] @ [0.0, 1.0, 0.0] / np.linalg.norm(world[:3, :3] @ [0.0, 1.0, 0.0]),
                               [0.0, 0.0, 1.0], atol=1e-6)
    for frame in normalized["frames"]:  # every camera looks down in the world, and the frame is whole
        c2w = np.asarray(frame["transform_matrix"])
        assert np.isfinite(c2w).all() and -c2w[2, 2] < -0.9
    assert all(np.isfinite(v).all() for v in map(np.asarray, jsonable_numbers(normalized)))


def jsonable_numbers(value):
    """Every list of numbers in a JSON value."""
    if isinstance(value, dict):
        for item in value.values():
            yield from jsonable_numbers(item)
    elif isinstance(value, list) and value and all(isinstance(v, (int, float)) for v in value):
        yield value
    elif isinstance(value, list):
        for item in value:
            yield from jsonable_numbers(item)
