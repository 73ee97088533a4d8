// The CPU core's shared parts: the grid as the kernels see it, the ray march every rendering op runs, per-thread
// gradient accumulation, the live-block bookkeeping of empty-space skipping, and the checks of the operators'
// arguments. All per-sample math comes from plenoxels_math.h, shared with the CUDA kernels.
//
// Parameters live in one packed table `data` [N, S]: column 0 is raw density, columns 1..3K the SH
// coefficients (K per channel, R then G then B), the rest padding so that rows are whole vectors.
// Gradients use the same layout. Each thread accumulates into its own buffer of the caller's
// scratch (grad_scratch: zero pages mapped on first touch; the first thread writes straight into the
// caller's gradient), and a thread records which rows it touched, so no step ever zeroes or scans
// the whole grid.
#pragma once

#include <ATen/ATen.h>
#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <tuple>
#include <vector>

#include "ops.h"
#include "plenoxels_math.h"

namespace plx_cpu {

using plx::row_stride;

using at::Tensor;

struct GridView {
    const float* data;
    const int32_t* links;
    const uint8_t* cell_occ;   // [Rx-1, Ry-1, Rz-1]: any corner allocated
    const uint8_t* block_occ;  // cells grouped in cubes of `block`: any cell occupied
    int res[3];
    int block;
    int bres[3];
    plx::Lattice lattice;  // fit frame -> grid coordinates
    int64_t corner_offset[8];  // links index of corner c less that of corner 0 (plx::corner_index)
};

struct MarchOptions {
    double step;  // grid units
    float stop_transmittance;
    double near;
    float sigma_threshold;
    int max_samples;
    bool contract;  // the grid is in contracted space (plx::contract_point)
    // Below this transmittance a ray shows nothing of the background (plx::light_past_grid): the march's stop where
    // the background is the spheres, drawn only where light gets past the grid; 0 where it shows on every ray.
    float background_stop = 0.0f;
};

using Ray = plx::RayMarch;

GridView make_view(const at::Tensor& data, const at::Tensor& links, const at::Tensor& cell_occ,
                   const at::Tensor& block_occ, int block, c10::ArrayRef<double> lattice);

inline void setup_ray(const GridView& g, const float* o, const float* d, const MarchOptions& opt, Ray* r) {
    plx::setup_ray(g.lattice, o, d, opt.near, opt.step, opt.max_samples, opt.contract, r);
}

using plx::cell_of;

// How many samples ahead the march prefetches rows (about two cells at the default step of 0.5).
constexpr int kLookahead = 4;

// Loads the cache lines of `count` floats from `row` ahead of their use (for writing: in a state that takes a write).
inline void prefetch_floats(const float* row, int64_t count, bool for_write) {
    for (int64_t k = 0; k < count; k += 16) {
        if (for_write)
            __builtin_prefetch(row + k, 1, 3);
        else
            __builtin_prefetch(row + k, 0, 3);
    }
}

template <int S>
inline void prefetch_row(const float* row, bool for_write) {
    prefetch_floats(row, S, for_write);
}

// What an unallocated corner holds (rows are at most this long).
alignas(64) constexpr float kZeroRow[row_stride(3)] = {};

// A sample that passed empty-space skipping and has density above the threshold.
struct Sample {
    int32_t rows[8];
    float w[8];
    float sigma, delta, alpha, transmittance_factor, t_before, t;
    float colour[3], raw[3];
};

// Marches one ray and calls visit(sample, shading) for each contributing sample in front-to-back
// order; visit returns the transmittance after the sample, and the march stops below the threshold.
// `interp` receives the interpolated row (density and SH) of the sample.
template <int S, typename Visit>
inline float march(const GridView& g, const Ray& ray, const MarchOptions& opt, float* interp, Visit visit) {
    float transmittance = 1.0f;
    Ray r = ray;  // a lattice ray lays out its pieces as it goes
    plx::MarchWalk walk = plx::march_start(r);
    // The far stage's cells by sample index, so that the near stage finds a cell it already located.
    struct Ahead {
        int i = -1;
        int cell[3];
    } ahead[2 * kLookahead];
    while (plx::next_sample(g.res, g.bres, g.block, g.block_occ, g.cell_occ, g.lattice, &r, &walk)) {
        const int* cell = walk.cell;
        // Rows scattered over hundreds of MB miss the cache, so the march loads ahead in two stages: the links (and
        // occupancy) of the cell 2 kLookahead samples ahead, then the rows of the cell kLookahead ahead, whose links
        // the first stage has brought in; each stage's misses overlap the work on this sample.
        if (walk.i - 1 + 2 * kLookahead < r.n) {
            float q[3];
            plx::point_ahead(g.res, g.lattice, r, walk, 2 * kLookahead, q);
            Ahead& slot = ahead[(walk.i - 1) % (2 * kLookahead)];
            slot.i = walk.i - 1 + 2 * kLookahead;
            int* far = slot.cell;
            for (int a = 0; a < 3; ++a) far[a] = cell_of(q[a], g.res[a]);
            const int32_t* links = g.links + plx::corner_index(far, g.res, 0);
            for (int c = 0; c < 8; c += 2) __builtin_prefetch(links + g.corner_offset[c], 0, 3);
            __builtin_prefetch(g.cell_occ + plx::cell_index(g.res, far), 0, 3);
        }
        if (walk.i - 1 + kLookahead < r.n) {
            const Ahead& slot = ahead[(walk.i - 1 + kLookahead) % (2 * kLookahead)];
            int next[3];
            if (slot.i == walk.i - 1 + kLookahead) {
                for (int a = 0; a < 3; ++a) next[a] = slot.cell[a];
            } else {
                float q[3];
                plx::point_ahead(g.res, g.lattice, r, walk, kLookahead, q);
                for (int a = 0; a < 3; ++a) next[a] = cell_of(q[a], g.res[a]);
            }
            if (next[0] != cell[0] || next[1] != cell[1] || next[2] != cell[2]) {
                const int32_t* links = g.links + plx::corner_index(next, g.res, 0);
                for (int c = 0; c < 8; ++c) {
                    const int32_t row = links[g.corner_offset[c]];
                    if (row < 0) continue;
                    prefetch_row<S>(g.data + (int64_t)row * S, false);
                }
            }
        }
        Sample s;
        plx::trilinear(walk.p, g.res, walk.cell, s.w);
        // An unallocated corner reads a row of zeros, so the sums below run without branches, in registers.
        const float* corner[8];
        float raw_density = 0.0f;
        const int32_t* links = g.links + plx::corner_index(cell, g.res, 0);
        for (int c = 0; c < 8; ++c) {
            s.rows[c] = links[g.corner_offset[c]];
            corner[c] = s.rows[c] >= 0 ? g.data + (int64_t)s.rows[c] * S : kZeroRow;
            raw_density += s.w[c] * corner[c][0];
        }
        if (!(raw_density > opt.sigma_threshold)) continue;
#pragma omp simd
        for (int k = 0; k < S; ++k) {
            float v = 0.0f;
            for (int c = 0; c < 8; ++c) v += s.w[c] * corner[c][k];
            interp[k] = v;
        }
        s.sigma = raw_density;
        s.delta = (float)walk.delta;
        s.alpha = plx::sample_alpha(s.sigma, s.delta, &s.transmittance_factor);
        s.t_before = transmittance;
        s.t = (float)walk.t;
        transmittance = visit(s, interp);
        if (transmittance < opt.stop_transmittance) break;
    }
    return transmittance;
}

// Asks the kernel to back [ptr, ptr + bytes) with 2 MiB pages where the system allows it
// (transparent huge pages in `madvise` mode). Random row access over hundreds of MiB otherwise
// misses the TLB on nearly every load. Only whole 2 MiB pages inside the range are advised.
bool advise_huge_pages(void* ptr, size_t bytes);

// Per-thread gradient accumulation into the packed [N, S] layout, with touched-row bookkeeping:
// a view of the caller's scratch tensors (grad_scratch), whose slot t-1 belongs to thread t. A slot's rows
// hold whatever an earlier call left there: a thread zeroes a row when it first touches it in a call (its
// mask says which it has), so merge reads them and never writes them back, and every call leaves the
// masks clear again.
class ThreadGrads {
   public:
    ThreadGrads(const at::Tensor& grad_data, const at::Tensor& scratch_grad, const at::Tensor& scratch_mask)
        : rows_(grad_data.size(0)), stride_((int)grad_data.size(1)) {
        TORCH_CHECK(scratch_grad.device().is_cpu() && scratch_grad.scalar_type() == at::kFloat &&
                        scratch_grad.is_contiguous() && scratch_grad.dim() == 3 && scratch_grad.size(1) == rows_ &&
                        scratch_grad.size(2) == stride_,
                    "scratch gradient must be float32 [threads-1, N, S] for this grid (grad_scratch)");
        TORCH_CHECK(scratch_mask.device().is_cpu() && scratch_mask.scalar_type() == at::kByte &&
                        scratch_mask.is_contiguous() && scratch_mask.dim() == 2 &&
                        scratch_mask.size(0) == scratch_grad.size(0) && scratch_mask.size(1) == rows_,
                    "scratch mask must be uint8 [threads-1, N] (grad_scratch)");
        threads_ = std::min<int>(omp_get_max_threads(), (int)scratch_grad.size(0) + 1);
        buffers_ = scratch_grad.data_ptr<float>();
        masks_ = scratch_mask.data_ptr<uint8_t>();
        if ((int)lists_.size() < threads_) lists_.resize(threads_);
        for (auto& list : lists_) list.clear();
    }

    int stride() const { return stride_; }
    // Threads a parallel region may use: one per scratch slot plus the caller's.
    int threads() const { return threads_; }
    float* buffer(int thread) { return buffers_ + (int64_t)(thread - 1) * rows_ * stride_; }
    uint8_t* mask(int thread) { return masks_ + (int64_t)(thread - 1) * rows_; }
    std::vector<int32_t>& list(int thread) { return lists_[thread]; }

   private:
    int64_t rows_;
    int stride_;
    int threads_;
    float* buffers_;
    uint8_t* masks_;
    // The touched-row lists outlive the call (one set, behind lock_), so their memory is faulted in once, not on every
    // call as they grow: a 256^3 batch lists about a million rows a thread.
    static inline std::mutex mutex_;
    static inline std::vector<std::vector<int32_t>> lists_;
    std::lock_guard<std::mutex> lock_{mutex_};
};

// Where one thread writes gradients: thread 0 adds into the caller's tensors, the others into their scratch.
struct GradSink {
    float* buf;
    int stride;
    uint8_t* mask;
    int32_t* main_rows;  // thread 0 only: the caller's touched-row list
    int64_t* main_count;
    std::vector<int32_t>* list;  // other threads

    // The gradient row to add into, recorded as touched.
    inline float* row(int32_t r) {
        float* dst = buf + (int64_t)r * stride;
        if (mask[r]) return dst;
        mask[r] = 1;
        if (main_rows) {
            main_rows[(*main_count)++] = r;
        } else {
            list->push_back(r);
            for (int k = 0; k < stride; ++k) dst[k] = 0.0f;
        }
        return dst;
    }
};

struct GradTarget {
    float* data;
    uint8_t* mask;
    int32_t* rows;
    int64_t count;
};

inline GradSink sink_for(int thread, GradTarget* target, ThreadGrads* scratch) {
    const int S = scratch->stride();
    if (thread == 0) return GradSink{target->data, S, target->mask, target->rows, &target->count, nullptr};
    return GradSink{scratch->buffer(thread), S, scratch->mask(thread), nullptr, nullptr, &scratch->list(thread)};
}

// Adds every other thread's gradients into the caller's tensors and clears their masks. Rows new to the caller's
// list are gathered by each worker as it merges them (a row is in a thread's list once, so no two workers meet at
// a mask byte) and appended after, in no set order.
void merge(GradTarget* target, ThreadGrads* scratch, int threads);

void check_float_rows(const at::Tensor& t, const char* name);

// `background_past_grid_only`: the background shows only where light gets past the grid (MarchOptions.background_stop).
inline MarchOptions make_options(double step, double stop_transmittance, double near, double sigma_threshold,
                                 int64_t max_samples, bool contract, bool background_past_grid_only = false) {
    return MarchOptions{step, (float)stop_transmittance, near, (float)sigma_threshold, (int)max_samples, contract,
                        background_past_grid_only ? (float)stop_transmittance : 0.0f};
}

#define PLX_DISPATCH_DEGREE(degree, ...)                                     \
    switch (degree) {                                                        \
        case 0: { constexpr int D = 0; __VA_ARGS__; break; }                 \
        case 1: { constexpr int D = 1; __VA_ARGS__; break; }                 \
        case 2: { constexpr int D = 2; __VA_ARGS__; break; }                 \
        case 3: { constexpr int D = 3; __VA_ARGS__; break; }                 \
        default: TORCH_CHECK(false, "sh_degree must be 0..3, got ", std::to_string(degree)); \
    }

void check_grid(const Tensor& data, const Tensor& links, const Tensor& cell_occ, const Tensor& block_occ, int degree);

void check_rays(const Tensor& origins, const Tensor& dirs);

// Range of occupancy blocks whose cells have vertex coordinate x as a corner: b*block <= x <= (b+1)*block.
inline void blocks_of_vertex(int x, int block, int nblocks, int* first, int* last) {
    *first = std::max((x + block - 1) / block - 1, 0);
    *last = std::min(x / block, nblocks - 1);
}

// Adds `delta` to the live-vertex count of every block that has vertex `xyz` as a cell corner, and
// appends to `crossed` the blocks whose count this update took across zero (0 -> 1 or 1 -> 0). The
// flags are not written here: two threads updating one block would each write a flag from their own
// count, and the later write may be the older count (a block left marked empty while it holds a
// live vertex, so the march would skip it). Callers rewrite the flags of `crossed` blocks from the
// counts once every update is done.
inline void add_live_vertex(const int32_t* xyz, int block, const int nb[3], int32_t* counts, int delta,
                            std::vector<int64_t>* crossed) {
    int lo[3], hi[3];
    for (int a = 0; a < 3; ++a) blocks_of_vertex(xyz[a], block, nb[a], &lo[a], &hi[a]);
    for (int x = lo[0]; x <= hi[0]; ++x)
        for (int y = lo[1]; y <= hi[1]; ++y)
            for (int z = lo[2]; z <= hi[2]; ++z) {
                const int64_t b = ((int64_t)x * nb[1] + y) * nb[2] + z;
                const int32_t now = __atomic_add_fetch(counts + b, delta, __ATOMIC_RELAXED);
                if (crossed && now == (delta > 0 ? 1 : 0)) crossed->push_back(b);
            }
}

// The multi-sphere background as a kernel reads it along rays (cpu_background.cpp), with the forward's record of each
// ray's layers for its backward: texel rows [B, K, 4] int32 (-1 where the ray met no layer: a sphere it missed, one
// behind where it stopped, or every sphere of a ray that drew none) and their bilinear weights [B, K, 4].
struct Spheres {
    const float *origins, *dirs, *centre, *radii, *texture, *far_colour;
    int count, height, width;
    int32_t* texels = nullptr;
    float* weights = nullptr;
};

Spheres spheres_view(const Tensor& origins, const Tensor& dirs, const Tensor& centre, const Tensor& radii,
                     const Tensor& texture, const Tensor& far_colour, const std::optional<Tensor>& layer_texels,
                     const std::optional<Tensor>& layer_weights);

// Ray b's background colour into rgb [3], its layers recorded where there is a record; `drawn` false: black, and
// no layers recorded (a ray the grid stops sees nothing behind it).
void sphere_colour(const Spheres& s, int64_t b, bool drawn, float rgb[3]);

// The operators' CPU kernels, registered in kernels_cpu.cpp, each of its operator's signature (ops.h).
plx::op::grad_scratch grad_scratch;
plx::op::build_occupancy build_occupancy;
plx::op::count_live_blocks count_live_blocks;
plx::op::row_coords row_coords;
plx::op::sample sample;
plx::op::render render;
plx::op::loss_and_grad loss_and_grad;
plx::op::loss_and_grad_spheres loss_and_grad_spheres;
plx::op::max_weights max_weights;
plx::op::sample_counts sample_counts;
plx::op::tv_loss_and_grad tv_loss_and_grad;
plx::op::rmsprop_step rmsprop_step;
plx::op::background_render background_render;
plx::op::background_backward background_backward;
plx::op::adam_rows adam_rows;
plx::op::pixel_rays pixel_rays;
plx::op::splat_composite splat_composite;
plx::op::splat_composite_backward splat_composite_backward;

}  // namespace plx_cpu
