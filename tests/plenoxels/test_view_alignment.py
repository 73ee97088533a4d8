"""Aligning a mesh to the training views' colours: a patterned sphere's mesh set off its surface, inwards or
outwards, comes back onto it; a mesh already on it, or on a surface with no pattern, stays; views without colour and
a reach under one step leave it as it is."""
import math

import numpy as np
import torch
import trimesh

from plenoxels.core.cameras import Intrinsics, look_at
from plenoxels.core.fit_frame import FitFrame
from plenoxels.core.grid import SparseGrid
from plenoxels.core.render import COLOUR_OFFSET, SH_C0
from plenoxels.surface.views import ViewRender, render_views
from plenoxels.surface.view_alignment import STEP_VOXELS, align_to_views

CENTRE = np.array([0.05, -0.03, 0.02])
RADIUS = 0.55
RES = 64
VOXEL = 2 / (RES - 1)


class _Quiet:
    def track(self, items, total=None, desc=""):
        return items


def sphere_grid(pattern: bool) -> SparseGrid:
    """A solid sphere (50% opacity per voxel at its surface, a couple of voxels' ramp) whose view-independent colour
    is a pattern of blobs a few voxels across, or one grey."""
    axes = np.linspace(-1, 1, RES)
    p = np.stack(np.meshgrid(axes, axes, axes, indexing="ij"), axis=-1)
    dist = np.linalg.norm(p - CENTRE, axis=-1)
    density = 2 * math.log(2) / VOXEL / (1 + np.exp(-(RADIUS - dist) / (0.7 * VOXEL)))
    if pattern:
        waves = [np.sin(7.0 * p @ d + phase) for d, phase in
                 ((np.array([1.0, 0.3, 0.2]), 0.0), (np.array([-0.2, 1.0, 0.4]), 1.0), (np.array([0.3, -0.4, 1.0]), 2.0))]
        colour = np.stack([0.5 + 0.4 * waves[0] * waves[1], 0.5 + 0.4 * waves[1] * waves[2], 0.5 + 0.4 * waves[2] * waves[0]],
                          axis=-1)
    else:
        colour = np.full(p.shape, 0.5)
    sh = ((colour - COLOUR_OFFSET) / SH_C0).reshape(-1, 3)
    links = torch.arange(density.size, dtype=torch.int32).reshape(density.shape)
    return SparseGrid.from_values(links, torch.as_tensor(density.reshape(-1), dtype=torch.float32),
                                  torch.as_tensor(sh, dtype=torch.float32), (-1, -1, -1), (1, 1, 1), sh_degree=0)


def frames(size: int = 128) -> list[dict]:
    """Twelve views on two rings around the sphere, a pixel about a voxel wide on its near side."""
    records = []
    for i in range(12):
        angle, height = 2 * math.pi * i / 6 + (0.5 if i >= 6 else 0.0), (0.5 if i < 6 else -0.4)
        eye = CENTRE + 2.4 * np.array([math.cos(angle), math.sin(angle), height])
        records.append({"transform_matrix": look_at(eye, CENTRE).tolist(), "fl_x": size * 1.1, "fl_y": size * 1.1,
                        "cx": size / 2, "cy": size / 2, "w": size, "h": size, "split": "train"})
    return records


def offset_sphere(offset_voxels: float) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=5, radius=RADIUS + offset_voxels * VOXEL).apply_translation(CENTRE)


def radial_voxels(mesh: trimesh.Trimesh) -> np.ndarray:
    return (np.linalg.norm(mesh.vertices - CENTRE, axis=1) - RADIUS) / VOXEL


def align(mesh: trimesh.Trimesh, views: list[ViewRender], reach: float = 2.5):
    # Seen up to two voxels behind what the views render, so a mesh set inside the sphere keeps its views.
    return align_to_views(mesh, views, FitFrame(), VOXEL, 2 * VOXEL, 0.5, reach)


def test_a_mesh_set_off_a_patterned_surface_comes_back_onto_it():
    views = render_views(sphere_grid(pattern=True), FitFrame(), frames(), 1.0, 0, _Quiet())
    on_surface = np.median(radial_voxels(align(offset_sphere(0.0), views)[0]))
    for start in (1.5, -1.5):
        aligned, record = align(offset_sphere(start), views)
        seen = np.abs(radial_voxels(aligned) - start) > 0.1  # the underside no view faces stays
        assert seen.mean() > 0.5 and record["moved"] > 0.5
        # Most of the way back to where the same alignment puts a mesh that starts on the level set (the prior
        # against moving far holds some vertices short of it, by up to a step or two).
        before = abs(start - on_surface)
        assert np.median(np.abs(radial_voxels(aligned)[seen] - on_surface)) < 0.5 * before, start
        assert len(aligned.faces) == len(offset_sphere(start).faces)
    # On this sphere the views' colours line up within a step of its level set.
    assert abs(on_surface) <= STEP_VOXELS


def test_a_mesh_on_a_surface_without_pattern_stays_where_it_is():
    views = render_views(sphere_grid(pattern=False), FitFrame(), frames(), 1.0, 0, _Quiet())
    aligned, record = align(offset_sphere(1.0), views)
    assert np.allclose(aligned.vertices, offset_sphere(1.0).vertices)
    assert record["moved"] == 0.0


def test_no_colour_or_no_reach_leaves_the_mesh_alone():
    views = render_views(sphere_grid(pattern=True), FitFrame(), frames(32), 1.0, 0, _Quiet())
    mesh = offset_sphere(1.5)
    colourless = [ViewRender(v.c2w, v.k, v.t, v.opacity) for v in views]
    for kept, record in (align(mesh, colourless), align(mesh, views, reach=STEP_VOXELS / 2), align(mesh, [])):
        assert kept is mesh and record["moved"] == 0.0
    assert isinstance(views[0].k, Intrinsics) and views[0].rgb.dtype == np.uint8
