"""Splat files: the PLY read back with a PLY reader has exactly the 3D Gaussian Splatting properties and loses nothing;
the GLB's JSON and buffers hold what KHR_gaussian_splatting defines (names, types, counts, value ranges, COLOR_0) and
read back to the same splats, rendering the same pixels; the export stage writes both in the input frame."""
import numpy as np
import pytest
import torch
import trimesh
from plyfile import PlyData

from plenoxels.core.cameras import Intrinsics, look_at
from plenoxels.core.background import MultiSphereBackground
from plenoxels.core.fit_frame import FitFrame
from plenoxels.core.scene_model import SceneModel
from plenoxels.splats.distill import psnr
from plenoxels.splats.background_splats import OUTSIDE_CAMERAS
from plenoxels.splats.model import Splats
from plenoxels.splats.rasterize import render
from stages.interchange.splat_files import (EXTENSION, read_glb, read_splat_glb, read_splat_ply, write_splat_glb,
                                            write_splat_ply)
from stages.common.json_files import read_json
from stages.settings.export import Settings
from tests.stages.test_export import (SPHERE_CENTRE, SPHERE_RADIUS, cluttered_sphere_field, forward_rig,
                                      identity_scene, orbit_frames, run_stage, sphere_field)


def some_splats(n: int, degree: int, seed: int = 0) -> Splats:
    g = torch.Generator().manual_seed(seed)
    return Splats(torch.randn(n, 3, generator=g) * 0.5, torch.log(0.02 + 0.1 * torch.rand(n, 3, generator=g)),
                  torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=1), torch.randn(n, generator=g) * 2,
                  torch.randn(n, 3, (degree + 1) ** 2, generator=g) * 0.5)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_ply_has_the_original_layout_and_round_trips_exactly(tmp_path, degree):
    splats = some_splats(50, degree)
    write_splat_ply(tmp_path / "s.ply", splats)
    ply = PlyData.read(str(tmp_path / "s.ply"))
    assert [e.name for e in ply.elements] == ["vertex"] and ply.byte_order == "<"
    rest = 3 * ((degree + 1) ** 2 - 1)
    expected = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(rest)]
                + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    assert [p.name for p in ply["vertex"].properties] == expected
    assert all(p.val_dtype in ("f4", "float32", "float") for p in ply["vertex"].properties)
    v = ply["vertex"]
    # f_rest runs through all of red's coefficients, then green's, then blue's; rot_0 is w.
    if degree:
        assert np.allclose(v["f_rest_0"], splats.sh[:, 0, 1]) and np.allclose(v[f"f_rest_{rest // 3}"], splats.sh[:, 1, 1])
    assert np.allclose(v["rot_0"], splats.quats[:, 0]) and np.allclose(v["scale_1"], splats.log_scales[:, 1])
    back = read_splat_ply(tmp_path / "s.ply")
    for name, t in splats.tensors().items():
        assert torch.equal(getattr(back, name), t.float()), name


def test_glb_follows_khr_gaussian_splatting_and_round_trips(tmp_path):
    splats = some_splats(64, 2, seed=1)
    write_splat_glb(tmp_path / "s.glb", splats)
    document, values = read_glb(tmp_path / "s.glb")
    assert document["asset"]["version"] == "2.0" and EXTENSION in document["extensionsUsed"]
    primitive = document["meshes"][0]["primitives"][0]
    assert primitive["mode"] == 0
    ext = primitive["extensions"][EXTENSION]
    assert ext["kernel"] == "ellipse" and ext["colorSpace"] == "srgb_rec709_display"
    sh_names = [f"{EXTENSION}:SH_DEGREE_{l}_COEF_{n}" for l in range(3) for n in range(2 * l + 1)]
    expected = {"POSITION": "VEC3", "COLOR_0": "VEC4", f"{EXTENSION}:ROTATION": "VEC4", f"{EXTENSION}:SCALE": "VEC3",
                f"{EXTENSION}:OPACITY": "SCALAR", **{name: "VEC3" for name in sh_names}}
    assert set(primitive["attributes"]) == set(expected)
    for name, kind in expected.items():
        accessor = document["accessors"][primitive["attributes"][name]]
        assert (accessor["type"], accessor["componentType"], accessor["count"]) == (kind, 5126, 64), name
        view = document["bufferViews"][accessor["bufferView"]]
        assert view["byteOffset"] % 4 == 0 and view["byteLength"] == 64 * 4 * values[name].shape[1]
    position = document["accessors"][primitive["attributes"]["POSITION"]]
    assert np.allclose(position["min"], values["POSITION"].min(0)) and np.allclose(position["max"], values["POSITION"].max(0))
    assert np.allclose(np.linalg.norm(values[f"{EXTENSION}:ROTATION"], axis=1), 1, atol=1e-6)
    assert (values[f"{EXTENSION}:SCALE"] > 0).all()
    opacity = values[f"{EXTENSION}:OPACITY"][:, 0]
    assert ((opacity >= 0) & (opacity <= 1)).all() and np.allclose(values["COLOR_0"][:, 3], opacity)
    assert ((values["COLOR_0"] >= 0) & (values["COLOR_0"] <= 1)).all()
    # y-up: glTF's y is the frame's z, and the scale and opacity are the PLY's, linear and past the sigmoid.
    assert np.allclose(values["POSITION"], splats.means.numpy()[:, [0, 2, 1]] * [1, 1, -1], atol=1e-6)
    assert np.allclose(values[f"{EXTENSION}:SCALE"], torch.exp(splats.log_scales), rtol=1e-5)
    assert np.allclose(opacity, torch.sigmoid(splats.opacity_logits), atol=1e-6)
    # COLOR_0 is the degree-0 colour in linear light: a mid grey in sRGB (0.5) is about 0.214 linear.
    grey = Splats(torch.zeros(1, 3), torch.zeros(1, 3), torch.tensor([[1.0, 0, 0, 0]]), torch.zeros(1), torch.zeros(1, 3, 1))
    write_splat_glb(tmp_path / "grey.glb", grey)
    assert np.allclose(read_glb(tmp_path / "grey.glb")[1]["COLOR_0"][0, :3], 0.2140, atol=1e-3)

    back = read_splat_glb(tmp_path / "s.glb")
    assert torch.allclose(back.means, splats.means, atol=1e-6) and torch.allclose(back.sh, splats.sh, atol=1e-5)
    assert torch.allclose(back.covariances(), splats.covariances(), atol=1e-6)
    assert torch.allclose(back.opacity_logits, splats.opacity_logits, atol=1e-4)
    c2w = look_at(np.array([1.5, -2.0, 1.0]), (0.0, 0.0, 0.0))
    k = Intrinsics(40, 40, 16, 16, 32, 32)
    assert (render(back, c2w, k)["rgb"] - render(splats, c2w, k)["rgb"]).abs().max() < 1e-4


def test_export_stage_writes_both_files_in_the_input_frame_and_they_render_like_the_field(tmp_path):
    field = sphere_field(32)
    input_from_world = trimesh.transformations.rotation_matrix(2.0, [0.2, 0.9, -0.4]) * 1.7
    input_from_world[3] = [0, 0, 0, 1]
    input_from_world[:3, 3] = [3.0, -2.0, 0.5]
    frames = orbit_frames(6, size=32)
    scene = {"type": "object", "input_from_world": input_from_world.tolist(),
             "world_from_input": np.linalg.inv(input_from_world).tolist(),
             "foreground": {"min": [-0.8] * 3, "max": [0.8] * 3}, "frames": frames}
    # No distillation: the test holds to the start from the grid, which the machine's load cannot change.
    settings = Settings(points=500, point_scale=1.0, texture=False, align_voxels=0, splat_scale=1.0, splat_seconds=0)
    summary, folder = run_stage(tmp_path, field, scene, settings, "splats", splats=True)
    record = read_json(folder / "export.json")
    assert record["files"]["splats_ply"] == "splats.ply" and record["files"]["splats_glb"] == "splats.glb"
    assert summary["splats"] == record["splats"]["count"] > 500 and "splats" in summary["line"]
    assert record["splats"]["distillation"]["steps"] == 0
    ply, glb = read_splat_ply(folder / "splats.ply"), read_splat_glb(folder / "splats.glb")
    assert ply.count == glb.count == record["splats"]["count"]
    assert torch.allclose(ply.means, glb.means, atol=1e-5) and torch.allclose(ply.sh, glb.sh, atol=1e-4)
    # In the input frame: mapped back to the normalised world, they sit on the sphere and render like the field.
    back = ply.transformed(np.linalg.inv(input_from_world))
    radii = (back.means - torch.as_tensor(SPHERE_CENTRE, dtype=torch.float32)).norm(dim=1)
    heavy = back.opacities() > 0.3
    assert (radii[heavy] - SPHERE_RADIUS).abs().median() < 2 * 2 / 31
    model = SceneModel(field, "object")
    scores = []
    for frame in frames[:3]:
        c2w, k = np.asarray(frame["transform_matrix"]), Intrinsics.from_frame(frame)
        scores.append(psnr(render(back, c2w, k)["rgb"], model.render_camera(c2w, k)["rgb"]))
    assert np.mean(scores) > 20, scores
    # The same splats left in the input frame do not: the check can tell.
    assert psnr(render(ply, c2w, k)["rgb"], model.render_camera(c2w, k)["rgb"]) < 15


def test_a_forward_scene_s_ndc_grid_becomes_splats_in_the_world_and_a_background_model_becomes_splats(tmp_path):
    c2w, ndc, view = forward_rig()
    forward = -c2w[:3, 2]
    behind = lambda p: ((p - c2w[:3, 3]) @ forward > 9.0) & ((p - c2w[:3, 3]) @ forward < 15.0)  # noqa: E731
    field = cluttered_sphere_field(40, behind, FitFrame(ndc).to_world, (-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    settings = Settings(frame="normalized", points=500, point_scale=1.0, texture=False, splat_seconds=2,
                        splat_window=32, splat_scale=1.0)
    run_stage(tmp_path, field, identity_scene("forward", [{**view, "split": "train"}]), settings, "forward", ndc=ndc,
              splats=True)
    splats = read_splat_ply(tmp_path / "forward" / "export" / "splats.ply")
    on_sphere = (splats.means - torch.as_tensor(SPHERE_CENTRE, dtype=torch.float32)).norm(dim=1) < SPHERE_RADIUS + 0.1
    assert on_sphere.sum() > 200  # world positions, not NDC ones
    model = SceneModel(field, "forward", fit_frame=FitFrame(ndc))
    k = Intrinsics.from_frame(view)
    assert psnr(render(splats, c2w, k)["rgb"], model.render_camera(c2w, k)["rgb"]) > 22

    background = MultiSphereBackground.around_box([-0.8] * 3, [0.8] * 3, n_spheres=2, height=4, width=8)
    settings = Settings(frame="normalized", points=500, point_scale=1.0, texture=False, splat_seconds=0,
                        texture_size=256, align_voxels=0)
    frames = orbit_frames(4, size=24)
    run_stage(tmp_path, sphere_field(24), identity_scene("unbounded", frames), settings, "unbounded",
              background=background, splats=True)
    record = read_json(tmp_path / "unbounded" / "export" / "export.json")["splats"]
    # Every texel of the two 4x8 spheres holds the initial density, not clear: a splat each, on its sphere, or beyond
    # the cameras where they stand outside it (the model reads a sphere only where rays leave it).
    assert record["background_splats"] == 64 and record["count"] == record["grid_splats"] + 64
    assert "spheres" in record["background"] and record["grid_splats"] > 100
    radii = (read_splat_ply(tmp_path / "unbounded" / "export" / "splats.ply").means[-64:]
             - background.centre).norm(dim=1)
    reach = max(float(np.linalg.norm(np.asarray(f["transform_matrix"])[:3, 3] - background.centre.numpy()))
                for f in frames)
    assert background.radii[0] < reach < background.radii[1]  # the cameras stand outside the inner sphere
    expected = background.radii.clamp_min(OUTSIDE_CAMERAS * reach).repeat_interleave(32)
    assert torch.allclose(radii.sort().values, expected.float(), rtol=1e-4)
