"""The fitted scene: the voxel grid plus what decides how a world ray reaches it and what lies behind it.

A SceneModel ties together
- `grid`: the SparseGrid, in the *fit frame*: the normalised world (object and unbounded scenes) or
  NDC (forward scenes);
- `fit_frame`: the FitFrame that maps world rays and points into the grid's frame and back;
- `background`: the multi-sphere background model behind the grid (unbounded scenes), or None;
- `background_color`: the constant colour rays see behind the grid when there is no background model
  (white for masked object captures such as lego);
- `render_options`: the sampling the fit used (step size, early termination), the default for renders.

A new model comes from `SceneModel.create(scene, ModelOptions(...), resolution)`. Everything the model
is asked takes rays and cameras in the normalised world frame (scene.json's frame); the model maps them
into the fit frame itself. Later stages load it with `SceneModel.load(fit_dir)` and then
- render: `render_camera(c2w, intrinsics)` -> {"rgb" [h,w,3], "depth" [h,w], "opacity" [h,w]} with
  depth the world distance along the unit ray to the expected termination point (weights
  renormalised by opacity; 0 where nothing is hit), or `render_rays(o, d)` for any batch of rays;
- query the field: `grid.sample(points_fit)` -> (raw density [M], SH [M, 3K]) at fit-frame points,
  with `fit_frame` moving points between the frames; activated density is relu(raw), colour is
  relu(SH . basis(dir) + 0.5) (csrc/plenoxels_math.h).

Files in a fit folder: `grid.pt` (SparseGrid.save), `model.json` (scene type, fit frame, NDC and
background parameters, render options, the scene transforms) and `background.pt` (the background
model's tensors) when there is one.
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from plenoxels.core.background import MultiSphereBackground
from plenoxels.core.cameras import Intrinsics, rays_from_camera
from plenoxels.core.errors import UserError
from plenoxels.core.files import GRID_FILE, MODEL_FILE, write_whole
from plenoxels.core.fit_frame import CONTRACTED_BOX, Contraction, FitFrame
from plenoxels.core.grid import SparseGrid, knots_record
from plenoxels.core.memory import check_dense_level
from plenoxels.core.ndc import NDCMapping
from plenoxels.core.options import ModelOptions
from plenoxels.core.photo_colour import PhotoGains, field_image
from plenoxels.core.render import RenderOptions, RenderResult, render


MODEL_FORMAT = "voxfield-scene-model"
MODEL_VERSION = 1
# Rays per render call when rendering whole images: bounds the memory of one call.
RENDER_CHUNK = 1 << 16
# Rays with less opacity than this have no meaningful termination depth.
MIN_DEPTH_OPACITY = 1e-4
# scene.json's transforms between the normalised world and the input frame, kept with the model.
TRANSFORM_KEYS = ("world_from_input", "input_from_world", "scale")


def _uses(toggle: str, wanted: bool) -> bool:
    return wanted if toggle == "auto" else toggle == "on"


def grid_shape(extent: np.ndarray, resolution: int) -> tuple[int, int, int]:
    """Vertices per axis for a box of `extent` whose longest side gets `resolution` vertices, so that
    voxels are about cubic."""
    longest = float(np.max(extent))
    return tuple(max(2, int(round(resolution * float(e) / longest))) for e in extent)


class SceneModel:
    def __init__(self, grid: SparseGrid, scene_type: str, fit_frame: FitFrame | None = None,
                 background: MultiSphereBackground | None = None, background_color=(1.0, 1.0, 1.0),
                 render_options: RenderOptions | None = None, transforms: dict | None = None,
                 photo_gains: PhotoGains | None = None):
        self.grid = grid
        self.scene_type = scene_type
        self.fit_frame = fit_frame or FitFrame()
        self.background = background
        self.background_color = tuple(float(c) for c in background_color)
        self.render_options = render_options or RenderOptions()
        # world_from_input, input_from_world, scale: scene.json's, kept so exports need only the fit folder.
        self.transforms = dict(transforms or {})
        # Each photo's colour where the fit measured them (fit.photo_colour): a render of a photo's camera through its
        # gains is that photo as taken; the field itself holds the photos' common colour.
        self.photo_gains = photo_gains

    # ---- construction ---------------------------------------------------------------------------
    @classmethod
    def create(cls, scene: dict, options: ModelOptions, resolution: int, focal_px: float | None = None,
               mean_colour=None) -> "SceneModel":
        """An initial model for normalize/scene.json at `resolution` vertices along the grid's longest
        axis, every vertex allocated; NDC, the contraction and the background model follow the scene type where the
        options say auto. `focal_px`, the training photos' focal length in pixels, sizes the background's
        texture when options.background_width is 0 (without it: 128 texels). `mean_colour`, the training photos' mean
        RGB, is what a contracted grid's rays see past infinity when no photo has a mask: the least wrong colour for
        the sky a new view sees and no photo did (bench/README.md, "Real captures"); so does a bounded grid of a scene that is no object when its background model is off."""
        scene_type = scene.get("type", "object")
        ndc = NDCMapping.from_scene(scene) if _uses(options.ndc, scene_type == "forward") else None
        lo, hi = foreground_box(scene, options.box_padding)
        contraction = None
        if ndc is None and _uses(options.contract, scene_type == "unbounded" and reaches_far(scene)):
            contraction = Contraction.around_box(lo, hi)
        knots = None
        if ndc is None and contraction is None and scene_type == "unbounded":
            # A room's bounded grid holds the walls and floor near the foreground too (normalize's surroundings box),
            # in cells that grow coarser past the foreground's.
            inner = (lo, hi)
            lo, hi = foreground_box(scene, options.box_padding, "surroundings")
            knots = surroundings_knots(inner, (lo, hi), options.surroundings_cells)
        background = None
        if _uses(options.background, scene_type == "unbounded" and contraction is None):
            width = options.background_width or background_width_for(focal_px, options.background_texel_px)
            background = MultiSphereBackground.around_box(
                lo, hi, n_spheres=options.background_spheres, height=max(2, width // 2), width=width,
                far_colour=tuple(options.background_color), tv_density=options.tv_background,
                tv_colour=options.tv_background)
        if ndc is not None:
            lo, hi = ndc.grid_box()
            shape = ndc.grid_resolution(resolution)
        else:
            if contraction is not None:
                lo, hi = CONTRACTED_BOX
                knots = surroundings_knots(INNER_CUBE, CONTRACTED_BOX, options.shell_cells)
            shape = grid_shape(lattice_extent(lo, hi, knots), resolution)
        check_dense_level(shape, options.sh_degree)
        grid = SparseGrid.dense(shape, lo, hi, options.sh_degree, init_density=options.init_density,
                                contracted=contraction is not None, knots=knots)
        render_options = RenderOptions(step_size=options.step_size, stop_transmittance=options.stop_transmittance)
        nears = [f["near"] for f in scene.get("frames", []) if f.get("near")]
        far_colour = options.background_color
        if contraction is not None and nears:
            render_options.near = options.near_share * min(nears) / contraction.half_size
        # Past a world grid with nothing modelled there (a contracted grid's infinity, or a room's bounded grid with its
        # background model turned off) and no masks to say it is empty, the photos' mean colour is the least wrong:
        # white there paints a room's walls white (bench/README.md, "The scene model by trial").
        unmodelled = ndc is None and background is None and (contraction is not None or scene_type != "object")
        if unmodelled and mean_colour is not None and not any(f.get("mask_path") for f in scene.get("frames", [])):
            far_colour = [float(c) for c in mean_colour]
        return cls(grid, scene_type, FitFrame(ndc, contraction), background, far_colour, render_options,
                   {k: scene[k] for k in TRANSFORM_KEYS if k in scene})

    def resolution_for(self, resolution: int) -> tuple[int, int, int]:
        """The grid shape this model uses at `resolution` vertices along its longest axis."""
        if self.fit_frame.ndc is not None:
            return self.fit_frame.ndc.grid_resolution(resolution)
        return grid_shape(lattice_extent(self.grid.bbox_min, self.grid.bbox_max, self.grid.knots), resolution)

    def to(self, device: torch.device) -> "SceneModel":
        """Moves the grid and the background model to `device` (in place; returns self)."""
        self.grid = self.grid.to(device)
        if self.background is not None:
            self.background.to(device)
        return self

    def foreground_model(self) -> "SceneModel":
        """What exports read: this model, or a contracted grid's inner cube (where the contraction is the identity:
        the foreground, at full resolution) as a plain grid in the inner frame, with nothing behind it."""
        contraction = self.fit_frame.contraction
        if contraction is None or not self.grid.contracted:
            return self
        faces = self.grid.world_to_grid(torch.tensor(INNER_CUBE, dtype=torch.float64)).tolist()
        first = [max(0, math.floor(g + 1e-9)) for g in faces[0]]
        last = [min(r - 1, math.ceil(g - 1e-9)) for g, r in zip(faces[1], self.grid.resolution)]
        return SceneModel(self.grid.crop(tuple(first), tuple(last)), self.scene_type,
                          FitFrame(contraction=contraction.inner()), None, self.background_color, self.render_options,
                          self.transforms)

    # ---- rendering ------------------------------------------------------------------------------
    def background_rgb(self, o_world: torch.Tensor, d_world: torch.Tensor) -> torch.Tensor:
        """What each ray sees behind the grid [B, 3]: the background model's colour (differentiable
        with respect to its parameters) or the constant background colour."""
        if self.background is not None:
            return self.background(o_world.to(torch.float32), d_world.to(torch.float32))
        return torch.tensor(self.background_color, dtype=torch.float32).expand(o_world.shape[0], 3)

    def render_rays(self, o_world: torch.Tensor, d_world: torch.Tensor,
                    opts: RenderOptions | None = None) -> RenderResult:
        """Renders world rays [B, 3]; depth is the fit-frame expected depth (weights not renormalised)."""
        o, d = self.fit_frame.rays(o_world, d_world)
        with torch.no_grad():
            bg = self.background_rgb(o_world, d_world)
        return render(self.grid, o, d, bg, opts or self.render_options, self.background_past_grid_only)

    @property
    def background_past_grid_only(self) -> bool:
        """Whether what lies behind the grid shows only on rays the grid lets light past (render.light_past_grid): so
        with the background spheres, which then need not be drawn behind the rays the grid stops (most of a room's
        training rays); a flat colour shows on every ray."""
        return self.background is not None

    def world_depth(self, o_world: torch.Tensor, d_world: torch.Tensor, result: RenderResult) -> torch.Tensor:
        """World distance along each unit ray to its expected termination point (0 where nothing is hit)."""
        hit = result.opacity > MIN_DEPTH_OPACITY
        depth = torch.where(hit, result.depth / result.opacity.clamp_min(MIN_DEPTH_OPACITY), torch.zeros_like(result.depth))
        if self.fit_frame.ndc is None:
            return depth * self.fit_frame.world_distance_scale()
        o, d = self.fit_frame.rays(o_world, d_world)
        unit = d / d.norm(dim=-1, keepdim=True)
        world = self.fit_frame.ndc.world_distance(o_world, d_world, o + depth[:, None] * unit)
        return torch.where(hit, world, torch.zeros_like(world))

    def render_camera(self, c2w, intrinsics: Intrinsics, opts: RenderOptions | None = None,
                      chunk: int = RENDER_CHUNK, backdrop=None, photo: str | None = None) -> dict[str, torch.Tensor]:
        """One pinhole view (world camera-to-world, OpenGL convention) -> {"rgb" [h,w,3] in [0,1],
        "depth" [h,w] world distance (see world_depth), "opacity" [h,w]}. `backdrop`: an RGB colour to show past the
        grid in place of the model's own (a photo's own backdrop, scene.json's frame `backdrop`); a background model
        keeps its colours. `photo`: the name of the capture's photo this camera took, rendered in that photo's colour
        where the fit measured the photos' colours (photo_gains); else, and for a new view, in their common colour."""
        origins, dirs = rays_from_camera(c2w, intrinsics)
        origins, dirs = origins.reshape(-1, 3), dirs.reshape(-1, 3)
        rgb, depth, opacity = [], [], []
        for start in range(0, origins.shape[0], chunk):
            o, d = origins[start:start + chunk], dirs[start:start + chunk]
            result = self.render_rays(o, d, opts)
            # Clamped once in the photo's colour: a clipped highlight trained as a floor may render above 1.
            rgb.append(self.on_backdrop(result.rgb, result.opacity, backdrop).clamp(min=0.0))
            depth.append(self.world_depth(o, d, result))
            opacity.append(result.opacity)
        h, w = intrinsics.h, intrinsics.w
        opacity = torch.cat(opacity)
        rgb = self.as_photographed(torch.cat(rgb).reshape(h, w, 3), photo, opacity.reshape(h, w), backdrop).clamp(0, 1)
        return {"rgb": rgb, "depth": torch.cat(depth).reshape(h, w), "opacity": opacity.reshape(h, w)}

    def on_backdrop(self, rgb: torch.Tensor, opacity: torch.Tensor, backdrop=None) -> torch.Tensor:
        """Rendered colours [N, 3] with what shows past the grid put on `backdrop` (an RGB colour: a photo's own
        backdrop) in place of the model's colour, where the model has no background model; as they are otherwise."""
        if backdrop is None or self.background is not None:
            return rgb
        swap = torch.tensor(backdrop, dtype=rgb.dtype, device=rgb.device) - torch.tensor(self.background_color,
                                                                                       dtype=rgb.dtype, device=rgb.device)
        return rgb + (1.0 - opacity)[:, None] * swap

    def as_photographed(self, rgb: torch.Tensor, photo: str | None, opacity: torch.Tensor | None = None,
                        backdrop=None) -> torch.Tensor:
        """Colours [..., 3] rendered in the common colour, as capture photo `photo` was taken (its gains, or its
        capture neighbours'; photo_gains); as they are for no photo or where the fit took the photos as they are.
        Where the colour past the object came with the photos as taken (photo_gains.backdrop_as_taken: their masks', or
        each photo's own backdrop), the gains leave that part, the backdrop (`backdrop`, else the model's colour) times
        one less the render's `opacity` [...], as it is. An image [h, w, 3] takes the photo's gain lattice across its
        frame where the fit measured one (PhotoGains.field_of)."""
        if photo is None or self.photo_gains is None:
            return rgb
        field = self.photo_gains.field_of(photo) if rgb.dim() == 3 else None
        if field is not None:
            gain = field_image(field, rgb.shape[0], rgb.shape[1]).reshape(rgb.shape).to(rgb)
        else:
            gain = torch.as_tensor(self.photo_gains.of(photo), dtype=rgb.dtype, device=rgb.device)
        if not self.photo_gains.backdrop_as_taken or self.background is not None:
            return (rgb * gain).clamp(0, 1)
        colour = torch.as_tensor(backdrop if backdrop is not None else self.background_color, dtype=rgb.dtype,
                                 device=rgb.device)
        put_in = (1.0 - opacity.to(rgb.dtype))[..., None] * colour
        return ((rgb - put_in) * gain + put_in).clamp(0, 1)

    # ---- facts ----------------------------------------------------------------------------------
    def region_box(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """The world box the grid holds at its full resolution: its own box, or a contracted grid's inner cube."""
        contraction = self.fit_frame.contraction
        if contraction is None:
            return self.grid.bbox_min, self.grid.bbox_max
        centre = np.asarray(contraction.centre)
        return tuple(centre - contraction.half_size), tuple(centre + contraction.half_size)

    def memory_bytes(self) -> dict[str, int]:
        grid = self.grid.memory_bytes()
        background = self.background.memory_bytes() if self.background is not None else 0
        return {"grid": grid, "background": background, "total": grid + background}

    def describe(self) -> dict[str, Any]:
        return {"fit_frame": self.fit_frame.name,
                "resolution": list(self.grid.resolution), "occupied": self.grid.num_occupied, "sh_degree": self.grid.sh_degree,
                "background_model": self.background is not None, "memory_bytes": self.memory_bytes()}

    # ---- persistence ----------------------------------------------------------------------------
    def save(self, folder: Path, extra: dict | None = None) -> None:
        """Writes grid.pt, model.json and (with a background model) background.pt into `folder`."""
        folder = Path(folder)
        self.grid.save(folder / GRID_FILE)
        background = None
        if self.background is not None:
            state = self.background.state_dict()
            write_whole(folder / "background.pt", lambda tmp: torch.save(state, tmp))
            background = {"kind": "multi_sphere", "config": self.background.config(), "file": "background.pt"}
        record = {
            "format": MODEL_FORMAT, "version": MODEL_VERSION, "scene_type": self.scene_type,
            "fit_frame": self.fit_frame.name,
            "ndc": self.fit_frame.ndc.to_dict() if self.fit_frame.ndc is not None else None,
            "contraction": self.fit_frame.contraction.to_dict() if self.fit_frame.contraction is not None else None,
            "background": background, "background_color": list(self.background_color),
            "render_options": asdict(self.render_options),
            "grid": {"file": GRID_FILE, "resolution": list(self.grid.resolution), "bbox_min": list(self.grid.bbox_min),
                     "bbox_max": list(self.grid.bbox_max), "sh_degree": self.grid.sh_degree,
                     "occupied": self.grid.num_occupied, "knots": knots_record(self.grid.knots)},
            "photo_gains": self.photo_gains.record() if self.photo_gains is not None else None,
            **self.transforms, **(extra or {}),
        }
        (folder / MODEL_FILE).write_text(json.dumps(record, indent=2))

    @classmethod
    def load(cls, folder: Path) -> "SceneModel":
        folder = Path(folder)
        path = folder / MODEL_FILE
        if not path.is_file():
            raise UserError(f"{folder} holds no fitted model (model.json missing): run the fit stage")
        record = json.loads(path.read_text())
        if record.get("format") != MODEL_FORMAT or record.get("version") != MODEL_VERSION:
            raise UserError(f"{path} is not a voxfield scene model of version {MODEL_VERSION}: fit again")
        grid, _ = SparseGrid.load(folder / record["grid"]["file"])
        ndc = NDCMapping.from_dict(record["ndc"]) if record.get("ndc") else None
        contraction = Contraction.from_dict(record["contraction"]) if record.get("contraction") else None
        background = None
        if record.get("background"):
            background = MultiSphereBackground.from_config(record["background"]["config"])
            state = torch.load(folder / record["background"]["file"], map_location="cpu", weights_only=True)
            background.load_state_dict(state)
        transforms = {k: record[k] for k in TRANSFORM_KEYS if k in record}
        return cls(grid, record.get("scene_type", "object"), FitFrame(ndc, contraction), background,
                   record.get("background_color", (1, 1, 1)), RenderOptions(**record.get("render_options", {})),
                   transforms, PhotoGains.from_record(record.get("photo_gains")))


def reaches_far(scene: dict) -> bool:
    """Whether normalize found a share of the sparse points far beyond the foreground (its beyond_fraction, at least
    the share that makes a scene unbounded): content a bounded grid cannot hold and background spheres place only by
    direction, which a contracted grid holds in depth. (Where all of it lies near, in a room around an object, the
    bounded grid keeps twice the contracted one's resolution on the foreground and no coarse space near the cameras to
    hide floaters in; bench/README.md, "Real captures".)"""
    measured, thresholds = scene.get("measured") or {}, scene.get("thresholds") or {}
    return float(measured.get("beyond_fraction", 0.0)) >= float(thresholds.get("unbounded_min_beyond_fraction", 0.1))


# An object fit with one colour behind its grid (no background model, no masks) that reproduces its own training photos
# worse than this at the end of its coarsest resolution is missing what surrounds the object: a backdrop that is not
# that colour (a white table in some photos, a dark room in others). The threshold sits between the object fits with a
# flat backdrop and a room smeared into an object's grid ("Fit: quality against cost" and "Object captures" in
# bench/README.md).
BACKDROP_MIN_TRAIN_PSNR = 20.0
# A coarsest resolution of fewer steps has not converged far enough for its PSNR to say anything of the backdrop.
BACKDROP_CHECK_MIN_STEPS = 100


def backdrop_check_step(model: "SceneModel", resolutions: list[int], steps: list[int]) -> int | None:
    """The step at which an object fit must reproduce its photos to BACKDROP_MIN_TRAIN_PSNR (the end of its first,
    coarsest resolution, its early-pruned rest included); None where something other than one colour lies behind
    the grid (a background model, NDC, a contracted grid), or where that resolution has too few steps to tell."""
    if model.background is not None or model.fit_frame.ndc is not None or model.fit_frame.contraction is not None:
        return None
    leading = next((level for level, r in enumerate(resolutions) if r != resolutions[0]), len(resolutions))
    return sum(steps[:leading]) if sum(steps[:leading]) >= BACKDROP_CHECK_MIN_STEPS else None


# The contracted frame's inner cube: the foreground box, where the contraction is the identity.
INNER_CUBE = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))

# Knots closer than this share of the surroundings' size to its faces would make cells thinner than the rest: none.
MIN_SURROUNDINGS_SHARE = 0.02


def surroundings_knots(inner, outer, coarsening: float):
    """Knots (grid.py) for a grid over the box `outer` whose cells are `coarsening` times coarser outside the box
    `inner` than in it: per axis, where the inner box lies inside, its faces with the share of the lattice below each
    (each stretch of the axis takes vertices in proportion to its length over its cell size)."""
    if coarsening <= 1.0:
        return None
    knots = []
    for a in range(3):
        lo, hi = float(outer[0][a]), float(outer[1][a])
        cuts = [x for x in (float(inner[0][a]), float(inner[1][a])) if lo + MIN_SURROUNDINGS_SHARE * (hi - lo) < x <
                hi - MIN_SURROUNDINGS_SHARE * (hi - lo)]
        xs = [lo] + cuts + [hi]
        fine_lo, fine_hi = max(lo, float(inner[0][a])), min(hi, float(inner[1][a]))
        cells = [(x1 - x0) / (1.0 if x0 >= fine_lo - 1e-12 and x1 <= fine_hi + 1e-12 else coarsening)
                 for x0, x1 in zip(xs, xs[1:])]
        below = np.cumsum(cells)[:-1] / sum(cells)
        knots.append(tuple(zip(cuts, below.tolist())))
    return tuple(knots) if any(knots) else None


def lattice_extent(lo, hi, knots) -> np.ndarray:
    """The box's size per axis in cells of the finest size: its size without knots; with them, each stretch between
    knots counted at its share of the lattice."""
    extent = np.subtract(hi, lo).astype(np.float64)
    for a, axis in enumerate(knots or ()):
        if axis:
            xs = [lo[a]] + [x for x, _ in axis] + [hi[a]]
            fs = [0.0] + [f for _, f in axis] + [1.0]
            extent[a] = min((x1 - x0) / (f1 - f0) for x0, x1, f0, f1 in zip(xs, xs[1:], fs, fs[1:]))
    return extent


def background_width_for(focal_px: float | None, texel_px: float) -> int:
    """Texels around the background's equator so that one spans about `texel_px` pixels of photos with this focal
    length: a pixel subtends 1/focal radians, so 2 pi focal / texel_px texels (a multiple of 8, in [64, 2048])."""
    if not focal_px or focal_px <= 0:
        return 128
    width = 2.0 * math.pi * focal_px / max(texel_px, 1e-6)
    return int(min(max(round(width / 8) * 8, 64), 2048))


def foreground_box(scene: dict, padding: float, key: str = "foreground") -> tuple[tuple[float, ...], tuple[float, ...]]:
    """scene.json's foreground box (or another of its boxes: `key`, falling back to the foreground's where the scene
    has none) grown by `padding` of its size on each side ([-1, 1]^3 if absent)."""
    fg = scene.get(key) or scene.get("foreground") or {}
    lo = np.asarray(fg.get("min", (-1.0, -1.0, -1.0)), dtype=np.float64)
    hi = np.asarray(fg.get("max", (1.0, 1.0, 1.0)), dtype=np.float64)
    if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(lo)) or not np.all(np.isfinite(hi)) \
            or not np.all(hi > lo):
        raise UserError("scene.json's foreground box is missing or empty; re-run the normalize stage")
    grow = (hi - lo) * padding
    return tuple((lo - grow).tolist()), tuple((hi + grow).tolist())


def psnr(mse: float) -> float:
    """PSNR in dB of colours in [0, 1] from their mean squared error."""
    return -10.0 * math.log10(max(mse, 1e-12))
