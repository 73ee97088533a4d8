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

// One ray prepared for marching, identically on every backend.
// On a contracted grid (see contract_point) og and dg are the ray's origin and unit direction in the frame before
// contraction, dt is the step in contracted units and n the most steps the ray may take.
struct RayMarch {
    double og[3], dg[3];  // grid-space origin and direction (per unit of fit-frame distance)
    double inv_dg[3];     // 1 / dg (0 where dg is 0): where the march meets a block's faces
    float dir[3];         // unit fit-frame direction
    double t_start, dt;   // sample i sits at t_start + (i + 0.5) * dt
    int n;                // samples on the ray (0: it misses the grid)
    bool contracted;
};

// Maps a fit-frame ray into grid coordinates (g = (p - bmin) * scale), clips it to the grid box and
// to t >= near, and lays out its samples `step` grid units apart. On a contracted grid the ray keeps its frame and
// starts at near; its samples are laid out as it is marched (next_sample).
PLX_HD void setup_ray(const int res[3], const double bmin[3], const double scale[3], const float* o, const float* d,
                      double near, double step, int max_samples, bool contracted, RayMarch* r) {
    const double norm = sqrt((double)d[0] * d[0] + (double)d[1] * d[1] + (double)d[2] * d[2]);
    double dg2 = 0.0, hi[3], finest = 0.0;
    r->contracted = contracted;
    for (int a = 0; a < 3; ++a) {
        const double u = d[a] / norm;
        r->dir[a] = (float)u;
        r->og[a] = contracted ? (double)o[a] : ((double)o[a] - bmin[a]) * scale[a];
        r->dg[a] = contracted ? u : u * scale[a];
        r->inv_dg[a] = r->dg[a] != 0.0 ? 1.0 / r->dg[a] : 0.0;
        dg2 += r->dg[a] * r->dg[a];
        hi[a] = res[a] - 1;
        finest = scale[a] > finest ? scale[a] : finest;
    }
    if (contracted) {
        r->t_start = near;
        r->dt = step / finest;
        r->n = max_samples;
        return;
    }
    double t_enter, t_exit;
    r->n = 0;
    r->dt = 1.0;
    r->t_start = 0.0;
    if (!ray_box(r->og, r->dg, hi, &t_enter, &t_exit)) return;
    r->t_start = t_enter < near ? near : t_enter;
    r->n = sample_lattice(r->t_start, t_exit, step / sqrt(dg2), max_samples, &r->dt);
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

// ---- Scene contraction (unbounded scenes) ------------------------------------------------------------------------
// The contraction of the frame the rays come in (mip-NeRF 360's, in the max norm as MERF and nerfstudio have it): a
// point q with |q|_inf <= 1 stays, one beyond moves to (2 - 1/m) q / m with m = |q|_inf, so all of space lies in the
// cube [-2, 2]^3 that the grid spans, the inner cube [-1, 1]^3 (the foreground) at full resolution and the rest at a
// resolution falling off as 1/m^2. Rays bend in the contracted frame, so they are marched in their own frame with
// steps of constant contracted length dt, and each sample integrates density over dt: density is per contracted unit,
// which is the frame's own unit in the inner cube. Returns |contracted q|_inf.
// The axis of |q|_inf: the first of the largest.
PLX_HD int major_axis(const double q[3]) {
    const double x = fabs(q[0]), y = fabs(q[1]), z = fabs(q[2]);
    if (x >= y && x >= z) return 0;
    return y >= z ? 1 : 2;
}

PLX_HD double contract_point(const double q[3], double c[3]) {
    const double m = fabs(q[major_axis(q)]);
    if (m <= 1.0) {
        for (int a = 0; a < 3; ++a) c[a] = q[a];
        return m;
    }
    const double f = (2.0 - 1.0 / m) / m;
    for (int a = 0; a < 3; ++a) c[a] = f * q[a];
    return 2.0 - 1.0 / m;
}

// |J(q) u|: contracted length per unit of t along direction u at q. Beyond the inner cube, with k the major axis,
// m = |q_k| and f(m) = (2 - 1/m) / m: c_k = (2 - 1/m) sign(q_k) moves by u_k / m^2, and every other c_j = f(m) q_j by
// f(m) u_j + q_j f'(m) sign(q_k) u_k.
PLX_HD double contracted_speed(const double q[3], const double u[3]) {
    const int k = major_axis(q);
    const double m = fabs(q[k]);
    if (m <= 1.0) return sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]);
    const double f = (2.0 - 1.0 / m) / m, df = (2.0 / m - 2.0) / (m * m);
    const double along = q[k] < 0.0 ? -u[k] : u[k];
    double sum = 0.0;
    for (int a = 0; a < 3; ++a) {
        const double v = a == k ? u[k] / (m * m) : f * u[a] + q[a] * df * along;
        sum += v * v;
    }
    return sqrt(sum);
}

// The grid point (clamped) of the contracted ray at distance t; returns |contracted point|_inf there.
PLX_HD double contracted_grid_point(const int res[3], const double bmin[3], const double scale[3], const RayMarch& r,
                                    double t, float p[3]) {
    double q[3], c[3];
    for (int a = 0; a < 3; ++a) q[a] = r.og[a] + t * r.dg[a];
    const double radius = contract_point(q, c);
    for (int a = 0; a < 3; ++a) p[a] = clamp_to((float)((c[a] - bmin[a]) * scale[a]), 0.0f, (float)(res[a] - 1));
    return radius;
}

// A march along one ray: where it stands and the sample it is at.
struct MarchWalk {
    int i;              // steps taken (on a lattice: the index of the next sample)
    double cursor, dt;  // contracted ray: where its next step begins, and the last step's length
    double t, delta;    // the sample: its distance along the ray and the length it integrates density over
    float p[3];         // its grid point (clamped)
    int cell[3];        // its cell
};

PLX_HD MarchWalk march_start(const RayMarch& r) {
    MarchWalk w;
    w.i = 0;
    w.cursor = r.t_start;
    w.dt = w.delta = r.dt;
    return w;
}

// A contracted ray's step from t may not shrink or grow |q|_inf by more than this share of it (at least 1), so a ray
// coming in from far away, where the contraction is slow, does not leap over the foreground in one step.
#define PLX_CONTRACTED_MAX_STEP 0.25

// Where a contracted ray's step put its sample: inside the grid's reach, in the shell beyond it (half a step from the
// cube's faces, that is, at infinity) coming in, or there and moving out, gone: |q|_inf is convex along a ray, so once
// it grows it never shrinks again.
enum ContractedSample { kInside, kBeyondComingIn, kGone };

// One step of a contracted ray: dt contracted units long at the speed where it starts (at most
// PLX_CONTRACTED_MAX_STEP of |q|_inf), its sample half way, integrating density over the step's contracted length (by
// the midpoint rule). Fills the walk's t, delta and p.
PLX_HD ContractedSample contracted_step(const int res[3], const double bmin[3], const double scale[3],
                                        const RayMarch& r, MarchWalk* w) {
    double q[3];
    for (int a = 0; a < 3; ++a) q[a] = r.og[a] + w->cursor * r.dg[a];
    const double reach = fabs(q[major_axis(q)]);
    const double cap = PLX_CONTRACTED_MAX_STEP * (reach > 1.0 ? reach : 1.0);
    const double dt = r.dt / contracted_speed(q, r.dg);
    w->dt = dt < cap ? dt : cap;
    w->t = w->cursor + 0.5 * w->dt;
    w->cursor += w->dt;
    ++w->i;
    for (int a = 0; a < 3; ++a) q[a] = r.og[a] + w->t * r.dg[a];
    w->delta = w->dt * contracted_speed(q, r.dg);
    if (contracted_grid_point(res, bmin, scale, r, w->t, w->p) < 2.0 - 0.5 * r.dt) return kInside;
    const int k = major_axis(q);
    return (q[k] < 0.0 ? -r.dg[k] : r.dg[k]) < 0.0 ? kBeyondComingIn : kGone;
}

// Moves the walk to the next sample worth visiting (its cell may hold density); false when the ray has none left. A
// lattice ray's samples sit at t_start + (i + 0.5) dt, each dt long, and skip empty blocks whole. A contracted ray
// steps as contracted_step says, skips samples beyond the grid's reach and ends where it is gone or after n steps.
PLX_HD bool next_sample(const int res[3], const int bres[3], int block, const uint8_t* block_occ,
                        const uint8_t* cell_occ, const double bmin[3], const double scale[3], const RayMarch& r,
                        MarchWalk* w) {
    if (!r.contracted) {
        while (w->i < r.n) {
            w->t = r.t_start + (w->i + 0.5) * r.dt;
            grid_point(res, r, w->t, w->p);
            const int next = occupied_or_next(res, bres, block, block_occ, cell_occ, r, w->p, w->i, w->cell);
            if (next == w->i) {
                ++w->i;
                return true;
            }
            w->i = next;
        }
        return false;
    }
    while (w->i < r.n) {
        const ContractedSample where = contracted_step(res, bmin, scale, r, w);
        if (where == kGone) return false;
        if (where == kInside && cell_occupied(res, bres, block, block_occ, cell_occ, w->p, w->cell)) return true;
    }
    return false;
}

// The grid point about `ahead` samples past the walk's (for prefetching; clamped).
PLX_HD void point_ahead(const int res[3], const double bmin[3], const double scale[3], const RayMarch& r,
                        const MarchWalk& w, int ahead, float p[3]) {
    if (r.contracted)
        contracted_grid_point(res, bmin, scale, r, w.t + ahead * w.dt, p);
    else
        grid_point(res, r, w.t + ahead * r.dt, p);
}

// Samples on the ray before any occupancy test or early stop: n on a lattice, the steps inside the grid's reach on a
// contracted ray (reports and benchmarks).
PLX_HD int ray_length_samples(const int res[3], const double bmin[3], const double scale[3], const RayMarch& r) {
    if (!r.contracted) return r.n;
    MarchWalk w = march_start(r);
    int samples = 0;
    while (w.i < r.n) {
        const ContractedSample where = contracted_step(res, bmin, scale, r, &w);
        if (where == kGone) break;
        samples += where == kInside;
    }
    return samples;
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

// ---- The multi-sphere background (plenoxels/background.py; its twin is reference.background_colour) ------------
// Concentric spheres, each an equirectangular texture of 4 channels (raw density, then colour logits R, G, B) laid
// out as rows [sphere][row][column][4]. A ray reads each sphere where it leaves it; a layer's opacity is
// 1 - exp(-relu(density)) and its colour sigmoid(logits); spheres composite front (small radius) to back, and the
// transmittance left sees far_colour.

// Where a ray (origin relative to the centre `rel`, unit direction `unit`) leaves the sphere of `radius`, as a unit
// direction from the centre; false when it misses or the exit lies behind the origin. Double precision so that
// spheres at a million times the foreground's size still meet the ray where they should.
PLX_HD bool bg_exit(const double rel[3], const double unit[3], double radius, double p[3]) {
    const double b = rel[0] * unit[0] + rel[1] * unit[1] + rel[2] * unit[2];
    const double c = rel[0] * rel[0] + rel[1] * rel[1] + rel[2] * rel[2] - radius * radius;
    const double disc = b * b - c;
    if (disc < 0.0) return false;
    const double t = -b + sqrt(disc);
    if (!(t > 0.0)) return false;
    // The exit point lies on the sphere, so dividing by the radius makes it a unit vector (to rounding, which the
    // texel lookup's clamp absorbs).
    const double inv = 1.0 / radius;
    for (int a = 0; a < 3; ++a) p[a] = (rel[a] + t * unit[a]) * inv;
    return true;
}

// The 4 texels (row * width + column, within one sphere) and bilinear weights at unit direction p: texel centres
// at (i + 0.5) / W of the azimuth from -pi and (j + 0.5) / H of the polar angle from +z; azimuth wraps, rows clamp.
PLX_HD void bg_texels(const double p[3], int height, int width, int texel[4], float w[4]) {
    // Single precision from here: the direction is already exact to ~1e-7 rad, far finer than any texel.
    const float kPi = 3.14159265358979323846f;
    const float z = (float)p[2];
    const float azimuth = atan2f((float)p[1], (float)p[0]);
    const float elevation = asinf(z < -1.0f ? -1.0f : (z > 1.0f ? 1.0f : z));
    const float u = (azimuth + kPi) / (2.0f * kPi) * width - 0.5f;
    float v = (0.5f * kPi - elevation) / kPi * height - 0.5f;
    v = v < 0.0f ? 0.0f : (v > height - 1.0f ? height - 1.0f : v);
    const float fu = floorf(u), fv = floorf(v);
    const float au = u - fu, av = v - fv;
    int c0 = (int)fu % width;
    if (c0 < 0) c0 += width;
    const int c1 = (c0 + 1) % width;
    const int r0 = (int)fv < height - 1 ? (int)fv : height - 1;
    const int r1 = r0 + 1 < height ? r0 + 1 : height - 1;
    texel[0] = r0 * width + c0;
    texel[1] = r0 * width + c1;
    texel[2] = r1 * width + c0;
    texel[3] = r1 * width + c1;
    w[0] = (1.0f - au) * (1.0f - av);
    w[1] = au * (1.0f - av);
    w[2] = (1.0f - au) * av;
    w[3] = au * av;
}

// One sphere's interpolated channels for a ray: false when the ray does not meet it.
struct BgLayer {
    int texel[4];    // rows of the texture table (sphere offset included)
    float w[4];
    float raw[4];    // interpolated raw density and colour logits
};

// The interpolated channels of the texels `layer` names (texel rows and bilinear weights already set).
PLX_HD void bg_read(const float* texture, BgLayer* layer) {
    for (int c = 0; c < 4; ++c) layer->raw[c] = 0.0f;
    for (int i = 0; i < 4; ++i) {
        const float* row = texture + 4 * (int64_t)layer->texel[i];
        for (int c = 0; c < 4; ++c) layer->raw[c] += layer->w[i] * row[c];
    }
}

// Where a ray meets sphere k: its texels and weights (sphere offset included) and their channels.
PLX_HD bool bg_layer(const float* texture, int k, int height, int width, const double rel[3], const double unit[3],
                     double radius, BgLayer* layer) {
    double p[3];
    if (!bg_exit(rel, unit, radius, p)) return false;
    bg_texels(p, height, width, layer->texel, layer->w);
    const int64_t base = (int64_t)k * height * width;
    for (int i = 0; i < 4; ++i) layer->texel[i] += (int)base;
    bg_read(texture, layer);
    return true;
}

PLX_HD float bg_sigmoid(float x) { return 1.0f / (1.0f + expf(-x)); }

// Ray set-up shared by forward and backward: origin relative to the centre, unit direction.
PLX_HD void bg_ray(const float* o, const float* d, const float* centre, double rel[3], double unit[3]) {
    double n = 0.0;
    for (int a = 0; a < 3; ++a) {
        rel[a] = (double)o[a] - (double)centre[a];
        unit[a] = d[a];
        n += unit[a] * unit[a];
    }
    n = sqrt(n) > 1e-30 ? sqrt(n) : 1e-30;
    for (int a = 0; a < 3; ++a) unit[a] /= n;
}

// A ray stops compositing spheres once this little light gets through (as the grid's rays stop at
// stop_transmittance): the spheres behind an opaque one cost nothing. reference.background_colour does the same.
#define PLX_BG_STOP_TRANSMITTANCE 1e-4f

// The compositing below takes each sphere's layer from `layer(k, &out)` (false: the ray does not meet sphere k), so
// one statement of the math serves rays that intersect the spheres as they go (bg_layer) and a backward pass that
// reads back the layers its forward pass recorded.

// Colour of one ray: front-to-back composite of the spheres, then far_colour.
#ifdef __CUDACC__
#pragma nv_exec_check_disable  // `layer` is a device functor on the GPU, a host one on the CPU
#endif
template <typename Layer>
PLX_HD void bg_composite(int spheres, Layer layer, const float* far_colour, float rgb[3]) {
    float transmittance = 1.0f;
    rgb[0] = rgb[1] = rgb[2] = 0.0f;
    for (int k = 0; k < spheres && transmittance >= PLX_BG_STOP_TRANSMITTANCE; ++k) {
        BgLayer l;
        if (!layer(k, &l)) continue;
        const float alpha = 1.0f - expf(-(l.raw[0] > 0.0f ? l.raw[0] : 0.0f));
        const float weight = transmittance * alpha;
        for (int c = 0; c < 3; ++c) rgb[c] += weight * bg_sigmoid(l.raw[1 + c]);
        transmittance *= 1.0f - alpha;
    }
    for (int c = 0; c < 3; ++c) rgb[c] += transmittance * far_colour[c];
}

PLX_HD void bg_forward(const float* texture, const float* radii, int spheres, int height, int width, const double rel[3],
                       const double unit[3], const float* far_colour, float rgb[3]) {
    bg_composite(spheres, [&](int k, BgLayer* l) { return bg_layer(texture, k, height, width, rel, unit, radii[k], l); },
                 far_colour, rgb);
}

// d loss / d texel channels of one ray given its colour `total` (bg_forward's) and d loss / d colour `g`, handed
// texel by texel to `add(row, grad[4])`. With A_k the colour composited up to and including sphere k and C the
// ray's colour, d C / d sigma_k = T_k (1 - alpha_k) c_k - (C - A_k) for sigma_k > 0: no division by 1 - alpha, so
// opaque layers stay finite.
#ifdef __CUDACC__
#pragma nv_exec_check_disable  // `layer` and `add` are device functors on the GPU, host ones on the CPU
#endif
template <typename Layer, typename Add>
PLX_HD void bg_composite_backward(int spheres, Layer layer, const float total[3], const float g[3], Add add) {
    float transmittance = 1.0f, acc[3] = {0.0f, 0.0f, 0.0f};
    for (int k = 0; k < spheres && transmittance >= PLX_BG_STOP_TRANSMITTANCE; ++k) {
        BgLayer l;
        if (!layer(k, &l)) continue;
        const bool positive = l.raw[0] > 0.0f;
        const float alpha = 1.0f - expf(-(positive ? l.raw[0] : 0.0f));
        const float weight = transmittance * alpha;
        float colour[3], grad[4];
        float dsigma = 0.0f;
        for (int c = 0; c < 3; ++c) {
            colour[c] = bg_sigmoid(l.raw[1 + c]);
            acc[c] += weight * colour[c];
            grad[1 + c] = g[c] * weight * colour[c] * (1.0f - colour[c]);
            dsigma += g[c] * (transmittance * (1.0f - alpha) * colour[c] - (total[c] - acc[c]));
        }
        grad[0] = positive ? dsigma : 0.0f;
        for (int i = 0; i < 4; ++i) {
            float texel_grad[4];
            for (int c = 0; c < 4; ++c) texel_grad[c] = l.w[i] * grad[c];
            add(l.texel[i], texel_grad);
        }
        transmittance *= 1.0f - alpha;
    }
}

#ifdef __CUDACC__
#pragma nv_exec_check_disable  // `add` is a device functor on the GPU, a host one on the CPU
#endif
template <typename Add>
PLX_HD void bg_backward(const float* texture, const float* radii, int spheres, int height, int width,
                        const double rel[3], const double unit[3], const float total[3], const float g[3], Add add) {
    bg_composite_backward(
        spheres, [&](int k, BgLayer* l) { return bg_layer(texture, k, height, width, rel, unit, radii[k], l); }, total,
        g, add);
}

}  // namespace plx
