// Total variation on the CPU, at sampled rows of the grid.
#include "cpu_kernels.h"

namespace plx_cpu {

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

}  // namespace plx_cpu
