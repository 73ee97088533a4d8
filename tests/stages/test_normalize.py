"""The normalize stage on small synthetic scenes with true poses and sparse points sampled on the true surfaces."""
from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from pipeline import config
from pipeline.report import Reporter
from pipeline.runner import Pipeline
from stages.framing.foreground import surroundings_box
from stages.framing.options import SceneOptions
from stages.framing.scene_frame import normalize_scene
from stages.framing.sightings import Points, read_points
from pipeline.stage import StageContext
from stages.capture.synthetic import write_scene
from stages.capture.synthetic_scenes import build_scene, trace
from plenoxels.core.cameras import Intrinsics, look_at, pixel_directions
from plenoxels.core.errors import UserError
from stages import normalize
from stages.settings.normalize import Settings

N_VIEWS = 16
WIDTH, HEIGHT = 48, 36
RAYS_PER_VIEW = 150


def _rotation(axis, angle_deg: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = math.radians(angle_deg)
    return np.eye(3) + math.sin(a) * k + (1 - math.cos(a)) * k @ k


def _sample_points(kind: str, transforms: dict, seed: int) -> dict:
    """Sparse points the way SfM would see them: hits of random pixel rays on the true surfaces, each
    observed by every camera that has it in its image with nothing in front of it."""
    scene = build_scene(kind, seed)
    rng = np.random.default_rng(seed)
    k = Intrinsics.from_frame(transforms)
    dirs_cam = pixel_directions(k).numpy().reshape(-1, 3).astype(np.float64)
    c2ws = [np.asarray(f["transform_matrix"]) for f in transforms["frames"]]
    xyz = []
    for c2w in c2ws:
        dirs = dirs_cam[rng.choice(len(dirs_cam), RAYS_PER_VIEW, replace=False)] @ c2w[:3, :3].T
        t, _ = trace(scene, c2w[:3, 3], dirs)
        xyz.append(c2w[:3, 3] + t[np.isfinite(t), None] * dirs[np.isfinite(t)])
    xyz = np.concatenate(xyz)
    obs_frame, obs_point = [], []
    for f, c2w in enumerate(c2ws):
        to_point = xyz - c2w[:3, 3]
        distance = np.linalg.norm(to_point, axis=1)
        local = to_point @ c2w[:3, :3]
        depth = -local[:, 2]
        u = k.fl_x * local[:, 0] / depth + k.cx
        v = -k.fl_y * local[:, 1] / depth + k.cy
        t, _ = trace(scene, c2w[:3, 3], to_point / distance[:, None])
        seen = (depth > 0) & (u >= 0) & (u <= k.w) & (v >= 0) & (v <= k.h) & (t > distance * (1 - 1e-6))
        obs_frame += [f] * int(seen.sum())
        obs_point += np.flatnonzero(seen).tolist()
    return {"xyz": xyz, "obs_frame": np.asarray(obs_frame), "obs_point": np.asarray(obs_point)}


def _poses_folder(root: Path, kind: str, seed: int = 0, alpha: bool = False, with_points: bool = True) -> Path:
    """A poses/ folder in the poses stage's layout, from a synthetic scene's true cameras."""
    synth = write_scene(kind, root / "synth", n_views=N_VIEWS, width=WIDTH, height=HEIGHT, seed=seed,
                        alpha=alpha, supersample=1)
    poses = root / "poses"
    (poses / "images").mkdir(parents=True)
    transforms = json.loads((synth / "transforms.json").read_text())
    for frame in transforms["frames"]:
        name = Path(frame["file_path"]).stem
        frame["name"] = name
        if alpha:
            # As ingest does: RGB image plus the alpha channel as a separate mask.
            (poses / "masks").mkdir(exist_ok=True)
            with Image.open(synth / frame["file_path"]) as im:
                im.convert("RGB").save(poses / "images" / f"{name}.png")
                im.getchannel("A").save(poses / "masks" / f"{name}.png")
            frame["mask_path"] = f"masks/{name}.png"
        else:
            shutil.copy(synth / frame["file_path"], poses / "images" / f"{name}.png")
        frame["file_path"] = f"images/{name}.png"
    transforms["source"] = "transforms"
    (poses / "transforms.json").write_text(json.dumps(transforms))
    if with_points:
        np.savez(poses / "points.npz", **_sample_points(kind, transforms, seed))
    else:
        np.savez(poses / "points.npz", xyz=np.zeros((0, 3)), obs_frame=np.zeros(0, int), obs_point=np.zeros(0, int))
    return poses


def _run_stage(poses: Path, settings: Settings | None = None) -> tuple[dict, dict]:
    out = poses.parent
    work = out / ".work" / "normalize"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    ctx = StageContext(scene=out, out=out, work=work, scratch=out / ".resume", settings=settings or Settings(),
                       upstream={"poses": poses}, scene_type=None, report=Reporter(quiet=True))
    summary = normalize.run(ctx)
    return json.loads((work / "scene.json").read_text()), summary


def _load(poses: Path) -> tuple[dict, Points]:
    return json.loads((poses / "transforms.json").read_text()), read_points(poses / "points.npz")


def _to_world(scene: dict, xyz: np.ndarray) -> np.ndarray:
    m = np.asarray(scene["world_from_input"])
    return xyz @ m[:3, :3].T + m[:3, 3]


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> dict[str, Path]:
    return {kind: _poses_folder(tmp_path_factory.mktemp(kind), kind) for kind in ("object", "forward", "unbounded")}


@pytest.mark.parametrize("kind", ["object", "forward", "unbounded"])
def test_synthetic_kinds_are_classified_from_true_poses(scenes, kind):
    scene, summary = _run_stage(scenes[kind])
    assert scene["type"] == kind, scene["reasons"]
    assert scene["detected"] == kind and scene["overridden"] is False
    assert summary["line"].startswith(f"{kind} scene (")
    assert set(scene["thresholds"]) >= {"forward_max_cone_deg", "beyond_factor"}
    truth = json.loads((scenes[kind].parent / "synth" / "ground_truth" / "scene.json").read_text())

    # The true world is z-up: its up axis must come out as +z.
    rotation = np.asarray(scene["world_from_input"])[:3, :3] / scene["scale"]
    assert np.degrees(np.arccos(np.clip(rotation @ truth["world_up"] @ [0, 0, 1], -1, 1))) < 2.0

    lo, hi = np.asarray(scene["foreground"]["min"]), np.asarray(scene["foreground"]["max"])
    assert np.all(lo >= -1) and np.all(hi <= 1) and np.max(hi - lo) > 1.6
    if kind != "forward":
        # The true object is inside the unit cube and fills a fair part of it (less in the unbounded scene,
        # where the ground most cameras see around the object is foreground too).
        mesh = trimesh.load(scenes[kind].parent / "synth" / "ground_truth" / "mesh.ply")
        vertices = _to_world(scene, np.asarray(mesh.vertices))
        assert np.abs(vertices).max() <= 1.0 and np.ptp(vertices, axis=0).max() > (0.8 if kind == "object" else 0.5)
        assert "forward" not in scene
    else:
        reference = np.asarray(scene["forward"]["reference_c2w"])
        mean_view = np.mean([-np.asarray(f["transform_matrix"])[:3, 2] for f in scene["frames"]], axis=0)
        assert np.degrees(np.arccos(-reference[:3, 2] @ mean_view / np.linalg.norm(mean_view))) < 1.0
        # NDC's near plane lies in front of the nearest true surface.
        true_near = min(v["near_depth"] for v in truth["views"]) * scene["scale"]
        assert 0 < scene["forward"]["near"] <= true_near

    for frame, view in zip(sorted(scene["frames"], key=lambda f: f["name"]), truth["views"]):
        # Per-image near/far bracket what the sampled points show of the true depth range.
        assert 0 < frame["near"] <= view["near_depth"] * scene["scale"] * 1.25
        assert frame["far"] >= view["near_depth"] * scene["scale"]
        assert frame["file_path"] == f"poses/images/{frame['name']}.png"


def test_forward_scene_far_covers_back_wall(scenes):
    scene, _ = _run_stage(scenes["forward"])
    truth = json.loads((scenes["forward"].parent / "synth" / "ground_truth" / "scene.json").read_text())
    for frame, view in zip(sorted(scene["frames"], key=lambda f: f["name"]), truth["views"]):
        assert frame["far"] >= 0.8 * view["far_distance"] * scene["scale"]


def test_transforms_round_trip(scenes):
    transforms, points = _load(scenes["object"])
    scene = normalize_scene(transforms, points, SceneOptions())
    forward, backward = np.asarray(scene["world_from_input"]), np.asarray(scene["input_from_world"])
    assert np.allclose(forward @ backward, np.eye(4), atol=1e-9)
    p = np.array([0.7, -2.0, 3.1, 1.0])
    assert np.allclose(backward @ (forward @ p), p)
    # The normalised cameras are the input ones carried through the transform (rotation kept orthonormal).
    by_name = {f["name"]: np.asarray(f["transform_matrix"]) for f in scene["frames"]}
    for frame in transforms["frames"]:
        c2w_in = np.asarray(frame["transform_matrix"])
        c2w = by_name[frame["name"]]
        assert np.allclose(c2w[:3, :3].T @ c2w[:3, :3], np.eye(3), atol=1e-9)
        assert np.allclose((forward @ c2w_in)[:3, 3], c2w[:3, 3])
        assert np.allclose(backward[:3, :3] @ c2w[:3, :3] / np.linalg.norm(backward[:3, 0]), c2w_in[:3, :3], atol=1e-9)


@pytest.mark.parametrize("kind", ["object", "forward", "unbounded"])
def test_rotated_scaled_shifted_input_normalises_the_same(scenes, kind):
    transforms, points = _load(scenes[kind])
    rng = np.random.default_rng(3)
    similarity = np.eye(4)
    scale = 3.7
    similarity[:3, :3] = scale * _rotation(rng.normal(size=3), 71.0)
    similarity[:3, 3] = [5.0, -12.0, 40.0]
    moved = json.loads(json.dumps(transforms))
    for frame in moved["frames"]:
        c2w = similarity @ np.asarray(frame["transform_matrix"])
        c2w[:3, :3] /= scale
        frame["transform_matrix"] = c2w.tolist()
    moved_points = Points(points.xyz @ similarity[:3, :3].T + similarity[:3, 3], points.obs_frame, points.obs_point)

    a = normalize_scene(transforms, points, SceneOptions(), scenes[kind])
    b = normalize_scene(moved, moved_points, SceneOptions(), scenes[kind])
    assert a["type"] == b["type"] == kind
    assert math.isclose(b["scale"] * scale, a["scale"], rel_tol=1e-6)
    for fa, fb in zip(a["frames"], b["frames"]):
        assert np.allclose(fa["transform_matrix"], fb["transform_matrix"], atol=1e-6)
        assert math.isclose(fa["near"], fb["near"], rel_tol=1e-6) and math.isclose(fa["far"], fb["far"], rel_tol=1e-6)
    assert np.allclose(a["foreground"]["min"], b["foreground"]["min"], atol=1e-6)
    # Both map the same physical point to the same normalised point.
    assert np.allclose(np.asarray(b["world_from_input"]) @ similarity, a["world_from_input"], atol=1e-6)


def test_a_rooms_surroundings_box_holds_the_wall_beside_the_foreground_but_no_camera():
    rng = np.random.default_rng(0)
    foreground = np.array([[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]])
    object_points = rng.uniform(-0.5, 0.5, size=(2000, 3))
    wall = np.column_stack([np.full(1000, 1.2), rng.uniform(-1.0, 1.0, size=(1000, 2))])
    far_away = rng.uniform(5.0, 9.0, size=(50, 3))  # beyond 2x the foreground: the background model's, not the grid's
    xyz = np.concatenate([object_points, wall, far_away])
    angles = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    circle = np.column_stack([3 * np.cos(angles), 3 * np.sin(angles), np.zeros_like(angles)])

    box, growth = surroundings_box(xyz, foreground, circle, beyond_factor=2.0)
    assert growth == 1.0
    assert np.allclose(box[1], [1.2, 1.0, 1.0], atol=0.01) and np.allclose(box[0], [-0.5, -1.0, -1.0], atol=0.01)

    # A camera between the foreground and the wall stops the growth before it stands inside the box.
    cameras = np.concatenate([circle, [[0.9, 0.0, 0.0]]])
    box, growth = surroundings_box(xyz, foreground, cameras, beyond_factor=2.0)
    assert 0 < growth < 0.6
    assert box[1][0] < 0.9 and np.all(box[0] <= foreground[0]) and np.all(box[1] >= foreground[1])
    assert not np.any(np.all((cameras > box[0]) & (cameras < box[1]), axis=1))

    # A camera inside the foreground box leaves it as it is.
    box, growth = surroundings_box(xyz, foreground, np.array([[0.0, 0.0, 0.0]]), beyond_factor=2.0)
    assert growth == 0.0 and np.array_equal(box, foreground)


def test_an_unbounded_scene_writes_a_surroundings_box_around_its_foreground(scenes):
    scene, _ = _run_stage(scenes["unbounded"])
    lo, hi = np.asarray(scene["surroundings"]["min"]), np.asarray(scene["surroundings"]["max"])
    assert np.all(lo <= np.asarray(scene["foreground"]["min"])) and np.all(hi >= np.asarray(scene["foreground"]["max"]))
    origins = np.array([np.asarray(f["transform_matrix"])[:3, 3] for f in scene["frames"]])
    assert not np.any(np.all((origins > lo) & (origins < hi), axis=1))


def test_a_can_on_a_wide_floor_stays_in_the_foreground_box():
    # The floor's many points outvote the can's few in the box of the points most cameras see; the cameras circling
    # the can are aimed at it, and the box must hold what they are aimed at, or no grid there can show the can.
    rng = np.random.default_rng(1)
    r = np.sqrt(rng.uniform(0, 1.5 ** 2, 6000))
    a = rng.uniform(0, 2 * np.pi, 6000)
    floor = np.column_stack([r * np.cos(a), r * np.sin(a), rng.normal(0, 0.003, 6000)])
    a, z = rng.uniform(0, 2 * np.pi, 120), rng.uniform(0.0, 0.8, 120)
    can = np.column_stack([0.15 * np.cos(a), 0.15 * np.sin(a), z])
    frames = []
    for i, angle in enumerate(np.linspace(0, 2 * np.pi, 24, endpoint=False)):
        eye = (2.0 * np.cos(angle), 2.0 * np.sin(angle), 0.6)
        frames.append({"file_path": f"images/{i:03d}.png", "name": f"{i:03d}",
                       "transform_matrix": look_at(eye, (0.0, 0.0, 0.4)).tolist()})
    transforms = {"fl_x": 60.0, "fl_y": 60.0, "cx": 48.0, "cy": 36.0, "w": 96, "h": 72, "frames": frames}
    scene = normalize_scene(transforms, Points(np.concatenate([floor, can]), np.zeros(0, int), np.zeros(0, int)),
                            SceneOptions())
    outside, aimed = map(int, scene["measured"]["aimed_outside_box"].split("/"))
    assert aimed == 24 and outside > 0
    lo, hi = np.asarray(scene["foreground"]["min"]), np.asarray(scene["foreground"]["max"])
    # Every camera's view of the can's middle, where it is aimed, crosses the box: the can is in the grid there.
    aimed_at = _to_world(scene, np.array([[0.0, 0.0, 0.4], [0.0, 0.0, 0.5], [0.15, 0.0, 0.4], [0.0, -0.15, 0.4]]))
    assert np.all((aimed_at >= lo) & (aimed_at <= hi)), (aimed_at, lo, hi)
    assert "aimed at" in scene["measured"]["foreground_from"]


def test_up_survives_a_few_tilted_shots(scenes):
    transforms, points = _load(scenes["object"])
    for index, roll in ((2, 35.0), (9, -50.0)):
        c2w = np.asarray(transforms["frames"][index]["transform_matrix"])
        c2w[:3, :3] = c2w[:3, :3] @ _rotation([0, 0, 1], roll)  # a roll about the camera's own viewing axis
        transforms["frames"][index]["transform_matrix"] = c2w.tolist()
    scene = normalize_scene(transforms, points, SceneOptions())
    rotation = np.asarray(scene["world_from_input"])[:3, :3] / scene["scale"]
    assert np.degrees(np.arccos(np.clip(rotation[2] @ [0, 0, 1], -1, 1))) < 2.0


@pytest.mark.parametrize("pitch_deg", [-90.0, -80.0])
def test_a_survey_flown_back_and_forth_looking_down_takes_up_against_the_way_it_looks(pitch_deg):
    # Rows flown back and forth over the ground: each camera's up axis points along its row, half one way and half
    # the other, so their mean says nothing; the way they all look says down.
    frames = []
    for row, y in enumerate(np.linspace(-1.0, 1.0, 4)):
        heading = np.array([0.0, 1.0 if row % 2 == 0 else -1.0, 0.0])
        look = math.cos(math.radians(pitch_deg)) * heading + math.sin(math.radians(pitch_deg)) * np.array([0, 0, 1.0])
        for x in np.linspace(-1.0, 1.0, 5):
            eye = np.array([x, y, 3.0])
            frames.append({"file_path": f"images/{len(frames):03d}.png", "name": f"{len(frames):03d}",
                           "transform_matrix": look_at(eye, eye + look, up=heading).tolist()})
    ground = np.random.default_rng(2).uniform([-2.5, -2.5, 0.0], [2.5, 2.5, 0.3], size=(3000, 3))
    transforms = {"fl_x": 60.0, "fl_y": 60.0, "cx": 48.0, "cy": 36.0, "w": 96, "h": 72, "frames": frames}
    scene = normalize_scene(transforms, Points(ground, np.zeros(0, int), np.zeros(0, int)), SceneOptions())
    assert "looking down" in scene["measured"]["up_from"]
    rotation = np.asarray(scene["world_from_input"])[:3, :3] / scene["scale"]
    assert np.degrees(np.arccos(np.clip(rotation[2] @ [0, 0, 1], -1, 1))) < 1.0
    assert all(np.isfinite(np.asarray(f["transform_matrix"])).all() for f in scene["frames"])


def test_split_holds_out_every_nth_by_sorted_name(scenes):
    transforms, points = _load(scenes["object"])
    transforms["frames"] = transforms["frames"][::-1]  # the split must not depend on the input order
    names = sorted(f["name"] for f in transforms["frames"])
    scene = normalize_scene(transforms, points, SceneOptions(holdout_every=8))
    assert [f["name"] for f in scene["frames"]] == names
    assert [f["name"] for f in scene["frames"] if f["split"] == "test"] == names[::8]
    scene = normalize_scene(transforms, points, SceneOptions(holdout_every=5))
    assert [f["name"] for f in scene["frames"] if f["split"] == "test"] == names[::5]
    scene = normalize_scene(transforms, points, SceneOptions(holdout_every=0))
    assert all(f["split"] == "train" for f in scene["frames"])


def test_train_every_trains_on_every_nth_training_photo_and_keeps_the_held_out_ones(scenes):
    transforms, points = _load(scenes["object"])
    names = sorted(f["name"] for f in transforms["frames"])
    scene = normalize_scene(transforms, points, SceneOptions(holdout_every=8, train_every=4))
    held_out = names[::8]
    training = [n for n in names if n not in held_out]
    assert [f["name"] for f in scene["frames"] if f["split"] == "test"] == held_out
    assert [f["name"] for f in scene["frames"] if f["split"] == "train"] == training[::4]
    assert sum(f["split"] == "unused" for f in scene["frames"]) == len(training) - len(training[::4])


def test_without_points_masks_or_scenery_decide(tmp_path):
    masked = _poses_folder(tmp_path / "masked", "object", alpha=True, with_points=False)
    scene, _ = _run_stage(masked)
    assert scene["type"] == "object", scene["reasons"]
    assert scene["frames"][0]["mask_path"] == f"poses/masks/{scene['frames'][0]['name']}.png"
    # No points: the masks' visual hull frames the object.
    assert scene["measured"]["foreground_from"].startswith("visual hull of")
    assert scene["measured"]["visual_hull"]["source"] == "masks"
    for frame in scene["frames"]:
        # Near/far from the foreground box: every camera is outside it, and the box lies between near and far.
        origin = np.asarray(frame["transform_matrix"])[:3, 3]
        assert np.abs(origin).max() > 1 and 0 < frame["near"] < np.linalg.norm(origin) < frame["far"]

    scenery = _poses_folder(tmp_path / "scenery", "unbounded", with_points=False)
    scene, summary = _run_stage(scenery)
    assert scene["type"] == "unbounded", scene["reasons"]
    assert "no points" in summary["line"]


def test_llff_bounds_give_near_far_without_points(scenes):
    transforms, _ = _load(scenes["forward"])
    for n, frame in enumerate(transforms["frames"]):
        frame["near"], frame["far"] = 2.0 + 0.01 * n, 9.5
    scene = normalize_scene(transforms, Points.empty(), SceneOptions())
    assert scene["type"] == "forward"
    assert scene["measured"]["near_far_from"] == {"llff bounds": N_VIEWS}
    assert scene["forward"]["from"] == "llff bounds"
    assert math.isclose(scene["forward"]["near"], 2.0 * scene["scale"] * 0.9, rel_tol=1e-9)
    near = {f["name"]: f["near"] for f in scene["frames"]}
    assert math.isclose(near["0003"], 2.03 * scene["scale"] * 0.9, rel_tol=1e-9)


def test_setting_overrides_the_scene_type(scenes):
    scene, summary = _run_stage(scenes["object"], Settings(scene_type="unbounded"))
    assert scene["type"] == "unbounded" and scene["detected"] == "object" and scene["overridden"] is True
    assert "set by normalize.scene_type" in summary["line"]
    scene, _ = _run_stage(scenes["object"], Settings(scene_type="forward"))
    assert scene["type"] == "forward" and "reference_c2w" in scene["forward"]


def test_bad_settings_and_missing_poses_are_user_errors(tmp_path):
    with pytest.raises(UserError, match="holdout_every"):
        config.build(Settings, "normalize", {"holdout_every": 1})
    with pytest.raises(UserError, match="scene_type"):
        config.build(Settings, "normalize", {"scene_type": "indoor"})
    (tmp_path / "poses").mkdir()
    with pytest.raises(UserError, match="run the poses stage"):
        _run_stage(tmp_path / "poses")
    (tmp_path / "poses" / "transforms.json").write_text(json.dumps({"frames": []}))
    with pytest.raises(UserError, match="at least 2"):
        _run_stage(tmp_path / "poses")


# Sizes at which SfM poses most of each synthetic scene (the orbit needs views close enough to match).
SFM_SCENES = {"object": (32, 192, 144), "forward": (20, 160, 120), "unbounded": (32, 192, 144)}


@pytest.mark.parametrize("kind", list(SFM_SCENES))
def test_synthetic_kinds_are_classified_from_sfm(tmp_path, kind):
    """Through ingest and COLMAP SfM: the poses come in COLMAP's arbitrary frame, yet the type is right and
    the up found is the true up (carried into COLMAP's frame by the rotation that best aligns its cameras
    with the true ones)."""
    n_views, width, height = SFM_SCENES[kind]
    synth = write_scene(kind, tmp_path / "synth", n_views=n_views, width=width, height=height, seed=0, supersample=1)
    pipeline = Pipeline(synth / "images", tmp_path / "out", overrides=["poses.source=sfm"], reporter=Reporter(quiet=True))
    pipeline.run(["normalize"])
    scene = json.loads((tmp_path / "out" / "normalize" / "scene.json").read_text())
    assert scene["type"] == kind, scene["reasons"]
    assert len(scene["frames"]) >= n_views // 2

    truth = {Path(f["file_path"]).stem: np.asarray(f["transform_matrix"])[:3, :3]
             for f in json.loads((synth / "transforms.json").read_text())["frames"]}
    sfm = {f["name"]: np.asarray(f["transform_matrix"])[:3, :3]
           for f in json.loads((tmp_path / "out" / "poses" / "transforms.json").read_text())["frames"]}
    u, _, vt = np.linalg.svd(sum(truth[name] @ sfm[name].T for name in sfm))
    true_from_sfm = u @ vt
    up_in_sfm = np.asarray(scene["world_from_input"])[2, :3] / scene["scale"]
    assert np.degrees(np.arccos(np.clip(true_from_sfm @ up_in_sfm @ [0, 0, 1], -1, 1))) < 1.5


def _arc_in_front_of_a_wall(spread_deg: float, jitter_deg: float = 0.0, seed: int = 0, n: int = 15) -> dict:
    """Cameras on a horizontal arc of `spread_deg` around a wall's centre, 4 units away, each aimed at the centre
    (turned by up to `jitter_deg` where given): a facade shot from a few steps apart."""
    rng = np.random.default_rng(seed)
    frames = []
    for i, angle in enumerate(np.radians(np.linspace(-spread_deg / 2, spread_deg / 2, n))):
        eye = np.array([4 * math.sin(angle), -4 * math.cos(angle), 1.5])
        c2w = look_at(eye, np.array([0.0, 0.0, 1.5]), np.array([0.0, 0.0, 1.0]))
        if jitter_deg:
            c2w[:3, :3] = _rotation(rng.normal(size=3), rng.uniform(0, jitter_deg)) @ c2w[:3, :3]
        frames.append({"name": f"{i:03d}", "file_path": f"images/{i:03d}.png", "transform_matrix": c2w.tolist()})
    return {"fl_x": 60.0, "fl_y": 60.0, "cx": 32.0, "cy": 24.0, "w": 64, "h": 48, "frames": frames}


@pytest.mark.parametrize("spread_deg", [20, 40, 50, 60, 66, 72, 80, 100, 140])
def test_an_arc_near_the_forward_limit_is_borderline_and_stable(spread_deg):
    options = SceneOptions()
    scene = normalize_scene(_arc_in_front_of_a_wall(spread_deg), Points.empty(), options)
    cone = scene["measured"]["view_cone_deg"]
    near = abs(cone - options.forward_max_cone_deg) <= options.borderline_deg
    assert scene["measured"]["borderline"] == near
    assert (scene["type"] == "forward") == (cone < options.forward_max_cone_deg - options.borderline_deg)
    if near:
        assert any("borderline" in r for r in scene["reasons"]) and scene["type"] != "forward"
        assert "borderline" in normalize.summary_line(scene)
    # A degree of pose noise changes the decision only where the spread sits at the band's edges.
    for seed in range(3):
        shaken = normalize_scene(_arc_in_front_of_a_wall(spread_deg, 1.0, seed), Points.empty(), options)
        edges = (options.forward_max_cone_deg - options.borderline_deg, options.forward_max_cone_deg + options.borderline_deg)
        if min(abs(cone - e) for e in edges) > 1.5:
            assert shaken["type"] == scene["type"]
