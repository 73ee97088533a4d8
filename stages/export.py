"""Export: the fitted radiance field -> a textured mesh and a coloured point cloud, in the input frame.

Writes export/mesh.ply (vertex colours), mesh.obj + mesh.mtl + mesh.png and mesh.glb (textured; with vertex colours
when export.texture is off), points.ply (points where the training views' rays terminate, with colours and normals)
and export.json (the frame, counts, sizes, bounds, level, resolution, what was cut away, the decimation and the
texture). One mesh: marching cubes over the fitted density (the solids' small openings sealed first,
export.fill_voxels), small pieces and floaters removed, cropped to the foreground box (or export.crop), faces no
training view sees dropped, the ground and the room cut away for object and unbounded scenes, decimated to
export.max_faces, its vertices moved onto where the training views agree on the colour (export.align_voxels), then
unwrapped and its texture baked (plenoxels/surface/mesh.py, plenoxels/surface/ground.py,
plenoxels/surface/view_alignment.py, plenoxels/surface/texture.py; files: stages/interchange/mesh_files.py).

Splats (export.splats): splats.ply (the original 3D Gaussian Splatting layout) and splats.glb (KHR_gaussian_splatting,
COLOR_0 for viewers without it) of the field itself, view-dependent colour and soft matter included: a splat per grid
cell the training views see (at most export.max_splats) and one per texel of a background model's spheres, distilled
for export.splat_seconds against the field's renders of the training views, then rendered from the held-out views and
scored against the photos and the field's render (export.json `splats` and the summary line; plenoxels/splats/,
stages/interchange/splat_files.py, stages/scoring/splat_views.py).

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

from stages.common.media import write_points
from stages.common.json_files import read_json, write_json
from stages.interchange.mesh_files import write_mesh_files
from stages.interchange.splat_files import write_splat_glb, write_splat_ply
from stages.scoring.splat_views import score_splats
from plenoxels.surface.mesh import (LEVEL_RAY_OPACITY, build_mesh, grid_lattice_voxel, surface_colours, transform_normals,
                            transform_points)
from plenoxels.core import memory
from plenoxels.core.scene_model import SceneModel
from plenoxels.surface.views import point_normals, ray_terminations, render_views, snap_to_level
from plenoxels.surface.texture import texture_mesh, view_sight
from plenoxels.surface.view_alignment import align_to_views
from plenoxels.splats.field_splats import fit_splats
from stages.settings.export import Settings
from stages.common.layout import EXPORT_JSON, MEMORY_AS_SET, MODEL_JSON, SCENE_JSON
from stages.exporting.memory_plan import MAX_TERMINATIONS, lowered_words, within_memory


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


def run(ctx) -> dict:
    s: Settings = ctx.settings
    scene = read_json(ctx.upstream["normalize"] / SCENE_JSON)
    # A contracted grid's far world is coarse and squeezed: exports read its inner cube, which holds the foreground box.
    fitted = SceneModel.load(ctx.upstream["fit"])
    model = fitted.foreground_model()
    grid = model.grid
    frame = model.fit_frame
    box_min = np.asarray(scene["foreground"]["min"], dtype=np.float64)
    box_max = np.asarray(scene["foreground"]["max"], dtype=np.float64)
    if s.crop:
        box_min, box_max = np.asarray(s.crop[:3], dtype=np.float64), np.asarray(s.crop[3:], dtype=np.float64)

    s, lowered, need_as_set = within_memory(s, grid, scene["frames"])
    if lowered:
        ctx.report.warn(f"the export as set would not fit in the memory this process may use: {lowered_words(lowered)}")
    crop_min, crop_max = box_min - s.crop_margin * (box_max - box_min), box_max + s.crop_margin * (box_max - box_min)
    views = render_views(grid, frame, scene["frames"], s.point_scale, s.point_views, ctx.report)
    terminations = ray_terminations(views, frame, s.point_opacity, MAX_TERMINATIONS, s.seed)
    ends = terminations.world(frame)
    inside = _in_box(ends, crop_min, crop_max)
    terminations = terminations.subset(inside)
    memory.release_freed()
    # The level comes from nearly opaque rays only: a fainter one grazes an edge or crosses a thin part, whose peak is low.
    opaque = terminations.opacity >= LEVEL_RAY_OPACITY
    object_only = s.object_only == "on" or (s.object_only == "auto" and scene.get("type") != "forward")
    masked = scene.get("type") == "object" and all(f.get("mask_path") for f in scene["frames"])
    mesh, decisions = build_mesh(grid, frame, box_min, box_max, s, ctx.report, terminations.subset(opaque), views,
                                 object_only=object_only, user_box=bool(s.crop), masked=masked)
    memory.release_freed()
    # The atlas is charted on the level set as it came (the same faces): xatlas charts the aligned surface, rougher by
    # a fraction of a voxel, several times slower (bench/README.md), and a shift that small does not stretch the UVs.
    layout = np.asarray(mesh.vertices).copy()
    decisions["aligned"] = {"reach_voxels": 0.0}
    if s.align_voxels > 0:
        ctx.report.info(f"aligning {_count(len(mesh.vertices))} vertices to the training views' colours")
        voxel_world = decisions["voxel_world"]
        mesh, decisions["aligned"] = align_to_views(mesh, views, frame, voxel_world, s.seen_tolerance * voxel_world,
                                                    s.point_opacity, s.align_voxels)
        mesh.visual.vertex_colors = surface_colours(grid, frame.from_world(np.asarray(mesh.vertices)),
                                                    grid_lattice_voxel(grid))
    voxel = grid_lattice_voxel(grid)
    if len(terminations.t) > 2 * s.points:  # the snap drops some rays: keep a margin, subsample after
        terminations = terminations.subset(np.random.default_rng(s.seed).choice(len(terminations.t), 2 * s.points,
                                                                                  replace=False))
    points = snap_to_level(grid, terminations, decisions["level"], voxel).world(frame)
    # A ray that grazes the foreground can snap onto matter beyond it (the ground of an unbounded scene).
    points = points[_in_box(points, crop_min, crop_max)]
    ground = decisions["object_only"].get("ground")
    if decisions["object_only"].get("ground_faces_cut"):  # the ground the mesh lost goes from the points too
        points = points[points @ np.asarray(ground["normal"]) - ground["offset"] >= ground["cut_height"]]
    if len(points) > s.points:
        points = points[np.sort(np.random.default_rng(s.seed).choice(len(points), s.points, replace=False))]
    colours = surface_colours(grid, frame.from_world(points), voxel)
    normals = point_normals(grid, frame, points, voxel)
    if len(terminations.t) == 0:
        ctx.report.warn(f"no training-view pixel is {s.point_opacity:.0%} opaque inside the foreground box: the "
                        "level comes from export.level_opacity and points.ply is empty; lower export.point_opacity")
    # What the texture needs of the views (which see each vertex, how squarely), so they are let go before it bakes.
    sight = (view_sight(grid, frame, mesh, views, s.seen_tolerance, s.point_opacity)
             if s.texture and s.texture_colour == "view" else None)
    del views, terminations
    memory.release_freed()
    texture = None
    if s.texture:
        ctx.report.info(f"unwrapping {_count(len(mesh.faces))} faces and baking a {s.texture_size}-texel texture")
        texture = texture_mesh(grid, frame, mesh, s.texture_size, s.texture_colour, sight=sight,
                               view_count=s.texture_views, layout_vertices=layout)
        decisions["texture"] = {"size": list(texture.atlas.size), "charts": texture.atlas.charts,
                                "colour": texture.colour, "atlas_vertices": len(texture.atlas.uv)}
        del sight
        memory.release_freed()

    if s.frame == "input":
        to_output = np.asarray(scene["input_from_world"], dtype=np.float64)
        mesh.apply_transform(to_output)
        points, normals = transform_points(to_output, points), transform_normals(to_output, normals)
    else:
        to_output = np.eye(4)
    files = write_mesh_files(mesh, ctx.work, texture)
    if s.points > 0:
        write_points(ctx.work / "points.ply", points, colours, normals)
        files["points"] = "points.ply"
    del texture, layout   # written: the splats start from what the mesh's files leave
    memory.release_freed()
    splats = None
    if s.splats:
        ctx.report.info(f"fitting up to {_count(s.max_splats)} splats to the field ({s.splat_seconds:g} s distillation)")
        splats, splat_record = fit_splats(model, scene["frames"], s.max_splats, s.splat_min_weight, s.splat_scale,
                                          s.splat_views, s.splat_seconds, s.splat_window, s.seed, ctx.report.track)
        fit_scale = float(read_json(ctx.upstream["fit"] / MODEL_JSON).get("fit_settings", {}).get("image_scale", 1.0))
        splat_record["held_out"] = score_splats(ctx.out, splats, fitted, scene["frames"], fit_scale,
                                                s.splat_score_views, ctx.report.track)
        splat_record["background"] = _splat_background(fitted, model, splat_record)
        writable = splats.transformed(to_output)
        write_splat_ply(ctx.work / "splats.ply", writable)
        write_splat_glb(ctx.work / "splats.glb", writable)
        files.update(splats_ply="splats.ply", splats_glb="splats.glb")
    sizes = {name: (ctx.work / f).stat().st_size for name, f in files.items()}

    frame_name = "input (the poses' COLMAP frame)" if s.frame == "input" else "normalized (z up, foreground in [-1, 1]^3)"
    place = scene.get("georeference") if s.frame == "input" else None  # the poses in metres of a place (their GPS)
    if place:
        frame_name = "input (the poses' frame: {}, {:.6f}, {:.6f}, {:.1f} m)".format(place["axes"], *place["origin"])
    record = {
        "frame": s.frame,
        "frame_description": frame_name,
        **({"georeference": place} if place else {}),
        "output_from_normalized": to_output.tolist(),
        "scene_type": scene.get("type"),
        "fit_frame": "ndc" if frame.ndc is not None else "inner cube of a contracted grid"
        if frame.contraction is not None else "normalized",
        "files": files,
        "file_bytes": sizes,
        "mesh": {"vertices": len(mesh.vertices), "faces": len(mesh.faces), "bounds": _bounds(mesh.vertices)},
        "points": {"count": len(points), "bounds": _bounds(points)},
        "splats": splat_record if splats is not None else None,
        "lowered_to_fit_memory": lowered,
        "memory_as_set": need_as_set if lowered else None,
        "axes": "PLY: the frame's own; OBJ and GLB y-up, (x, z, -y) of the frame: z-up importers such as Blender's "
                "restore the frame's coordinates",
        **decisions,
    }
    write_json(ctx.work / EXPORT_JSON, record)
    lo, hi = record["mesh"]["bounds"]["min"], record["mesh"]["bounds"]["max"]
    line = (f"mesh {_count(len(mesh.faces))} faces ({_size(sizes['ply'])} PLY), {_count(len(points))} points "
            f"({_size(sizes.get('points', 0))}) in the {s.frame} frame"
            + (" (metres east, north and up of {:.6f}, {:.6f}, {:.1f} m)".format(*place["origin"]) if place else "")
            + ", bounds "
            f"[{', '.join(f'{v:.3g}' for v in lo)}] to [{', '.join(f'{v:.3g}' for v in hi)}], "
            f"level {decisions['level']:.3g}{' (auto)' if s.level == 'auto' else ''}, resolution {decisions['resolution']}"
            + (f", texture {'x'.join(map(str, decisions['texture']['size']))}" if s.texture else ", vertex colours")
            + f"; cut away: {decisions['object_only']['cut']}"
            + (_splat_line(splat_record, sizes) if splats is not None else "")
            + (f"; to fit in memory {lowered_words(lowered)}" if lowered else ""))
    return {"line": line, "frame": s.frame, "faces": len(mesh.faces), "vertices": len(mesh.vertices),
            "points": len(points), "level": decisions["level"], "resolution": decisions["resolution"],
            "cut_away": decisions["object_only"]["cut"], "splats": splats.count if splats is not None else 0,
            **(_splat_summary(splat_record, sizes) if splats is not None else {"splat_psnr": None}),
            MEMORY_AS_SET: need_as_set if lowered else None}


def _splat_summary(record: dict, sizes: dict) -> dict:
    """The splats' scores, sizes and time for the run's summary: evaluate runs before export and scores the field
    alone, so the splats' held-out scores are the export stage's to report (export.json `splats` holds them all)."""
    held = record["held_out"]
    return {"splat_psnr": held.get("psnr"), "splat_psnr_vs_field": held.get("psnr_vs_field"),
            "splat_field_psnr": held.get("field_psnr"), "splat_ply_bytes": sizes["splats_ply"],
            "splat_glb_bytes": sizes["splats_glb"], "splat_seconds": record["seconds"],
            "splat_background": record["background"]}


def _splat_background(fitted: SceneModel, model: SceneModel, record: dict) -> str:
    """What stands for the scene behind the foreground grid among the splats, in words (export.json, summary line)."""
    colour = list(model.background_color)
    if model.background is not None:
        return (f"{record['background_splats']} splats on the background model's spheres (one per texel not clear), "
                f"composited on its far colour {colour}")
    if fitted.fit_frame.contraction is not None and fitted.grid.contracted:
        return (f"left out: the contracted grid's outer shell beyond the inner cube; the splats are composited on the "
                f"colour {colour}")
    return f"none: composited on the background colour {colour}"


def _splat_line(record: dict, sizes: dict) -> str:
    held = record["held_out"]
    scores = (f", held-out PSNR {held['psnr']:.2f} dB (the field's {held['field_psnr']:.2f} dB; "
              f"{held['psnr_vs_field']:.2f} dB against its render)" if held["views"] else "")
    left_out = "; the scene behind them left out" if record["background"].startswith("left out") else ""
    return (f"; {_count(record['count'])} splats ({_size(sizes['splats_ply'])} PLY, {_size(sizes['splats_glb'])} GLB, "
            f"{record['seconds']:.0f} s){scores}{left_out}")
