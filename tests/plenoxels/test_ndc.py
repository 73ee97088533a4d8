"""NDC: the projective map against its closed forms, rays, the near-plane limit and parallel rays."""
import math

import numpy as np
import pytest
import torch

from plenoxels.core.cameras import Intrinsics, project, rays_from_camera
from plenoxels.core.errors import UserError
from plenoxels.core.ndc import MAX_BOX_REACH, MAX_Z_NDC, NDCMapping


def _rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    cy, sy, cp, sp, cr, sr = (math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch),
                              math.cos(roll), math.sin(roll))
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    ry = np.array([[cr, 0, sr], [0, 1, 0], [-sr, 0, cr]])
    return rz @ rx @ ry


def _mapping(centred: bool = True, near: float = 0.7) -> NDCMapping:
    c2w = np.eye(4)
    c2w[:3, :3] = _rotation(0.4, 1.1, -0.2)
    c2w[:3, 3] = [0.3, -1.5, 0.2]
    w, h = 40, 30
    cx, cy = (w / 2, h / 2) if centred else (23.0, 13.5)
    return NDCMapping(reference_c2w=c2w.tolist(), near=near, fl_x=35.0, fl_y=33.0, cx=cx, cy=cy, w=w, h=h)


def _to_camera(m: NDCMapping, p_world: np.ndarray) -> np.ndarray:
    c2w = np.asarray(m.reference_c2w)
    return (p_world - c2w[:3, 3]) @ c2w[:3, :3]


def _llff_ndc_rays(m: NDCMapping, o: np.ndarray, d: np.ndarray):
    """LLFF's ndc_rays, written out from its formulas, in the reference camera frame (centred principal point)."""
    H, W, focal_x, focal_y, near = m.h, m.w, m.fl_x, m.fl_y, m.near
    t = -(near + o[:, 2]) / d[:, 2]
    o = o + t[:, None] * d
    o0 = -1.0 / (W / (2.0 * focal_x)) * o[:, 0] / o[:, 2]
    o1 = -1.0 / (H / (2.0 * focal_y)) * o[:, 1] / o[:, 2]
    o2 = 1.0 + 2.0 * near / o[:, 2]
    d0 = -1.0 / (W / (2.0 * focal_x)) * (d[:, 0] / d[:, 2] - o[:, 0] / o[:, 2])
    d1 = -1.0 / (H / (2.0 * focal_y)) * (d[:, 1] / d[:, 2] - o[:, 1] / o[:, 2])
    d2 = -2.0 * near / o[:, 2]
    return np.stack([o0, o1, o2], -1), np.stack([d0, d1, d2], -1)


def _points_in_front(m: NDCMapping, n: int, rng) -> np.ndarray:
    cam = np.stack([rng.uniform(-3, 3, n), rng.uniform(-3, 3, n), -rng.uniform(m.near * 1.01, 50.0, n)], -1)
    c2w = np.asarray(m.reference_c2w)
    return cam @ c2w[:3, :3].T + c2w[:3, 3]


def test_points_match_the_reference_image_projection():
    """x_ndc, y_ndc are the reference camera's pixel coordinates scaled to [-1, 1] (y up); z from 1 + 2 near / z."""
    rng = np.random.default_rng(0)
    for centred in (True, False):
        m = _mapping(centred)
        p = _points_in_front(m, 200, rng)
        uv, depth = project(p, np.asarray(m.reference_c2w), Intrinsics(m.fl_x, m.fl_y, m.cx, m.cy, m.w, m.h))
        ndc = m.points_to_ndc(torch.from_numpy(p)).numpy()
        np.testing.assert_allclose(ndc[:, 0], 2 * uv[:, 0] / m.w - 1, atol=1e-10)
        np.testing.assert_allclose(ndc[:, 1], 1 - 2 * uv[:, 1] / m.h, atol=1e-10)
        np.testing.assert_allclose(ndc[:, 2], 1 - 2 * m.near / depth, atol=1e-10)


def test_rays_match_llff_closed_form():
    rng = np.random.default_rng(1)
    m = _mapping(centred=True)
    c2w = np.asarray(m.reference_c2w)
    o_cam = rng.uniform(-0.3, 0.3, (300, 3))
    d_cam = np.concatenate([rng.uniform(-0.6, 0.6, (300, 2)), -rng.uniform(0.5, 1.5, (300, 1))], -1)
    o_ref, d_ref = _llff_ndc_rays(m, o_cam, d_cam)
    o_world, d_world = o_cam @ c2w[:3, :3].T + c2w[:3, 3], d_cam @ c2w[:3, :3].T
    o_ndc, d_ndc = m.rays(torch.from_numpy(o_world), torch.from_numpy(d_world))
    np.testing.assert_allclose(o_ndc.numpy(), o_ref, atol=1e-9)
    np.testing.assert_allclose(d_ndc.numpy(), d_ref, atol=1e-9)


def test_points_along_a_world_ray_lie_on_its_ndc_ray_in_order():
    rng = np.random.default_rng(2)
    m = _mapping(centred=False)
    o, d = rays_from_camera(np.asarray(m.reference_c2w) @ np.diag([1, 1, 1, 1.0]),
                            Intrinsics(m.fl_x, m.fl_y, m.cx, m.cy, m.w, m.h), torch.float64)
    # Cameras of a forward capture sit near the reference one, behind the near plane.
    o = (o + torch.from_numpy(rng.uniform(-0.2, 0.2, 3))).reshape(-1, 3)
    d = d.reshape(-1, 3)
    o_ndc, d_ndc = m.rays(o, d)
    depths = torch.tensor([1.5, 2.0, 5.0, 30.0, 400.0], dtype=torch.float64)
    p_world = o[:, None] + depths[None, :, None] * d[:, None]
    p_ndc = m.points_to_ndc(p_world)
    # Solve p = o_ndc + t d_ndc for t from z (d_ndc z is 2), then x and y must agree.
    t = (p_ndc[..., 2] - o_ndc[:, None, 2]) / d_ndc[:, None, 2]
    on_ray = o_ndc[:, None] + t[..., None] * d_ndc[:, None]
    torch.testing.assert_close(on_ray, p_ndc, atol=1e-9, rtol=1e-9)
    assert bool((t > 0).all() and (t < 1).all()), "points between the near plane and infinity have t in (0, 1)"
    assert bool((t.diff(dim=1) > 0).all()), "farther world points are farther along the NDC ray"


def test_round_trip_world_ndc_world():
    rng = np.random.default_rng(3)
    m = _mapping(centred=False)
    p = torch.from_numpy(_points_in_front(m, 500, rng))
    back = m.points_to_world(m.points_to_ndc(p))
    torch.testing.assert_close(back, p, atol=1e-8, rtol=1e-8)
    q = torch.from_numpy(np.stack([rng.uniform(-1, 1, 200), rng.uniform(-1, 1, 200), rng.uniform(-1, 0.99, 200)], -1))
    torch.testing.assert_close(m.points_to_ndc(m.points_to_world(q)), q, atol=1e-9, rtol=1e-9)


def test_near_plane_maps_to_minus_one_and_far_tends_to_one():
    m = _mapping()
    c2w = np.asarray(m.reference_c2w)
    depths = np.array([m.near, 10 * m.near, 1e3 * m.near, 1e6 * m.near])
    cam = np.stack([0.1 * depths, -0.05 * depths, -depths], -1)
    z = m.points_to_ndc(torch.from_numpy(cam @ c2w[:3, :3].T + c2w[:3, 3]))[:, 2].numpy()
    assert z[0] == pytest.approx(-1.0, abs=1e-12)
    assert np.all(np.diff(z) > 0) and np.all(z < 1)
    assert 1 - z[-1] == pytest.approx(2e-6, rel=1e-6)
    # The inverse clamps z_ndc = 1 (infinity) to a finite point, far beyond the near plane.
    far = m.points_to_world(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))
    depth = -_to_camera(m, far.numpy())[0, 2]
    assert np.isfinite(depth) and depth == pytest.approx(2 * m.near / (1 - MAX_Z_NDC), rel=1e-6)


def test_ray_crosses_near_plane_at_z_minus_one_and_reaches_infinity_at_t_one():
    rng = np.random.default_rng(4)
    m = _mapping()
    targets = torch.from_numpy(_points_in_front(m, 50, rng))
    o = torch.from_numpy(np.asarray(m.reference_c2w)[:3, 3]).expand_as(targets)
    d = targets - o
    o_ndc, d_ndc = m.rays(o, d)
    near_point = m.points_to_world(o_ndc)
    np.testing.assert_allclose(-_to_camera(m, near_point.numpy())[:, 2], m.near, rtol=1e-9)
    end = o_ndc + d_ndc
    torch.testing.assert_close(end[:, 2], torch.ones(50, dtype=torch.float64))
    # The end is the ray's vanishing point: where points very far along the ray project.
    far = m.points_to_ndc(o + 1e9 * d / d.norm(dim=-1, keepdim=True))
    torch.testing.assert_close(end[:, :2], far[:, :2], atol=1e-6, rtol=1e-6)
    # world_distance turns an NDC point on the ray back into a distance along the world ray.
    t = (m.points_to_ndc(targets)[:, 2] + 1) / 2
    torch.testing.assert_close(m.world_distance(o, d, o_ndc + t[:, None] * d_ndc), d.norm(dim=-1))


def test_rays_parallel_to_the_image_plane_are_finite_and_miss_the_grid():
    m = _mapping()
    c2w = torch.tensor(m.reference_c2w, dtype=torch.float64)
    angles = torch.linspace(0, 2 * math.pi, 17, dtype=torch.float64)[:-1]
    d_cam = torch.stack([torch.cos(angles), torch.sin(angles), torch.zeros_like(angles)], -1)
    # Also rays pointing back out of the scene, and origins around the reference camera.
    d_cam = torch.cat([d_cam, d_cam + torch.tensor([0.0, 0.0, 0.3], dtype=torch.float64)])
    o_cam = torch.tensor([[0.05, -0.02, 0.01]], dtype=torch.float64).expand_as(d_cam)
    for dtype in (torch.float64, torch.float32):
        o = (o_cam @ c2w[:3, :3].T + c2w[:3, 3]).to(dtype)
        d = (d_cam @ c2w[:3, :3].T).to(dtype)
        o_ndc, d_ndc = m.rays(o, d)
        assert torch.isfinite(o_ndc).all() and torch.isfinite(d_ndc).all()
        # Sample the NDC ray densely: no point of it is inside the grid box.
        t = torch.linspace(0, 1, 2001, dtype=torch.float64)
        pts = o_ndc.double()[:, None] + t[None, :, None] * d_ndc.double()[:, None]
        inside = (pts.abs() <= 1).all(dim=-1)
        assert not inside.any()


def test_from_scene_and_dict_round_trip_and_resolution():
    m = _mapping(centred=False)
    frames = [{"fl_x": m.fl_x, "fl_y": m.fl_y, "cx": m.cx, "cy": m.cy, "w": m.w, "h": m.h, "split": "train"}] * 3
    frames.append({"fl_x": 999.0, "fl_y": 999.0, "cx": 1.0, "cy": 1.0, "w": 7, "h": 7, "split": "test"})
    scene = {"type": "forward", "frames": frames,
             "forward": {"reference_c2w": [list(r) for r in m.reference_c2w], "near": m.near, "far": 40.0}}
    built = NDCMapping.from_scene(scene)
    assert built == m
    assert NDCMapping.from_dict(built.to_dict()) == m
    rx, ry, rz = m.grid_resolution(256)
    assert (rx, ry) == (256, 192) and rz < ry
    # Depth stays at most 128 cells at fine levels (Plenoxels' 1408 x 1156 x 128 for LLFF).
    wide = NDCMapping.from_dict({**m.to_dict(), "w": 1008, "h": 756})
    assert wide.grid_resolution(1408) == (1408, 1056, 128)
    with pytest.raises(UserError):
        NDCMapping.from_scene({"type": "object", "frames": frames})
    with pytest.raises(UserError):
        NDCMapping.from_dict({**m.to_dict(), "near": 0.0})
    with pytest.raises(UserError):
        NDCMapping.from_dict({**m.to_dict(), "box_min": [0.5, -1.0], "box_max": [0.2, 1.0]})


def _forward_rig(m: NDCMapping, n: int, spread: float, turn: float, rng) -> list[dict]:
    """Training frames around the reference camera: shifted up to `spread` across its view and along it,
    turned up to `turn` radians, with its intrinsics."""
    ref = np.asarray(m.reference_c2w)
    frames = []
    for _ in range(n):
        c2w = ref.copy()
        c2w[:3, :3] = ref[:3, :3] @ _rotation(*rng.uniform(-turn, turn, 3))
        c2w[:3, 3] = ref[:3, 3] + ref[:3, :3] @ (rng.uniform(-spread, spread, 3) * [1.0, 1.0, 0.2])
        frames.append({"transform_matrix": c2w.tolist(), "fl_x": m.fl_x, "fl_y": m.fl_y, "cx": m.cx, "cy": m.cy,
                       "w": m.w, "h": m.h, "split": "train"})
    return frames


def test_grid_box_holds_what_every_training_camera_sees():
    """Every pixel's ray of every training camera lies inside the grid box from the near plane to infinity,
    the box is no wider than that needs (plus its margin), and cells keep their size in reference pixels."""
    rng = np.random.default_rng(5)
    m = _mapping(centred=False)
    frames = _forward_rig(m, 6, spread=0.25, turn=0.06, rng=rng)
    scene = {"type": "forward", "frames": frames,
             "forward": {"reference_c2w": [list(r) for r in m.reference_c2w], "near": m.near}}
    built = NDCMapping.from_scene(scene)
    lo, hi = (torch.tensor(v, dtype=torch.float64) for v in built.grid_box())
    assert bool((lo[:2] < -1).any() or (hi[:2] > 1).any()), "shifted cameras see beyond the reference image"
    reach_lo, reach_hi = torch.full((2,), 9.0, dtype=torch.float64), torch.full((2,), -9.0, dtype=torch.float64)
    for frame in frames:
        k = Intrinsics(m.fl_x, m.fl_y, m.cx, m.cy, m.w, m.h)
        o, d = rays_from_camera(np.asarray(frame["transform_matrix"]), k, torch.float64)
        o_ndc, d_ndc = built.rays(o.reshape(-1, 3), d.reshape(-1, 3))
        t = torch.linspace(0, 1, 33, dtype=torch.float64)
        pts = o_ndc[:, None] + t[None, :, None] * d_ndc[:, None]
        assert bool(((pts >= lo) & (pts <= hi)).all())
        reach_lo = torch.minimum(reach_lo, pts[..., :2].reshape(-1, 2).min(dim=0).values)
        reach_hi = torch.maximum(reach_hi, pts[..., :2].reshape(-1, 2).max(dim=0).values)
    # Pixel centres stop half a pixel short of the corners the box is built from; the margin is 2% a side.
    slack = 0.05 * (hi[:2] - lo[:2])
    assert bool((lo[:2] > torch.minimum(reach_lo, torch.tensor(-1.0)) - slack).all())
    assert bool((hi[:2] < torch.maximum(reach_hi, torch.tensor(1.0)) + slack).all())
    assert NDCMapping.from_dict(built.to_dict()) == built
    # Cells stay square in the reference image's pixels: 80 cells across its longer side (its width).
    rx, ry, _ = built.grid_resolution(80)
    cell_x = (hi[0] - lo[0]) / 2 * m.w / rx
    cell_y = (hi[1] - lo[1]) / 2 * m.h / ry
    assert float(cell_x) == pytest.approx(m.w / 80, rel=0.02) and float(cell_y) == pytest.approx(m.w / 80, rel=0.03)


def test_grid_box_of_the_reference_camera_alone_is_its_image_and_far_off_cameras_are_capped():
    m = _mapping(centred=False)
    alone = {"transform_matrix": [list(r) for r in m.reference_c2w], "fl_x": m.fl_x, "fl_y": m.fl_y, "cx": m.cx,
             "cy": m.cy, "w": m.w, "h": m.h}
    (x0, y0), (x1, y1) = m.covering_box([alone])
    np.testing.assert_allclose([x0, y0, x1, y1], np.array([-1, -1, 1, 1]) * 1.04, atol=1e-9)
    # A camera turned half-way to the side sees far beyond any useful box: the box stops at the cap.
    turned = np.asarray(m.reference_c2w).copy()
    turned[:3, :3] = turned[:3, :3] @ _rotation(0.0, 0.0, 0.8)
    lo, hi = m.covering_box([alone, {**alone, "transform_matrix": turned.tolist()}])
    assert max(abs(v) for v in (*lo, *hi)) == pytest.approx(MAX_BOX_REACH)
