"""How much memory the export will hold, and the settings it runs with where the memory this process may use is
short: its largest phase's setting halved down to a floor until the need fits, or one line that stops it before it
writes anything (stages/export.py runs the export; this plans it)."""
from __future__ import annotations

import math
from dataclasses import replace

from plenoxels.core import memory
from plenoxels.core.cameras import Intrinsics
from plenoxels.splats.field_splats import training_views
from stages.common.text import format_count
from stages.settings.export import Settings

# The training views' opaque rays kept for the level, the free-space test and the points: a seeded share of each
# view's. 64 bytes a ray: a hundred 400x400 views give about 5 M, 320 MB, and twice that while they are joined.
MAX_TERMINATIONS = 1_000_000
# What the export holds at its peak past what is loaded, per unit of each phase's work, measured on lego `default`
# (bench/README.md, "Faults"), rounded up: the training views rendered (depth, opacity and colour per pixel, and the
# renderer's own) and their opaque rays, held through the mesh (marching cubes, sealing and cleaning, per cell of the
# lattice) and the points. The texture (rasterising and baking in bands and chunks, per texel of an atlas up to
# ATLAS_SIDE times texture_size on a side: xatlas grows it to fit the charts) and the splats (attributes, Adam's
# moments and copies, the distillation's target views and the scoring renders' pairs) come after, counted on top of
# the mesh phase's peak: above what lego holds now that they start from well below it (bench/README.md, "Faults"), and
# sound where a small grid's mesh phase leaves a large atlas little to stand on.
VIEW_PIXEL_BYTES = 20
TERMINATION_BYTES = 2 * 64
LATTICE_CELL_BYTES = 100
ATLAS_SIDE = 1.5
TEXEL_BYTES = 50
SPLAT_BYTES = 1200
TARGET_PIXEL_BYTES = 16
SCORING_BYTES = 200 << 20


# What shrinks each phase, for the line that stops an export that would not fit.
SHRINK = {"mesh": "lower export.point_scale (the training views rendered beside the fitted grid's own lattice)",
          "texture": "lower export.texture_size, or export.texture=false for vertex colours",
          "splats": "lower export.max_splats, or export.splats=false for none"}
# What the export lowers by itself where it would not fit in memory as set: each phase's setting, halved down to no
# less than its floor. A coarser texture or fewer splats or points is a lesser export; an error is none.
SHRINKS_ITSELF = {"mesh": ("point_scale", 0.125), "texture": ("texture_size", 512), "splats": ("max_splats", 50_000)}


def memory_need(s: Settings, grid, frames: list[dict]) -> tuple[int, str, str, str]:
    """Bytes the export will hold at its peak (resident now, and the largest phase's share: the constants above), what
    they are for, in words, what shrinks them, and that phase."""
    def pixels(scale: float, limit: int) -> int:
        chosen = training_views(frames, limit)
        return sum(Intrinsics.from_frame(f).scaled(scale).w * Intrinsics.from_frame(f).scaled(scale).h for f in chosen)
    view_pixels = pixels(s.point_scale, s.point_views)
    native = max(grid.resolution) - 1
    cells = math.prod(grid.resolution) * (1.0 if s.resolution == "auto" else max(int(s.resolution) / native, 1.0) ** 3)
    texels = (ATLAS_SIDE * s.texture_size) ** 2 if s.texture else 0
    splats = min(s.max_splats, grid.num_occupied) if s.splats else 0
    views = view_pixels * VIEW_PIXEL_BYTES + min(view_pixels, MAX_TERMINATIONS) * TERMINATION_BYTES
    mesh = views + cells * LATTICE_CELL_BYTES
    phases = {"mesh": mesh, "texture": mesh + texels * TEXEL_BYTES,
              "splats": mesh + splats * SPLAT_BYTES + pixels(s.splat_scale, s.splat_views) * TARGET_PIXEL_BYTES
              + SCORING_BYTES if splats else 0}
    largest = max(phases, key=phases.get)
    need = memory.resident_memory() + phases[largest]
    of_splats = f" of up to {format_count(splats)}" if largest == "splats" else ""
    what = (f"the export of a {'x'.join(map(str, grid.resolution))} grid ({format_count(view_pixels)} training-view "
            f"pixels; at its largest, the {largest}{of_splats})")
    return int(need), what, SHRINK[largest], largest


def within_memory(s: Settings, grid, frames: list[dict],
                  limit: memory.MemoryLimit | None = None) -> tuple[Settings, dict, int]:
    """The settings the export runs with: as set where it fits in what this process may use; else with its largest
    phase's setting halved (SHRINKS_ITSELF) until it fits, and what was lowered ({setting: [as set, taken]}); and the
    bytes the settings as set need. Where not even the floors fit, it stops with one line on the settings as set,
    before anything is written."""
    limit = memory.memory_limit() if limit is None else limit
    as_set = memory_need(s, grid, frames)
    taken, need = s, as_set
    while need[0] > limit.bytes:
        # The largest phase's own setting; at its floor, the training views', which every phase carries.
        for name, floor in (SHRINKS_ITSELF[need[3]], SHRINKS_ITSELF["mesh"]):
            smaller = type(getattr(taken, name))(getattr(taken, name) / 2)
            if smaller >= floor:
                taken = replace(taken, **{name: smaller})
                break
        else:
            memory.check_fits(*as_set[:3], limit)
            break
        need = memory_need(taken, grid, frames)
    return taken, {name: [getattr(s, name), getattr(taken, name)] for name, _ in SHRINKS_ITSELF.values()
                   if getattr(taken, name) != getattr(s, name)}, as_set[0]


def lowered_words(lowered: dict) -> str:
    """What was lowered, for the export's summary and warning."""
    return ", ".join(f"export.{name} {was:g} -> {now:g}" for name, (was, now) in lowered.items())
