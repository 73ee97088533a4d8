"""Agisoft Metashape's cameras, as File > Export > Export Cameras writes them (cameras.xml), turned into the distorted
COLMAP model the other importers make (pose_import.py).

Metashape's frame camera (its manual's appendix on camera models): a point (X, Y, Z) in the camera's axes (x right,
y down, z forward: OpenCV's) is seen at x = X/Z, y = Y/Z, bent by radial K1-K4 (r^2 to r^8) and tangential P1, P2 (in
the order OpenCV's p2, p1 take), then u = w/2 + cx + x'(f + B1) + y' B2, v = h/2 + cy + y' f, pixels from the image's
corner. COLMAP has no r^8 term: K1-K4 become FULL_OPENCV's ratio of two cubics in r^2, fitted over the image, and
refused where they miss it by more than MAX_MODEL_ERROR_PX. Its fisheye is the equidistant model bent by K1-K4 in the
angle: OPENCV_FISHEYE. A camera's <transform> is its camera-to-world in its component's own frame (the chunk's where
the file has no components), and a component's <transform> takes that frame to the world's, often geographic (metres
from the earth's centre, which a float32 mesh cannot hold to the millimetre). So the cameras are kept in the first
component's own frame: the others' brought into it by their transforms relative to its, the world's left out, but for
the earth's up in it where the world is the earth's centre's frame (`gravity`). A
spherical sensor's photos are equirectangular (longitude atan2(X, Z) across, latitude down the rows): ingest cuts them
into views, and each takes its photo's pose turned to its yaw (imported_model.add_view)."""
from __future__ import annotations

import math
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import numpy as np

from plenoxels.core.cameras import OPENCV_TO_OPENGL_AXES, Intrinsics
from plenoxels.core.errors import UserError

# Skew, tangential terms a fisheye drops, and the ratio standing in for K1-K4: the most they may move a pixel (a drone
# camera's skew in Metashape, b2 -0.31 at 3956 px high: 0.17 px).
MAX_MODEL_ERROR_PX = 0.5
# The distances from the earth's centre a georeferenced chunk's origin lies at: the earth's radius (6357 to 6378 km)
# less the deepest land, plus the highest.
EARTH_RADIUS_M = (6.35e6, 6.39e6)


def calibrations(chunk: ElementTree.Element, path: Path) -> dict[str, tuple[str, dict[str, float] | None]]:
    """Each sensor's type (frame, fisheye, spherical, ...) and its calibration (the adjusted one where both are
    there, None where it has none): f, cx, cy, b1, b2, k1-k4, p1, p2 and the size it holds for."""
    found = {}
    for sensor in chunk.iterfind("sensors/sensor"):
        chosen = sensor.findall("calibration")
        chosen = [c for c in chosen if c.get("class") == "adjusted"] or chosen
        if not chosen:
            found[sensor.get("id")] = (sensor.get("type", "frame"), None)
            continue
        calibration = chosen[0]
        resolution = calibration.find("resolution")
        if resolution is None:
            resolution = sensor.find("resolution")
        values = {"w": resolution.get("width") if resolution is not None else None,
                  "h": resolution.get("height") if resolution is not None else None}
        values |= {key: (calibration.findtext(key) or "0") for key in
                   ("f", "cx", "cy", "b1", "b2", "k1", "k2", "k3", "k4", "p1", "p2")}
        try:
            numbers = {key: float(value) for key, value in values.items()}
        except (TypeError, ValueError):
            raise UserError(f"{path}: sensor {sensor.get('label', sensor.get('id'))} has a calibration value that is "
                            "not a number; export the cameras again or set poses.source=sfm") from None
        if not all(math.isfinite(v) for v in numbers.values()) or min(numbers["f"], numbers["w"], numbers["h"]) <= 0:
            raise UserError(f"{path}: sensor {sensor.get('label', sensor.get('id'))} has no positive finite focal "
                            "length and size; export the cameras again or set poses.source=sfm")
        found[sensor.get("id")] = (calibration.get("type", sensor.get("type", "frame")), numbers)
    return found


def _similarity(transform: ElementTree.Element, what: str, path: Path) -> np.ndarray:
    """A <transform>'s 4x4 similarity (scale times rotation, translation)."""
    try:
        rotation = np.array(transform.findtext("rotation", "1 0 0 0 1 0 0 0 1").split(), float).reshape(3, 3)
        translation = np.array(transform.findtext("translation", "0 0 0").split(), float).reshape(3)
        scale = float(transform.findtext("scale", "1"))
        if not (scale > 0 and np.isfinite([*rotation.ravel(), *translation, scale]).all()
                and abs(np.linalg.det(rotation)) > 0.5):
            raise ValueError
    except ValueError:
        raise UserError(f"{path}: {what}'s transform is not a rotation, a translation and a positive scale; export "
                        "the cameras again or set poses.source=sfm") from None
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = scale * rotation, translation
    return matrix


def component_transforms(chunk: ElementTree.Element, path: Path) -> dict[str, np.ndarray]:
    """Each component's 4x4 similarity from its cameras' frame to the first component's (`camera_to_world`)."""
    found = {component.get("id"): _similarity(component.find("transform"), f"component {component.get('id')}", path)
             for component in chunk.iterfind("components/component") if component.find("transform") is not None}
    first = next(iter(found.values()), None)
    return {key: np.linalg.solve(first, matrix) for key, matrix in found.items()}


def gravity(chunk: ElementTree.Element, path: Path) -> tuple[float, float, float] | None:
    """The world's up in the cameras' frame (the first component's, else the chunk's), where that frame's transform
    takes it to the earth's centre's frame (a georeferenced chunk: its origin the earth's radius from the centre, up
    the direction away from the centre); None for a chunk in local coordinates."""
    if "LOCAL_CS" in (chunk.findtext("reference") or ""):
        return None
    placed = chunk.find("components/component/transform")
    placed = placed if placed is not None else chunk.find("transform")
    if placed is None:
        return None
    matrix = _similarity(placed, "the chunk", path)
    if not EARTH_RADIUS_M[0] < np.linalg.norm(matrix[:3, 3]) < EARTH_RADIUS_M[1]:
        return None
    up = np.linalg.solve(matrix[:3, :3], matrix[:3, 3])
    return tuple(float(v) for v in up / np.linalg.norm(up))


def camera_and_lens(kind: str, c: dict[str, float], where: str) -> tuple[Intrinsics, str, tuple[float, ...]]:
    """The pinhole intrinsics and COLMAP lens (model, coefficients) of a Metashape calibration, at its own size."""
    w, h = c["w"], c["h"]
    k = Intrinsics(c["f"] + c["b1"], c["f"], w / 2 + c["cx"], h / 2 + c["cy"], int(round(w)), int(round(h)))
    corner = math.hypot(w, h) / 2 / c["f"]  # the farthest a pixel lies from the centre, in the image plane's units
    skew = abs(c["b2"]) * (h / 2 + abs(c["cy"])) / c["f"]  # b2 y' at the top or bottom row
    if skew > MAX_MODEL_ERROR_PX:
        raise UserError(f"{where}: its skew (b2 {c['b2']:g}) moves pixels by up to {skew:.2f} px, which no COLMAP "
                        "camera holds; set poses.source=sfm")
    if kind == "fisheye":
        tangential = (abs(c["p1"]) + abs(c["p2"])) * 3 * corner ** 2 * c["f"]
        if tangential > MAX_MODEL_ERROR_PX:
            raise UserError(f"{where}: a fisheye with tangential distortion (p1, p2), which COLMAP's fisheye lacks; "
                            "set poses.source=sfm")
        return k, "OPENCV_FISHEYE", (c["k1"], c["k2"], c["k3"], c["k4"])
    if kind != "frame":
        raise UserError(f"{where}: a {kind} camera, which this tool does not import (frame and fisheye cameras); "
                        "set poses.source=sfm")
    radial = rational_radial((c["k1"], c["k2"], c["k3"], c["k4"]), corner)
    s = np.linspace(0.0, corner ** 2, 256)
    polynomial = 1 + s * (c["k1"] + s * (c["k2"] + s * (c["k3"] + s * c["k4"])))
    ratio = ((1 + s * (radial[0] + s * (radial[1] + s * radial[2])))
             / (1 + s * (radial[3] + s * (radial[4] + s * radial[5]))))
    missed = float(np.max(np.abs(ratio - polynomial) * np.sqrt(s))) * c["f"]
    if missed > MAX_MODEL_ERROR_PX:
        raise UserError(f"{where}: its radial distortion (k1-k4) is no ratio of cubics COLMAP holds to within "
                        f"{MAX_MODEL_ERROR_PX} px ({missed:.2f} px off); set poses.source=sfm")
    p1, p2 = c["p2"], c["p1"]  # Metashape's P1 multiplies r^2 + 2x^2 in x, which is OpenCV's p2
    return k, "FULL_OPENCV", (radial[0], radial[1], p1, p2, radial[2], radial[3], radial[4], radial[5])


def rational_radial(k: tuple[float, float, float, float], corner: float) -> tuple[float, ...]:
    """FULL_OPENCV's (k1, k2, k3) over (k4, k5, k6), its radial factor (1 + k1 s + k2 s^2 + k3 s^3) /
    (1 + k4 s + k5 s^2 + k6 s^3) in s = r^2, fitted to 1 + K1 s + K2 s^2 + K3 s^3 + K4 s^4 out to r = `corner`;
    K4 = 0 is the polynomial itself."""
    if k[3] == 0:
        return (k[0], k[1], k[2], 0.0, 0.0, 0.0)
    s = np.linspace(0.0, max(corner, 1e-6) ** 2, 256)
    target = 1 + s * (k[0] + s * (k[1] + s * (k[2] + s * k[3])))
    # numerator = target * denominator, as (numerator - 1) - target * (denominator - 1) = target - 1: linear in the six
    system = np.stack([s, s ** 2, s ** 3, -target * s, -target * s ** 2, -target * s ** 3], -1)
    solution, *_ = np.linalg.lstsq(system, target - 1, rcond=None)
    return tuple(float(v) for v in solution)


def camera_to_world(transform: str, component: np.ndarray | None, where: str) -> np.ndarray:
    """Our camera-to-world (OpenGL axes) from a camera's <transform> (OpenCV axes), in the first component's frame
    (`component`: its own component's frame to that one)."""
    try:
        c2w = np.array(transform.split(), float).reshape(4, 4)
    except ValueError:
        raise UserError(f"{where}: its transform is not 16 numbers; export the cameras again or set "
                        "poses.source=sfm") from None
    c2w = c2w @ OPENCV_TO_OPENGL_AXES
    return c2w if component is None else component @ c2w


def read(path: Path) -> tuple[ElementTree.Element, dict, dict, list[tuple[str, str, str | None, str]]]:
    """The chunk with posed cameras (the first; Metashape writes the active one), its sensors' calibrations, its
    components' transforms, and each camera's (label, sensor id, component id, transform text)."""
    try:
        chunks = ElementTree.parse(path).getroot().findall(".//chunk")
    except (ElementTree.ParseError, OSError) as e:
        raise UserError(f"cannot read {path} as Metashape cameras ({str(e).splitlines()[0]}); export them again or "
                        "set poses.source=sfm") from None
    for chunk in chunks:
        cameras = [(c.get("label", ""), c.get("sensor_id"), c.get("component_id"), c.findtext("transform"))
                   for c in chunk.iter("camera") if c.findtext("transform")]
        if cameras:
            return chunk, calibrations(chunk, path), component_transforms(chunk, path), cameras
    raise UserError(f"{path} holds no aligned camera (a <camera> with a <transform>); align the photos in Metashape "
                    "and export the cameras again, or set poses.source=sfm")
