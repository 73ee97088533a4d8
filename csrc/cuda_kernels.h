// Launchers of the CUDA kernels (kernels_cuda.cu). Plain pointers and sizes, no torch, so the .cu
// file compiles with nvcc and this header alone (the compile-only check in tests/test_cuda.py);
// bindings_cuda.cpp turns torch tensors into these arguments.
//
// Layouts are those of the CPU core (cpu_kernels.h): a packed parameter table `data` [N, stride]
// (column 0 raw density, then K SH coefficients per channel R, G, B, then padding), `links`
// [Rx, Ry, Rz] int32 (row or -1), cell and block occupancy as uint8. Gradients use the same layout.
// Instead of the CPU's per-thread touched-row lists, the kernels set grad_mask[row] = 1 (a plain
// byte store: every writer stores the same value) and the caller compacts the mask into rows.
#pragma once

#include <cuda_runtime_api.h>
#include <stdint.h>

#include "plenoxels_math.h"

namespace plx_cuda {

struct Grid {
    const float* data;
    const int32_t* links;
    const uint8_t* cell_occ;   // [Rx-1, Ry-1, Rz-1]
    const uint8_t* block_occ;  // [ceil((Rx-1)/block), ...]
    int stride;                // columns of a data row
    int res[3];
    int block;
    int bres[3];
    plx::Lattice lattice;  // fit frame -> grid coordinates
};

struct March {
    double step;  // grid units
    float stop_transmittance;
    double near;
    float sigma_threshold;
    int max_samples;
    bool contract;  // the grid is in contracted space (plx::contract_point)
    float background_stop = 0.0f;  // as the CPU's MarchOptions
};

struct Rays {
    const float* origins;     // [B, 3]
    const float* dirs;        // [B, 3], any length
    const float* background;  // [B, 3] or null (render only)
    int64_t count;
};

// Colour, expected depth and opacity per ray.
cudaError_t render(const Grid& grid, const March& march, int degree, const Rays& rays, float* rgb, float* depth,
                   float* opacity, cudaStream_t stream);

// Mean squared error over the batch (sum of squares written per ray into sse_per_ray) and its
// gradient, added into grad_data (each sample's share plx::near_gradient_scale); grad_background gets d loss /
// d background per ray.
cudaError_t loss_and_grad(const Grid& grid, const March& march, int degree, const Rays& rays, const float* targets,
                          float loss_scale, float near_gradient, double* sse_per_ray, float* grad_background, float* grad_data,
                          uint8_t* grad_mask, cudaStream_t stream);

// out[row] = max(out[row], largest compositing weight of any sample that interpolates the row).
cudaError_t max_weights(const Grid& grid, const March& march, const Rays& rays, float* out, cudaStream_t stream);

// Over all rays: samples on the rays' lattices inside the box, and samples that contributed (passed
// the occupancy test and the density threshold before the ray stopped); added into counts[0..1].
cudaError_t sample_counts(const Grid& grid, const March& march, const Rays& rays, unsigned long long* counts,
                          cudaStream_t stream);

// Live-vertex bookkeeping for empty-space skipping: a vertex is live when its raw density is > 0;
// counts[b] is the number of live vertices that are a cell corner in occupancy block b, and
// blocks[b] = counts[b] > 0. A block with no live vertex holds no sample with density > 0.
struct LiveBlocks {
    const int32_t* coords;  // [N, 3] grid coordinates of each row; null: no bookkeeping
    int block;
    int nblocks[3];
    int32_t* counts;
    uint8_t* blocks;
};
// Recounts from scratch (counts and blocks are overwritten).
cudaError_t count_live_blocks(const float* data, int stride, int64_t rows, const LiveBlocks& live,
                              cudaStream_t stream);

// Total variation at the rows sample_rows[0..count): loss_per_sample[m] gets the sample's term,
// gradients are added into grad_data. Columns [column_begin, column_end) take part; column 0 is
// scaled by scale_density, the others by scale_sh.
struct TVArgs {
    const float* data;
    int stride;
    const int32_t* links;
    int res[3];
    const int32_t* coords;  // [N, 3] grid coordinates of each row
    const int64_t* sample_rows;
    int64_t count;
    int column_begin, column_end;
    float scale_density, scale_sh;
};
cudaError_t tv_loss_and_grad(const TVArgs& args, double* loss_per_sample, float* grad_data, uint8_t* grad_mask,
                             cudaStream_t stream);

// RMSProp on rows[0..count) and columns [0, columns); clears their gradient and mask. With live
// bookkeeping (live.coords not null), a row whose density changes sign updates the counts, and the
// block flags are then rewritten from the counts.
struct RMSPropArgs {
    float* data;
    float* second_moment;
    float* grad_data;
    uint8_t* grad_mask;
    const int32_t* rows;
    int64_t count;
    int stride, columns;
    float lr_density, lr_sh, beta, one_minus_beta, eps;  // 1 - beta rounded from double, as on the CPU
};
cudaError_t rmsprop_step(const RMSPropArgs& args, const LiveBlocks& live, cudaStream_t stream);

// Cell occupancy (any corner allocated) and block occupancy (any cell occupied).
cudaError_t build_occupancy(const int32_t* links, const int res[3], int block, uint8_t* cells, uint8_t* blocks,
                            cudaStream_t stream);

// out[p] = trilinear interpolation of the stride columns at grid point points[p] (zeros outside the box).
cudaError_t sample(const float* data, int stride, const int32_t* links, const int res[3], const float* points,
                   int64_t count, float* out, cudaStream_t stream);

// out[row] = (x, y, z) of every allocated row below `rows`; out must be prefilled with -1.
cudaError_t row_coords(const int32_t* links, const int res[3], int64_t rows, int32_t* out, cudaStream_t stream);

// The multi-sphere background (device pointers): centre [3], radii [K], texture [K, H, W, 4], far_colour [3].
struct Background {
    const float* centre;
    const float* radii;
    const float* texture;
    const float* far_colour;
    int spheres, height, width;
};

// Colour [B, 3] of each ray behind everything.
cudaError_t background_render(const Background& bg, const Rays& rays, float* rgb, cudaStream_t stream);

// Adds d loss / d texel rows [K*H*W, 4] from the rays' colours (background_render's) and d loss / d colour [B, 3],
// and sets grad_mask on the texels it touched.
cudaError_t background_backward(const Background& bg, const Rays& rays, const float* rgb, const float* grad_rgb,
                                float* grad_texture, uint8_t* grad_mask, cudaStream_t stream);

}  // namespace plx_cuda
