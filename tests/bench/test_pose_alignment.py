"""The held-out views' pose alignment (bench/pose_alignment.py): a camera moved off the pose its photo was taken from
is brought back, and a photo with other gains scores higher with them fitted."""
import numpy as np
import torch
from scipy.spatial.transform import Rotation

from bench.pose_alignment import align, aligned_scores, moved
from plenoxels.core.cameras import Intrinsics, look_at
from plenoxels.core.grid import SparseGrid
from plenoxels.core.render import SH_C0
from plenoxels.core.scene_model import SceneModel
from stages.scoring.metrics import image_scores


def textured_ball(res: int = 40) -> SceneModel:
    """A ball whose colour changes every tenth of a unit along each axis: edges for a pose to lock onto."""
    axes = [np.linspace(-0.6, 0.6, res)] * 3
    p = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    density = 60.0 / (1 + np.exp(-(0.5 - np.linalg.norm(p, axis=1)) / 0.02))
    checks = (np.floor(p / 0.1).astype(int).sum(1) % 2).astype(float)
    colour = np.stack([0.2 + 0.6 * checks, 0.8 - 0.6 * checks, 0.5 + 0.3 * np.sin(p[:, 2] * 9)], axis=1)
    links = torch.arange(len(p), dtype=torch.int32).reshape(res, res, res)
    grid = SparseGrid.from_values(links, torch.tensor(density, dtype=torch.float32),
                                  torch.tensor((colour - 0.5) / SH_C0, dtype=torch.float32), [-0.6] * 3, [0.6] * 3, 0)
    return SceneModel(grid, "object", background_color=(1.0, 1.0, 1.0))


def pose_gap(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """How far apart two camera-to-world poses are: centres (scene units) and rotation (degrees)."""
    return (float(np.linalg.norm(a[:3, 3] - b[:3, 3])),
            float(np.degrees(Rotation.from_matrix(a[:3, :3].T @ b[:3, :3]).magnitude())))


def test_a_camera_moved_off_its_photo_is_aligned_back_to_it():
    model = textured_ball()
    k = Intrinsics(70.0, 70.0, 32.0, 32.0, 64, 64)
    c2w = look_at(np.array([0.3, -2.0, 0.6]), np.zeros(3))
    truth = model.render_camera(c2w, k)["rgb"].numpy()
    distance = float(np.linalg.norm(c2w[:3, 3]))
    # About a pixel and a half of rotation and a hundredth of the distance sideways.
    off = moved(c2w, np.array([0.012, -0.015, 0.01, 0.01, -0.008, 0.004]), distance)

    fit = align(model, off, k, truth, {"name": "a"})

    before, after = pose_gap(off, c2w), pose_gap(fit["c2w"], c2w)
    assert after[0] < 0.2 * before[0] and after[1] < 0.2 * before[1]
    assert fit["subset_psnr"][1] > fit["subset_psnr"][0] + 10


def test_the_aligned_scores_fit_the_photos_gains_where_its_colour_differs():
    model = textured_ball()
    k = Intrinsics(70.0, 70.0, 32.0, 32.0, 64, 64)
    c2w = look_at(np.array([0.3, -2.0, 0.6]), np.zeros(3))
    render = model.render_camera(c2w, k)["rgb"].numpy()
    darker = render * np.array([0.8, 0.9, 0.7], dtype=np.float32)

    scores = aligned_scores(model, {"name": "a", "transform_matrix": c2w.tolist()}, k, darker, render)

    assert scores["regained"]["psnr"] > image_scores(render, darker, with_lpips=False)["psnr"] + 10
    assert scores["aligned_regained"]["psnr"] > scores["aligned"]["psnr"] + 10
    assert scores["aligned"]["rotation_px"] < 0.1


def test_a_photo_with_its_own_backdrop_is_aligned_and_scored_on_that_backdrop():
    model = textured_ball()  # white past the grid, as fitted
    k = Intrinsics(70.0, 70.0, 32.0, 32.0, 64, 64)
    c2w = look_at(np.array([0.3, -2.0, 0.6]), np.zeros(3))
    frame = {"name": "a", "transform_matrix": c2w.tolist(), "backdrop": [0.1, 0.2, 0.05]}
    truth = model.render_camera(c2w, k, backdrop=frame["backdrop"])["rgb"].numpy()

    scores = aligned_scores(model, frame, k, truth, truth)

    assert scores["aligned"]["subset_psnr"][0] > 50 and scores["aligned"]["psnr"] > 50
    assert scores["aligned"]["rotation_px"] < 0.05
