// Per-sample math of the contracted grid of unbounded scenes, shared by the CPU and CUDA kernels.
// Included by plenoxels_math.h, after the definitions it uses; include that header, not this one.
#pragma once

namespace plx {

// ---- Scene contraction (unbounded scenes) ------------------------------------------------------------------------
// The contraction of the frame the rays come in (mip-NeRF 360's, in the max norm as MERF and nerfstudio have it): a
// point q with |q|_inf <= 1 stays, one beyond moves to (2 - 1/m) q / m with m = |q|_inf, so all of space lies in the
// cube [-2, 2]^3 that the grid spans, the inner cube [-1, 1]^3 (the foreground) at full resolution and the rest at a
// resolution falling off as 1/m^2 (and coarser still where the grid's knots say so). Rays bend in the contracted
// frame, so they are marched in their own frame with steps of constant length in grid units, and each sample
// integrates density over its step's contracted length: density is per contracted unit, which is the frame's own unit
// in the inner cube.
// The axis of |q|_inf: the first of the largest.
PLX_HD int major_axis(const double q[3]) {
    const double x = fabs(q[0]), y = fabs(q[1]), z = fabs(q[2]);
    if (x >= y && x >= z) return 0;
    return y >= z ? 1 : 2;
}

// Contracts q into c; returns |c|_inf.
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

// J(q) u: the contracted point's velocity per unit of t along direction u at q. Beyond the inner cube, with k the
// major axis, m = |q_k| and f(m) = (2 - 1/m) / m: c_k = (2 - 1/m) sign(q_k) moves by u_k / m^2, and every other
// c_j = f(m) q_j by f(m) u_j + q_j f'(m) sign(q_k) u_k.
PLX_HD void contracted_velocity(const double q[3], const double u[3], double v[3]) {
    const int k = major_axis(q);
    const double m = fabs(q[k]);
    if (m <= 1.0) {
        for (int a = 0; a < 3; ++a) v[a] = u[a];
        return;
    }
    const double f = (2.0 - 1.0 / m) / m, df = (2.0 / m - 2.0) / (m * m);
    const double along = q[k] < 0.0 ? -u[k] : u[k];
    for (int a = 0; a < 3; ++a) v[a] = a == k ? u[k] / (m * m) : f * u[a] + q[a] * df * along;
}

// |J(q) u|: contracted length per unit of t along direction u at q.
PLX_HD double contracted_speed(const double q[3], const double u[3]) {
    double v[3];
    contracted_velocity(q, u, v);
    return sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
}

// Grid units per unit of t along direction u at q: the contracted velocity through the lattice's slopes where the
// contracted point lies (on a lattice of one cell size, the finest slope times contracted_speed).
PLX_HD double contracted_grid_speed(const Lattice& L, const double q[3], const double u[3]) {
    double v[3], c[3];
    contracted_velocity(q, u, v);
    contract_point(q, c);
    double sum = 0.0;
    for (int a = 0; a < 3; ++a) {
        const double s = L.slope[a][lattice_piece(L, a, c[a])] * v[a];
        sum += s * s;
    }
    return sqrt(sum);
}

// The grid point (clamped) of the contracted ray at distance t; returns |contracted point|_inf there.
PLX_HD double contracted_grid_point(const int res[3], const Lattice& L, const RayMarch& r, double t, float p[3]) {
    double q[3], c[3];
    for (int a = 0; a < 3; ++a) q[a] = r.og[a] + t * r.dg[a];
    const double radius = contract_point(q, c);
    for (int a = 0; a < 3; ++a) p[a] = clamp_to((float)lattice_coord(L, a, c[a]), 0.0f, (float)(res[a] - 1));
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

// One step of a contracted ray: `step` grid units long at the grid speed where it starts (contracted_grid_speed; so
// longer through a coarser shell; at most PLX_CONTRACTED_MAX_STEP of |q|_inf), its sample half way, integrating
// density over the step's contracted length (by the midpoint rule). Fills the walk's t, delta and p.
PLX_HD ContractedSample contracted_step(const int res[3], const Lattice& L, const RayMarch& r, MarchWalk* w) {
    double q[3];
    for (int a = 0; a < 3; ++a) q[a] = r.og[a] + w->cursor * r.dg[a];
    const double reach = fabs(q[major_axis(q)]);
    const double cap = PLX_CONTRACTED_MAX_STEP * (reach > 1.0 ? reach : 1.0);
    const double dt = r.step / contracted_grid_speed(L, q, r.dg);
    w->dt = dt < cap ? dt : cap;
    w->t = w->cursor + 0.5 * w->dt;
    w->cursor += w->dt;
    ++w->i;
    for (int a = 0; a < 3; ++a) q[a] = r.og[a] + w->t * r.dg[a];
    w->delta = w->dt * contracted_speed(q, r.dg);
    if (contracted_grid_point(res, L, r, w->t, w->p) < 2.0 - 0.5 * r.dt) return kInside;
    const int k = major_axis(q);
    return (q[k] < 0.0 ? -r.dg[k] : r.dg[k]) < 0.0 ? kBeyondComingIn : kGone;
}

// Moves the walk to the next sample worth visiting (its cell may hold density); false when the ray has none left. A
// lattice ray's samples sit at t_start + (i + 0.5) dt of their piece, each dt long, and skip empty blocks whole; at a
// piece's end the ray lays out its next piece (lay_piece) and the walk starts that piece's samples. A contracted ray
// steps as contracted_step says, skips samples beyond the grid's reach and ends where it is gone or after n steps.
PLX_HD bool next_sample(const int res[3], const int bres[3], int block, const uint8_t* block_occ,
                        const uint8_t* cell_occ, const Lattice& L, RayMarch* r, MarchWalk* w) {
    if (!r->contracted) {
        while (true) {
            while (w->i < r->n) {
                w->t = r->t_start + (w->i + 0.5) * r->dt;
                grid_point(res, *r, w->t, w->p);
                const int next = occupied_or_next(res, bres, block, block_occ, cell_occ, *r, w->p, w->i, w->cell);
                if (next == w->i) {
                    w->delta = r->dt;
                    ++w->i;
                    return true;
                }
                w->i = next;
            }
            if (!(r->t_piece_end < r->t_end)) return false;
            lay_piece(L, r->t_piece_end, r);
            w->i = 0;
        }
    }
    while (w->i < r->n) {
        const ContractedSample where = contracted_step(res, L, *r, w);
        if (where == kGone) return false;
        if (where == kInside && cell_occupied(res, bres, block, block_occ, cell_occ, w->p, w->cell)) return true;
    }
    return false;
}

// The grid point about `ahead` samples past the walk's (for prefetching; clamped; past a piece's end, on the piece's
// line).
PLX_HD void point_ahead(const int res[3], const Lattice& L, const RayMarch& r, const MarchWalk& w, int ahead,
                        float p[3]) {
    if (r.contracted)
        contracted_grid_point(res, L, r, w.t + ahead * w.dt, p);
    else
        grid_point(res, r, w.t + ahead * r.dt, p);
}

// Samples on the ray before any occupancy test or early stop: those of every piece on a lattice, the steps inside
// the grid's reach on a contracted ray (reports and benchmarks).
PLX_HD int ray_length_samples(const int res[3], const Lattice& L, const RayMarch& ray) {
    RayMarch r = ray;
    if (!r.contracted) {
        int samples = r.n;
        while (r.t_piece_end < r.t_end) {
            lay_piece(L, r.t_piece_end, &r);
            samples += r.n;
        }
        return samples;
    }
    MarchWalk w = march_start(r);
    int samples = 0;
    while (w.i < r.n) {
        const ContractedSample where = contracted_step(res, L, r, &w);
        if (where == kGone) break;
        samples += where == kInside;
    }
    return samples;
}

}  // namespace plx
