// Sparse RMSProp on the CPU: only the rows a step touched are updated, and the live-block counts follow.
#include "cpu_kernels.h"

namespace plx_cpu {

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

// Adam on the given rows of a table [N, D] (the splats' distillation: each step touches the rows of one window's
// splats). Each row keeps its own step count for the bias correction; the rate of column c is rates[c], times the
// row's row_factor on the columns [scaled_begin, scaled_end). Rows must be distinct.
void adam_rows(Tensor data, Tensor first, Tensor second, Tensor steps, Tensor rows, Tensor grad, Tensor rates,
               Tensor row_factor, int64_t scaled_begin, int64_t scaled_end, double beta1, double beta2, double eps) {
    for (auto [t, name] : {std::pair{&data, "data"}, {&first, "first moment"}, {&second, "second moment"},
                           {&grad, "grad"}, {&rates, "rates"}, {&row_factor, "row factor"}, {&steps, "steps"}})
        check_float_rows(*t, name);
    const int64_t d = data.size(1), n = rows.numel();
    TORCH_CHECK(data.dim() == 2 && first.sizes() == data.sizes() && second.sizes() == data.sizes() &&
                steps.numel() == data.size(0) && row_factor.numel() == data.size(0) && rates.numel() == d,
                "adam_rows: moments [N, D], steps and row factor [N], rates [D]");
    TORCH_CHECK(rows.scalar_type() == at::kLong && rows.is_contiguous() && grad.dim() == 2 && grad.size(0) == n &&
                grad.size(1) == d, "adam_rows: rows int64 [R], grad [R, D]");
    float *p = data.data_ptr<float>(), *m = first.data_ptr<float>(), *v = second.data_ptr<float>();
    float* t = steps.data_ptr<float>();
    const float *g = grad.data_ptr<float>(), *rate = rates.data_ptr<float>(), *factor = row_factor.data_ptr<float>();
    const int64_t* row = rows.data_ptr<int64_t>();
    for (int64_t i = 0; i < n; ++i) TORCH_CHECK(row[i] >= 0 && row[i] < data.size(0), "adam_rows: a row outside the table");
    // 1 - beta and the bias corrections in double: 1 - 0.999f is 1.3e-5 off 0.001.
    const float b1 = (float)beta1, b2 = (float)beta2, e = (float)eps, rest1 = (float)(1.0 - beta1),
                rest2 = (float)(1.0 - beta2);
#pragma omp parallel for schedule(static)
    for (int64_t i = 0; i < n; ++i) {
        const int64_t r = row[i];
        const float step = (t[r] += 1.0f);
        const float correct1 = (float)(1.0 - std::pow(beta1, (double)step)),
                    correct2 = (float)(1.0 - std::pow(beta2, (double)step));
        for (int64_t c = 0; c < d; ++c) {
            const float gc = g[i * d + c];
            float& mc = m[r * d + c];
            float& vc = v[r * d + c];
            mc = b1 * mc + rest1 * gc;
            vc = b2 * vc + rest2 * gc * gc;
            const float lr = rate[c] * (c >= scaled_begin && c < scaled_end ? factor[r] : 1.0f);
            p[r * d + c] -= lr * (mc / correct1) / (std::sqrt(vc / correct2) + e);
        }
    }
}

}  // namespace plx_cpu
