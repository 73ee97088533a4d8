"""The web viewer: a tiny scene's output folder served on a free loopback port and looked at by headless
Chromium (selenium), whose screenshots must show our render where the object is and the camera frustums,
and change when the camera is dragged, and the exported splats when their layer is on; plus the camera
conversions, stale render requests, the live checkpoint pick-up, the closed share tunnel, and the crop box
from the viewer to the export stage."""
import io
import json
import math
import shutil
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

from pipeline import config
from stages.common.media import read_rgb, write_png
from stages.common.json_files import read_json, write_json
from pipeline.report import Reporter
from pipeline.stage import StageContext
from pipeline.viewer import Viewer, ViewOptions
from pipeline.viewer.crop import CROP_FILE, read_crop
from pipeline.viewer.model_source import CHECKPOINT, ModelSource
from pipeline.viewer.rendering import Frame, RenderLoop, ViewRequest, opencv_pose, render_view, view_camera
from pipeline.viewer.server import HELD_OUT_COLOUR, TRAIN_COLOUR, LocalOnlyServer
from stages.scoring.visuals import to_uint8
from plenoxels.core.cameras import Intrinsics, look_at
from plenoxels.core.errors import UserError
from plenoxels.core.grid import SparseGrid
from plenoxels.core.scene_model import ModelOptions, SceneModel
from plenoxels.core.train import Fitter, TrainOptions
from plenoxels.core.ray_set import RaySet
from stages import export
from stages.interchange.splat_files import write_splat_ply
from plenoxels.splats.model import Splats
from prerequisites import missing

SH_C0 = 0.28209479177387814
RED, BLUE = np.array([0.9, 0.1, 0.1]), np.array([0.1, 0.1, 0.9])
RADIUS = 0.45
PHOTO = 48


def sphere_model(res: int = 32) -> SceneModel:
    """A sphere, red where x > 0 and blue elsewhere (so that orbiting it changes the view), on white."""
    axes = [np.linspace(-0.6, 0.6, res)] * 3
    p = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    density = 60.0 / (1 + np.exp(-(RADIUS - np.linalg.norm(p, axis=1)) / 0.02))
    colour = np.where(p[:, :1] > 0, RED, BLUE)
    links = torch.arange(len(p), dtype=torch.int32).reshape(res, res, res)
    grid = SparseGrid.from_values(links, torch.tensor(density, dtype=torch.float32),
                                  torch.tensor((colour - 0.5) / SH_C0, dtype=torch.float32), [-0.6] * 3, [0.6] * 3, 0)
    return SceneModel(grid, "object", background_color=(1.0, 1.0, 1.0))


def ring_frames(n: int = 8) -> list[dict]:
    frames = []
    for i in range(n):
        angle = 2 * math.pi * i / n
        eye = np.array([2.4 * math.cos(angle), 2.4 * math.sin(angle), 1.0])
        frames.append({"name": f"{i:03d}", "file_path": f"images/{i:03d}.png",
                       "transform_matrix": look_at(eye, np.zeros(3), np.array([0, 0, 1.0])).tolist(),
                       "fl_x": PHOTO, "fl_y": PHOTO, "cx": PHOTO / 2, "cy": PHOTO / 2, "w": PHOTO, "h": PHOTO,
                       "split": "test" if i % 4 == 0 else "train"})
    return frames


@pytest.fixture(scope="module")
def scene_out(tmp_path_factory) -> Path:
    """An output folder as the stages leave it: poses/points.npz, normalize/scene.json with photos, fit/, export/."""
    out = tmp_path_factory.mktemp("viewer") / "sphere"
    model = sphere_model()
    frames = ring_frames()
    (out / "images").mkdir(parents=True)
    for frame in frames:
        rgb = model.render_camera(np.asarray(frame["transform_matrix"]), Intrinsics.from_frame(frame))["rgb"]
        write_png(out / frame["file_path"], to_uint8(rgb.numpy()))
    for stage in ("poses", "normalize", "fit", "export"):
        (out / stage).mkdir()
    write_json(out / "normalize" / "scene.json", {
        "type": "object", "world_from_input": np.eye(4).tolist(), "input_from_world": np.eye(4).tolist(), "scale": 1.0,
        "foreground": {"min": [-0.5] * 3, "max": [0.5] * 3}, "frames": frames})
    surface = trimesh.creation.icosphere(subdivisions=2, radius=RADIUS)
    rng = np.random.default_rng(0)
    sparse = surface.vertices[rng.choice(len(surface.vertices), 40, replace=False)]
    np.savez(out / "poses" / "points.npz", xyz=sparse, rgb=rng.integers(0, 255, (len(sparse), 3)))
    model.save(out / "fit")
    surface.export(out / "export" / "mesh.ply")
    trimesh.PointCloud(surface.vertices).export(out / "export" / "points.ply")
    write_splat_ply(out / "export" / "splats.ply", surface_splats(surface.vertices))
    write_json(out / "export" / "export.json", {"frame": "normalized"})
    return out


def surface_splats(points: np.ndarray) -> Splats:
    """Small round splats on the sphere's surface points, red where x > 0 and blue elsewhere."""
    n = len(points)
    colour = np.where(points[:, :1] > 0, RED, BLUE)
    return Splats(torch.tensor(points, dtype=torch.float32), torch.full((n, 3), math.log(0.03)),
                  torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.full((n,), 3.0),
                  torch.tensor((colour - 0.5) / SH_C0, dtype=torch.float32)[:, :, None])


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(condition, timeout: float, what):
    """condition()'s first true value within `timeout` seconds; else fails naming `what` (a string, or a function
    that says what it last saw)."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what() if callable(what) else what}")


# ---- without a browser ---------------------------------------------------------------------------

def test_the_browser_camera_of_a_frustum_renders_what_that_camera_sees(scene_out):
    model = SceneModel.load(scene_out / "fit")
    frame = ring_frames()[1]
    c2w = np.asarray(frame["transform_matrix"])
    wxyz, position = opencv_pose(c2w)
    view = ViewRequest(tuple(wxyz), tuple(position), fov=2 * math.atan(0.5), aspect=1.0)
    back, k = view_camera(view, PHOTO)
    assert np.allclose(back, c2w, atol=1e-9) and (k.w, k.h) == (PHOTO, PHOTO)
    assert k.fl_x == pytest.approx(PHOTO) and k.cx == pytest.approx(PHOTO / 2)
    rendered = render_view(model, view, PHOTO)
    direct = to_uint8(model.render_camera(c2w, Intrinsics.from_frame(frame))["rgb"].numpy())
    assert np.abs(rendered.image.astype(int) - direct).max() <= 1
    wide = view_camera(ViewRequest(tuple(wxyz), tuple(position), fov=1.0, aspect=2.0), 320)[1]
    assert (wide.w, wide.h) == (320, 160)


def test_a_render_loop_shows_a_preview_then_the_refined_view_and_drops_stale_requests():
    shown, rendered, gate = [], [], threading.Event()

    def render(view: ViewRequest, side: int) -> Frame:
        rendered.append((view.fov, side))
        if view.fov == 1.0:
            gate.wait(5)  # a slow render, during which newer requests arrive
        return Frame(np.zeros((side, side, 3), np.uint8), 0.0)

    loop = RenderLoop(render, lambda frame: shown.append(frame), preview_side=lambda: 8, full_side=lambda: 32,
                      settle=0.2)
    try:
        loop.request(ViewRequest((1, 0, 0, 0), (0, 0, 0), fov=1.0, aspect=1.0))
        wait_for(lambda: rendered, 5, "the first render")
        for fov in (2.0, 3.0, 4.0):
            loop.request(ViewRequest((1, 0, 0, 0), (0, 0, 0), fov=fov, aspect=1.0))
        gate.set()
        wait_for(lambda: any(f.refined for f in shown), 5, "a refined frame")
        time.sleep(0.3)
    finally:
        loop.stop()
    # The stale first request is never shown; of the three newer ones only the last is rendered.
    assert rendered == [(1.0, 8), (4.0, 8), (4.0, 32)]
    assert [(f.image.shape[0], f.refined) for f in shown] == [(8, False), (32, True)]


def test_a_new_checkpoint_of_a_running_fit_replaces_the_model(scene_out, tmp_path):
    out = tmp_path / "live"
    shutil.copytree(scene_out, out, ignore=shutil.ignore_patterns("fit", "export"))
    source = ModelSource(out)
    assert source.latest() is None
    viewer = Viewer(out, ViewOptions(port=free_port(), poll=0.1))
    viewer.start()
    try:
        assert viewer.model is None and "no fit yet" in viewer.model_line
        frames = [f for f in ring_frames() if f["split"] == "train"]
        images = [read_rgb(out / f["file_path"]).astype(np.float32) / 255 for f in frames]
        scene = {"type": "object", "foreground": {"min": [-0.5] * 3, "max": [0.5] * 3}}
        fitter = Fitter(SceneModel.create(scene, ModelOptions(sh_degree=0), 16),
                        TrainOptions(resolutions=[16], steps=[20], batch_size=256),
                        RaySet(images, [np.asarray(f["transform_matrix"]) for f in frames],
                               [Intrinsics.from_frame(f) for f in frames]))
        (out / CHECKPOINT).parent.mkdir(parents=True)
        for step in (3, 6):
            while fitter.step < step:
                fitter.train_step()
            fitter.save_checkpoint(out / CHECKPOINT)
            wait_for(lambda: f"checkpoint at step {step}" in viewer.model_line, 10, f"the checkpoint of step {step}")
            assert torch.equal(viewer.model.grid.data, fitter.model.grid.data)
    finally:
        viewer.stop()


def test_the_viewer_listens_on_loopback_prints_the_ssh_line_and_never_shares(scene_out, capsys):
    assert ViewOptions().host == "127.0.0.1"
    viewer = Viewer(scene_out, ViewOptions(port=free_port()))
    viewer.start()
    try:
        lines = viewer.address_lines()
        assert viewer.url == f"http://127.0.0.1:{viewer.port}" and viewer.url in lines[0]
        assert f"ssh -N -L {viewer.port}:127.0.0.1:{viewer.port}" in lines[1]
        assert isinstance(viewer.server, LocalOnlyServer) and viewer.server.request_share_url() is None
        # The exported splats are a layer, off until asked for, with the colours and places of the file.
        splats = viewer.content.splats
        assert splats is not None and splats.count == len(trimesh.creation.icosphere(subdivisions=2).vertices)
        assert np.allclose(splats.means.norm(dim=1), RADIUS, atol=1e-5)
        assert np.allclose(splats.diffuse()[splats.means[:, 0] > 0.01], RED, atol=1e-5)
        assert len(viewer.handles["splats"]) == 1 and not viewer.handles["splats"][0].visible
        with socket.create_connection(("127.0.0.1", viewer.port), timeout=5):
            pass
        path = viewer.save_crop((0.2, -0.3, -0.4), (-0.1, 0.3, 0.4))
        assert path == scene_out / CROP_FILE
        lo, hi = read_crop(scene_out)
        assert np.allclose(lo, [-0.1, -0.3, -0.4]) and np.allclose(hi, [0.2, 0.3, 0.4])
        assert "export.crop=[-0.1,-0.3,-0.4,0.2,0.3,0.4]" in capsys.readouterr().out
    finally:
        viewer.stop()
        (scene_out / CROP_FILE).unlink(missing_ok=True)



def run_export(scene_out: Path, tmp_path: Path, overrides: list[str]) -> trimesh.Trimesh:
    """The export stage as the runner calls it on the scene's fit, with `--set` overrides; the mesh and points
    it writes, in the normalised frame."""
    values = {"frame": "normalized", "points": 2000, "splats": False, "texture": False,
              **config.parse_overrides(overrides).get("export", {})}
    work = tmp_path / f"export{len(list(tmp_path.iterdir()))}"
    work.mkdir()
    ctx = StageContext(scene=scene_out, out=scene_out, work=work, scratch=tmp_path / "scratch",
                       settings=config.build(export.Settings, "export", values),
                       upstream={"normalize": scene_out / "normalize", "fit": scene_out / "fit"}, scene_type="object",
                       report=Reporter(quiet=True))
    export.run(ctx)
    return trimesh.load(work / "mesh.ply", force="mesh", process=False), np.asarray(trimesh.load(work / "points.ply").vertices)


def test_the_crop_saved_in_the_viewer_limits_the_export(scene_out, tmp_path):
    viewer = Viewer(scene_out, ViewOptions(port=free_port()))
    viewer.start()
    try:
        path = viewer.save_crop((-0.6, -0.6, -0.6), (0.0, 0.6, 0.6))
    finally:
        viewer.stop()
    setting = read_json(path)["setting"]
    path.unlink()
    whole, whole_points = run_export(scene_out, tmp_path, [])
    cropped, cropped_points = run_export(scene_out, tmp_path, [setting])
    assert whole.vertices[:, 0].max() > 0.4 and whole_points[:, 0].max() > 0.4
    # Kept: what lies inside the box grown by export.crop_margin (5% of its size on each side).
    reach = 0.05 * 0.6 + 1e-6
    assert cropped.vertices[:, 0].max() <= reach and cropped_points[:, 0].max() <= reach
    assert cropped.vertices[:, 0].min() == pytest.approx(whole.vertices[:, 0].min(), abs=0.01)
    assert 0.3 * len(whole.faces) < len(cropped.faces) < 0.7 * len(whole.faces)
    with pytest.raises(UserError, match="export.crop"):
        config.build(export.Settings, "export", {"crop": [0, 0, 0, 1, 1]})


# ---- in a real browser -----------------------------------------------------------------------------

CHROMIUM = ("chromium", "chromium-browser", "google-chrome")
CHROMEDRIVER = ("chromedriver",)
WINDOW = (960, 640)


def _which(names) -> str | None:
    return next((path for path in map(shutil.which, names) if path), None)


@pytest.fixture
def browser():
    try:
        from selenium import webdriver
    except ImportError:
        missing("selenium is missing: make install")
    chromium, driver = _which(CHROMIUM), _which(CHROMEDRIVER)
    if not chromium or not driver:
        missing("headless Chromium is missing: apt-get install chromium chromium-driver")
    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    for flag in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--use-angle=swiftshader",
                 "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist", f"--window-size={WINDOW[0]},{WINDOW[1]}"):
        options.add_argument(flag)
    chrome = webdriver.Chrome(options=options, service=webdriver.ChromeService(executable_path=driver))
    try:
        yield chrome
    finally:
        chrome.quit()


def screenshot(chrome) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(chrome.get_screenshot_as_png())).convert("RGB")).astype(np.int32)


def near(image: np.ndarray, colour, tolerance: int = 40) -> np.ndarray:
    return np.abs(image - np.asarray(colour)).max(axis=-1) <= tolerance


def object_pixels(shot: np.ndarray, frame: Frame) -> tuple[np.ndarray, np.ndarray]:
    """The screenshot's pixels over the render's red and blue parts (the render fills the page's canvas)."""
    h, w = shot.shape[:2]
    rows = (np.arange(h) * frame.image.shape[0] / h).astype(int)
    cols = (np.arange(w) * frame.image.shape[1] / w).astype(int)
    rendered = frame.image.astype(np.int32)[rows][:, cols]
    # The control panel floats over the right of the page, a notice about software WebGL over its top left.
    rendered[:, int(0.6 * w):] = 255
    rendered[:int(0.35 * h), :int(0.35 * w)] = 255
    return near(rendered, to_uint8(RED)) | near(rendered, to_uint8(BLUE)), rendered


def object_area(frame: Frame) -> int:
    return int((near(frame.image.astype(np.int32), to_uint8(RED)) | near(frame.image.astype(np.int32), to_uint8(BLUE))).sum())


def test_the_page_shows_the_render_and_the_frustums_and_follows_a_drag(scene_out, browser):
    from selenium.webdriver import ActionChains
    from selenium.webdriver.common.by import By

    started = time.time()
    viewer = Viewer(scene_out, ViewOptions(port=free_port(), resolution=256, settle=0.2))
    viewer.start()
    try:
        browser.get(viewer.url)
        canvas = wait_for(lambda: browser.find_elements(By.TAG_NAME, "canvas"), 30, "the page's canvas")[0]

        def page_showing(frame: Frame):
            """A screenshot once the page shows `frame` where it has the object (the page fades new
            content in), or None."""
            shot = screenshot(browser)
            on_object, rendered = object_pixels(shot, frame)
            # Points and axes drawn over the object hide a little of it.
            matching = np.mean(np.abs(shot[on_object] - rendered[on_object]).max(axis=-1) < 40)
            return (shot, on_object) if on_object.sum() > 500 and matching > 0.6 else None

        def refined_after(count: int) -> Frame:
            wait_for(lambda: viewer.frames_shown > count and viewer.last_frame.refined, 30, "a refined render")
            return viewer.last_frame

        frame = refined_after(0)
        assert frame.seconds < 1.0, f"a {frame.image.shape[1]}x{frame.image.shape[0]} render took {frame.seconds:.2f} s"
        shot, on_object = wait_for(lambda: page_showing(frame), 20, "the page to show our render of the sphere")
        assert near(shot, TRAIN_COLOUR, 60).sum() > 50, "no training frustum drawn"
        assert near(shot, HELD_OUT_COLOUR, 60).sum() > 20, "no held-out frustum drawn"

        shown = viewer.frames_shown
        ActionChains(browser).move_to_element_with_offset(canvas, -150, 0).click_and_hold() \
            .move_by_offset(120, 0).move_by_offset(120, 0).release().perform()
        moved = refined_after(shown)
        changed = np.abs(moved.image.astype(int) - frame.image.astype(int)).max(axis=-1) > 40
        assert changed.sum() > 0.2 * object_area(frame), "the render did not change with the camera"
        moved_shot, on_moved = wait_for(lambda: page_showing(moved), 20, "the page to show the new render")
        assert np.abs(moved_shot.astype(int) - shot).max(axis=-1).mean() > 2, "the page did not change with the camera"
    finally:
        viewer.stop()
    assert time.time() - started < 60


CHECKPOINT_FRAME = {"fl_x": 40.0, "fl_y": 40.0, "cx": 32.0, "cy": 24.0, "w": 64, "h": 48, "split": "train", "name": "a",
                    "transform_matrix": np.eye(4).tolist(), "near": 1.0, "far": 20.0}


def unbounded_out(tmp_path, **scene) -> dict:
    """An output folder with an unbounded scene.json of one frame (plus `scene`'s keys); returns the scene."""
    scene = {"type": "unbounded", "foreground": {"min": [-1, -1, -1], "max": [1, 1, 1]}, "frames": [CHECKPOINT_FRAME],
             **scene}
    (tmp_path / "normalize").mkdir()
    (tmp_path / "normalize" / "scene.json").write_text(json.dumps(scene))
    return scene


def live_model_of_checkpoint(tmp_path, model: SceneModel) -> tuple[SceneModel, str]:
    """A fit's checkpoint of `model` written where the fit writes it, and what the viewer loads from it."""
    image = np.zeros((48, 64, 3), dtype=np.float32)
    rays = RaySet([image], [np.eye(4)], [Intrinsics.from_frame(CHECKPOINT_FRAME)])
    fitter = Fitter(model, TrainOptions(resolutions=[8], steps=[1]), rays)
    (tmp_path / CHECKPOINT).parent.mkdir(parents=True)
    fitter.save_checkpoint(tmp_path / CHECKPOINT)
    source = ModelSource(tmp_path)
    return source.load(source.latest())


def test_a_checkpoint_of_an_unbounded_fit_loads_with_its_background(tmp_path):
    # The background's texture is one table [K, H, W, 4] in checkpoints; the live model rebuilds it to that shape.
    scene = unbounded_out(tmp_path)
    model = SceneModel.create(scene, ModelOptions(sh_degree=1, background_spheres=3, background_width=12), 8)
    with torch.no_grad():
        model.background.texture.normal_(generator=torch.Generator().manual_seed(0))
    live, line = live_model_of_checkpoint(tmp_path, model)
    assert "checkpoint" in line and live.background is not None
    torch.testing.assert_close(live.background.texture, model.background.texture)


def test_a_checkpoint_of_a_contracted_fit_loads_contracted_with_its_far_colour(tmp_path):
    scene = unbounded_out(tmp_path, measured={"beyond_fraction": 0.4}, thresholds={"unbounded_min_beyond_fraction": 0.1})
    model = SceneModel.create(scene, ModelOptions(sh_degree=1), 8, mean_colour=(0.2, 0.3, 0.4))
    live, _ = live_model_of_checkpoint(tmp_path, model)
    assert live.grid.contracted and live.fit_frame.contraction == model.fit_frame.contraction
    assert live.background is None and live.background_color == (0.2, 0.3, 0.4)
    o, d = torch.zeros(4, 3), torch.nn.functional.normalize(torch.randn(4, 3, generator=torch.Generator().manual_seed(0)))
    torch.testing.assert_close(live.render_rays(o, d).rgb, model.render_rays(o, d).rgb)


def test_the_splat_layer_draws_the_exported_splats_in_the_page(scene_out, browser):
    """With the field's render off, turning the layer "exported splats" on paints the sphere's red and blue where it
    stands, in the middle of the page (viser's own splat renderer, in WebGL), and turning it off takes them away."""
    viewer = Viewer(scene_out, ViewOptions(port=free_port(), resolution=128, settle=0.2))
    viewer.start()
    try:
        browser.get(viewer.url)
        wait_for(lambda: viewer.frames_shown > 0, 30, "a first render")
        viewer.mode.value = "off"

        def coloured() -> int:
            """Red or blue pixels around the page's middle (the splats blend into the white page at their edges)."""
            shot = screenshot(browser)
            h, w = shot.shape[:2]
            middle = shot[int(0.25 * h):int(0.75 * h), int(0.35 * w):int(0.65 * w)]
            red = middle[..., 0] - np.maximum(middle[..., 1], middle[..., 2]) > 60
            blue = middle[..., 2] - np.maximum(middle[..., 0], middle[..., 1]) > 60
            return int((red | blue).sum())

        # The foreground box's blue edges and the frustums' thumbnails stay: what counts is what the layer adds.
        time.sleep(2)
        without = coloured()
        viewer.handles["splats"][0].visible = True
        with_splats = wait_for(lambda: (lambda n: n if n > without + 1500 else None)(coloured()), 30,
                               f"the splats in the page (red and blue pixels without them: {without})")
        viewer.handles["splats"][0].visible = False
        # On a loaded machine the page (software WebGL) may take as long to clear the splats as to draw them.
        seen = []
        wait_for(lambda: seen.append(coloured()) or seen[-1] < without + 300, 30,
                 lambda: f"the splats gone again (without them {without}, with them {with_splats}, now {seen[-1]})")
    finally:
        viewer.stop()
