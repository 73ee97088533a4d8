"""The viewer's web server (viser): the scene's cameras, points, mesh and foreground box as browser-side
objects, our own render of the field as each browser's background image, the crop box, and a watcher
that swaps in each new checkpoint of a running fit."""
from __future__ import annotations

import contextlib
import getpass
import io
import ipaddress
import socket
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import viser

from pipeline.viewer.content import SceneContent, load_content
from pipeline.viewer.crop import crop_setting, read_crop, write_crop
from pipeline.viewer.model_source import ModelSource, ModelVersion
from pipeline.viewer.rendering import MODES, Frame, RenderLoop, ViewRequest, opencv_pose, render_view
from plenoxels.core.errors import UserError
from plenoxels.core.scene_model import SceneModel

TRAIN_COLOUR = (0, 170, 60)
HELD_OUT_COLOUR = (220, 120, 0)
FOREGROUND_COLOUR = (60, 110, 230)
CROP_COLOUR = (230, 40, 40)
# The first view stands this many times farther from the foreground than the first training camera, and
# higher by this much of that distance.
INITIAL_PULL_BACK = 1.6
INITIAL_RISE = 0.6
# A model that failed to load is tried again after this many seconds.
RETRY_SECONDS = 10.0
# The twelve edges of a box, as pairs of corner indices (corner bits: x, y, z).
BOX_EDGES = [(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7)]


@dataclass
class ViewOptions:
    host: str = "127.0.0.1"
    """Address to listen on: 127.0.0.1 keeps the viewer on this machine (reach it through ssh -L)."""
    port: int = 8080
    """Port to listen on (0: any free one)."""
    resolution: int = 320
    """Longest side in pixels of the refined render, made once the camera stands still."""
    preview: int = 96
    """Longest side in pixels of the render made while the camera moves."""
    settle: float = 0.25
    """Seconds the camera must stand still before the refined render."""
    poll: float = 1.0
    """Seconds between looks for a new checkpoint of a running fit."""


class LocalOnlyServer(viser.ViserServer):
    """viser's server with its share link (a public tunnel through viser's relay) disabled for good."""

    def request_share_url(self, verbose: bool = True) -> None:
        print("[view] share links are disabled: reach the viewer through ssh -L instead")
        return None


def box_segments(lo, hi) -> np.ndarray:
    corners = np.array([[(hi if (i >> a) & 1 else lo)[a] for a in range(3)] for i in range(8)], dtype=np.float32)
    return np.stack([corners[[a, b]] for a, b in BOX_EDGES])


def is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(socket.gethostbyname(host)).is_loopback
    except (OSError, ValueError):
        return False


class Viewer:
    """One scene's viewer: `start()` serves it in background threads, `serve_forever()` until Ctrl-C."""

    def __init__(self, out: Path, options: ViewOptions | None = None):
        self.out = Path(out)
        self.options = options or ViewOptions()
        self.content: SceneContent = load_content(self.out)
        self.source = ModelSource(self.out)
        self.model: SceneModel | None = None
        self.model_line = "no fit yet: cameras, points and the mesh only"
        self._version: ModelVersion | None = None
        self._failed: tuple[ModelVersion, float] | None = None
        self._loops: dict[int, RenderLoop] = {}
        self._render_lock = threading.Lock()
        self._stop = threading.Event()
        self.frames_shown = 0
        """Renders sent to browsers (refined or preview), for progress reports and tests."""
        self.last_frame: Frame | None = None
        self._preview_line = ""
        self.server: LocalOnlyServer | None = None

    # ---- lifecycle ------------------------------------------------------------------------------
    def start(self) -> str:
        """Starts serving in background threads; returns the page's address."""
        self._reload_model()
        o = self.options
        with contextlib.redirect_stdout(io.StringIO()):  # viser's own banner; address_lines() says more
            self.server = LocalOnlyServer(host=o.host, port=o.port, label="voxfield", verbose=False)
        self.server.gui.configure_theme(show_share_button=False, control_width="medium")
        self.server.scene.set_up_direction("+z")
        self._set_initial_camera()
        self._add_scene()
        self._add_gui()
        self.server.on_client_connect(self._client_connected)
        self.server.on_client_disconnect(self._client_disconnected)
        threading.Thread(target=self._watch, name="viewer-watch", daemon=True).start()
        return self.url

    @property
    def port(self) -> int:
        return self.server.get_port()

    @property
    def url(self) -> str:
        host = self.options.host if self.options.host not in ("0.0.0.0", "::") else socket.gethostname()
        return f"http://{host}:{self.port}"

    def address_lines(self) -> list[str]:
        port = self.port
        lines = [f"viewer of {self.out} on {self.url}  (Ctrl-C to stop)"]
        if is_loopback(self.options.host):
            lines.append(f"from another machine: ssh -N -L {port}:127.0.0.1:{port} {getpass.getuser()}@"
                         f"{socket.gethostname()}  then open http://localhost:{port}")
        else:
            lines.append(f"warning: listening on {self.options.host}, so anyone who can reach this machine "
                         f"can open the viewer; the default host 127.0.0.1 with ssh -L keeps it private")
        return lines

    def stop(self) -> None:
        self._stop.set()
        for loop in list(self._loops.values()):
            loop.stop()
        if self.server is not None:
            self.server.stop()

    def serve_forever(self) -> None:
        self.start()
        for line in self.address_lines():
            print(line, flush=True)
        try:
            while not self._stop.wait(3600):
                pass
        except KeyboardInterrupt:
            print("viewer stopped", flush=True)
        finally:
            self.stop()

    # ---- the scene ------------------------------------------------------------------------------
    def _set_initial_camera(self) -> None:
        """Behind and above the first training camera, looking at the foreground's centre, z up, so that the
        cameras around the scene are in view and the nearest one is not in front of the scene."""
        c = self.content
        centre = (c.foreground[0] + c.foreground[1]) / 2 if c.foreground else np.zeros(3)
        train = [cam for cam in c.cameras if cam.split == "train"] or c.cameras
        offset = train[0].c2w[:3, 3] - centre if train else np.array([3.0, 3.0, 2.0])
        distance = np.linalg.norm(offset)
        direction = offset / distance + np.array([0.0, 0.0, INITIAL_RISE])
        eye = centre + INITIAL_PULL_BACK * distance * direction / np.linalg.norm(direction)
        camera = self.server.initial_camera
        camera.position, camera.look_at, camera.up = tuple(eye), tuple(centre), (0.0, 0.0, 1.0)

    def _add_scene(self) -> None:
        scene, c = self.server.scene, self.content
        size = 0.06 * c.radius
        scene.add_frame("/world", axes_length=size * 2, axes_radius=size * 0.05, show_axes=True)
        self.handles: dict[str, list] = {"train": [], "test": []}
        for i, cam in enumerate(c.cameras):
            k = cam.intrinsics
            wxyz, position = opencv_pose(cam.c2w)
            split = "test" if cam.split == "test" else "train"
            handle = scene.add_camera_frustum(
                f"/cameras/{split}/{i:04d}", fov=2 * np.arctan(k.h / 2 / k.fl_y), aspect=k.w / k.h, scale=size,
                thickness=size * 0.04, color=TRAIN_COLOUR if split == "train" else HELD_OUT_COLOUR,
                image=cam.thumbnail, format="jpeg", wxyz=wxyz, position=position)
            handle.on_click(self._jump_to(cam.c2w))
            self.handles[split].append(handle)
        self.handles["sparse"] = [scene.add_point_cloud("/sparse_points", c.sparse_points[0].astype(np.float32),
                                                        c.sparse_points[1], point_size=0.005 * c.radius)] \
            if c.sparse_points else []
        self.handles["mesh"] = [scene.add_mesh_trimesh("/export/mesh", c.mesh, visible=False)] if c.mesh else []
        self.handles["points"] = [scene.add_point_cloud("/export/points", c.points[0].astype(np.float32), c.points[1],
                                                        point_size=0.004 * c.radius, visible=False)] if c.points else []
        self.handles["splats"] = [scene.add_gaussian_splats(
            "/export/splats", c.splats.means.numpy(), c.splats.covariances().numpy(), c.splats.diffuse().numpy(),
            c.splats.opacities()[:, None].numpy(), visible=False)] if c.splats is not None else []
        self.handles["foreground"] = [scene.add_line_segments("/foreground", box_segments(*c.foreground),
                                                              FOREGROUND_COLOUR, thickness=2.0,
                                                              thickness_units="screen")] if c.foreground else []

    def _jump_to(self, c2w: np.ndarray):
        wxyz, position = opencv_pose(c2w)

        def jump(event) -> None:
            with event.client.atomic():
                event.client.camera.wxyz, event.client.camera.position = wxyz, position
        return jump

    def _add_gui(self) -> None:
        gui, c = self.server.gui, self.content
        n_train = sum(cam.split != "test" for cam in c.cameras)
        scale = f"1 unit = {1 / c.scale:.3g} input (COLMAP) units" if c.scale else "scale unknown"
        gui.add_markdown(f"**{self.out.name}**: {n_train} training, {len(c.cameras) - n_train} held-out cameras; "
                         f"z is up; {scale}")
        self.status = gui.add_markdown(self.model_line)
        self.timing = gui.add_markdown("frame time: -")
        with gui.add_folder("render"):
            self.mode = gui.add_dropdown("show", (*MODES, "off"), initial_value="rgb")
            self.resolution = gui.add_slider("resolution", min=64, max=1024, step=32,
                                             initial_value=self.options.resolution)
        self.mode.on_update(lambda _: self._render_all())
        self.resolution.on_update(lambda _: self._render_all())
        with gui.add_folder("layers"):
            for key, label, visible in (("train", "training cameras", True), ("test", "held-out cameras", True),
                                        ("sparse", "sparse points", True), ("mesh", "exported mesh", False),
                                        ("points", "exported point cloud", False), ("splats", "exported splats", False),
                                        ("foreground", "foreground box", True)):
                box = gui.add_checkbox(label, visible, disabled=not self.handles[key])
                box.on_update(self._toggle(key, box))
        self._add_crop_gui()

    def _toggle(self, key: str, box):
        def toggle(_) -> None:
            for handle in self.handles[key]:
                handle.visible = box.value
        return toggle

    def _add_crop_gui(self) -> None:
        gui = self.server.gui
        saved = read_crop(self.out)
        lo, hi = saved if saved is not None else (self.content.foreground or (np.full(3, -1.0), np.full(3, 1.0)))
        with gui.add_folder("crop box", expand_by_default=False):
            self.crop_min = gui.add_vector3("min", tuple(float(x) for x in lo), step=0.01)
            self.crop_max = gui.add_vector3("max", tuple(float(x) for x in hi), step=0.01)
            show = gui.add_checkbox("show", saved is not None)
            save = gui.add_button("save crop")
            self.crop_note = gui.add_markdown(f"saved: `{crop_setting(lo, hi)}`" if saved is not None else
                                              "the export stage crops to this box with the setting shown on save")
        self.crop_box = self.server.scene.add_line_segments("/crop", box_segments(lo, hi), CROP_COLOUR, thickness=2.5,
                                                            thickness_units="screen", visible=saved is not None)

        def moved(_) -> None:
            lo, hi = np.minimum(self.crop_min.value, self.crop_max.value), np.maximum(self.crop_min.value, self.crop_max.value)
            self.crop_box.points = box_segments(lo, hi)
            self.crop_box.visible = show.value = True

        self.crop_min.on_update(moved)
        self.crop_max.on_update(moved)
        show.on_update(lambda _: setattr(self.crop_box, "visible", show.value))
        save.on_click(lambda _: self.save_crop(self.crop_min.value, self.crop_max.value))

    def save_crop(self, lo, hi) -> Path:
        path = write_crop(self.out, lo, hi)
        setting = crop_setting(np.minimum(lo, hi), np.maximum(lo, hi))
        self.crop_note.content = f"saved to `{path}`; export with `--set {setting}`"
        print(f"[view] crop saved to {path}; export with: python -m pipeline export SCENE --set {setting}", flush=True)
        return path

    # ---- renders --------------------------------------------------------------------------------
    def _client_connected(self, client: viser.ClientHandle) -> None:
        loop = RenderLoop(lambda view, side: self._render(view, side), lambda frame: self._show(client, frame),
                          preview_side=lambda: min(self.options.preview, int(self.resolution.value)),
                          full_side=lambda: int(self.resolution.value), settle=self.options.settle)
        self._loops[client.client_id] = loop
        client.camera.on_update(lambda camera: self._request(client))
        self._request(client)

    def _client_disconnected(self, client: viser.ClientHandle) -> None:
        loop = self._loops.pop(client.client_id, None)
        if loop is not None:
            loop.stop()

    def _request(self, client: viser.ClientHandle) -> None:
        loop = self._loops.get(client.client_id)
        if loop is None:
            return
        if self.model is None or self.mode.value == "off":
            client.scene.set_background_image(None)
            return
        camera = client.camera
        loop.request(ViewRequest(tuple(camera.wxyz), tuple(camera.position), float(camera.fov),
                                 float(camera.aspect), self.mode.value))

    def _render_all(self) -> None:
        for client in self.server.get_clients().values():
            self._request(client)

    def _render(self, view: ViewRequest, side: int) -> Frame:
        with self._render_lock:
            model = self.model
            if model is None:
                raise UserError("no model")
            return render_view(model, view, side)

    def _show(self, client: viser.ClientHandle, frame: Frame) -> None:
        # Without depth: viser's depth compositing alters the image's colours, and the page must show our render.
        client.scene.set_background_image(frame.image, format="jpeg", jpeg_quality=90)
        self.frames_shown += 1
        self.last_frame = frame
        h, w = frame.image.shape[:2]
        line = f"{frame.seconds * 1000:.0f} ms at {w}x{h}"
        if frame.refined:
            self.timing.content = f"frame time: {line}" + (f" (preview {self._preview_line})" if self._preview_line else "")
        else:
            self._preview_line = line

    # ---- live fit -------------------------------------------------------------------------------
    def _reload_model(self) -> bool:
        """Loads the newest model when it changed; returns whether it did."""
        version = self.source.latest()
        if version is None or version == self._version or \
                (self._failed and self._failed[0] == version and time.monotonic() - self._failed[1] < RETRY_SECONDS):
            return False
        try:
            model, line = self.source.load(version)
        except Exception as exc:  # a fit folder being swapped in, or a model this viewer cannot read
            print(f"[view] could not load {version.path} ({exc}); waiting for the next one", flush=True)
            self._failed = (version, time.monotonic())
            return False
        with self._render_lock:
            self.model, self.model_line, self._version = model, line, version
        return True

    def _watch(self) -> None:
        while not self._stop.wait(self.options.poll):
            if self._reload_model():
                self.status.content = self.model_line
                print(f"[view] {self.model_line}", flush=True)
                self._render_all()
