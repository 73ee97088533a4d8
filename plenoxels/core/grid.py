"""The sparse voxel grid: a dense index volume pointing into a compact table of occupied vertices.

Values live at grid vertices. A fit-frame point p maps to grid coordinates
g = (p - bbox_min) * (R - 1) / (bbox_max - bbox_min) per axis, so vertex (i, j, k) sits at integer
coordinates in [0, R-1]; a point is interpolated trilinearly from the 8 vertices of its cell, and an
unallocated vertex counts as all zeros. A grid may bend that map at `knots`: per axis, fit-frame positions inside the
box with the share of the lattice below each, so that its cells are fine across a foreground and grow coarser out to
its surroundings, one lattice throughout (csrc/plenoxels_math.h, Lattice); on a contracted grid the knots lie in the
contracted frame, where the inner cube's faces part the foreground from the shell around it. Shares, not vertex indices,
so a grid keeps its knots at every resolution.

Parameters are stored packed, one padded row per vertex (`data` [N, S]: raw density, then the SH
coefficients of R, G and B), so the kernels read a whole vertex in one or two cache lines; the row
stride is defined once, in csrc/plenoxels_math.h. `density` and `sh` are views into that table; write
through them (in place), never rebind them. Every operation runs the native core on the device of
the grid's tensors.
"""
from __future__ import annotations

from pathlib import Path

import torch

from plenoxels.core import native
from plenoxels.core.errors import UserError
from plenoxels.core.files import write_whole

FORMAT = "voxfield-plenoxels-grid"
FORMAT_VERSION = 1
OCCUPANCY_BLOCK = 4  # cells per side of the coarse blocks used to skip empty space


def sh_count(sh_degree: int) -> int:
    """SH coefficients per colour channel."""
    return (sh_degree + 1) ** 2


def row_stride(sh_degree: int) -> int:
    """Floats per packed row: 1 + 3K rounded up to whole 16-float (64-byte) vectors (4 when it fits in 4)."""
    return native.row_stride(sh_degree)


def _check_box(bbox_min, bbox_max) -> tuple[tuple[float, ...], tuple[float, ...]]:
    lo, hi = tuple(float(v) for v in bbox_min), tuple(float(v) for v in bbox_max)
    if len(lo) != 3 or len(hi) != 3 or not all(h > l for l, h in zip(lo, hi)):
        raise UserError(f"grid box must satisfy bbox_min < bbox_max on every axis, got {lo} and {hi}")
    return lo, hi


Knots = tuple[tuple[tuple[float, float], ...], ...]  # per axis, (fit-frame position, share of the lattice below it)


def _check_knots(knots, lo, hi) -> Knots:
    if knots is None:
        return ((), (), ())
    checked = tuple(tuple((float(x), float(f)) for x, f in axis) for axis in knots)
    for a, axis in enumerate(checked):
        xs = [lo[a]] + [x for x, _ in axis] + [hi[a]]
        fs = [0.0] + [f for _, f in axis] + [1.0]
        if len(checked) != 3 or len(axis) > 2 or any(b <= a_ for a_, b in zip(xs, xs[1:])) or \
                any(b <= a_ for a_, b in zip(fs, fs[1:])):
            raise UserError(f"grid knots must be at most two per axis, inside the box and increasing, got {knots}")
    return checked


def _check_resolution(resolution) -> tuple[int, int, int]:
    res = tuple(int(r) for r in resolution)
    if len(res) != 3 or min(res) < 2:
        raise UserError(f"grid resolution must be three integers >= 2, got {tuple(resolution)}")
    return res


HUGE_PAGE_MIN_BYTES = 8 << 20


def large_table(t: torch.Tensor) -> torch.Tensor:
    """A contiguous CPU tensor of 8 MiB or more, moved into memory advised for huge pages: the
    kernels read and write its rows at random, and 4 KiB pages would miss the TLB on almost every
    access. Smaller tensors and other devices: returned as they are (contiguous)."""
    t = t.contiguous()
    if t.device.type != "cpu" or t.numel() * t.element_size() < HUGE_PAGE_MIN_BYTES:
        return t
    return large_empty(t.shape, t.dtype).copy_(t)


def large_empty(shape, dtype: torch.dtype, device="cpu") -> torch.Tensor:
    """An uninitialised table; on the CPU, advised for huge pages where it is large (see large_table) before any page
    of it is touched."""
    fresh = torch.empty(shape, dtype=dtype, device=device)
    if fresh.device.type == "cpu" and fresh.numel() * fresh.element_size() >= HUGE_PAGE_MIN_BYTES:
        native.ops.advise_huge_pages(fresh)
    return fresh


def large_rows(table: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """table[rows] gathered straight into a table laid out as large_table lays it out, with no copy between."""
    fresh = large_empty((rows.shape[0], *table.shape[1:]), table.dtype, table.device)
    return torch.index_select(table, 0, rows.to(device=table.device, dtype=torch.long), out=fresh)


def large_zeros(like: torch.Tensor) -> torch.Tensor:
    """zeros_like for tables the kernels access at random (see large_table), without a second copy."""
    if like.device.type != "cpu" or like.numel() * like.element_size() < HUGE_PAGE_MIN_BYTES:
        return torch.zeros_like(like)
    return large_empty(like.shape, like.dtype).zero_()


def dilated(volume: torch.Tensor, radius: int) -> torch.Tensor:
    """A boolean volume grown by `radius` voxels in every direction (a cube of 2 * radius + 1 around each true voxel),
    axis by axis, in the volume's own bytes rather than as floats through a max pool."""
    grown = volume.clone()
    for axis in range(3):
        src, n = grown.clone(), grown.shape[axis]
        for shift in range(1, min(radius, n - 1) + 1):
            grown.narrow(axis, shift, n - shift).logical_or_(src.narrow(axis, 0, n - shift))
            grown.narrow(axis, 0, n - shift).logical_or_(src.narrow(axis, shift, n - shift))
    return grown


class SparseGrid:
    def __init__(self, links: torch.Tensor, data: torch.Tensor, bbox_min, bbox_max, sh_degree: int,
                 contracted: bool = False, knots: Knots | None = None, owned: bool = False):
        """`owned`: `links` and `data` were made for this grid alone, laid out as large_table lays them out (int32
        and float32, contiguous): kept as they are, not copied."""
        if not 0 <= int(sh_degree) <= 3:
            raise UserError(f"sh_degree must be 0, 1, 2 or 3, got {sh_degree}")
        self.sh_degree = int(sh_degree)
        self.bbox_min, self.bbox_max = _check_box(bbox_min, bbox_max)
        # The box lies in contracted space (csrc/plenoxels_math.h, contract_point): rays come in the frame before the
        # contraction and bend through the grid.
        self.contracted = bool(contracted)
        self.knots = _check_knots(knots, self.bbox_min, self.bbox_max)
        _check_resolution(links.shape)
        stride = row_stride(self.sh_degree)
        if data.dim() != 2 or data.shape[1] != stride:
            raise ValueError(f"packed data must be [N, {stride}] for SH degree {sh_degree}, got {tuple(data.shape)}")
        self._links = links if owned else large_table(links.to(torch.int32))
        self.data = data if owned else large_table(data.to(torch.float32))
        self._cells = None
        self._live = None  # (counts, blocks, (data pointer, data version) they were computed for)
        self._coords = None

    # ---- construction -------------------------------------------------------------------------
    @classmethod
    def from_values(cls, links, density, sh, bbox_min, bbox_max, sh_degree, contracted: bool = False,
                    knots: Knots | None = None) -> "SparseGrid":
        """A grid from unpacked values: density [N], sh [N, 3K]."""
        k3 = 3 * sh_count(sh_degree)
        if sh.shape != (density.shape[0], k3):
            raise ValueError(f"sh must be [N, {k3}] for SH degree {sh_degree}, got {tuple(sh.shape)}")
        data = torch.zeros(density.shape[0], row_stride(sh_degree), dtype=torch.float32)
        data[:, 0] = density
        data[:, 1 : 1 + k3] = sh
        return cls(links, data, bbox_min, bbox_max, sh_degree, contracted, knots)

    @classmethod
    def dense(cls, resolution, bbox_min, bbox_max, sh_degree: int, init_density=0.1, init_sh=0.0,
              contracted: bool = False, knots: Knots | None = None) -> "SparseGrid":
        res = _check_resolution(resolution)
        n = res[0] * res[1] * res[2]
        links = torch.arange(n, dtype=torch.int32).reshape(res)
        data = torch.zeros(n, row_stride(int(sh_degree)), dtype=torch.float32)
        data[:, 0] = init_density
        data[:, 1 : 1 + 3 * sh_count(int(sh_degree))] = init_sh
        return cls(links, data, bbox_min, bbox_max, sh_degree, contracted, knots)

    # ---- views and facts ----------------------------------------------------------------------
    @property
    def links(self) -> torch.Tensor:
        return self._links

    @property
    def density(self) -> torch.Tensor:
        return self.data[:, 0]

    @property
    def sh(self) -> torch.Tensor:
        return self.data[:, 1 : 1 + 3 * sh_count(self.sh_degree)]

    @property
    def resolution(self) -> tuple[int, int, int]:
        return tuple(self._links.shape)

    @property
    def num_occupied(self) -> int:
        return self.data.shape[0]

    @property
    def warped(self) -> bool:
        """Whether the cells differ in size along some axis (the grid has knots)."""
        return any(self.knots)

    def axis_knots(self, axis: int) -> tuple[list[float], list[float]]:
        """Axis `axis`'s knots, box ends included: fit-frame positions and their grid coordinates."""
        r = self.resolution[axis] - 1
        xs = [self.bbox_min[axis]] + [x for x, _ in self.knots[axis]] + [self.bbox_max[axis]]
        gs = [0.0] + [f * r for _, f in self.knots[axis]] + [float(r)]
        return xs, gs

    def axis_slopes(self, axis: int) -> list[float]:
        """Grid units per fit-frame unit between each two knots of axis `axis` (one value without knots)."""
        xs, gs = self.axis_knots(axis)
        return [(g1 - g0) / (x1 - x0) for x0, x1, g0, g1 in zip(xs, xs[1:], gs, gs[1:])]

    def coarsening(self) -> float:
        """How many times the coarsest cells' side is the finest's, along the axis where that is most (1: one size)."""
        return max(max(slopes) / min(slopes) for slopes in map(self.axis_slopes, range(3)))

    def lattice(self) -> list[float]:
        """The map to grid coordinates as the kernels take it: per axis [k, k positions, k grid coordinates]."""
        flat = []
        for a in range(3):
            xs, gs = self.axis_knots(a)
            flat += [float(len(xs))] + xs + gs
        return flat

    @property
    def scale(self) -> tuple[float, float, float]:
        """Grid units per fit-frame unit, per axis (where the cells are finest on a warped grid)."""
        if not self.warped:
            return tuple((r - 1) / (hi - lo) for r, lo, hi in zip(self.resolution, self.bbox_min, self.bbox_max))
        return tuple(max(self.axis_slopes(a)) for a in range(3))

    def memory_bytes(self) -> int:
        """Parameters plus the index volume (and the occupancy structure once built)."""
        total = self.data.numel() * 4 + self._links.numel() * 4
        if self._cells is not None:
            total += self._cells.numel()
        if self._live is not None:
            total += self._live[0].numel() * 5
        if self._coords is not None:
            total += self._coords.numel() * 4
        return total

    def world_to_grid(self, points: torch.Tensor) -> torch.Tensor:
        """Fit-frame points [..., 3] -> grid coordinates (linear past the box, as the kernels map them)."""
        if not self.warped:
            lo = torch.tensor(self.bbox_min, dtype=points.dtype, device=points.device)
            scale = torch.tensor(self.scale, dtype=points.dtype, device=points.device)
            return (points - lo) * scale
        return torch.stack([_piecewise(points[..., a], *self.axis_knots(a)) for a in range(3)], dim=-1)

    def grid_to_world(self, g: torch.Tensor) -> torch.Tensor:
        """Grid coordinates [..., 3] -> fit-frame points (world_to_grid's inverse)."""
        return torch.stack([_piecewise(g[..., a], *reversed(self.axis_knots(a))) for a in range(3)], dim=-1)

    # ---- cached helpers for the kernels -------------------------------------------------------
    def occupancy(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(cells, blocks) uint8 for empty-space skipping. A cell is occupied if any corner is
        allocated (built once: links never change in place). A block of OCCUPANCY_BLOCK^3 cells is
        live if any of its corner vertices has density > 0; the native optimiser step keeps the
        counts behind this current, and any other in-place change of `data` (seen through the
        tensor's version counter) makes the next call recount."""
        if self._cells is None:
            self._cells = native.ops.build_occupancy(self._links, OCCUPANCY_BLOCK)[0]
        return self._cells, self.live_blocks()[1]

    def live_blocks(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(counts int32, blocks uint8) of live vertices per occupancy block, recounted if stale."""
        if not self.live_blocks_current():
            shape = tuple(-(-(r - 1) // OCCUPANCY_BLOCK) for r in self.resolution)
            counts = torch.zeros(shape, dtype=torch.int32, device=self.data.device)
            blocks = torch.zeros(shape, dtype=torch.uint8, device=self.data.device)
            native.ops.count_live_blocks(self.data, self.coords(), OCCUPANCY_BLOCK, counts, blocks)
            self._live = (counts, blocks, (self.data.data_ptr(), self.data._version))
        return self._live[0], self._live[1]

    def live_blocks_current(self) -> bool:
        """True when live-block counts exist and match `data` (the optimiser then keeps them current)."""
        return self._live is not None and self._live[2] == (self.data.data_ptr(), self.data._version)

    def coords(self) -> torch.Tensor:
        """int32 [N, 3]: the vertex (x, y, z) of each row."""
        if self._coords is None:
            occupied = torch.nonzero(self._links.reshape(-1) >= 0).squeeze(1)
            rows = self._links.reshape(-1)[occupied].long()
            ry, rz = self.resolution[1], self.resolution[2]
            xyz = torch.stack([occupied // (ry * rz), (occupied // rz) % ry, occupied % rz], dim=1)
            coords = torch.full((self.num_occupied, 3), -1, dtype=torch.int32, device=self._links.device)
            coords[rows] = xyz.to(torch.int32)
            self._coords = coords
        return self._coords

    # ---- queries ------------------------------------------------------------------------------
    def sample(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Trilinear raw density [M] and SH [M, 3K] at fit-frame points; outside the box -> 0."""
        points = points.to(torch.float32).reshape(-1, 3)
        g64 = self.world_to_grid(points.double())
        hi = torch.tensor(self.resolution, dtype=torch.float64, device=g64.device) - 1
        inside = ((g64 >= 0) & (g64 <= hi)).all(dim=1)
        # Rounding to float32 could move a point just outside the box onto its face: mark it outside first.
        g = torch.where(inside.unsqueeze(1), g64, torch.full_like(g64, -1.0)).to(torch.float32)
        values = native.ops.sample(self.data, self._links, g.to(self.data.device).contiguous())
        return values[:, 0], values[:, 1 : 1 + 3 * sh_count(self.sh_degree)]

    # ---- structure changes (each returns a new grid) ------------------------------------------
    def to(self, device) -> "SparseGrid":
        """The same grid with its tensors on `device`."""
        device = torch.device(device)
        native.check_device(device)
        if self.data.device == device:
            return self
        return SparseGrid(self._links.to(device), self.data.to(device), self.bbox_min, self.bbox_max, self.sh_degree,
                          self.contracted, self.knots)

    def prune(self, keep: torch.Tensor) -> tuple["SparseGrid", torch.Tensor]:
        """Keeps rows where `keep` is true; returns the new grid and, for each new row, its old row."""
        keep = keep.to(device=self._links.device, dtype=torch.bool).reshape(-1)
        if keep.shape[0] != self.num_occupied:
            raise ValueError(f"keep must have one entry per occupied vertex ({self.num_occupied}), got {keep.shape[0]}")
        old_rows = torch.nonzero(keep).squeeze(1)
        new_index = torch.full((self.num_occupied,), -1, dtype=torch.int32, device=self._links.device)
        new_index[old_rows] = torch.arange(old_rows.shape[0], dtype=torch.int32, device=self._links.device)
        flat = self._links.reshape(-1)
        occupied = flat >= 0
        links = large_empty(self._links.shape, torch.int32, self._links.device).fill_(-1)
        links.view(-1)[occupied] = new_index[flat[occupied].long()]
        grid = SparseGrid(links, large_rows(self.data, old_rows),
                          self.bbox_min, self.bbox_max, self.sh_degree, self.contracted, self.knots, owned=True)
        return grid, old_rows

    def crop(self, first: tuple[int, int, int], last: tuple[int, int, int]) -> "SparseGrid":
        """The vertices from index `first` to `last` (inclusive) per axis as a grid of their own, over the box
        those vertices span (not contracted: the caller says which frame that box is in)."""
        lo_i, hi_i = [int(v) for v in first], [int(v) for v in last]
        if not all(0 <= a < b < r for a, b, r in zip(lo_i, hi_i, self.resolution)):
            raise ValueError(f"crop {lo_i}..{hi_i} is not a box of at least 2 vertices inside {self.resolution}")
        links = self._links[lo_i[0]:hi_i[0] + 1, lo_i[1]:hi_i[1] + 1, lo_i[2]:hi_i[2] + 1]
        old_rows = links[links >= 0].long()
        new_links = torch.full_like(links, -1)
        new_links[links >= 0] = torch.arange(old_rows.shape[0], dtype=torch.int32, device=links.device)
        if not self.warped:
            step = [(hi - lo) / (r - 1) for lo, hi, r in zip(self.bbox_min, self.bbox_max, self.resolution)]
            box_min = [lo + i * d for lo, i, d in zip(self.bbox_min, lo_i, step)]
            box_max = [lo + i * d for lo, i, d in zip(self.bbox_min, hi_i, step)]
            return SparseGrid(new_links.contiguous(), self.data[old_rows], box_min, box_max, self.sh_degree)
        corners = self.grid_to_world(torch.tensor([lo_i, hi_i], dtype=torch.float64))
        knots = []
        for a in range(3):  # the knots strictly inside the crop, as shares of the crop's own lattice
            xs, gs = self.axis_knots(a)
            span = hi_i[a] - lo_i[a]
            knots.append(tuple((x, (g - lo_i[a]) / span) for x, g in zip(xs[1:-1], gs[1:-1]) if lo_i[a] < g < hi_i[a]))
        return SparseGrid(new_links.contiguous(), self.data[old_rows], corners[0].tolist(), corners[1].tolist(),
                          self.sh_degree, knots=tuple(knots))

    def dilate(self, keep: torch.Tensor, radius: int = 1) -> torch.Tensor:
        """Grows a per-row keep mask to every allocated vertex within `radius` voxels (Chebyshev)."""
        keep = keep.to(device=self._links.device, dtype=torch.bool).reshape(-1)
        if radius <= 0:
            return keep.clone()
        occupied = self._links >= 0
        rows = self._links[occupied].long()
        volume = torch.zeros(self.resolution, dtype=torch.bool, device=self._links.device)
        volume[occupied] = keep[rows]
        grown = torch.empty_like(keep)
        grown[rows] = dilated(volume, radius)[occupied]
        return grown

    def upsample(self, resolution, chunk_points: int = 1 << 19) -> tuple["SparseGrid", torch.Tensor]:
        """Trilinear resample to a new resolution over the same box.

        A new vertex is allocated where it lies in an old cell with an allocated corner, and then
        the allocation grows by one new voxel in every direction (so the surface can move). Values
        are the old grid's trilinear interpolation there. Returns the new grid and, for each new row,
        the old row of the nearest old vertex (-1 where that vertex is empty): the optimiser copies
        its state from there.
        """
        res = _check_resolution(resolution)
        if self.data.device.type != "cpu":  # CUDA hook: resampled on the CPU, returned on the grid's device
            grid, old_rows = self.to("cpu").upsample(res, chunk_points)
            return grid.to(self.data.device), old_rows.to(self.data.device)
        old = torch.tensor(self.resolution, dtype=torch.float64)
        ratio = (old - 1) / (torch.tensor(res, dtype=torch.float64) - 1)
        alive = self._links >= 0
        ry, rz = res[1], res[2]
        slab = max(1, chunk_points // (ry * rz))
        grid_x = [torch.arange(n, dtype=torch.float64) * ratio[a] for a, n in enumerate(res)]
        cells = [torch.minimum(g.floor().long(), old.long()[a] - 2).clamp_min(0) for a, g in enumerate(grid_x)]
        allocated = torch.zeros(res, dtype=torch.bool)
        for x0 in range(0, res[0], slab):
            cx = cells[0][x0 : x0 + slab]
            for corner in range(8):
                dx, dy, dz = (corner >> 2) & 1, (corner >> 1) & 1, corner & 1
                allocated[x0 : x0 + slab] |= alive[cx + dx][:, cells[1] + dy][:, :, cells[2] + dz]
        grown = dilated(allocated, 1)
        vertices = torch.nonzero(grown)
        links = large_empty(res, torch.int32).fill_(-1)
        links[grown] = torch.arange(vertices.shape[0], dtype=torch.int32)
        data = large_empty((vertices.shape[0], row_stride(self.sh_degree)), torch.float32)
        old_rows = torch.empty(vertices.shape[0], dtype=torch.int64)
        for start in range(0, vertices.shape[0], chunk_points):  # each chunk's values straight into the new table
            g = vertices[start : start + chunk_points].double() * ratio
            clamped = torch.minimum(g.clamp_min(0), old - 1)  # the last new vertex lands on the old box's face
            rows = slice(start, start + g.shape[0])
            data[rows] = native.ops.sample(self.data, self._links, clamped.to(torch.float32).contiguous())
            near = torch.minimum(g.round().long(), old.long() - 1)
            old_rows[rows] = self._links[near[:, 0], near[:, 1], near[:, 2]]
        return SparseGrid(links, data, self.bbox_min, self.bbox_max, self.sh_degree, self.contracted,
                          self.knots, owned=True), old_rows

    # ---- persistence --------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """The grid as a fit checkpoint holds it (its tensors as they are); from_state_dict reads it back."""
        return {"links": self.links, "data": self.data, "bbox_min": self.bbox_min, "bbox_max": self.bbox_max,
                "sh_degree": self.sh_degree, "contracted": self.contracted, "knots": knots_record(self.knots)}

    @classmethod
    def from_state_dict(cls, state: dict) -> "SparseGrid":
        return cls(state["links"], state["data"], state["bbox_min"], state["bbox_max"], state["sh_degree"],
                   bool(state.get("contracted", False)), state.get("knots"))

    def save(self, path, extra: dict | None = None) -> None:
        payload = {
            "format": FORMAT,
            "version": FORMAT_VERSION,
            "links": self._links,
            "density": self.density.contiguous(),
            "sh": self.sh.contiguous(),
            "bbox_min": list(self.bbox_min),
            "bbox_max": list(self.bbox_max),
            "sh_degree": self.sh_degree,
            "contracted": self.contracted,
            "knots": knots_record(self.knots),
            "extra": dict(extra or {}),
        }
        write_whole(path, lambda tmp: torch.save(payload, tmp))

    @classmethod
    def load(cls, path) -> tuple["SparseGrid", dict]:
        path = Path(path)
        if not path.is_file():
            raise UserError(f"grid file {path} does not exist: run the fit stage first")
        try:
            payload = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # a truncated or foreign file
            raise UserError(f"{path} is not a readable grid file ({exc.__class__.__name__}): fit again") from exc
        if not isinstance(payload, dict) or payload.get("format") != FORMAT:
            raise UserError(f"{path} is not a voxfield Plenoxels grid: fit again")
        if payload.get("version") != FORMAT_VERSION:
            raise UserError(f"{path} has grid format version {payload.get('version')}, expected {FORMAT_VERSION}: fit again")
        grid = cls.from_values(payload["links"], payload["density"], payload["sh"], payload["bbox_min"],
                               payload["bbox_max"], payload["sh_degree"], bool(payload.get("contracted", False)),
                               payload.get("knots"))
        return grid, payload["extra"]


def knots_record(knots: Knots) -> list:
    """Knots as plain lists (grid files, checkpoints, model.json)."""
    return [[[x, f] for x, f in axis] for axis in knots]


def _piecewise(v: torch.Tensor, xs: list[float], ys: list[float]) -> torch.Tensor:
    """The piecewise-linear map through (xs[j], ys[j]) at v, linear past the ends; the piece is chosen as
    csrc/plenoxels_math.h's lattice_piece chooses it, and computed in its order of operations."""
    piece = torch.zeros(v.shape, dtype=torch.long, device=v.device)
    for x in xs[1:-1]:
        piece += (v >= x).long()
    x0 = torch.tensor(xs[:-1], dtype=v.dtype, device=v.device)[piece]
    y0 = torch.tensor(ys[:-1], dtype=v.dtype, device=v.device)[piece]
    slope = torch.tensor([(y1 - ya) / (x1 - xa) for xa, x1, ya, y1 in zip(xs, xs[1:], ys, ys[1:])],
                         dtype=torch.float64, device=v.device)[piece].to(v.dtype)
    return y0 + (v - x0) * slope
