// Per-sample math of the Plenoxels renderer, shared by the CPU (C++/OpenMP) and CUDA kernels so the
// two cannot drift. Plain inline functions on scalars and fixed-size arrays: no torch, no std::
// containers, so a .cu file can include this header unchanged.
//
// Conventions (the PyTorch twin in plenoxels/reference.py states the same math):
// - Grid coordinates: vertex (i, j, k) sits at integer coordinates; a fit-frame point p maps to
//   g = (p - bbox_min) * scale with scale = (R - 1) / (bbox_max - bbox_min) per axis.
// - A sample at grid point g interpolates the 8 vertices of cell floor(g) (clamped to the last cell).
// - Density: sigma = relu(interpolated raw density), per fit-frame unit of distance (per contracted unit on a
//   contracted grid: contract_point).
// - Colour: c = relu(sum_k sh_k * Y_k(dir) + 0.5) per channel, dir the unit fit-frame direction.
// - Compositing front to back: alpha = 1 - exp(-sigma * delta), weight = T * alpha, T *= 1 - alpha.
#pragma once

#include <math.h>
#include <stdint.h>

#ifdef __CUDACC__
#define PLX_HD __host__ __device__ __forceinline__
#else
#define PLX_HD inline __attribute__((always_inline))
#endif

namespace plx {

// Real spherical-harmonic basis constants up to degree 3.
constexpr float kSH_C0 = 0.28209479177387814f;
constexpr float kSH_C1 = 0.4886025119029199f;
constexpr float kSH_C2_0 = 1.0925484305920792f;
constexpr float kSH_C2_1 = -1.0925484305920792f;
constexpr float kSH_C2_2 = 0.31539156525252005f;
constexpr float kSH_C2_3 = -1.0925484305920792f;
constexpr float kSH_C2_4 = 0.5462742152960396f;
constexpr float kSH_C3_0 = -0.5900435899266435f;
constexpr float kSH_C3_1 = 2.890611442640554f;
constexpr float kSH_C3_2 = -0.4570457994644658f;
constexpr float kSH_C3_3 = 0.3731763325901154f;
constexpr float kSH_C3_4 = -0.4570457994644658f;
constexpr float kSH_C3_5 = 1.445305721320277f;
constexpr float kSH_C3_6 = -0.5900435899266435f;

// Added to the SH colour before the relu, so that all-zero coefficients give mid grey.
constexpr float kColourOffset = 0.5f;

// Number of SH coefficients per colour channel for a degree.
PLX_HD constexpr int sh_count(int degree) { return (degree + 1) * (degree + 1); }

// Floats per packed parameter row of `columns` values (raw density, then 3K SH coefficients):
// rounded up to whole 16-float (64-byte) vectors, or 4 floats for a row that fits in one float4, so
// a row is one or a few aligned loads on either device. The one definition of the row layout.
PLX_HD constexpr int padded_stride(int columns) { return columns <= 4 ? 4 : (columns + 15) / 16 * 16; }

// Floats per packed row for an SH degree.
PLX_HD constexpr int row_stride(int degree) { return padded_stride(1 + 3 * sh_count(degree)); }

// Evaluates the first (degree+1)^2 basis functions at unit direction (x, y, z) into `out`.
PLX_HD void sh_basis(int degree, float x, float y, float z, float* out) {
    out[0] = kSH_C0;
    if (degree < 1) return;
    out[1] = -kSH_C1 * y;
    out[2] = kSH_C1 * z;
    out[3] = -kSH_C1 * x;
    if (degree < 2) return;
    const float xx = x * x, yy = y * y, zz = z * z;
    const float xy = x * y, yz = y * z, xz = x * z;
    out[4] = kSH_C2_0 * xy;
    out[5] = kSH_C2_1 * yz;
    out[6] = kSH_C2_2 * (2.0f * zz - xx - yy);
    out[7] = kSH_C2_3 * xz;
    out[8] = kSH_C2_4 * (xx - yy);
    if (degree < 3) return;
    out[9] = kSH_C3_0 * y * (3.0f * xx - yy);
    out[10] = kSH_C3_1 * xy * z;
    out[11] = kSH_C3_2 * y * (4.0f * zz - xx - yy);
    out[12] = kSH_C3_3 * z * (2.0f * zz - 3.0f * xx - 3.0f * yy);
    out[13] = kSH_C3_4 * x * (4.0f * zz - xx - yy);
    out[14] = kSH_C3_5 * z * (xx - yy);
    out[15] = kSH_C3_6 * x * (xx - 3.0f * yy);
}

// Colour of one channel from its K interpolated coefficients; `raw` keeps the pre-relu value,
// whose sign decides whether the gradient passes.
PLX_HD float sh_colour(const float* coeffs, const float* basis, int K, float* raw) {
    float s = kColourOffset;
    for (int k = 0; k < K; ++k) s += coeffs[k] * basis[k];
    *raw = s;
    return s > 0.0f ? s : 0.0f;
}

// d colour / d raw: the relu's gradient (0 at and below 0, as torch's relu).
PLX_HD float colour_relu_grad(float raw) { return raw > 0.0f ? 1.0f : 0.0f; }

// The share of its photometric gradient a sample at distance t from the camera passes on (Philip and Deschaintre,
// "Floaters No More", 2023): (t / near_gradient)^2 nearer than near_gradient, else all of it (0: all of it
// everywhere). The space just in front of one photo's camera takes its own detail from that photo alone; scaled
// down there, what farther views say of the same space outweighs it, so it cannot fill with floaters.
PLX_HD float near_gradient_scale(float t, float near_gradient) {
    if (!(near_gradient > 0.0f) || t >= near_gradient) return 1.0f;
    const float q = t / near_gradient;
    return q * q;
}

// Ray against the box [0, hi] in grid coordinates. Origin og and direction dg are in grid units per
// unit of t. Returns false if the ray misses or only touches the box (an empty interval).
// A direction component that is exactly zero keeps the ray inside that slab or outside it for all t.
PLX_HD bool ray_box(const double og[3], const double dg[3], const double hi[3], double* t_enter,
                    double* t_exit) {
    double t0 = -1e300, t1 = 1e300;
    for (int a = 0; a < 3; ++a) {
        if (dg[a] == 0.0) {
            if (og[a] < 0.0 || og[a] > hi[a]) return false;
            continue;
        }
        double ta = (0.0 - og[a]) / dg[a];
        double tb = (hi[a] - og[a]) / dg[a];
        if (ta > tb) {
            const double s = ta;
            ta = tb;
            tb = s;
        }
        t0 = ta > t0 ? ta : t0;
        t1 = tb < t1 ? tb : t1;
    }
    *t_enter = t0;
    *t_exit = t1;
    return t1 > t0;
}

// The sample lattice of one ray: samples at t = t_start + (i + 0.5) * dt for 0 <= i < n, all with
// t < t_end. dt is `step` grid units converted to t; a ray needing more than max_samples samples
// gets a longer step so that it has exactly max_samples. Computed in double so every backend
// (float32 elsewhere) agrees on the number of samples.
PLX_HD int sample_lattice(double t_start, double t_end, double step_t, int max_samples, double* dt) {
    const double length = t_end - t_start;
    if (!(length > 0.0)) {
        *dt = step_t;
        return 0;
    }
    double n = ceil(length / step_t - 0.5);
    if (n < 0.0) n = 0.0;
    if (n > (double)max_samples) {
        *dt = length / (double)max_samples;
        return max_samples;
    }
    *dt = step_t;
    return (int)n;
}

// The map from the fit frame to grid coordinates, per axis piecewise linear: knots x[a][0] < ... < x[a][k-1] (fit
// frame) sit at grid coordinates g[a][0] = 0 < ... < g[a][k-1] = res - 1, and between two knots the map is linear. Two
// knots make the plain grid of one cell size over its box (g = (p - bbox_min) * scale); more let the cells of one
// lattice grow from a finely resolved foreground out to its coarser surroundings, with no seam where they meet (one
// lattice: interpolation, TV and pruning never see two cell sizes at once).
constexpr int kMaxKnots = 4;
struct Lattice {
    int knots[3];
    double x[3][kMaxKnots];
    double g[3][kMaxKnots];
    double slope[3][kMaxKnots - 1];  // grid units per fit-frame unit between knots j and j + 1
};

// Reads a lattice from its flat form, per axis [k, x_0 .. x_{k-1}, g_0 .. g_{k-1}]; the error says what is wrong, or
// is null. Host code (the operators' argument checks).
inline const char* read_lattice(const double* v, long n, const int res[3], Lattice* L) {
    long at = 0;
    for (int a = 0; a < 3; ++a) {
        if (at >= n) return "the lattice must list every axis: [k, k knots, k grid coordinates] per axis";
        const double k = v[at++];
        if (!(k >= 2 && k <= kMaxKnots) || k != (double)(int)k) return "the lattice needs 2 to 4 knots per axis";
        const int K = (int)k;
        if (at + 2 * K > n) return "the lattice ends before its knots do";
        L->knots[a] = K;
        for (int j = 0; j < K; ++j) {
            L->x[a][j] = v[at + j];
            L->g[a][j] = v[at + K + j];
        }
        at += 2 * K;
        if (L->g[a][0] != 0.0 || L->g[a][K - 1] != (double)(res[a] - 1))
            return "the lattice's grid coordinates must run from 0 to the axis' last vertex";
        for (int j = 0; j + 1 < K; ++j) {
            if (!(L->x[a][j + 1] > L->x[a][j]) || !(L->g[a][j + 1] > L->g[a][j]))
                return "the lattice's knots must increase";
            L->slope[a][j] = (L->g[a][j + 1] - L->g[a][j]) / (L->x[a][j + 1] - L->x[a][j]);
        }
    }
    return at == n ? nullptr : "the lattice has values past its third axis";
}

// The piece of axis a that holds fit-frame coordinate x (the first below x[a][1], the last at or past x[a][k-2]).
PLX_HD int lattice_piece(const Lattice& L, int a, double x) {
    int j = 0;
    while (j < L.knots[a] - 2 && x >= L.x[a][j + 1]) ++j;
    return j;
}

// The grid coordinate of fit-frame coordinate x on axis a (linear past the end knots).
PLX_HD double lattice_coord(const Lattice& L, int a, double x) {
    const int j = lattice_piece(L, a, x);
    return L.g[a][j] + (x - L.x[a][j]) * L.slope[a][j];
}

// The most grid units per fit-frame unit on any axis and piece: the finest cells.
PLX_HD double finest_slope(const Lattice& L) {
    double finest = 0.0;
    for (int a = 0; a < 3; ++a)
        for (int j = 0; j + 1 < L.knots[a]; ++j) finest = L.slope[a][j] > finest ? L.slope[a][j] : finest;
    return finest;
}

// One ray prepared for marching, identically on every backend.
// On a lattice a ray is marched a piece at a time: between two knot planes it crosses, the map to grid coordinates is
// linear, so og and dg are the piece's grid-space origin and direction, and its samples a lattice of their own
// (t_start, dt, n). On a contracted grid (see contract_point) og and dg are the ray's origin and unit direction in the
// frame before contraction, dt is the step in contracted units through the finest cells and n the most steps the ray
// may take.
struct RayMarch {
    double og[3], dg[3];  // grid-space origin and direction (per unit of fit-frame distance) of the piece
    double inv_dg[3];     // 1 / dg (0 where dg is 0): where the march meets a block's faces
    float dir[3];         // unit fit-frame direction
    double t_start, dt;   // sample i of the piece sits at t_start + (i + 0.5) * dt
    int n;                // samples on the piece (0: none)
    bool contracted;
    double o[3], u[3];    // fit-frame origin and unit direction (to lay out the next piece)
    double t_piece_end;   // where the piece ends: a knot plane, or t_end
    double t_end;         // where the ray leaves the grid's box
    double step;          // grid units between samples
    int budget;           // samples the ray may still take after this piece
};

// Lays out the piece of a lattice ray that starts at t0: it ends at the first knot plane the ray crosses after t0, or
// where it leaves the box; its samples are `step` grid units apart, at most the ray's remaining budget of them.
PLX_HD void lay_piece(const Lattice& L, double t0, RayMarch* r) {
    double t1 = r->t_end;
    for (int a = 0; a < 3; ++a) {
        if (r->u[a] == 0.0) continue;
        for (int j = 1; j + 1 < L.knots[a]; ++j) {
            const double tk = (L.x[a][j] - r->o[a]) / r->u[a];
            if (tk > t0 && tk < t1) t1 = tk;
        }
    }
    const double mid = 0.5 * (t0 + t1);
    double dg2 = 0.0;
    for (int a = 0; a < 3; ++a) {
        const int j = lattice_piece(L, a, r->o[a] + mid * r->u[a]);
        r->og[a] = L.g[a][j] + (r->o[a] - L.x[a][j]) * L.slope[a][j];
        r->dg[a] = r->u[a] * L.slope[a][j];
        r->inv_dg[a] = r->dg[a] != 0.0 ? 1.0 / r->dg[a] : 0.0;
        dg2 += r->dg[a] * r->dg[a];
    }
    r->t_start = t0;
    r->t_piece_end = t1;
    r->n = sample_lattice(t0, t1, r->step / sqrt(dg2), r->budget, &r->dt);
    r->budget -= r->n;
}

// Prepares a fit-frame ray for marching: clips it to the grid box and to t >= near and lays out its first piece
// (lay_piece). On a contracted grid the ray keeps its frame and starts at near; its samples are laid out as it is
// marched (next_sample).
PLX_HD void setup_ray(const Lattice& L, const float* o, const float* d, double near, double step, int max_samples,
                      bool contracted, RayMarch* r) {
    const double norm = sqrt((double)d[0] * d[0] + (double)d[1] * d[1] + (double)d[2] * d[2]);
    double from_min[3], extent[3];  // the origin from the box's low corner, and the box's size
    r->contracted = contracted;
    r->step = step;
    for (int a = 0; a < 3; ++a) {
        r->u[a] = d[a] / norm;
        r->o[a] = (double)o[a];
        r->dir[a] = (float)r->u[a];
        from_min[a] = r->o[a] - L.x[a][0];
        extent[a] = L.x[a][L.knots[a] - 1] - L.x[a][0];
    }
    if (contracted) {
        for (int a = 0; a < 3; ++a) {
            r->og[a] = r->o[a];
            r->dg[a] = r->u[a];
            r->inv_dg[a] = r->dg[a] != 0.0 ? 1.0 / r->dg[a] : 0.0;
        }
        r->t_start = near;
        r->dt = step / finest_slope(L);
        r->n = max_samples;
        return;
    }
    double t_enter, t_exit;
    r->n = 0;
    r->dt = 1.0;
    r->t_start = r->t_piece_end = r->t_end = 0.0;
    if (!ray_box(from_min, r->u, extent, &t_enter, &t_exit)) return;
    r->t_end = t_exit;
    r->budget = max_samples;
    lay_piece(L, t_enter < near ? near : t_enter, r);
}

// Clamps to [lo, hi] with comparisons only, so NaN passes through the same way on host and device.
PLX_HD float clamp_to(float v, float lo, float hi) {
    const float a = v < lo ? lo : v;
    return hi < a ? hi : a;
}

// The grid point at distance t along the ray, clamped into the grid.
PLX_HD void grid_point(const int res[3], const RayMarch& r, double t, float p[3]) {
    for (int a = 0; a < 3; ++a) p[a] = clamp_to((float)(r.og[a] + t * r.dg[a]), 0.0f, (float)(res[a] - 1));
}

// The cell holding grid coordinate p on an axis of res vertices (the last cell holds p = res - 1).
PLX_HD int cell_of(float p, int res) {
    const int i = (int)floorf(p);
    const int lo = i < 0 ? 0 : i;
    return lo < res - 2 ? lo : res - 2;
}

// The occupancy block (cubes of `block` cells, a power of two) holding cell coordinate x >= 0: a shift, where a
// division by a block size known only at run time costs the march tens of cycles per sample.
PLX_HD int block_of(int x, int block) {
#ifdef __CUDA_ARCH__
    return x >> (__ffs(block) - 1);
#else
    return x >> __builtin_ctz((unsigned)block);
#endif
}

// Index of the first sample at or after the point where the ray leaves the occupancy block (cubes of
// `block` cells) that holds `cell`; always > i so the march advances.
PLX_HD int skip_block(const int res[3], int block, const RayMarch& r, const int cell[3], int i) {
    double t_out = 1e300;
    for (int a = 0; a < 3; ++a) {
        if (r.dg[a] == 0.0) continue;
        const int b = block_of(cell[a], block);
        const int upper = (b + 1) * block < res[a] - 1 ? (b + 1) * block : res[a] - 1;
        const double face = r.dg[a] > 0.0 ? (double)upper : (double)(b * block);
        const double t_face = (face - r.og[a]) * r.inv_dg[a];
        t_out = t_face < t_out ? t_face : t_out;
    }
    const double next = ceil((t_out - r.t_start) / r.dt - 0.5);
    if (!(next > (double)i)) return i + 1;
    return next < (double)r.n ? (int)next : r.n;
}

// Flat indices of the occupancy block and of the cell (block_occ [bres], cell_occ [res - 1]) that hold `cell`.
PLX_HD int64_t block_index(const int bres[3], int block, const int cell[3]) {
    return ((int64_t)block_of(cell[0], block) * bres[1] + block_of(cell[1], block)) * bres[2] + block_of(cell[2], block);
}

PLX_HD int64_t cell_index(const int res[3], const int cell[3]) {
    return ((int64_t)cell[0] * (res[1] - 1) + cell[1]) * (res[2] - 1) + cell[2];
}

// Empty-space skipping for sample i at grid point p (already clamped): fills `cell` and returns i when the
// sample's cell may hold density, otherwise the index of the next sample worth visiting (always > i).
// block_occ flags cubes of `block` cells ([bres]) with any live vertex; cell_occ flags cells with any
// allocated corner ([res - 1]).
PLX_HD int occupied_or_next(const int res[3], const int bres[3], int block, const uint8_t* block_occ,
                            const uint8_t* cell_occ, const RayMarch& r, const float p[3], int i, int cell[3]) {
    for (int a = 0; a < 3; ++a) cell[a] = cell_of(p[a], res[a]);
    if (!block_occ[block_index(bres, block, cell)]) return skip_block(res, block, r, cell, i);
    return cell_occ[cell_index(res, cell)] ? i : i + 1;
}

// Whether the cell holding grid point p (already clamped) may hold density; fills `cell`.
PLX_HD bool cell_occupied(const int res[3], const int bres[3], int block, const uint8_t* block_occ,
                          const uint8_t* cell_occ, const float p[3], int cell[3]) {
    for (int a = 0; a < 3; ++a) cell[a] = cell_of(p[a], res[a]);
    return block_occ[block_index(bres, block, cell)] && cell_occ[cell_index(res, cell)];
}

// Cell and trilinear weights of grid point g (already clamped to [0, res-1]); res >= 2 per axis.
// Corner c = 4*dx + 2*dy + dz, with (dx, dy, dz) in {0,1}^3, gets weight w[c].
PLX_HD void trilinear(const float g[3], const int res[3], int cell[3], float w[8]) {
    float f[3];
    for (int a = 0; a < 3; ++a) {
        int i = (int)floorf(g[a]);
        if (i > res[a] - 2) i = res[a] - 2;
        if (i < 0) i = 0;
        cell[a] = i;
        f[a] = g[a] - (float)i;
    }
    const float fx0 = 1.0f - f[0], fy0 = 1.0f - f[1], fz0 = 1.0f - f[2];
    w[0] = fx0 * fy0 * fz0;
    w[1] = fx0 * fy0 * f[2];
    w[2] = fx0 * f[1] * fz0;
    w[3] = fx0 * f[1] * f[2];
    w[4] = f[0] * fy0 * fz0;
    w[5] = f[0] * fy0 * f[2];
    w[6] = f[0] * f[1] * fz0;
    w[7] = f[0] * f[1] * f[2];
}

// Flat index into links of corner c of a cell (links is [Rx, Ry, Rz], C order).
PLX_HD int64_t corner_index(const int cell[3], const int res[3], int c) {
    const int x = cell[0] + ((c >> 2) & 1), y = cell[1] + ((c >> 1) & 1), z = cell[2] + (c & 1);
    return ((int64_t)x * res[1] + y) * res[2] + z;
}

// Trilinear interpolation of the packed rows at grid point g (float32, not clamped: a point outside
// [0, res-1] on any axis, or NaN, gives zeros): out[0..stride) = sum_c w_c * row_c, an unallocated
// corner counting as zeros. Corners are summed in order c = 0..7, as the PyTorch twin does.
PLX_HD void interpolate_point(const float* data, int stride, const int32_t* links, const int res[3], const float g[3],
                              float* out) {
    for (int k = 0; k < stride; ++k) out[k] = 0.0f;
    for (int a = 0; a < 3; ++a)
        if (!(g[a] >= 0.0f && g[a] <= (float)(res[a] - 1))) return;
    int cell[3];
    float w[8];
    trilinear(g, res, cell, w);
    for (int c = 0; c < 8; ++c) {
        const int32_t row = links[corner_index(cell, res, c)];
        if (row < 0) continue;
        const float* v = data + (int64_t)row * stride;
        for (int k = 0; k < stride; ++k) out[k] += w[c] * v[k];
    }
}

// One compositing step: alpha of a sample and the transmittance after it.
PLX_HD float sample_alpha(float sigma, float delta, float* transmittance_factor) {
    const float f = expf(-sigma * delta);
    *transmittance_factor = f;
    return 1.0f - f;
}

// The light a ray carries past the grid to whatever lies behind it (the background), given the transmittance T the
// march ended with: none once the march stopped below stop_transmittance s, so a stopped ray's background need not be
// drawn at all; T from 2s up; between, a ramp T (T - s) / s, so that a ray's colour does not jump where the stop
// begins to take it (a render stays continuous in the camera's pose). s = 0: T on every ray. (The opacity stays 1 - T,
// what the samples took: depth divided by opacity is their mean depth.) The kernels pass the march's stop as s only
// where the background is the spheres, which cost a ray more than the grid; a flat colour costs nothing to draw, and
// cut it cost an object's fit under a strong sparsity prior 0.5 dB held-out (bench/README.md, "Real captures").
PLX_HD float light_past_grid(float transmittance, float stop_transmittance) {
    if (transmittance >= 2.0f * stop_transmittance) return transmittance;
    if (transmittance < stop_transmittance) return 0.0f;
    return transmittance * (transmittance - stop_transmittance) / stop_transmittance;
}

// T d(light_past_grid)/dT: how the background's share answers the grid's density (d share / d sigma_i is -delta_i
// times this), which the backward passes use in place of the share itself (equal to it outside the ramp).
PLX_HD float light_past_grid_rate(float transmittance, float stop_transmittance) {
    if (transmittance >= 2.0f * stop_transmittance) return transmittance;
    if (transmittance < stop_transmittance) return 0.0f;
    return transmittance * (2.0f * transmittance - stop_transmittance) / stop_transmittance;
}

// A pixel's error in one channel against its target. A target below zero is a floor at -target: a photo's clipped
// channel, whose light reached at least that much, so a render at or above it is not wrong.
PLX_HD float colour_error(float total, float target) {
    if (target >= 0.0f) return total - target;
    const float short_of_floor = total + target;
    return short_of_floor < 0.0f ? short_of_floor : 0.0f;
}

// d(pixel colour)/d(sigma_i) for one channel, with
//   t_after = transmittance after sample i, c = its colour,
//   behind = everything composited behind sample i (later samples plus the background term).
// Derivation: sigma_i scales every later transmittance by exp(-sigma_i delta) and sets
// alpha_i = 1 - exp(-sigma_i delta).
PLX_HD float dcolour_dsigma(float delta, float t_after, float c, float behind) {
    return delta * (t_after * c - behind);
}

// Total-variation term at one vertex for one channel: sqrt(dx^2 + dy^2 + dz^2 + eps), and its
// gradient with respect to the vertex value and the three +axis neighbours (absent differences
// are 0 and pass no gradient).
constexpr float kTVEps = 1e-9f;
PLX_HD float tv_term(float dx, float dy, float dz, float* inv_norm) {
    const float n = sqrtf(dx * dx + dy * dy + dz * dz + kTVEps);
    *inv_norm = 1.0f / n;
    return n;
}

}  // namespace plx


// The contracted grid's ray march and the background spheres, in headers of their own for length; one math.
#include "plenoxels_math_contraction.h"
#include "plenoxels_math_background.h"
