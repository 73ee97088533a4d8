"""Our renders of the field for a browser's camera, made off the page's thread: a low-resolution
preview as soon as the camera moves, the refined view once it has stood still, requests that went stale
while rendering dropped."""
from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from stages.scoring.visuals import colour_depth, to_uint8
from plenoxels.core.cameras import Intrinsics
from plenoxels.core.scene_model import SceneModel

MODES = ("rgb", "depth", "opacity")
# viser's cameras follow OpenCV (looking along +z, y down); ours follow OpenGL (looking along -z, y up).
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class ViewRequest:
    wxyz: tuple[float, float, float, float]
    position: tuple[float, float, float]
    fov: float
    """Vertical field of view in radians."""
    aspect: float
    """Width over height."""
    mode: str = "rgb"


@dataclass
class Frame:
    image: np.ndarray
    """uint8 RGB [h, w, 3]."""
    seconds: float
    refined: bool = False


def quaternion_matrix(wxyz) -> np.ndarray:
    w, x, y, z = np.asarray(wxyz, dtype=np.float64) / np.linalg.norm(wxyz)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def matrix_quaternion(rotation: np.ndarray) -> np.ndarray:
    """wxyz of a rotation matrix (the branch on the largest diagonal term keeps it stable)."""
    m = np.asarray(rotation, dtype=np.float64)
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + m[i, i] - m[j, j] - m[k, k], 1e-12))
        q = [0.0] * 4
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def opencv_pose(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Our camera-to-world -> viser's (wxyz, position)."""
    return matrix_quaternion(c2w[:3, :3] @ OPENCV_TO_OPENGL), np.asarray(c2w[:3, 3], dtype=np.float64)


def view_camera(view: ViewRequest, side: int) -> tuple[np.ndarray, Intrinsics]:
    """The camera-to-world (OpenGL) and pinhole intrinsics of the browser's view, longest side `side` pixels."""
    c2w = np.eye(4)
    c2w[:3, :3] = quaternion_matrix(view.wxyz) @ OPENCV_TO_OPENGL
    c2w[:3, 3] = view.position
    aspect = max(view.aspect, 1e-3)
    w, h = (side, max(1, round(side / aspect))) if aspect >= 1 else (max(1, round(side * aspect)), side)
    focal = h / 2 / math.tan(view.fov / 2)
    return c2w, Intrinsics(focal, focal, w / 2, h / 2, w, h)


def render_view(model: SceneModel, view: ViewRequest, side: int) -> Frame:
    started = time.perf_counter()
    c2w, k = view_camera(view, side)
    result = model.render_camera(c2w, k)
    rgb, depth, opacity = (result[key].detach().float().cpu().numpy() for key in ("rgb", "depth", "opacity"))
    if view.mode == "depth":
        image = colour_depth(depth, opacity)
    elif view.mode == "opacity":
        image = np.repeat(to_uint8(opacity)[..., None], 3, axis=-1)
    else:
        image = to_uint8(rgb)
    return Frame(image, time.perf_counter() - started)


class RenderLoop:
    """One browser's renders on a worker thread. `request` never blocks: it replaces whatever waited."""

    def __init__(self, render: Callable[[ViewRequest, int], Frame], show: Callable[[Frame], None],
                 preview_side: Callable[[], int], full_side: Callable[[], int], settle: float):
        self._render, self._show = render, show
        self._preview_side, self._full_side, self._settle = preview_side, full_side, settle
        self._changed = threading.Condition()
        self._pending: ViewRequest | None = None
        self._version = 0
        self._stopped = False
        self._thread = threading.Thread(target=self._run, name="viewer-render", daemon=True)
        self._thread.start()

    def request(self, view: ViewRequest) -> None:
        with self._changed:
            self._pending, self._version = view, self._version + 1
            self._changed.notify()

    def stop(self) -> None:
        with self._changed:
            self._stopped = True
            self._changed.notify()

    def _current(self, version: int) -> bool:
        with self._changed:
            return self._version == version and not self._stopped

    def _run(self) -> None:
        while True:
            with self._changed:
                self._changed.wait_for(lambda: self._pending is not None or self._stopped)
                if self._stopped:
                    return
                view, version, self._pending = self._pending, self._version, None
            preview, full = self._preview_side(), self._full_side()
            if preview < full:
                frame = self._safe_render(view, preview)
                if frame is not None and self._current(version):
                    self._show(frame)
                with self._changed:
                    if self._changed.wait_for(lambda: self._version != version or self._stopped, timeout=self._settle):
                        continue
            frame = self._safe_render(view, full)
            if frame is not None and self._current(version):
                frame.refined = True
                self._show(frame)

    def _safe_render(self, view: ViewRequest, side: int) -> Frame | None:
        try:
            return self._render(view, side)
        except Exception as exc:  # a broken frame must not end the browser's renders
            print(f"[view] render failed: {exc}")
            return None
