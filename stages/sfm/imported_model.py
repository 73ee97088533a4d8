"""The COLMAP model an import builds (pose_import.py and the readers beside it): its cameras, one a distinct
pinhole and lens at the ingested image size, and its images, each a photo's pose checked to be rigid; the views ingest
cut from a 360 frame, each its frame's pose turned."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from stages.capture.panorama import view_rotation
from plenoxels.core.cameras import Intrinsics, colmap_w2c_from_opengl_c2w
from plenoxels.core.errors import UserError

# The most one axis of a pose's rotation may be stretched beyond another (its singular values' ratio): a pose file's
# float noise, printed to six digits, stays below 1.0001; a sheared or hand-damaged matrix does not.
NON_RIGID_STRETCH = 1.02

# How far an image's size may be from the pose file's size after scaling before we call it a different image.
SIZE_TOLERANCE_PX = 1.5
# A photo's EXIF orientations that turn its stored pixels to show it upright -> the turn from the stored pixels'
# camera axes to the upright photo's (OpenCV's: x right, y down, z forward). 6: a quarter clockwise (a phone held
# upright), 8: anticlockwise, 3: a half turn (a phone held upside down). 2, 4, 5 and 7 also mirror it, which no camera
# does.
TURNS = {3: np.diag([-1.0, -1.0, 1.0]), 6: np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
         8: np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])}
QUARTER_TURNS = (6, 8)
# A lens as COLMAP models it: the camera model's name and its distortion coefficients (after fx, fy, cx, cy).
Lens = tuple[str, tuple[float, ...]]
NO_LENS: Lens = ("OPENCV", ())  # a pinhole


@dataclass
class Imported:
    reconstruction: pycolmap.Reconstruction
    path: Path                                    # the file or folder the poses came from
    missing: list[str]                            # ingested images the pose file has no entry for
    bounds: dict[str, tuple[float, float]] = field(default_factory=dict)  # name -> (near, far), LLFF only
    path_matches: int = 0                         # images matched by their path rather than only their stem
    gravity: tuple[float, float, float] | None = None  # world up, where the format fixes it (ARKit's +y, ENU's +z)


def file_stem(name: str) -> str:
    return Path(name.replace("\\", "/")).name.rsplit(".", 1)[0] if "." in Path(name).name else Path(name).name


def rigid_from_c2w(c2w, where: str, turn: np.ndarray | None = None) -> pycolmap.Rigid3d:
    """COLMAP's world-to-camera for our camera-to-world, turned by `turn` (3x3, in the camera's axes) where given; the
    rotation is projected onto SO(3) first because exported matrices carry float noise (and some tools fold a uniform
    scale into them). `where` names the pose in the file for the one line that refuses it."""
    try:
        c2w = np.array(c2w, dtype=np.float64)
    except (TypeError, ValueError):
        raise UserError(f"{where}: the camera pose is not a 4x4 matrix of numbers; fix the pose file or set "
                        "poses.source=sfm") from None
    # LAPACK's SVD can loop forever on inf or NaN, and a singular rotation has no nearest rigid pose
    if c2w.shape[-2:] not in ((3, 4), (4, 4)) or not np.isfinite(c2w).all() or abs(np.linalg.det(c2w[:3, :3])) < 1e-9:
        raise UserError(f"{where}: the camera pose is not a finite, invertible 3x4 or 4x4 matrix; fix the pose file or "
                        "set poses.source=sfm")
    u, singular, vt = np.linalg.svd(c2w[:3, :3])
    # A uniform scale is a convention; one axis stretched more than the others is a damaged or sheared matrix, whose
    # nearest rotation would be a guess.
    if singular[0] > NON_RIGID_STRETCH * singular[2]:
        raise UserError(f"{where}: the camera pose's rotation stretches one axis {singular[0] / singular[2]:.2f}x more "
                        "than another, so it is no rotation; fix the pose file or set poses.source=sfm")
    c2w[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt @ (np.eye(3) if turn is None else turn)
    rotation, translation = colmap_w2c_from_opengl_c2w(c2w)
    return pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), translation)


def finite_number(value, key: str, where: str, positive: bool = False) -> float:
    """A pose file's number, or one line that names the key and the file."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = float("nan")
    if not math.isfinite(number) or (positive and number <= 0):
        raise UserError(f"{where}: {key} is {value!r}, not a{' positive' if positive else ''} finite number; fix the "
                        "pose file or set poses.source=sfm")
    return number


def as_stored(record: dict, pose_w: float, pose_h: float) -> bool:
    """Whether a pose file describes the photo as stored, a quarter turn from upright (its EXIF orientation not
    applied, as COLMAP reads photos): its size has the other aspect, as the stored pixels do."""
    if record.get("orientation") not in QUARTER_TURNS:
        return False
    tolerance = SIZE_TOLERANCE_PX * max(1.0, record["height"] / pose_w)
    fits_stored = abs(pose_h * record["height"] / pose_w - record["width"]) <= tolerance
    fits_upright = abs(pose_h * record["width"] / pose_w - record["height"]) <= tolerance
    return fits_stored and not fits_upright


def ingested_size(record: dict, pose_w: float, pose_h: float) -> tuple[int, int]:
    """The ingested photo's (width, height) as the pose file sees it: as stored where it describes the pixels so."""
    turned = as_stored(record, pose_w, pose_h)
    return (record["height"], record["width"]) if turned else (record["width"], record["height"])


def scale_factor(record: dict, pose_w: float, pose_h: float, what: str) -> float:
    """The factor from the pose file's image size to the ingested one (as the pose file sees it: `ingested_size`);
    both sides must agree."""
    width, height = ingested_size(record, pose_w, pose_h)
    factor = width / pose_w
    if abs(pose_h * factor - height) > SIZE_TOLERANCE_PX * max(1.0, factor):
        raise UserError(f"{record['source']} is {record['original_width']}x{record['original_height']} but {what} "
                        f"describes {pose_w:g}x{pose_h:g} images (a different aspect); use the matching photos "
                        "or set poses.source=sfm")
    return factor


def at_ingested_size(k: Intrinsics, record: dict, what: str, pose_w: float = 0.0, pose_h: float = 0.0) -> Intrinsics:
    """`k`, a pose file's camera for its images of pose_w x pose_h (k's own size where not given), scaled to the
    ingested image as the pose file sees it (`scale_factor`; `turned_upright` turns it where that is as stored), or
    moved to the picture ingest cropped from a frame's black bars (`within_bars`)."""
    pose_w, pose_h = pose_w or k.w, pose_h or k.h
    if "frame_size" in record:
        return within_bars(k, record, what, pose_w, pose_h)
    scaled = k.scaled(scale_factor(record, pose_w, pose_h, what))
    return Intrinsics(scaled.fl_x, scaled.fl_y, scaled.cx, scaled.cy, *ingested_size(record, pose_w, pose_h))


def _frame_factor(record: dict, what: str, pose_w: float, pose_h: float) -> float:
    """The factor from a pose file's image size to the whole frame whose black bars ingest cropped; both sides must
    agree."""
    frame_w, frame_h = record["frame_size"]
    factor = frame_w / pose_w
    if abs(pose_h * factor - frame_h) > SIZE_TOLERANCE_PX * max(1.0, factor):
        raise UserError(f"{record['source']} is {frame_w}x{frame_h} but {what} describes {pose_w:g}x{pose_h:g} images "
                        "(a different aspect); use the matching photos or set poses.source=sfm")
    return factor


def within_bars(k: Intrinsics, record: dict, what: str, pose_w: float, pose_h: float) -> Intrinsics:
    """`k`, a pose file's camera of a whole frame (pose_w x pose_h), for the picture ingest cropped from within the
    frame's black bars (`bars_cropped`: x, y, width and height in the frame's pixels), at the ingested size: the crop
    moves the principal point, and a lens's terms, about it, stay as they are."""
    x, y, width, _ = record["bars_cropped"]
    whole, scale = k.scaled(_frame_factor(record, what, pose_w, pose_h)), record["width"] / width
    return Intrinsics(whole.fl_x * scale, whole.fl_y * scale, (whole.cx - x) * scale, (whole.cy - y) * scale,
                      record["width"], record["height"])


def camera_within_bars(camera: pycolmap.Camera, record: dict, what: str) -> pycolmap.Camera:
    """A COLMAP camera of a whole frame, moved to the picture ingest cropped from within its black bars and scaled to
    the ingested size, as `within_bars` moves a pinhole."""
    _frame_factor(record, what, camera.width, camera.height)  # its aspect the frame's, or one line that says not
    (frame_w, frame_h), (x, y, width, height) = record["frame_size"], record["bars_cropped"]
    moved = pycolmap.Camera(model=camera.model_name, width=camera.width, height=camera.height,
                            params=list(camera.params), camera_id=camera.camera_id)
    moved.rescale(frame_w, frame_h)
    moved.principal_point_x, moved.principal_point_y = moved.principal_point_x - x, moved.principal_point_y - y
    moved.width, moved.height = width, height
    moved.rescale(record["width"], record["height"])
    return moved


def pixels_within_bars(uv: np.ndarray, width: int, height: int, record: dict) -> np.ndarray:
    """Points [N, 2] of a whole frame's image of width x height where the picture ingest cropped from within its black
    bars has them, at the ingested size."""
    (frame_w, frame_h), (x, y, crop_w, crop_h) = record["frame_size"], record["bars_cropped"]
    return (uv * [frame_w / width, frame_h / height] - [x, y]) * [record["width"] / crop_w, record["height"] / crop_h]


def _camera(camera_id: int, k: Intrinsics, lens: Lens) -> pycolmap.Camera:
    model, coefficients = lens
    if model.endswith("OPENCV") and not any(coefficients):  # a fisheye without distortion is still no pinhole
        model, coefficients = "PINHOLE", ()
    return pycolmap.Camera(model=model, width=k.w, height=k.h, camera_id=camera_id,
                           params=[k.fl_x, k.fl_y, k.cx, k.cy, *coefficients])


class CameraTable:
    """Adds one COLMAP camera per distinct (intrinsics, lens), so a shared camera stays shared."""

    def __init__(self, reconstruction: pycolmap.Reconstruction):
        self.reconstruction = reconstruction
        self.ids: dict[tuple, int] = {}

    def id_for(self, k: Intrinsics, lens: Lens = NO_LENS) -> int:
        key = (round(k.fl_x, 6), round(k.fl_y, 6), round(k.cx, 6), round(k.cy, 6), k.w, k.h, lens[0],
               *(round(d, 9) for d in lens[1]))
        if key not in self.ids:
            self.ids[key] = len(self.ids) + 1
            self.reconstruction.add_camera_with_trivial_rig(_camera(self.ids[key], k, lens))
        return self.ids[key]


def add_image(reconstruction: pycolmap.Reconstruction, image_id: int, record: dict, camera_id: int,
              c2w: np.ndarray, where: str, turn: np.ndarray | None = None) -> None:
    image = pycolmap.Image(name=f"{record['name']}.png", camera_id=camera_id, image_id=image_id)
    reconstruction.add_image_with_trivial_frame(image, rigid_from_c2w(c2w, where, turn))


def add_view(reconstruction: pycolmap.Reconstruction, cameras: CameraTable, record: dict, model: str,
             equirect: bool, c2w, where: str) -> None:
    """A view ingest cut from a 360 frame: its frame's pose turned to the view's yaw and pitch, the pinhole it was cut
    as; `model` names the pose file's camera, `equirect` whether it is a 360 camera's."""
    if not equirect:
        raise UserError(f"{where}: ingest cut {record['source']} into 360 views (ingest.equirect), but the pose file's "
                        f"camera is {model}; set ingest.equirect=auto to import the photos as they are")
    if "panorama" not in record:
        raise UserError(f"{where}: a 360 camera ({model}), but ingest did not cut {record['source']} into views (it "
                        f"is {record['original_width']}x{record['original_height']}, or ingest.equirect=no); a 360 "
                        "frame is 2:1: give the frames as the camera wrote them and ingest.equirect=auto")
    side = record["width"]
    k = Intrinsics(record["focal"], record["focal"], side / 2, record["height"] / 2, side, record["height"])
    add_image(reconstruction, len(reconstruction.images) + 1, record, cameras.id_for(k), c2w, where,
              view_rotation(record["panorama"]["yaw"], record["panorama"].get("pitch", 0.0)))


# The camera models whose distortion is radial alone (a quarter turn keeps it), and those with OpenCV's tangential
# terms (their indices in the parameters), which turn with the photo.
RADIAL_MODELS = {"SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE",
                 "RADIAL_FISHEYE", "FOV"}
TANGENTIAL = {"OPENCV": (6, 7), "FULL_OPENCV": (6, 7)}


def upright_pixels(uv: np.ndarray, orientation: int, width: int, height: int) -> np.ndarray:
    """Points [N, 2] of a photo's stored pixels (width x height) where the photo shown upright has them (TURNS)."""
    u, v = uv[:, 0], uv[:, 1]
    moved = {3: (width - u, height - v), 6: (height - v, u), 8: (v, width - u)}[orientation]
    return np.stack(moved, axis=1)


def turned_camera(camera: pycolmap.Camera, orientation: int, camera_id: int) -> pycolmap.Camera:
    """The camera of a photo's stored pixels, turned to the photo shown upright (TURNS[orientation])."""
    if camera.model_name not in RADIAL_MODELS | set(TANGENTIAL):
        raise UserError(f"the pose file's {camera.model_name} camera describes photos as stored, turned from upright "
                        "(EXIF), and its lens does not turn with them here; give the photos upright (their pixels "
                        "turned) with their poses, or set poses.source=sfm")
    width, height = camera.width, camera.height
    quarter = orientation in QUARTER_TURNS
    turned = pycolmap.Camera(model=camera.model_name, width=height if quarter else width,
                             height=width if quarter else height, params=list(camera.params), camera_id=camera_id)
    if quarter:
        turned.focal_length_x, turned.focal_length_y = camera.focal_length_y, camera.focal_length_x
    (turned.principal_point_x, turned.principal_point_y), = upright_pixels(
        np.array([[camera.principal_point_x, camera.principal_point_y]]), orientation, width, height)
    if camera.model_name in TANGENTIAL:  # OpenCV's (p2, p1) is a vector in the image plane: it turns with it
        i1, i2 = TANGENTIAL[camera.model_name]
        p2, p1 = TURNS[orientation][:2, :2] @ [camera.params[i2], camera.params[i1]]
        params = turned.params
        params[i1], params[i2] = p1, p2
        turned.params = params
    return turned


def turned_upright(reconstruction: pycolmap.Reconstruction, records: list[dict],
                   half_turns: bool = False) -> tuple[pycolmap.Reconstruction, int]:
    """The model with each image a pose file describes as its photo is stored, turned from upright, turned to the
    photo as ingested (its camera, pose and keypoints); and how many were turned. A quarter turn shows in the
    camera's aspect (`as_stored`); a half turn does not, and is taken where `half_turns` says the pose file's tool
    reads photos as stored (COLMAP)."""
    by_name = {f"{record['name']}.png": record for record in records}

    def orientation(image) -> int | None:
        record, camera = by_name.get(image.name), reconstruction.cameras[image.camera_id]
        turn, size = (record or {}).get("orientation"), (camera.width, camera.height)
        if turn in QUARTER_TURNS and size == (record["height"], record["width"]) != (record["width"], record["height"]):
            return turn
        return turn if turn == 3 and half_turns and size == (record["width"], record["height"]) else None

    turns = {image_id: orientation(image) for image_id, image in reconstruction.images.items()}
    if not any(turns.values()):
        return reconstruction, 0
    out = pycolmap.Reconstruction()
    camera_ids: dict[tuple[int, int | None], int] = {}
    for image_id in sorted(turns):
        image, turn = reconstruction.images[image_id], turns[image_id]
        camera = reconstruction.cameras[image.camera_id]
        if (image.camera_id, turn) not in camera_ids:
            camera_ids[image.camera_id, turn] = new_id = len(camera_ids) + 1
            out.add_camera_with_trivial_rig(turned_camera(camera, turn, new_id) if turn else pycolmap.Camera(
                model=camera.model_name, width=camera.width, height=camera.height, params=list(camera.params),
                camera_id=new_id))
        keypoints = np.array([p.xy for p in image.points2D], dtype=np.float64).reshape(-1, 2)
        pose = image.cam_from_world()
        if turn:
            keypoints = upright_pixels(keypoints, turn, camera.width, camera.height)
            turn_matrix = TURNS[turn]
            pose = pycolmap.Rigid3d(pycolmap.Rotation3d(turn_matrix @ pose.rotation.matrix()),
                                    turn_matrix @ pose.translation)
        out.add_image_with_trivial_frame(pycolmap.Image(name=image.name, keypoints=keypoints,
                                                        camera_id=camera_ids[image.camera_id, turn],
                                                        image_id=image_id), pose)
    for point in reconstruction.points3D.values():
        out.add_point3D(point.xyz, point.track, point.color)
    out.update_point_3d_errors()
    return out, sum(1 for turn in turns.values() if turn)
