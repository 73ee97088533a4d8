"""Export: the fitted radiance field -> a coloured mesh and a coloured point cloud, in the input frame.

Writes export/mesh.ply, mesh.obj and mesh.glb (one mesh: marching cubes over the fitted density,
view-averaged colours, small pieces and floaters removed, cropped to the foreground, faces no
training view sees dropped, optionally decimated), export/points.ply (points where the training views' rays terminate, with colours and
normals) and export/export.json (the frame, counts, sizes, bounds, level and resolution).

Seen faces: a fit only pins down density where rays stop, so its surfaces are shells whose insides
(and the undersides no camera looks at) are guesses; marching cubes turns them into inner surfaces.
With `unseen: drop` (the default) a face stays only if a training view, rendered from the grid, sees
one of its vertices: facing the camera and not behind the view's own depth (`seen_tolerance` voxels).
The mesh then shows what the photos show and is open where they show nothing.

Frames: geometry is extracted in the fit frame (the normalised world, or NDC for forward scenes),
mapped to the normalised world, cropped there, then written in the input (COLMAP) frame through
scene.json's `input_from_world`, or left in the normalised frame with `frame: normalized`.
"""
from __future__ import annotations


import numpy as np
import trimesh

from pipeline.io import rgba8, write_mesh_files, write_points
from pipeline.json_files import read_json, write_json
from plenoxels.errors import UserError
from plenoxels.fit_frame import FitFrame
from plenoxels.mesh import (LEVEL_RAY_OPACITY, auto_level, clean_mesh, decimate, extract_surface, grid_lattice,
                            grid_lattice_voxel, grid_lattice_voxel_world, mesh_to_world, refine, submesh,
                            surface_colours, transform_normals, transform_points)
from plenoxels.scene_model import SceneModel
from plenoxels.surface import (Terminations, ViewRender, point_normals, ray_terminations, render_views,
                               seen_vertices, snap_to_level)
from stages.settings.export import Settings


def _in_box(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.all((points >= lo) & (points <= hi), axis=1)


def _size(n_bytes: int) -> str:
    for unit in ("B", "kB", "MB", "GB"):
        if n_bytes < 1000 or unit == "GB":
            return f"{n_bytes:.0f} {unit}" if unit == "B" else f"{n_bytes:.1f} {unit}"
        n_bytes /= 1000
    return f"{n_bytes} B"


def _count(n: int) -> str:
    return f"{n / 1e6:.2f}M" if n >= 1e6 else f"{n / 1e3:.1f}k" if n >= 1e4 else str(n)


def _bounds(points: np.ndarray) -> dict:
    if len(points) == 0:
        return {"min": None, "max": None}
    return {"min": points.min(0).round(6).tolist(), "max": points.max(0).round(6).tolist()}


def build_mesh(grid, frame: FitFrame, box_min: np.ndarray, box_max: np.ndarray, s: Settings, report,
               level_rays: Terminations | None = None, views: list[ViewRender] | None = None) -> tuple[trimesh.Trimesh, dict]:
    """The cleaned, coloured mesh in the normalised world, and what was decided on the way.
    `level_rays`: the training views' opaque rays (fit frame), for the auto level;
    `views`: the training views rendered, to drop the faces none of them sees (with unseen: drop)."""
    lattice = grid_lattice(grid)
    if s.level == "auto":
        level, level_source = auto_level(grid, lattice, level_rays, s.level_share, s.level_opacity, s.seed)
    else:
        level, level_source = float(s.level), "set"
    native = int(np.max(lattice.values.shape) - 1)
    resolution = native if s.resolution == "auto" else int(s.resolution)
    fine = refine(lattice, resolution, level)
    report.info(f"marching cubes at density {level:.4g} on a {'x'.join(map(str, fine.values.shape))} lattice")
    vertices, faces = extract_surface(fine, level)
    world, faces = mesh_to_world(vertices, faces, frame)
    mesh = trimesh.Trimesh(world, faces, process=False)

    size = box_max - box_min
    margin = s.crop_margin * size
    mesh, cleaning = clean_mesh(mesh, box_min - margin, box_max + margin, s.min_piece_fraction,
                                s.max_gap * float(np.linalg.norm(size)))
    if len(mesh.faces) == 0:
        raise UserError("the mesh is empty after cropping to the foreground box; check normalize's foreground "
                        "or raise export.crop_margin")
    unseen_faces = 0
    if s.unseen == "drop" and views:
        voxel_world = grid_lattice_voxel_world(grid, frame, mesh)
        seen = seen_vertices(mesh, views, frame, voxel_world, s.seen_tolerance * voxel_world, s.point_opacity)
        keep = seen[mesh.faces].any(axis=1)
        unseen_faces = int((~keep).sum())
        mesh, _ = clean_mesh(submesh(mesh, keep), box_min - margin, box_max + margin, s.min_piece_fraction,
                             s.max_gap * float(np.linalg.norm(size)))
        if len(mesh.faces) == 0:
            raise UserError("no training view sees any part of the mesh; set export.unseen=keep")
    faces_before_decimation = len(mesh.faces)
    mesh = decimate(mesh, s.target_faces)
    colours = surface_colours(grid, frame.from_world(np.asarray(mesh.vertices)), lattice.voxel)
    mesh.visual.vertex_colors = rgba8(colours)
    decisions = {
        "level": level,
        "level_source": level_source,
        "resolution": resolution,
        "fit_resolution": list(lattice.values.shape),
        "lattice": list(fine.values.shape),
        "voxel": fine.voxel,
        "cleaning": vars(cleaning),
        "unseen_faces_dropped": unseen_faces,
        "faces_before_decimation": faces_before_decimation,
        "decimated": len(mesh.faces) < faces_before_decimation,
    }
    return mesh, decisions


def run(ctx) -> dict:
    s: Settings = ctx.settings
    scene = read_json(ctx.upstream["normalize"] / "scene.json")
    # A contracted grid's far world is coarse and squeezed: exports read its inner cube, which holds the foreground box.
    model = SceneModel.load(ctx.upstream["fit"]).foreground_model()
    grid = model.grid
    frame = model.fit_frame
    box_min = np.asarray(scene["foreground"]["min"], dtype=np.float64)
    box_max = np.asarray(scene["foreground"]["max"], dtype=np.float64)
    if s.crop:
        box_min, box_max = np.asarray(s.crop[:3], dtype=np.float64), np.asarray(s.crop[3:], dtype=np.float64)

    crop_min, crop_max = box_min - s.crop_margin * (box_max - box_min), box_max + s.crop_margin * (box_max - box_min)
    views = render_views(grid, frame, scene["frames"], s.point_scale, s.point_views, ctx.report)
    terminations = ray_terminations(views, frame, s.point_opacity)
    ends = terminations.world(frame)
    inside = _in_box(ends, crop_min, crop_max)
    terminations = terminations.subset(inside)
    # The level comes from nearly opaque rays only: a fainter one grazes an edge or crosses a thin part, whose peak is low.
    opaque = terminations.opacity >= LEVEL_RAY_OPACITY
    mesh, decisions = build_mesh(grid, frame, box_min, box_max, s, ctx.report, terminations.subset(opaque), views)

    voxel = grid_lattice_voxel(grid)
    if len(terminations.t) > 2 * s.points:  # the snap drops some rays: keep a margin, subsample after
        terminations = terminations.subset(np.random.default_rng(s.seed).choice(len(terminations.t), 2 * s.points,
                                                                                  replace=False))
    points = snap_to_level(grid, terminations, decisions["level"], voxel).world(frame)
    # A ray that grazes the foreground can snap onto matter beyond it (the ground of an unbounded scene).
    points = points[_in_box(points, crop_min, crop_max)]
    if len(points) > s.points:
        points = points[np.sort(np.random.default_rng(s.seed).choice(len(points), s.points, replace=False))]
    colours = surface_colours(grid, frame.from_world(points), voxel)
    normals = point_normals(grid, frame, points, voxel)
    if len(terminations.t) == 0:
        ctx.report.warn(f"no training-view pixel is {s.point_opacity:.0%} opaque inside the foreground box: the "
                        "level comes from export.level_opacity and points.ply is empty; lower export.point_opacity")

    if s.frame == "input":
        to_output = np.asarray(scene["input_from_world"], dtype=np.float64)
        mesh.apply_transform(to_output)
        points, normals = transform_points(to_output, points), transform_normals(to_output, normals)
    else:
        to_output = np.eye(4)
    files = write_mesh_files(mesh, ctx.work)
    if s.points > 0:
        write_points(ctx.work / "points.ply", points, colours, normals)
        files["points"] = "points.ply"
    sizes = {name: (ctx.work / f).stat().st_size for name, f in files.items()}

    frame_name = "input (the poses' COLMAP frame)" if s.frame == "input" else "normalized (z up, foreground in [-1, 1]^3)"
    record = {
        "frame": s.frame,
        "frame_description": frame_name,
        "output_from_normalized": to_output.tolist(),
        "scene_type": scene.get("type"),
        "fit_frame": "ndc" if frame.ndc is not None else "inner cube of a contracted grid"
        if frame.contraction is not None else "normalized",
        "files": files,
        "file_bytes": sizes,
        "mesh": {"vertices": len(mesh.vertices), "faces": len(mesh.faces), "bounds": _bounds(mesh.vertices)},
        "points": {"count": len(points), "bounds": _bounds(points)},
        "glb_axes": "glTF y-up: (x, z, -y) of the frame; z-up importers such as Blender's restore the frame's coordinates",
        **decisions,
    }
    write_json(ctx.work / "export.json", record)
    lo, hi = record["mesh"]["bounds"]["min"], record["mesh"]["bounds"]["max"]
    line = (f"mesh {_count(len(mesh.faces))} faces ({_size(sizes['ply'])} PLY), {_count(len(points))} points "
            f"({_size(sizes.get('points', 0))}) in the {s.frame} frame, bounds "
            f"[{', '.join(f'{v:.3g}' for v in lo)}] to [{', '.join(f'{v:.3g}' for v in hi)}], "
            f"level {decisions['level']:.3g}{' (auto)' if s.level == 'auto' else ''}, resolution {decisions['resolution']}")
    return {"line": line, "frame": s.frame, "faces": len(mesh.faces), "vertices": len(mesh.vertices),
            "points": len(points), "level": decisions["level"], "resolution": decisions["resolution"]}
