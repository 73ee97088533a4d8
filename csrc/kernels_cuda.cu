// CUDA kernels of the Plenoxels core, one thread per ray (or per voxel / parameter). They mirror
// the CPU kernels (cpu_*.cpp) step by step: the same ray set-up, the same sample lattice computed in double,
// the same empty-space skipping and the same per-sample math from plenoxels_math.h, so a ray meets
// the same samples on either device. Gradients are scattered with atomicAdd instead of the CPU's
// per-thread buffers, and the backward pass re-marches the ray instead of keeping its samples.
#include <cuda_runtime.h>
#include <stdint.h>

#include "cuda_kernels.h"
#include "plenoxels_math.h"

namespace plx_cuda {
namespace {

constexpr int kThreads = 128;

// Rows are read and their gradients written as float4 (the padded row stride is a multiple of 4
// floats and the tables are 16-byte aligned: bindings_cuda.cpp checks), so C columns take
// float4s(C) vector accesses instead of C scalar ones.
__host__ __device__ constexpr int float4s(int columns) { return (columns + 3) / 4; }

inline unsigned blocks_for(int64_t n) { return (unsigned)((n + kThreads - 1) / kThreads); }

using RayState = plx::RayMarch;

__device__ __forceinline__ void setup_ray(const Grid& g, const float* o, const float* d, const March& opt, RayState* r) {
    plx::setup_ray(g.lattice, o, d, opt.near, opt.step, opt.max_samples, opt.contract, r);
}

struct Sample {
    int32_t rows[8];
    float w[8];
    float delta, alpha, transmittance_factor, t_before, t;
};

// Marches one ray front to back and calls visit(sample, density, interp) for each sample that
// passes the occupancy test and the density threshold; `interp` holds the first C interpolated
// columns of the sample's row (rounded up to whole float4s; C = 1 needs only the density, already
// at hand). visit returns the transmittance after the sample; the march stops below the threshold.
// Returns the final transmittance.
template <int C, typename Visit>
__device__ float march(const Grid& g, const RayState& ray, const March& opt, Visit visit) {
    float transmittance = 1.0f;
    RayState r = ray;  // a lattice ray lays out its pieces as it goes
    const int S = g.stride;
    plx::MarchWalk walk = plx::march_start(r);
    while (plx::next_sample(g.res, g.bres, g.block, g.block_occ, g.cell_occ, g.lattice, &r, &walk)) {
        Sample s;
        plx::trilinear(walk.p, g.res, walk.cell, s.w);
        float raw_density = 0.0f;
#pragma unroll
        for (int c = 0; c < 8; ++c) {
            s.rows[c] = g.links[plx::corner_index(walk.cell, g.res, c)];
            if (s.rows[c] >= 0) raw_density += s.w[c] * g.data[(int64_t)s.rows[c] * S];
        }
        if (!(raw_density > opt.sigma_threshold)) continue;
        float interp[4 * float4s(C)];
        if constexpr (C == 1) {
            interp[0] = raw_density;
        } else {
#pragma unroll
            for (int k = 0; k < 4 * float4s(C); ++k) interp[k] = 0.0f;
#pragma unroll
            for (int c = 0; c < 8; ++c) {
                if (s.rows[c] < 0) continue;
                const float4* row = reinterpret_cast<const float4*>(g.data + (int64_t)s.rows[c] * S);
                const float w = s.w[c];
#pragma unroll
                for (int q = 0; q < float4s(C); ++q) {
                    const float4 v = __ldg(row + q);
                    interp[4 * q] += w * v.x;
                    interp[4 * q + 1] += w * v.y;
                    interp[4 * q + 2] += w * v.z;
                    interp[4 * q + 3] += w * v.w;
                }
            }
        }
        s.delta = (float)walk.delta;
        s.alpha = plx::sample_alpha(raw_density, s.delta, &s.transmittance_factor);
        s.t_before = transmittance;
        s.t = (float)walk.t;
        transmittance = visit(s, raw_density, interp);
        if (transmittance < opt.stop_transmittance) break;
    }
    return transmittance;
}

template <int D>
__global__ void render_kernel(Grid g, March opt, Rays rays, float* __restrict__ rgb, float* __restrict__ depth,
                              float* __restrict__ opacity) {
    constexpr int K = (D + 1) * (D + 1);
    const int64_t b = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
    if (b >= rays.count) return;
    RayState r;
    setup_ray(g, rays.origins + 3 * b, rays.dirs + 3 * b, opt, &r);
    float basis[16];
    plx::sh_basis(D, r.dir[0], r.dir[1], r.dir[2], basis);
    float acc[3] = {0.0f, 0.0f, 0.0f}, acc_depth = 0.0f;
    const float t_final = march<1 + 3 * K>(g, r, opt, [&](const Sample& s, float, const float* row) {
        const float w = s.t_before * s.alpha;
        for (int ch = 0; ch < 3; ++ch) {
            float raw;
            acc[ch] += w * plx::sh_colour(row + 1 + ch * K, basis, K, &raw);
        }
        acc_depth += w * s.t;
        return s.t_before * s.transmittance_factor;
    });
    const float light = plx::light_past_grid(t_final, opt.background_stop);  // as the CPU's render
    for (int ch = 0; ch < 3; ++ch)
        rgb[3 * b + ch] = acc[ch] + (rays.background ? light * rays.background[3 * b + ch] : 0.0f);
    depth[b] = acc_depth;
    opacity[b] = 1.0f - t_final;
}

template <int D>
__global__ void loss_grad_kernel(Grid g, March opt, Rays rays, const float* __restrict__ targets, float loss_scale,
                                 float near_gradient, double* __restrict__ sse, float* __restrict__ grad_background,
                                 float* __restrict__ grad, uint8_t* __restrict__ mask) {
    constexpr int K = (D + 1) * (D + 1);
    constexpr int C = 1 + 3 * K;
    const int64_t b = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
    if (b >= rays.count) return;
    RayState r;
    setup_ray(g, rays.origins + 3 * b, rays.dirs + 3 * b, opt, &r);
    float basis[16];
    plx::sh_basis(D, r.dir[0], r.dir[1], r.dir[2], basis);
    float acc[3] = {0.0f, 0.0f, 0.0f};
    const float t_final = march<C>(g, r, opt, [&](const Sample& s, float, const float* row) {
        const float w = s.t_before * s.alpha;
        for (int ch = 0; ch < 3; ++ch) {
            float raw;
            acc[ch] += w * plx::sh_colour(row + 1 + ch * K, basis, K, &raw);
        }
        return s.t_before * s.transmittance_factor;
    });
    // As the CPU's loss: the background's share, and the rate at which it answers the density.
    const float light = plx::light_past_grid(t_final, opt.background_stop);
    const float rate_less_share = plx::light_past_grid_rate(t_final, opt.background_stop) - light;
    float total[3], dl_drgb[3];
    double sq = 0.0;
    for (int ch = 0; ch < 3; ++ch) {
        total[ch] = acc[ch] + light * rays.background[3 * b + ch];
        const float err = plx::colour_error(total[ch], targets[3 * b + ch]);
        sq += (double)err * err;
        dl_drgb[ch] = 2.0f * loss_scale * err;
        grad_background[3 * b + ch] = dl_drgb[ch] * light;
    }
    sse[b] = sq;
    // Backward: march the same samples again; what lies behind each one follows from the total.
    const int S = g.stride;
    float front[3] = {0.0f, 0.0f, 0.0f};
    march<C>(g, r, opt, [&](const Sample& s, float, const float* row) {
        const float w = s.t_before * s.alpha;
        const float t_after = s.t_before * s.transmittance_factor;
        const float share = plx::near_gradient_scale(s.t, near_gradient);
        float grow[4 * float4s(C)];
#pragma unroll
        for (int k = C; k < 4 * float4s(C); ++k) grow[k] = 0.0f;
        float dsigma = 0.0f;
        for (int ch = 0; ch < 3; ++ch) {
            float raw;
            const float colour = plx::sh_colour(row + 1 + ch * K, basis, K, &raw);
            front[ch] += w * colour;
            const float behind = total[ch] - front[ch] + rate_less_share * rays.background[3 * b + ch];
            dsigma += dl_drgb[ch] * plx::dcolour_dsigma(s.delta, t_after, colour, behind);
            const float dc = share * dl_drgb[ch] * w * plx::colour_relu_grad(raw);
            for (int k = 0; k < K; ++k) grow[1 + ch * K + k] = dc * basis[k];
        }
        grow[0] = share * dsigma;
        for (int c = 0; c < 8; ++c) {
            const int32_t row_index = s.rows[c];
            if (row_index < 0) continue;
            mask[row_index] = 1;
            float* dst = grad + (int64_t)row_index * S;
            const float wc = s.w[c];
#pragma unroll
            for (int q = 0; q < float4s(C); ++q) {
                const float4 v = make_float4(wc * grow[4 * q], wc * grow[4 * q + 1], wc * grow[4 * q + 2],
                                             wc * grow[4 * q + 3]);
                if (v.x == 0.0f && v.y == 0.0f && v.z == 0.0f && v.w == 0.0f) continue;
#if __CUDA_ARCH__ >= 900
                atomicAdd(reinterpret_cast<float4*>(dst) + q, v);  // one vector atomic per 4 columns
#else
                atomicAdd(dst + 4 * q, v.x);
                atomicAdd(dst + 4 * q + 1, v.y);
                atomicAdd(dst + 4 * q + 2, v.z);
                atomicAdd(dst + 4 * q + 3, v.w);
#endif
            }
        }
        return t_after;
    });
}

__global__ void max_weights_kernel(Grid g, March opt, Rays rays, unsigned int* __restrict__ out_bits) {
    const int64_t b = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
    if (b >= rays.count) return;
    RayState r;
    setup_ray(g, rays.origins + 3 * b, rays.dirs + 3 * b, opt, &r);
    march<1>(g, r, opt, [&](const Sample& s, float, const float*) {
        const float w = s.t_before * s.alpha;
        // Non-negative floats order like their bit patterns, so an integer max is a float max.
        const unsigned int bits = __float_as_uint(w);
        for (int c = 0; c < 8; ++c) {
            if (s.rows[c] < 0 || s.w[c] <= 0.0f) continue;
            atomicMax(out_bits + s.rows[c], bits);
        }
        return s.t_before * s.transmittance_factor;
    });
}

__global__ void sample_counts_kernel(Grid g, March opt, Rays rays, unsigned long long* __restrict__ counts) {
    const int64_t b = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
    if (b >= rays.count) return;
    RayState r;
    setup_ray(g, rays.origins + 3 * b, rays.dirs + 3 * b, opt, &r);
    unsigned long long used = 0;
    march<1>(g, r, opt, [&](const Sample& s, float, const float*) {
        ++used;
        return s.t_before * s.transmittance_factor;
    });
    const int lattice = plx::ray_length_samples(g.res, g.lattice, r);
    if (lattice > 0) atomicAdd(counts, (unsigned long long)lattice);
    if (used > 0) atomicAdd(counts + 1, used);
}

// Adds `delta` to the live count of every occupancy block that has vertex `xyz` as a cell corner:
// blocks b with b*block <= x <= (b+1)*block on every axis.
__device__ void add_live_vertex(const int32_t* xyz, const LiveBlocks& live, int delta) {
    int lo[3], hi[3];
    for (int a = 0; a < 3; ++a) {
        const int first = (xyz[a] + live.block - 1) / live.block - 1;
        const int last = xyz[a] / live.block;
        lo[a] = first > 0 ? first : 0;
        hi[a] = last < live.nblocks[a] - 1 ? last : live.nblocks[a] - 1;
    }
    for (int x = lo[0]; x <= hi[0]; ++x)
        for (int y = lo[1]; y <= hi[1]; ++y)
            for (int z = lo[2]; z <= hi[2]; ++z)
                atomicAdd(live.counts + ((int64_t)x * live.nblocks[1] + y) * live.nblocks[2] + z, delta);
}

__global__ void live_count_kernel(const float* __restrict__ data, int stride, int64_t rows, LiveBlocks live) {
    const int64_t r = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
    if (r >= rows || !(data[r * stride] > 0.0f)) return;
    add_live_vertex(live.coords + 3 * r, live, 1);
}

__global__ void live_flags_kernel(LiveBlocks live, int64_t count) {
    const int64_t b = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
    if (b < count) live.blocks[b] = live.counts[b] > 0;
}

__global__ void tv_kernel(TVArgs a, double* __restrict__ loss_out, float* __restrict__ grad,
                          uint8_t* __restrict__ mask) {
    const int64_t m = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
    if (m >= a.count) return;
    const int32_t row = (int32_t)a.sample_rows[m];
    const int32_t* p = a.coords + 3 * (int64_t)row;
    int32_t nb[3];
    for (int axis = 0; axis < 3; ++axis) {
        int q[3] = {p[0], p[1], p[2]};
        q[axis] += 1;
        nb[axis] = q[axis] < a.res[axis] ? a.links[((int64_t)q[0] * a.res[1] + q[1]) * a.res[2] + q[2]] : -1;
    }
    double loss = 0.0;
    if (nb[0] >= 0 || nb[1] >= 0 || nb[2] >= 0) {
        mask[row] = 1;
        for (int axis = 0; axis < 3; ++axis)
            if (nb[axis] >= 0) mask[nb[axis]] = 1;
        const float* v = a.data + (int64_t)row * a.stride;
        for (int k = a.column_begin; k < a.column_end; ++k) {
            const float scale = k == 0 ? a.scale_density : a.scale_sh;
            float diff[3];
            for (int axis = 0; axis < 3; ++axis)
                diff[axis] = nb[axis] >= 0 ? a.data[(int64_t)nb[axis] * a.stride + k] - v[k] : 0.0f;
            float inv;
            loss += scale * plx::tv_term(diff[0], diff[1], diff[2], &inv);
            float self = 0.0f;
            for (int axis = 0; axis < 3; ++axis) {
                if (nb[axis] < 0) continue;
                const float gd = scale * diff[axis] * inv;
                atomicAdd(grad + (int64_t)nb[axis] * a.stride + k, gd);
                self -= gd;
            }
            atomicAdd(grad + (int64_t)row * a.stride + k, self);
        }
    }
    loss_out[m] = loss;
}

__global__ void rmsprop_kernel(RMSPropArgs a, LiveBlocks live) {
    const int64_t i = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= a.count * a.columns) return;
    const int64_t j = i / a.columns;
    const int k = (int)(i - j * a.columns);
    const int64_t row = a.rows[j];
    const int64_t at = row * a.stride + k;
    const float before = a.data[at];
    const float gk = a.grad_data[at];
    const float vk = a.beta * a.second_moment[at] + a.one_minus_beta * gk * gk;
    a.second_moment[at] = vk;
    const float after = before - (k == 0 ? a.lr_density : a.lr_sh) * gk / (sqrtf(vk) + a.eps);
    a.data[at] = after;
    a.grad_data[at] = 0.0f;
    if (k != 0) return;
    a.grad_mask[row] = 0;
    const bool was_live = before > 0.0f, is_live = after > 0.0f;
    if (live.coords && was_live != is_live) add_live_vertex(live.coords + 3 * row, live, is_live ? 1 : -1);
}

__global__ void cell_occupancy_kernel(const int32_t* __restrict__ links, int rx, int ry, int rz,
                                      uint8_t* __restrict__ cells) {
    const int64_t i = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
    const int64_t cy = ry - 1, cz = rz - 1;
    if (i >= (int64_t)(rx - 1) * cy * cz) return;
    const int64_t x = i / (cy * cz), y = (i / cz) % cy, z = i % cz;
    bool any = false;
    for (int k = 0; k < 8 && !any; ++k)
        any = links[((x + ((k >> 2) & 1)) * ry + y + ((k >> 1) & 1)) * rz + z + (k & 1)] >= 0;
    cells[i] = any;
}

__global__ void block_occupancy_kernel(const uint8_t* __restrict__ cells, int cx, int cy, int cz, int block,
                                       int bx, int by, int bz, uint8_t* __restrict__ blocks) {
    const int64_t i = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= (int64_t)bx * by * bz) return;
    const int x = (int)(i / ((int64_t)by * bz)), y = (int)((i / bz) % by), z = (int)(i % bz);
    bool any = false;
    for (int a = x * block; a < min((x + 1) * block, cx) && !any; ++a)
        for (int b = y * block; b < min((y + 1) * block, cy) && !any; ++b)
            for (int c = z * block; c < min((z + 1) * block, cz) && !any; ++c)
                any = cells[((int64_t)a * cy + b) * cz + c];
    blocks[i] = any;
}

__global__ void row_coords_kernel(const int32_t* __restrict__ links, int ry, int rz, int64_t total, int64_t rows,
                                  int32_t* __restrict__ out) {
    const int64_t i = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= total) return;
    const int32_t r = links[i];
    if (r < 0 || r >= rows) return;
    out[3 * (int64_t)r] = (int32_t)(i / ((int64_t)ry * rz));
    out[3 * (int64_t)r + 1] = (int32_t)((i / rz) % ry);
    out[3 * (int64_t)r + 2] = (int32_t)(i % rz);
}

__global__ void sample_kernel(const float* __restrict__ data, int stride, const int32_t* __restrict__ links,
                              int rx, int ry, int rz, const float* __restrict__ points, int64_t count,
                              float* __restrict__ out) {
    const int64_t p = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
    if (p >= count) return;
    const int res[3] = {rx, ry, rz};
    plx::interpolate_point(data, stride, links, res, points + 3 * p, out + p * stride);
}

// The multi-sphere background: one thread per ray, the per-ray math of plenoxels_math.h.
__global__ void background_render_kernel(Background bg, Rays rays, float* __restrict__ rgb) {
    const int64_t b = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
    if (b >= rays.count) return;
    double rel[3], unit[3];
    plx::bg_ray(rays.origins + 3 * b, rays.dirs + 3 * b, bg.centre, rel, unit);
    plx::bg_forward(bg.texture, bg.radii, bg.spheres, bg.height, bg.width, rel, unit, bg.far_colour, rgb + 3 * b);
}

struct AtomicTexelSink {
    float* grad;
    uint8_t* mask;
    __device__ void operator()(int texel, const float g[4]) const {
        for (int c = 0; c < 4; ++c) atomicAdd(grad + 4 * (int64_t)texel + c, g[c]);
        mask[texel] = 1;
    }
};

__global__ void background_backward_kernel(Background bg, Rays rays, const float* __restrict__ rgb,
                                           const float* __restrict__ grad_rgb, float* __restrict__ grad_texture,
                                           uint8_t* __restrict__ grad_mask) {
    const int64_t b = (int64_t)blockIdx.x * blockDim.x + threadIdx.x;
    if (b >= rays.count) return;
    double rel[3], unit[3];
    plx::bg_ray(rays.origins + 3 * b, rays.dirs + 3 * b, bg.centre, rel, unit);
    plx::bg_backward(bg.texture, bg.radii, bg.spheres, bg.height, bg.width, rel, unit, rgb + 3 * b, grad_rgb + 3 * b,
                     AtomicTexelSink{grad_texture, grad_mask});
}

}  // namespace

#define PLX_CUDA_DEGREE(degree, ...)                   \
    switch (degree) {                                  \
        case 0: { constexpr int D = 0; __VA_ARGS__; } break; \
        case 1: { constexpr int D = 1; __VA_ARGS__; } break; \
        case 2: { constexpr int D = 2; __VA_ARGS__; } break; \
        case 3: { constexpr int D = 3; __VA_ARGS__; } break; \
        default: return cudaErrorInvalidValue;         \
    }

cudaError_t render(const Grid& grid, const March& march, int degree, const Rays& rays, float* rgb, float* depth,
                   float* opacity, cudaStream_t stream) {
    if (rays.count == 0) return cudaSuccess;
    PLX_CUDA_DEGREE(degree, render_kernel<D><<<blocks_for(rays.count), kThreads, 0, stream>>>(
                                grid, march, rays, rgb, depth, opacity));
    return cudaGetLastError();
}

cudaError_t loss_and_grad(const Grid& grid, const March& march, int degree, const Rays& rays, const float* targets,
                          float loss_scale, float near_gradient, double* sse_per_ray, float* grad_background,
                          float* grad_data, uint8_t* grad_mask, cudaStream_t stream) {
    if (rays.count == 0) return cudaSuccess;
    PLX_CUDA_DEGREE(degree, loss_grad_kernel<D><<<blocks_for(rays.count), kThreads, 0, stream>>>(
                                grid, march, rays, targets, loss_scale, near_gradient, sse_per_ray, grad_background, grad_data,
                                grad_mask));
    return cudaGetLastError();
}

cudaError_t max_weights(const Grid& grid, const March& march, const Rays& rays, float* out, cudaStream_t stream) {
    if (rays.count == 0) return cudaSuccess;
    max_weights_kernel<<<blocks_for(rays.count), kThreads, 0, stream>>>(grid, march, rays,
                                                                       reinterpret_cast<unsigned int*>(out));
    return cudaGetLastError();
}

cudaError_t sample_counts(const Grid& grid, const March& march, const Rays& rays, unsigned long long* counts,
                          cudaStream_t stream) {
    if (rays.count == 0) return cudaSuccess;
    sample_counts_kernel<<<blocks_for(rays.count), kThreads, 0, stream>>>(grid, march, rays, counts);
    return cudaGetLastError();
}

// Flags from counts over every block: exact whatever order the count updates ran in.
static cudaError_t write_live_flags(const LiveBlocks& live, cudaStream_t stream) {
    const int64_t count = (int64_t)live.nblocks[0] * live.nblocks[1] * live.nblocks[2];
    if (count == 0) return cudaSuccess;
    live_flags_kernel<<<blocks_for(count), kThreads, 0, stream>>>(live, count);
    return cudaGetLastError();
}

cudaError_t count_live_blocks(const float* data, int stride, int64_t rows, const LiveBlocks& live,
                              cudaStream_t stream) {
    const int64_t count = (int64_t)live.nblocks[0] * live.nblocks[1] * live.nblocks[2];
    cudaError_t err = cudaMemsetAsync(live.counts, 0, count * sizeof(int32_t), stream);
    if (err != cudaSuccess) return err;
    if (rows > 0) live_count_kernel<<<blocks_for(rows), kThreads, 0, stream>>>(data, stride, rows, live);
    err = cudaGetLastError();
    return err != cudaSuccess ? err : write_live_flags(live, stream);
}

cudaError_t tv_loss_and_grad(const TVArgs& args, double* loss_per_sample, float* grad_data, uint8_t* grad_mask,
                             cudaStream_t stream) {
    if (args.count == 0) return cudaSuccess;
    tv_kernel<<<blocks_for(args.count), kThreads, 0, stream>>>(args, loss_per_sample, grad_data, grad_mask);
    return cudaGetLastError();
}

cudaError_t rmsprop_step(const RMSPropArgs& args, const LiveBlocks& live, cudaStream_t stream) {
    const int64_t n = args.count * args.columns;
    if (n == 0) return cudaSuccess;
    rmsprop_kernel<<<blocks_for(n), kThreads, 0, stream>>>(args, live);
    const cudaError_t err = cudaGetLastError();
    return err != cudaSuccess || !live.coords ? err : write_live_flags(live, stream);
}

cudaError_t build_occupancy(const int32_t* links, const int res[3], int block, uint8_t* cells, uint8_t* blocks,
                            cudaStream_t stream) {
    const int cx = res[0] - 1, cy = res[1] - 1, cz = res[2] - 1;
    const int bx = (cx + block - 1) / block, by = (cy + block - 1) / block, bz = (cz + block - 1) / block;
    const int64_t ncells = (int64_t)cx * cy * cz, nblocks = (int64_t)bx * by * bz;
    if (ncells == 0) return cudaSuccess;
    cell_occupancy_kernel<<<blocks_for(ncells), kThreads, 0, stream>>>(links, res[0], res[1], res[2], cells);
    block_occupancy_kernel<<<blocks_for(nblocks), kThreads, 0, stream>>>(cells, cx, cy, cz, block, bx, by, bz,
                                                                        blocks);
    return cudaGetLastError();
}

cudaError_t row_coords(const int32_t* links, const int res[3], int64_t rows, int32_t* out, cudaStream_t stream) {
    const int64_t total = (int64_t)res[0] * res[1] * res[2];
    if (total == 0) return cudaSuccess;
    row_coords_kernel<<<blocks_for(total), kThreads, 0, stream>>>(links, res[1], res[2], total, rows, out);
    return cudaGetLastError();
}

cudaError_t sample(const float* data, int stride, const int32_t* links, const int res[3], const float* points,
                   int64_t count, float* out, cudaStream_t stream) {
    if (count == 0) return cudaSuccess;
    sample_kernel<<<blocks_for(count), kThreads, 0, stream>>>(data, stride, links, res[0], res[1], res[2], points, count,
                                                              out);
    return cudaGetLastError();
}

cudaError_t background_render(const Background& bg, const Rays& rays, float* rgb, cudaStream_t stream) {
    if (rays.count == 0) return cudaSuccess;
    background_render_kernel<<<blocks_for(rays.count), kThreads, 0, stream>>>(bg, rays, rgb);
    return cudaGetLastError();
}

cudaError_t background_backward(const Background& bg, const Rays& rays, const float* rgb, const float* grad_rgb,
                                float* grad_texture, uint8_t* grad_mask, cudaStream_t stream) {
    if (rays.count == 0) return cudaSuccess;
    background_backward_kernel<<<blocks_for(rays.count), kThreads, 0, stream>>>(bg, rays, rgb, grad_rgb, grad_texture,
                                                                                 grad_mask);
    return cudaGetLastError();
}

}  // namespace plx_cuda
