// CPU kernels of the Plenoxels core: render, fused loss+gradient, max weights, total variation and
// the sparse RMSProp step. All per-sample math comes from plenoxels_math.h.
//
// Parameters live in one packed table `data` [N, S]: column 0 is raw density, columns 1..3K the SH
// coefficients (K per channel, R then G then B), the rest padding so that rows are whole vectors.
// Gradients use the same layout. Each thread accumulates into its own buffer of the caller's
// scratch (grad_scratch: zero pages mapped on first touch; the first thread writes straight into the
// caller's gradient), and a thread records which rows it touched, so no step ever zeroes or scans
// the whole grid. The operator schema is declared once in ops.cpp; this file registers the CPU
// implementations.
#include <ATen/ATen.h>
#include <torch/library.h>

#include <omp.h>
#include <sys/mman.h>

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

namespace {

using plx::row_stride;

struct GridView {
    const float* data;
    const int32_t* links;
    const uint8_t* cell_occ;   // [Rx-1, Ry-1, Rz-1]: any corner allocated
    const uint8_t* block_occ;  // cells grouped in cubes of `block`: any cell occupied
    int res[3];
    int block;
    int bres[3];
    double bmin[3];
    double scale[3];
    int64_t corner_offset[8];  // links index of corner c less that of corner 0 (plx::corner_index)
};

struct MarchOptions {
    double step;  // grid units
    float stop_transmittance;
    double near;
    float sigma_threshold;
    int max_samples;
    bool contract;  // the grid is in contracted space (plx::contract_point)
};

using Ray = plx::RayMarch;

GridView make_view(const at::Tensor& data, const at::Tensor& links, const at::Tensor& cell_occ,
                   const at::Tensor& block_occ, int block, c10::ArrayRef<double> bmin, c10::ArrayRef<double> bmax) {
    TORCH_CHECK(block > 0 && (block & (block - 1)) == 0, "the occupancy block must be a power of two, got ",
                std::to_string(block));
    GridView g;
    g.data = data.data_ptr<float>();
    g.links = links.data_ptr<int32_t>();
    g.cell_occ = cell_occ.data_ptr<uint8_t>();
    g.block_occ = block_occ.data_ptr<uint8_t>();
    g.block = block;
    for (int a = 0; a < 3; ++a) {
        g.res[a] = (int)links.size(a);
        g.bres[a] = (int)block_occ.size(a);
        g.bmin[a] = bmin[a];
        g.scale[a] = (g.res[a] - 1) / (bmax[a] - bmin[a]);
    }
    const int origin[3] = {0, 0, 0};
    for (int c = 0; c < 8; ++c) g.corner_offset[c] = plx::corner_index(origin, g.res, c);
    return g;
}

void setup_ray(const GridView& g, const float* o, const float* d, const MarchOptions& opt, Ray* r) {
    plx::setup_ray(g.res, g.bmin, g.scale, o, d, opt.near, opt.step, opt.max_samples, opt.contract, r);
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
inline float march(const GridView& g, const Ray& r, const MarchOptions& opt, float* interp, Visit visit) {
    float transmittance = 1.0f;
    plx::MarchWalk walk = plx::march_start(r);
    // The far stage's cells by sample index, so that the near stage finds a cell it already located.
    struct Ahead {
        int i = -1;
        int cell[3];
    } ahead[2 * kLookahead];
    while (plx::next_sample(g.res, g.bres, g.block, g.block_occ, g.cell_occ, g.bmin, g.scale, r, &walk)) {
        const int* cell = walk.cell;
        // Rows scattered over hundreds of MB miss the cache, so the march loads ahead in two stages: the links (and
        // occupancy) of the cell 2 kLookahead samples ahead, then the rows of the cell kLookahead ahead, whose links
        // the first stage has brought in; each stage's misses overlap the work on this sample.
        if (walk.i - 1 + 2 * kLookahead < r.n) {
            float q[3];
            plx::point_ahead(g.res, g.bmin, g.scale, r, walk, 2 * kLookahead, q);
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
                plx::point_ahead(g.res, g.bmin, g.scale, r, walk, kLookahead, q);
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
bool advise_huge_pages(void* ptr, size_t bytes) {
    constexpr uintptr_t kHuge = 2u << 20;
    const uintptr_t begin = ((uintptr_t)ptr + kHuge - 1) & ~(kHuge - 1);
    const uintptr_t end = ((uintptr_t)ptr + bytes) & ~(kHuge - 1);
    if (end <= begin) return false;
    return madvise((void*)begin, end - begin, MADV_HUGEPAGE) == 0;
}

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

// Zeroed per-thread scratch for a gradient table: slots for threads 1..T-1 of T = omp_get_max_threads(), at most
// max_slots of them (the caller's memory share: random rays soon touch every page of a slot).
// Anonymous mappings are zero pages mapped lazily, so a thread's slot costs memory only for the rows it ever
// touches, and they start on a page, so rows stay whole cache lines (calloc's large blocks start 16 bytes in,
// which split every row across one more line).
std::vector<at::Tensor> grad_scratch(at::Tensor grad_data, int64_t max_slots) {
    TORCH_CHECK(grad_data.device().is_cpu() && grad_data.dim() == 2, "grad data must be a CPU [N, S] table");
    TORCH_CHECK(max_slots >= 0, "max_slots must be >= 0");
    const int64_t slots = std::min<int64_t>(std::max(omp_get_max_threads() - 1, 0), max_slots);
    const int64_t rows = grad_data.size(0), stride = grad_data.size(1);
    const auto zeroed = [](int64_t count, size_t size, at::IntArrayRef shape, at::ScalarType type, bool huge) {
        if (count == 0) return at::zeros(shape, at::TensorOptions().dtype(type));
        const size_t bytes = (size_t)count * size;
        void* p = mmap(nullptr, bytes, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
        TORCH_CHECK(p != MAP_FAILED, "out of memory for per-thread gradient buffers");
        if (huge) advise_huge_pages(p, bytes);
        return at::from_blob(p, shape, [bytes](void* q) { munmap(q, bytes); }, at::TensorOptions().dtype(type));
    };
    return {zeroed(slots * rows * stride, sizeof(float), {slots, rows, stride}, at::kFloat, true),
            zeroed(slots * rows, 1, {slots, rows}, at::kByte, false)};
}

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

GradSink sink_for(int thread, GradTarget* target, ThreadGrads* scratch) {
    const int S = scratch->stride();
    if (thread == 0) return GradSink{target->data, S, target->mask, target->rows, &target->count, nullptr};
    return GradSink{scratch->buffer(thread), S, scratch->mask(thread), nullptr, nullptr, &scratch->list(thread)};
}

// How many rows ahead merge prefetches.
constexpr int kMergeLookahead = 8;

// Adds every other thread's gradients into the caller's tensors and clears their masks. Rows new to the caller's
// list are gathered by each worker as it merges them (a row is in a thread's list once, so no two workers meet at
// a mask byte) and appended after, in no set order.
void merge(GradTarget* target, ThreadGrads* scratch, int threads) {
    const int S = scratch->stride();
    for (int t = 1; t < threads; ++t) {
        std::vector<int32_t>& list = scratch->list(t);
        if (list.empty()) continue;
        float* buf = scratch->buffer(t);
        uint8_t* mask = scratch->mask(t);
        const int64_t n = (int64_t)list.size();
#pragma omp parallel
        {
            thread_local std::vector<int32_t> fresh;
            fresh.clear();
#pragma omp for schedule(static) nowait
            for (int64_t j = 0; j < n; ++j) {
                // The rows lie scattered over the tables: ask for those a few iterations ahead.
                if (j + kMergeLookahead < n) {
                    const int64_t ahead = list[j + kMergeLookahead];
                    for (int k = 0; k < S; k += 16) {
                        __builtin_prefetch(buf + ahead * S + k, 0, 3);
                        __builtin_prefetch(target->data + ahead * S + k, 1, 3);
                    }
                    __builtin_prefetch(target->mask + ahead, 1, 3);
                }
                const int64_t row = list[j];
                const float* src = buf + row * S;
                float* dst = target->data + row * S;
#pragma omp simd
                for (int k = 0; k < S; ++k) dst[k] += src[k];
                mask[row] = 0;
                if (!target->mask[row]) {
                    target->mask[row] = 1;
                    fresh.push_back((int32_t)row);
                }
            }
#pragma omp critical(plx_merge_rows)
            {
                std::copy(fresh.begin(), fresh.end(), target->rows + target->count);
                target->count += (int64_t)fresh.size();
            }
        }
        list.clear();
    }
}

void check_float_rows(const at::Tensor& t, const char* name) {
    TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == at::kFloat && t.is_contiguous(), name,
                " must be a contiguous float32 CPU tensor");
}

template <int D>
void render_impl(const GridView& g, const MarchOptions& opt, const float* origins, const float* dirs,
                 const float* background, int64_t B, float* rgb, float* depth, float* opacity) {
    constexpr int K = (D + 1) * (D + 1);
    constexpr int S = row_stride(D);
#pragma omp parallel
    {
        alignas(64) float interp[S];
#pragma omp for schedule(dynamic, 16)
        for (int64_t b = 0; b < B; ++b) {
            Ray r;
            setup_ray(g, origins + 3 * b, dirs + 3 * b, opt, &r);
            float basis[16];
            plx::sh_basis(D, r.dir[0], r.dir[1], r.dir[2], basis);
            float acc[3] = {0.0f, 0.0f, 0.0f}, acc_depth = 0.0f;
            const float t_final = march<S>(g, r, opt, interp, [&](Sample& s, const float* row) {
                const float w = s.t_before * s.alpha;
                for (int ch = 0; ch < 3; ++ch) {
                    float raw;
                    acc[ch] += w * plx::sh_colour(row + 1 + ch * K, basis, K, &raw);
                }
                acc_depth += w * s.t;
                return s.t_before * s.transmittance_factor;
            });
            for (int ch = 0; ch < 3; ++ch) rgb[3 * b + ch] = acc[ch] + (background ? t_final * background[3 * b + ch] : 0.0f);
            depth[b] = acc_depth;
            opacity[b] = 1.0f - t_final;
        }
    }
}

template <int D>
double loss_grad_impl(const GridView& g, const MarchOptions& opt, const float* origins, const float* dirs,
                      const float* targets, const float* background, int64_t B, float loss_scale,
                      float* grad_background, GradTarget* target, ThreadGrads* scratch) {
    constexpr int K = (D + 1) * (D + 1);
    constexpr int S = row_stride(D);
    const int threads = scratch->threads();
    double sse = 0.0;
#pragma omp parallel num_threads(threads) reduction(+ : sse)
    {
        GradSink sink = sink_for(omp_get_thread_num(), target, scratch);
        std::vector<Sample> samples;
        samples.reserve(512);
        alignas(64) float interp[S];
        alignas(64) float grow[S];
#pragma omp for schedule(dynamic, 16)
        for (int64_t b = 0; b < B; ++b) {
            Ray r;
            setup_ray(g, origins + 3 * b, dirs + 3 * b, opt, &r);
            float basis[16];
            plx::sh_basis(D, r.dir[0], r.dir[1], r.dir[2], basis);
            samples.clear();
            float acc[3] = {0.0f, 0.0f, 0.0f};
            const float t_final = march<S>(g, r, opt, interp, [&](Sample& s, const float* row) {
                const float w = s.t_before * s.alpha;
                for (int ch = 0; ch < 3; ++ch) {
                    s.colour[ch] = plx::sh_colour(row + 1 + ch * K, basis, K, &s.raw[ch]);
                    acc[ch] += w * s.colour[ch];
                }
                // The backward pass writes these gradient rows once the ray is done: fetch them now.
                for (int c = 0; c < 8; ++c) {
                    if (s.rows[c] < 0) continue;
                    prefetch_row<S>(sink.buf + (int64_t)s.rows[c] * S, true);
                    __builtin_prefetch(sink.mask + s.rows[c], 1, 3);
                }
                samples.push_back(s);
                return s.t_before * s.transmittance_factor;
            });
            float total[3], dl_drgb[3];
            for (int ch = 0; ch < 3; ++ch) {
                total[ch] = acc[ch] + t_final * background[3 * b + ch];
                const float err = total[ch] - targets[3 * b + ch];
                sse += (double)err * err;
                dl_drgb[ch] = 2.0f * loss_scale * err;
                grad_background[3 * b + ch] = dl_drgb[ch] * t_final;
            }
            // Backward: walk the same samples again, with what lies behind each one known from the total.
            float front[3] = {0.0f, 0.0f, 0.0f};
            for (const Sample& s : samples) {
                const float w = s.t_before * s.alpha;
                const float t_after = s.t_before * s.transmittance_factor;
                float dsigma = 0.0f;
                for (int k = 0; k < S; ++k) grow[k] = 0.0f;
                for (int ch = 0; ch < 3; ++ch) {
                    front[ch] += w * s.colour[ch];
                    const float behind = total[ch] - front[ch];
                    dsigma += dl_drgb[ch] * plx::dcolour_dsigma(s.delta, t_after, s.colour[ch], behind);
                    const float dc = dl_drgb[ch] * w * plx::colour_relu_grad(s.raw[ch]);
                    for (int k = 0; k < K; ++k) grow[1 + ch * K + k] = dc * basis[k];
                }
                grow[0] = dsigma;
                for (int c = 0; c < 8; ++c) {
                    if (s.rows[c] < 0) continue;
                    float* dst = sink.row(s.rows[c]);
                    const float wc = s.w[c];
#pragma omp simd
                    for (int k = 0; k < S; ++k) dst[k] += wc * grow[k];
                }
            }
        }
    }
    merge(target, scratch, threads);
    return sse;
}

template <int D>
void max_weights_impl(const GridView& g, const MarchOptions& opt, const float* origins, const float* dirs,
                      int64_t B, float* out) {
    constexpr int S = row_stride(D);
    uint32_t* bits = reinterpret_cast<uint32_t*>(out);  // non-negative floats order like their bits
#pragma omp parallel
    {
        alignas(64) float interp[S];
#pragma omp for schedule(dynamic, 16)
        for (int64_t b = 0; b < B; ++b) {
            Ray r;
            setup_ray(g, origins + 3 * b, dirs + 3 * b, opt, &r);
            march<S>(g, r, opt, interp, [&](Sample& s, const float*) {
                const float w = s.t_before * s.alpha;
                uint32_t wbits;
                std::memcpy(&wbits, &w, 4);
                for (int c = 0; c < 8; ++c) {
                    if (s.rows[c] < 0 || s.w[c] <= 0.0f) continue;
                    uint32_t cur = __atomic_load_n(bits + s.rows[c], __ATOMIC_RELAXED);
                    while (wbits > cur &&
                           !__atomic_compare_exchange_n(bits + s.rows[c], &cur, wbits, true, __ATOMIC_RELAXED,
                                                        __ATOMIC_RELAXED)) {
                    }
                }
                return s.t_before * s.transmittance_factor;
            });
        }
    }
}

template <int D>
void sample_counts_impl(const GridView& g, const MarchOptions& opt, const float* origins, const float* dirs, int64_t B,
                        int64_t* lattice, int64_t* used) {
    constexpr int S = row_stride(D);
    int64_t lattice_total = 0, used_total = 0;
#pragma omp parallel reduction(+ : lattice_total, used_total)
    {
        alignas(64) float interp[S];
#pragma omp for schedule(dynamic, 16)
        for (int64_t b = 0; b < B; ++b) {
            Ray r;
            setup_ray(g, origins + 3 * b, dirs + 3 * b, opt, &r);
            lattice_total += plx::ray_length_samples(g.res, g.bmin, g.scale, r);
            march<S>(g, r, opt, interp, [&](Sample& s, const float*) {
                ++used_total;
                return s.t_before * s.transmittance_factor;
            });
        }
    }
    *lattice = lattice_total;
    *used = used_total;
}

using at::Tensor;

MarchOptions make_options(double step, double stop_transmittance, double near, double sigma_threshold,
                          int64_t max_samples, bool contract) {
    return MarchOptions{step, (float)stop_transmittance, near, (float)sigma_threshold, (int)max_samples, contract};
}

#define PLX_DISPATCH_DEGREE(degree, ...)                                     \
    switch (degree) {                                                        \
        case 0: { constexpr int D = 0; __VA_ARGS__; break; }                 \
        case 1: { constexpr int D = 1; __VA_ARGS__; break; }                 \
        case 2: { constexpr int D = 2; __VA_ARGS__; break; }                 \
        case 3: { constexpr int D = 3; __VA_ARGS__; break; }                 \
        default: TORCH_CHECK(false, "sh_degree must be 0..3, got ", std::to_string(degree)); \
    }

void check_grid(const Tensor& data, const Tensor& links, const Tensor& cell_occ, const Tensor& block_occ, int degree) {
    check_float_rows(data, "data");
    TORCH_CHECK(degree >= 0 && degree <= 3, "sh_degree must be 0..3");
    TORCH_CHECK(data.dim() == 2 && data.size(1) == row_stride(degree),
                "data must be [N, padded row] for this SH degree");
    TORCH_CHECK(links.scalar_type() == at::kInt && links.is_contiguous() && links.dim() == 3, "links must be int32 [Rx,Ry,Rz]");
    TORCH_CHECK(links.size(0) >= 2 && links.size(1) >= 2 && links.size(2) >= 2, "grid resolution must be >= 2 per axis");
    TORCH_CHECK(cell_occ.scalar_type() == at::kByte && cell_occ.is_contiguous(), "cell_occ must be uint8");
    TORCH_CHECK(block_occ.scalar_type() == at::kByte && block_occ.is_contiguous() && block_occ.dim() == 3, "block_occ must be uint8 3-D");
}

void check_rays(const Tensor& origins, const Tensor& dirs) {
    check_float_rows(origins, "origins");
    check_float_rows(dirs, "dirs");
    TORCH_CHECK(origins.dim() == 2 && origins.size(1) == 3 && dirs.sizes() == origins.sizes(), "origins and dirs must be [B,3]");
}

std::vector<Tensor> render(Tensor data, Tensor links, Tensor cell_occ, Tensor block_occ, int64_t block,
                           c10::ArrayRef<double> bmin, c10::ArrayRef<double> bmax, int64_t degree, Tensor origins,
                           Tensor dirs, std::optional<Tensor> background, double step, double stop_transmittance,
                           double near, double sigma_threshold, int64_t max_samples, bool contract) {
    check_grid(data, links, cell_occ, block_occ, (int)degree);
    check_rays(origins, dirs);
    const int64_t B = origins.size(0);
    const float* bg = nullptr;
    if (background.has_value()) {
        check_float_rows(*background, "background");
        TORCH_CHECK(background->sizes() == origins.sizes(), "background must be [B,3]");
        bg = background->data_ptr<float>();
    }
    const GridView g = make_view(data, links, cell_occ, block_occ, (int)block, bmin, bmax);
    const MarchOptions opt = make_options(step, stop_transmittance, near, sigma_threshold, max_samples, contract);
    Tensor rgb = at::empty({B, 3}, data.options());
    Tensor depth = at::empty({B}, data.options());
    Tensor opacity = at::empty({B}, data.options());
    PLX_DISPATCH_DEGREE(degree, render_impl<D>(g, opt, origins.data_ptr<float>(), dirs.data_ptr<float>(), bg, B,
                                               rgb.data_ptr<float>(), depth.data_ptr<float>(), opacity.data_ptr<float>()));
    return {rgb, depth, opacity};
}

std::tuple<double, Tensor, int64_t> loss_and_grad(Tensor data, Tensor links, Tensor cell_occ, Tensor block_occ,
                                                  int64_t block, c10::ArrayRef<double> bmin, c10::ArrayRef<double> bmax,
                                                  int64_t degree, Tensor origins, Tensor dirs, Tensor targets,
                                                  Tensor background, double step, double stop_transmittance,
                                                  double near, double sigma_threshold, int64_t max_samples, bool contract,
                                                  Tensor grad_data, Tensor grad_mask, Tensor grad_rows,
                                                  int64_t num_touched, Tensor scratch_grad, Tensor scratch_mask) {
    check_grid(data, links, cell_occ, block_occ, (int)degree);
    check_rays(origins, dirs);
    check_float_rows(targets, "targets");
    check_float_rows(background, "background");
    check_float_rows(grad_data, "grad data");
    TORCH_CHECK(targets.sizes() == origins.sizes() && background.sizes() == origins.sizes(), "targets and background must be [B,3]");
    TORCH_CHECK(grad_data.sizes() == data.sizes(), "gradient storage does not match the grid");
    ThreadGrads scratch(grad_data, scratch_grad, scratch_mask);
    const int64_t B = origins.size(0);
    const GridView g = make_view(data, links, cell_occ, block_occ, (int)block, bmin, bmax);
    const MarchOptions opt = make_options(step, stop_transmittance, near, sigma_threshold, max_samples, contract);
    Tensor grad_background = at::empty({B, 3}, data.options());
    GradTarget target{grad_data.data_ptr<float>(), grad_mask.data_ptr<uint8_t>(), grad_rows.data_ptr<int32_t>(), num_touched};
    const float loss_scale = B > 0 ? 1.0f / (3.0f * (float)B) : 0.0f;
    double sse = 0.0;
    PLX_DISPATCH_DEGREE(degree, sse = loss_grad_impl<D>(g, opt, origins.data_ptr<float>(), dirs.data_ptr<float>(),
                                                        targets.data_ptr<float>(), background.data_ptr<float>(), B,
                                                        loss_scale, grad_background.data_ptr<float>(), &target, &scratch));
    return {sse, grad_background, target.count};
}

void max_weights(Tensor data, Tensor links, Tensor cell_occ, Tensor block_occ, int64_t block,
                   c10::ArrayRef<double> bmin, c10::ArrayRef<double> bmax, int64_t degree, Tensor origins, Tensor dirs,
                   double step, double stop_transmittance, double near, double sigma_threshold, int64_t max_samples, bool contract,
                   Tensor out) {
    check_grid(data, links, cell_occ, block_occ, (int)degree);
    check_rays(origins, dirs);
    check_float_rows(out, "out");
    TORCH_CHECK(out.numel() == data.size(0), "out must have one entry per row");
    const GridView g = make_view(data, links, cell_occ, block_occ, (int)block, bmin, bmax);
    const MarchOptions opt = make_options(step, stop_transmittance, near, sigma_threshold, max_samples, contract);
    PLX_DISPATCH_DEGREE(degree, max_weights_impl<D>(g, opt, origins.data_ptr<float>(), dirs.data_ptr<float>(),
                                                    origins.size(0), out.data_ptr<float>()));
}

// (samples on the rays' lattices inside the box, samples that contributed): for benchmarks and reports.
std::tuple<int64_t, int64_t> sample_counts(Tensor data, Tensor links, Tensor cell_occ, Tensor block_occ, int64_t block,
                                           c10::ArrayRef<double> bmin, c10::ArrayRef<double> bmax, int64_t degree,
                                           Tensor origins, Tensor dirs, double step, double stop_transmittance,
                                           double near, double sigma_threshold, int64_t max_samples, bool contract) {
    check_grid(data, links, cell_occ, block_occ, (int)degree);
    check_rays(origins, dirs);
    const GridView g = make_view(data, links, cell_occ, block_occ, (int)block, bmin, bmax);
    const MarchOptions opt = make_options(step, stop_transmittance, near, sigma_threshold, max_samples, contract);
    int64_t lattice = 0, used = 0;
    PLX_DISPATCH_DEGREE(degree, sample_counts_impl<D>(g, opt, origins.data_ptr<float>(), dirs.data_ptr<float>(),
                                                      origins.size(0), &lattice, &used));
    return {lattice, used};
}

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

// Live-vertex counts per block from scratch: a vertex is live when its raw density is > 0. A block
// with no live vertex can hold no sample with density > 0 (interpolation is a convex combination
// and empty corners count as 0), so the march skips it whatever sigma_threshold (>= 0) is.
void count_live_blocks(Tensor data, Tensor coords, int64_t block, Tensor counts, Tensor blocks) {
    check_float_rows(data, "data");
    TORCH_CHECK(coords.scalar_type() == at::kInt && coords.is_contiguous(), "coords must be int32 [N,3]");
    TORCH_CHECK(counts.scalar_type() == at::kInt && counts.is_contiguous() && counts.dim() == 3, "counts must be int32 3-D");
    TORCH_CHECK(blocks.scalar_type() == at::kByte && blocks.is_contiguous() && blocks.sizes() == counts.sizes(), "blocks must be uint8 like counts");
    counts.zero_();
    const int64_t n = data.size(0), S = data.size(1), nblocks = counts.numel();
    const int nb[3] = {(int)counts.size(0), (int)counts.size(1), (int)counts.size(2)};
    const float* d = data.data_ptr<float>();
    const int32_t* xyz = coords.data_ptr<int32_t>();
    int32_t* c = counts.data_ptr<int32_t>();
    uint8_t* bl = blocks.data_ptr<uint8_t>();
#pragma omp parallel
    {
#pragma omp for schedule(static)
        for (int64_t r = 0; r < n; ++r)
            if (d[r * S] > 0.0f) add_live_vertex(xyz + 3 * r, (int)block, nb, c, 1, nullptr);
#pragma omp for schedule(static)
        for (int64_t b = 0; b < nblocks; ++b) bl[b] = c[b] > 0;
    }
}

// Occupancy for empty-space skipping: a cell is occupied when any of its corners is allocated, a
// block when any of its cells is.
std::vector<Tensor> build_occupancy(Tensor links, int64_t block) {
    TORCH_CHECK(links.scalar_type() == at::kInt && links.is_contiguous() && links.dim() == 3, "links must be int32 [Rx,Ry,Rz]");
    const int64_t rx = links.size(0), ry = links.size(1), rz = links.size(2);
    TORCH_CHECK(rx >= 2 && ry >= 2 && rz >= 2, "grid resolution must be >= 2 per axis");
    const int64_t cx = rx - 1, cy = ry - 1, cz = rz - 1;
    const int64_t bx = (cx + block - 1) / block, by = (cy + block - 1) / block, bz = (cz + block - 1) / block;
    Tensor cells = at::zeros({cx, cy, cz}, at::kByte);
    Tensor blocks = at::zeros({bx, by, bz}, at::kByte);
    const int32_t* l = links.data_ptr<int32_t>();
    uint8_t* c = cells.data_ptr<uint8_t>();
    uint8_t* bl = blocks.data_ptr<uint8_t>();
#pragma omp parallel for schedule(static)
    for (int64_t x = 0; x < cx; ++x) {
        for (int64_t y = 0; y < cy; ++y) {
            const int32_t* l00 = l + (x * ry + y) * rz;
            const int32_t* l01 = l00 + rz;
            const int32_t* l10 = l00 + ry * rz;
            const int32_t* l11 = l10 + rz;
            uint8_t* row = c + (x * cy + y) * cz;
            // The AND of the eight corners has its sign bit set exactly when every corner is < 0
            // (unallocated); no branch, so the loop vectorises (a 512^3 index is 134M cells).
            for (int64_t z = 0; z < cz; ++z)
                row[z] = (l00[z] & l00[z + 1] & l01[z] & l01[z + 1] & l10[z] & l10[z + 1] & l11[z] & l11[z + 1]) >= 0;
        }
    }
#pragma omp parallel for schedule(static)
    for (int64_t x = 0; x < bx; ++x) {
        for (int64_t y = 0; y < by; ++y) {
            for (int64_t z = 0; z < bz; ++z) {
                bool any = false;
                for (int64_t i = x * block; i < std::min((x + 1) * block, cx) && !any; ++i)
                    for (int64_t j = y * block; j < std::min((y + 1) * block, cy) && !any; ++j)
                        for (int64_t k = z * block; k < std::min((z + 1) * block, cz) && !any; ++k)
                            any = c[(i * cy + j) * cz + k];
                bl[(x * by + y) * bz + z] = any;
            }
        }
    }
    return {cells, blocks};
}

// How many samples apart total variation loads each stage of a sample's reads ahead.
constexpr int64_t kTvAhead = 4;

// Total variation at sampled rows: for each channel with a non-zero weight,
// weight * mean over samples of sqrt(dx^2 + dy^2 + dz^2 + eps), with d* the forward differences to
// the allocated +x, +y, +z neighbours (a missing neighbour contributes no difference).
std::tuple<double, int64_t> tv_loss_and_grad(Tensor data, Tensor links, Tensor coords, Tensor sample_rows,
                                              double weight_density, double weight_sh, int64_t degree,
                                              Tensor grad_data, Tensor grad_mask, Tensor grad_rows,
                                              int64_t num_touched, Tensor scratch_grad, Tensor scratch_mask) {
    check_float_rows(data, "data");
    check_float_rows(grad_data, "grad data");
    TORCH_CHECK(coords.scalar_type() == at::kInt && coords.is_contiguous(), "coords must be int32 [N,3]");
    TORCH_CHECK(sample_rows.scalar_type() == at::kLong && sample_rows.is_contiguous(), "sample rows must be int64");
    const int S = (int)data.size(1);
    const int C = 1 + 3 * (int)((degree + 1) * (degree + 1));
    const int res[3] = {(int)links.size(0), (int)links.size(1), (int)links.size(2)};
    const int64_t M = sample_rows.numel();
    if (M == 0) return {0.0, num_touched};
    const float* d = data.data_ptr<float>();
    const int32_t* l = links.data_ptr<int32_t>();
    const int32_t* xyz = coords.data_ptr<int32_t>();
    const int64_t* rows = sample_rows.data_ptr<int64_t>();
    GradTarget target{grad_data.data_ptr<float>(), grad_mask.data_ptr<uint8_t>(), grad_rows.data_ptr<int32_t>(), num_touched};
    ThreadGrads scratch(grad_data, scratch_grad, scratch_mask);
    const int threads = scratch.threads();
    const int c_begin = weight_density != 0.0 ? 0 : 1;
    const int c_end = weight_sh != 0.0 ? C : 1;
    double loss = 0.0;
#pragma omp parallel num_threads(threads) reduction(+ : loss)
    {
        GradSink sink = sink_for(omp_get_thread_num(), &target, &scratch);
        // The links of a row's +x, +y and +z neighbours (-1 past the grid's edge).
        const auto neighbour_links = [&](int32_t row, int64_t* at) {
            const int32_t* p = xyz + 3 * (int64_t)row;
            for (int a = 0; a < 3; ++a) {
                int q[3] = {p[0], p[1], p[2]};
                q[a] += 1;
                at[a] = q[a] < res[a] ? ((int64_t)q[0] * res[1] + q[1]) * res[2] + q[2] : -1;
            }
        };
#pragma omp for schedule(static)
        for (int64_t m = 0; m < M; ++m) {
            // A sample's reads depend on each other (its coordinates, then its neighbours' links, then their rows), and
            // samples are far apart in the tables: load each stage ahead, kTvAhead samples apart.
            if (m + 3 * kTvAhead < M) __builtin_prefetch(xyz + 3 * rows[m + 3 * kTvAhead], 0, 3);
            if (m + 2 * kTvAhead < M) {
                const int32_t ahead = (int32_t)rows[m + 2 * kTvAhead];
                int64_t at[3];
                neighbour_links(ahead, at);
                for (int a = 0; a < 3; ++a)
                    if (at[a] >= 0) __builtin_prefetch(l + at[a], 0, 3);
                prefetch_floats(d + (int64_t)ahead * S, S, false);
                prefetch_floats(sink.buf + (int64_t)ahead * S, S, true);
            }
            if (m + kTvAhead < M) {
                int64_t at[3];
                neighbour_links((int32_t)rows[m + kTvAhead], at);
                for (int a = 0; a < 3; ++a) {
                    const int32_t n = at[a] >= 0 ? l[at[a]] : -1;
                    if (n < 0) continue;
                    prefetch_floats(d + (int64_t)n * S, S, false);
                    prefetch_floats(sink.buf + (int64_t)n * S, S, true);
                }
            }
            const int32_t row = (int32_t)rows[m];
            int32_t nb[3];
            {
                int64_t at[3];
                neighbour_links(row, at);
                for (int a = 0; a < 3; ++a) nb[a] = at[a] >= 0 ? l[at[a]] : -1;
            }
            if (nb[0] < 0 && nb[1] < 0 && nb[2] < 0) continue;
            float* grad_self = sink.row(row);
            float* grad_nb[3];
            for (int a = 0; a < 3; ++a) grad_nb[a] = nb[a] >= 0 ? sink.row(nb[a]) : nullptr;
            const float* v = d + (int64_t)row * S;
            for (int k = c_begin; k < c_end; ++k) {
                const float scale = (float)((k == 0 ? weight_density : weight_sh) / (double)M);
                float diff[3];
                for (int a = 0; a < 3; ++a) diff[a] = nb[a] >= 0 ? d[(int64_t)nb[a] * S + k] - v[k] : 0.0f;
                float inv;
                loss += scale * plx::tv_term(diff[0], diff[1], diff[2], &inv);
                float self = 0.0f;
                for (int a = 0; a < 3; ++a) {
                    if (nb[a] < 0) continue;
                    const float gd = scale * diff[a] * inv;
                    grad_nb[a][k] += gd;
                    self -= gd;
                }
                grad_self[k] += self;
            }
        }
    }
    merge(&target, &scratch, threads);
    return {loss, target.count};
}

// How many rows ahead the optimiser step loads the rows it updates, and the share of a grid's rows (one in this many)
// above which a step walks its touched rows in memory order.
constexpr int64_t kRowsAhead = 16;
constexpr int64_t kMemoryOrderShare = 64;

// RMSProp on the touched rows only: v = beta v + (1 - beta) g^2; p -= lr g / (sqrt(v) + eps).
// Clears the gradient of those rows afterwards. A zero gradient with zero v moves nothing.
// When live coords, block, counts and blocks are given, a row whose density changes sign updates the
// live-block counts so that empty-space skipping stays exact without a rebuild.
void rmsprop_step(Tensor data, Tensor second_moment, Tensor grad_data, Tensor grad_mask, Tensor grad_rows,
                  int64_t num_touched, int64_t columns, double lr_density, double lr_sh, double beta, double eps,
                  std::optional<Tensor> live_coords, int64_t live_block, std::optional<Tensor> live_counts,
                  std::optional<Tensor> live_blocks) {
    check_float_rows(data, "data");
    check_float_rows(second_moment, "second moment");
    check_float_rows(grad_data, "grad data");
    const int64_t S = data.size(1);
    float* p = data.data_ptr<float>();
    float* v = second_moment.data_ptr<float>();
    float* g = grad_data.data_ptr<float>();
    uint8_t* mask = grad_mask.data_ptr<uint8_t>();
    const int32_t* rows = grad_rows.data_ptr<int32_t>();
    const float b = (float)beta, one_minus_b = (float)(1.0 - beta), e = (float)eps;
    const float lr_d = (float)lr_density, lr_s = (float)lr_sh;
    const int32_t* xyz = nullptr;
    int32_t* counts = nullptr;
    uint8_t* blocks = nullptr;
    int block = 1, nb[3] = {0, 0, 0};
    if (live_coords.has_value()) {
        TORCH_CHECK(live_counts.has_value() && live_blocks.has_value() && live_block > 0,
                    "live bookkeeping needs coords, block, counts and blocks");
        const Tensor& c = *live_coords;
        const Tensor& n = *live_counts;
        const Tensor& b = *live_blocks;
        TORCH_CHECK(c.scalar_type() == at::kInt && c.is_contiguous() && c.size(0) == data.size(0), "coords must be int32 [N,3]");
        TORCH_CHECK(n.scalar_type() == at::kInt && n.is_contiguous() && n.dim() == 3, "counts must be int32 3-D");
        TORCH_CHECK(b.scalar_type() == at::kByte && b.is_contiguous() && b.sizes() == n.sizes(), "blocks must be uint8 like counts");
        xyz = c.data_ptr<int32_t>();
        block = (int)live_block;
        counts = n.data_ptr<int32_t>();
        blocks = b.data_ptr<uint8_t>();
        for (int a = 0; a < 3; ++a) nb[a] = (int)n.size(a);
    }
    // Each thread updates its share of the touched rows: in memory order (the mask read in order) when the step
    // touched more than one row in kMemoryOrderShare, as nearby rows then share pages and a fit's rows lie in
    // clusters; else, where reading the whole mask would cost more than that saves, in the list's first-touch order.
    // Either way it loads rows kRowsAhead ahead of the one it updates: touched rows lie scattered over tables of
    // hundreds of MB, and each would otherwise wait on its misses in turn. Any order gives the same update.
    const int64_t N = data.size(0);
    const bool in_memory_order = num_touched * kMemoryOrderShare > N;
#pragma omp parallel
    {
        // Blocks whose live count this thread took across zero: only their flags can change.
        std::vector<int64_t> crossed;
        const int T = omp_get_num_threads(), t = omp_get_thread_num();
        const int64_t span = in_memory_order ? N : num_touched;
        const int64_t begin = span * t / T, end = span * (t + 1) / T;
        thread_local std::vector<int32_t> mine;
        mine.clear();
        if (in_memory_order) {
            mine.resize(end - begin + 1);
            int64_t n = 0;
            for (int64_t j = begin; j < end; ++j) {  // without a branch: which rows are touched is unpredictable
                mine[n] = (int32_t)j;
                n += mask[j] != 0;
            }
            mine.resize(n);
        }
        const int32_t* list = in_memory_order ? mine.data() : rows + begin;
        const int64_t count = in_memory_order ? (int64_t)mine.size() : end - begin;
        for (int64_t j = 0; j < count; ++j) {
            if (j + kRowsAhead < count) {
                const int64_t ahead = (int64_t)list[j + kRowsAhead] * S;
                for (int64_t k = 0; k < columns; k += 16) {
                    __builtin_prefetch(p + ahead + k, 1, 3);
                    __builtin_prefetch(v + ahead + k, 1, 3);
                    __builtin_prefetch(g + ahead + k, 1, 3);
                }
            }
            const int64_t row = list[j];
            float* pr = p + row * S;
            const bool was_live = pr[0] > 0.0f;
            float* vr = v + row * S;
            float* gr = g + row * S;
            for (int64_t k = 0; k < columns; ++k) {
                const float gk = gr[k];
                const float vk = b * vr[k] + one_minus_b * gk * gk;
                vr[k] = vk;
                pr[k] -= (k == 0 ? lr_d : lr_s) * gk / (std::sqrt(vk) + e);
                gr[k] = 0.0f;
            }
            mask[row] = 0;
            const bool is_live = pr[0] > 0.0f;
            if (counts && is_live != was_live) add_live_vertex(xyz + 3 * row, block, nb, counts, is_live ? 1 : -1, &crossed);
        }
#pragma omp barrier
        // After the loop's barrier every count is final; threads sharing a block write the same flag.
        for (const int64_t blk : crossed)
            __atomic_store_n(blocks + blk, (uint8_t)(__atomic_load_n(counts + blk, __ATOMIC_RELAXED) > 0), __ATOMIC_RELAXED);
    }
}

void check_background(const Tensor& origins, const Tensor& dirs, const Tensor& centre, const Tensor& radii,
                      const Tensor& texture, const Tensor& far_colour) {
    check_rays(origins, dirs);
    check_float_rows(centre, "centre");
    check_float_rows(radii, "radii");
    check_float_rows(texture, "texture");
    check_float_rows(far_colour, "far_colour");
    TORCH_CHECK(centre.numel() == 3 && far_colour.numel() == 3, "centre and far_colour must hold 3 values");
    TORCH_CHECK(texture.dim() == 4 && texture.size(3) == 4 && texture.size(0) == radii.numel() && texture.size(1) >= 1 &&
                texture.size(2) >= 1, "texture must be [K, H, W, 4] with one sphere per radius");
}

// A forward pass's record of each ray's layers for its backward pass: texel rows [B, K, 4] int32 (-1 where the ray
// met no layer: a sphere it missed, or one behind where it stopped) and their bilinear weights [B, K, 4].
struct LayerRecord {
    int32_t* texels = nullptr;
    float* weights = nullptr;
};

LayerRecord layer_record(const std::optional<Tensor>& texels, const std::optional<Tensor>& weights, int64_t B, int K) {
    TORCH_CHECK(texels.has_value() == weights.has_value(), "the background's layer record needs texels and weights");
    if (!texels.has_value()) return {};
    TORCH_CHECK(texels->scalar_type() == at::kInt && texels->is_contiguous() && texels->numel() == B * K * 4,
                "layer texels must be int32 [B, K, 4]");
    check_float_rows(*weights, "layer weights");
    TORCH_CHECK(weights->numel() == B * K * 4, "layer weights must be float32 [B, K, 4]");
    return {texels->data_ptr<int32_t>(), weights->data_ptr<float>()};
}

Tensor background_render(Tensor origins, Tensor dirs, Tensor centre, Tensor radii, Tensor texture, Tensor far_colour,
                         std::optional<Tensor> layer_texels, std::optional<Tensor> layer_weights) {
    check_background(origins, dirs, centre, radii, texture, far_colour);
    const int64_t B = origins.size(0);
    const int K = (int)texture.size(0), H = (int)texture.size(1), W = (int)texture.size(2);
    const LayerRecord record = layer_record(layer_texels, layer_weights, B, K);
    Tensor rgb = at::empty({B, 3}, origins.options());
    const float *o = origins.data_ptr<float>(), *d = dirs.data_ptr<float>(), *c = centre.data_ptr<float>();
    const float *r = radii.data_ptr<float>(), *tex = texture.data_ptr<float>(), *far = far_colour.data_ptr<float>();
    float* out = rgb.data_ptr<float>();
#pragma omp parallel for schedule(static)
    for (int64_t b = 0; b < B; ++b) {
        double rel[3], unit[3];
        plx::bg_ray(o + 3 * b, d + 3 * b, c, rel, unit);
        if (!record.texels) {
            plx::bg_forward(tex, r, K, H, W, rel, unit, far, out + 3 * b);
            continue;
        }
        int32_t* texels = record.texels + b * K * 4;
        float* weights = record.weights + b * K * 4;
        for (int k = 0; k < K; ++k) texels[4 * k] = -1;
        const auto layer = [&](int k, plx::BgLayer* l) {
            if (!plx::bg_layer(tex, k, H, W, rel, unit, r[k], l)) return false;
            for (int i = 0; i < 4; ++i) {
                texels[4 * k + i] = l->texel[i];
                weights[4 * k + i] = l->w[i];
            }
            return true;
        };
        plx::bg_composite(K, layer, far, out + 3 * b);
    }
    return rgb;
}

int64_t background_backward(Tensor origins, Tensor dirs, Tensor centre, Tensor radii, Tensor texture, Tensor far_colour,
                             Tensor rgb, Tensor grad_rgb, std::optional<Tensor> layer_texels,
                             std::optional<Tensor> layer_weights, Tensor grad_texture, Tensor grad_mask, Tensor grad_rows,
                             int64_t num_touched, Tensor scratch_grad, Tensor scratch_mask) {
    check_background(origins, dirs, centre, radii, texture, far_colour);
    check_float_rows(grad_rgb, "grad_rgb");
    check_float_rows(grad_texture, "grad_texture");
    const int64_t B = origins.size(0);
    const int K = (int)texture.size(0), H = (int)texture.size(1), W = (int)texture.size(2);
    const int64_t texels = (int64_t)K * H * W;
    check_float_rows(rgb, "rgb");
    TORCH_CHECK(grad_rgb.sizes() == origins.sizes() && rgb.sizes() == origins.sizes(), "rgb and grad_rgb must be [B, 3] like the rays");
    TORCH_CHECK(grad_texture.dim() == 2 && grad_texture.size(0) == texels && grad_texture.size(1) == 4,
                "grad_texture must be [K*H*W, 4]");
    TORCH_CHECK(grad_mask.scalar_type() == at::kByte && grad_mask.is_contiguous() && grad_mask.numel() == texels &&
                grad_rows.scalar_type() == at::kInt && grad_rows.is_contiguous() && grad_rows.numel() >= texels,
                "grad mask and rows need one uint8 / int32 entry per texel");
    // Every ray reads the same few spheres, so many rays share each texel: each thread adds into its own table (the
    // grid's per-thread scheme, merged after), where atomic adds would fight over the same cache lines. With the
    // forward's record of the layers, the backward reads the same texels and weights back instead of intersecting
    // every sphere again (the square roots and arc functions that are most of a ray's cost).
    const LayerRecord record = layer_record(layer_texels, layer_weights, B, K);
    ThreadGrads scratch(grad_texture, scratch_grad, scratch_mask);
    GradTarget target{grad_texture.data_ptr<float>(), grad_mask.data_ptr<uint8_t>(), grad_rows.data_ptr<int32_t>(),
                      num_touched};
    const float *o = origins.data_ptr<float>(), *d = dirs.data_ptr<float>(), *c = centre.data_ptr<float>();
    const float *r = radii.data_ptr<float>(), *tex = texture.data_ptr<float>();
    const float *g = grad_rgb.data_ptr<float>(), *colour = rgb.data_ptr<float>();
    const int threads = scratch.threads();
#pragma omp parallel num_threads(threads)
    {
        GradSink sink = sink_for(omp_get_thread_num(), &target, &scratch);
        const auto add = [&sink](int texel, const float grad[4]) {
            float* row = sink.row(texel);
            for (int k = 0; k < 4; ++k) row[k] += grad[k];
        };
#pragma omp for schedule(static)
        for (int64_t b = 0; b < B; ++b) {
            if (record.texels) {
                const int32_t* texels = record.texels + b * K * 4;
                const float* weights = record.weights + b * K * 4;
                const auto layer = [&](int k, plx::BgLayer* l) {
                    if (texels[4 * k] < 0) return false;
                    for (int i = 0; i < 4; ++i) {
                        l->texel[i] = texels[4 * k + i];
                        l->w[i] = weights[4 * k + i];
                    }
                    plx::bg_read(tex, l);
                    return true;
                };
                plx::bg_composite_backward(K, layer, colour + 3 * b, g + 3 * b, add);
                continue;
            }
            double rel[3], unit[3];
            plx::bg_ray(o + 3 * b, d + 3 * b, c, rel, unit);
            plx::bg_backward(tex, r, K, H, W, rel, unit, colour + 3 * b, g + 3 * b, add);
        }
    }
    merge(&target, &scratch, threads);
    return target.count;
}

// Trilinear interpolation of every packed column at grid-frame points [P, 3]: [P, S], zeros outside the box.
Tensor sample(Tensor data, Tensor links, Tensor points) {
    check_float_rows(data, "data");
    check_float_rows(points, "points");
    TORCH_CHECK(data.dim() == 2, "data must be [N, S]");
    TORCH_CHECK(links.scalar_type() == at::kInt && links.is_contiguous() && links.dim() == 3, "links must be int32 [Rx,Ry,Rz]");
    TORCH_CHECK(links.size(0) >= 2 && links.size(1) >= 2 && links.size(2) >= 2, "grid resolution must be >= 2 per axis");
    TORCH_CHECK(points.dim() == 2 && points.size(1) == 3, "points must be [P,3]");
    const int64_t P = points.size(0);
    const int S = (int)data.size(1);
    const int res[3] = {(int)links.size(0), (int)links.size(1), (int)links.size(2)};
    Tensor out = at::empty({P, S}, data.options());
    const float* d = data.data_ptr<float>();
    const int32_t* l = links.data_ptr<int32_t>();
    const float* g = points.data_ptr<float>();
    float* o = out.data_ptr<float>();
#pragma omp parallel for schedule(static)
    for (int64_t p = 0; p < P; ++p) plx::interpolate_point(d, S, l, res, g + 3 * p, o + p * S);
    return out;
}

// Grid coordinates (x, y, z) of every allocated row.
Tensor row_coords(Tensor links, int64_t rows) {
    TORCH_CHECK(links.scalar_type() == at::kInt && links.is_contiguous() && links.dim() == 3, "links must be int32 [Rx,Ry,Rz]");
    Tensor out = at::full({rows, 3}, -1, at::kInt);
    const int64_t ry = links.size(1), rz = links.size(2), total = links.numel();
    const int32_t* l = links.data_ptr<int32_t>();
    int32_t* o = out.data_ptr<int32_t>();
#pragma omp parallel for schedule(static)
    for (int64_t i = 0; i < total; ++i) {
        const int32_t r = l[i];
        if (r < 0 || r >= rows) continue;
        o[3 * (int64_t)r] = (int32_t)(i / (ry * rz));
        o[3 * (int64_t)r + 1] = (int32_t)((i / rz) % ry);
        o[3 * (int64_t)r + 2] = (int32_t)(i % rz);
    }
    return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(voxfield, CPU, m) {
    m.impl("advise_huge_pages", [](const Tensor& t) {
        TORCH_CHECK(t.is_contiguous(), "advise_huge_pages needs a contiguous CPU tensor");
        return advise_huge_pages(t.data_ptr(), (size_t)t.nbytes());
    });
    PLX_IMPL_DEVICE_OPS(m);
}
