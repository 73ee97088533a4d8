// Rendering on the CPU: colour, depth and opacity of rays; the fused photometric loss and its gradient (with the
// background spheres drawn in the same pass, only where light gets past the grid: opt.background_stop); each
// voxel's largest weight along the rays (for pruning); and the sample counts reports quote.
#include "cpu_kernels.h"

namespace plx_cpu {

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
            // What lies behind shows as plx::light_past_grid has it (the spheres: none on a ray the march stopped);
            // the opacity is what the samples took, so depth / opacity stays the samples' mean depth.
            const float light = plx::light_past_grid(t_final, opt.background_stop);
            for (int ch = 0; ch < 3; ++ch) rgb[3 * b + ch] = acc[ch] + (background ? light * background[3 * b + ch] : 0.0f);
            depth[b] = acc_depth;
            opacity[b] = 1.0f - t_final;
        }
    }
}

// `behind(b, light)`: the colour [3] behind the grid on ray b, of which `light` shows (0: none, so it need not be
// drawn): colours drawn beforehand, or the background spheres drawn here, only for the rays the grid lets light past.
template <int D, typename Behind>
double loss_grad_impl(const GridView& g, const MarchOptions& opt, const float* origins, const float* dirs,
                      const float* targets, Behind behind_grid, int64_t B, float loss_scale, float near_gradient,
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
            const float light = plx::light_past_grid(t_final, opt.background_stop);
            // Behind each sample the background counts at the rate its share answers the density (equal to the share
            // outside the stop's ramp).
            const float rate_less_share = plx::light_past_grid_rate(t_final, opt.background_stop) - light;
            const float* background = behind_grid(b, light);
            float total[3], dl_drgb[3];
            for (int ch = 0; ch < 3; ++ch) {
                total[ch] = acc[ch] + light * background[ch];
                const float err = plx::colour_error(total[ch], targets[3 * b + ch]);
                sse += (double)err * err;
                dl_drgb[ch] = 2.0f * loss_scale * err;
                grad_background[3 * b + ch] = dl_drgb[ch] * light;
            }
            // Backward: walk the same samples again, with what lies behind each one known from the total.
            float front[3] = {0.0f, 0.0f, 0.0f};
            for (const Sample& s : samples) {
                const float w = s.t_before * s.alpha;
                const float t_after = s.t_before * s.transmittance_factor;
                const float share = plx::near_gradient_scale(s.t, near_gradient);
                float dsigma = 0.0f;
                for (int k = 0; k < S; ++k) grow[k] = 0.0f;
                for (int ch = 0; ch < 3; ++ch) {
                    front[ch] += w * s.colour[ch];
                    const float behind = total[ch] - front[ch] + rate_less_share * background[ch];
                    dsigma += dl_drgb[ch] * plx::dcolour_dsigma(s.delta, t_after, s.colour[ch], behind);
                    const float dc = share * dl_drgb[ch] * w * plx::colour_relu_grad(s.raw[ch]);
                    for (int k = 0; k < K; ++k) grow[1 + ch * K + k] = dc * basis[k];
                }
                grow[0] = share * dsigma;
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
            lattice_total += plx::ray_length_samples(g.res, g.lattice, r);
            march<S>(g, r, opt, interp, [&](Sample& s, const float*) {
                ++used_total;
                return s.t_before * s.transmittance_factor;
            });
        }
    }
    *lattice = lattice_total;
    *used = used_total;
}

std::vector<Tensor> render(Tensor data, Tensor links, Tensor cell_occ, Tensor block_occ, int64_t block,
                           c10::ArrayRef<double> lattice, int64_t degree, Tensor origins,
                           Tensor dirs, std::optional<Tensor> background, bool past_grid_only, double step,
                           double stop_transmittance, double near, double sigma_threshold, int64_t max_samples,
                           bool contract) {
    check_grid(data, links, cell_occ, block_occ, (int)degree);
    check_rays(origins, dirs);
    const int64_t B = origins.size(0);
    const float* bg = nullptr;
    if (background.has_value()) {
        check_float_rows(*background, "background");
        TORCH_CHECK(background->sizes() == origins.sizes(), "background must be [B,3]");
        bg = background->data_ptr<float>();
    }
    const GridView g = make_view(data, links, cell_occ, block_occ, (int)block, lattice);
    const MarchOptions opt = make_options(step, stop_transmittance, near, sigma_threshold, max_samples, contract,
                                          past_grid_only);
    Tensor rgb = at::empty({B, 3}, data.options());
    Tensor depth = at::empty({B}, data.options());
    Tensor opacity = at::empty({B}, data.options());
    PLX_DISPATCH_DEGREE(degree, render_impl<D>(g, opt, origins.data_ptr<float>(), dirs.data_ptr<float>(), bg, B,
                                               rgb.data_ptr<float>(), depth.data_ptr<float>(), opacity.data_ptr<float>()));
    return {rgb, depth, opacity};
}

std::tuple<double, Tensor, int64_t> loss_and_grad(Tensor data, Tensor links, Tensor cell_occ, Tensor block_occ,
                                                  int64_t block, c10::ArrayRef<double> lattice,
                                                  int64_t degree, Tensor origins, Tensor dirs, Tensor targets,
                                                  Tensor background, bool past_grid_only, double step,
                                                  double stop_transmittance, double near, double sigma_threshold, int64_t max_samples, bool contract,
                                                  double near_gradient, Tensor grad_data, Tensor grad_mask, Tensor grad_rows,
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
    const GridView g = make_view(data, links, cell_occ, block_occ, (int)block, lattice);
    const MarchOptions opt = make_options(step, stop_transmittance, near, sigma_threshold, max_samples, contract,
                                          past_grid_only);
    Tensor grad_background = at::empty({B, 3}, data.options());
    GradTarget target{grad_data.data_ptr<float>(), grad_mask.data_ptr<uint8_t>(), grad_rows.data_ptr<int32_t>(), num_touched};
    const float loss_scale = B > 0 ? 1.0f / (3.0f * (float)B) : 0.0f;
    double sse = 0.0;
    const float* drawn = background.data_ptr<float>();
    const auto behind = [drawn](int64_t b, float) { return drawn + 3 * b; };
    PLX_DISPATCH_DEGREE(degree, sse = loss_grad_impl<D>(g, opt, origins.data_ptr<float>(), dirs.data_ptr<float>(),
                                                        targets.data_ptr<float>(), behind, B,
                                                        loss_scale, (float)near_gradient, grad_background.data_ptr<float>(),
                                                        &target, &scratch));
    return {sse, grad_background, target.count};
}

std::tuple<double, Tensor, Tensor, int64_t> loss_and_grad_spheres(
    Tensor data, Tensor links, Tensor cell_occ, Tensor block_occ, int64_t block, c10::ArrayRef<double> lattice,
    int64_t degree, Tensor origins, Tensor dirs, Tensor targets, Tensor sphere_origins, Tensor sphere_dirs,
    Tensor centre, Tensor radii, Tensor texture, Tensor far_colour, Tensor layer_texels, Tensor layer_weights,
    double step, double stop_transmittance, double near, double sigma_threshold, int64_t max_samples, bool contract,
    double near_gradient, Tensor grad_data, Tensor grad_mask, Tensor grad_rows, int64_t num_touched,
    Tensor scratch_grad, Tensor scratch_mask) {
    check_grid(data, links, cell_occ, block_occ, (int)degree);
    check_rays(origins, dirs);
    check_float_rows(targets, "targets");
    check_float_rows(grad_data, "grad data");
    TORCH_CHECK(targets.sizes() == origins.sizes() && sphere_origins.sizes() == origins.sizes(),
                "targets and the spheres' rays must be [B,3] like the grid's");
    TORCH_CHECK(grad_data.sizes() == data.sizes(), "gradient storage does not match the grid");
    const Spheres spheres = spheres_view(sphere_origins, sphere_dirs, centre, radii, texture, far_colour, layer_texels,
                                         layer_weights);
    TORCH_CHECK(spheres.texels != nullptr, "loss_and_grad_spheres needs the layer record its backward reads");
    ThreadGrads scratch(grad_data, scratch_grad, scratch_mask);
    const int64_t B = origins.size(0);
    const GridView g = make_view(data, links, cell_occ, block_occ, (int)block, lattice);
    const MarchOptions opt = make_options(step, stop_transmittance, near, sigma_threshold, max_samples, contract, true);
    Tensor grad_background = at::empty({B, 3}, data.options());
    Tensor background = at::empty({B, 3}, data.options());
    float* drawn = background.data_ptr<float>();
    const auto behind = [&spheres, drawn](int64_t b, float light) {
        sphere_colour(spheres, b, light > 0.0f, drawn + 3 * b);
        return (const float*)(drawn + 3 * b);
    };
    GradTarget target{grad_data.data_ptr<float>(), grad_mask.data_ptr<uint8_t>(), grad_rows.data_ptr<int32_t>(), num_touched};
    const float loss_scale = B > 0 ? 1.0f / (3.0f * (float)B) : 0.0f;
    double sse = 0.0;
    PLX_DISPATCH_DEGREE(degree, sse = loss_grad_impl<D>(g, opt, origins.data_ptr<float>(), dirs.data_ptr<float>(),
                                                        targets.data_ptr<float>(), behind, B,
                                                        loss_scale, (float)near_gradient, grad_background.data_ptr<float>(),
                                                        &target, &scratch));
    return {sse, grad_background, background, target.count};
}

void max_weights(Tensor data, Tensor links, Tensor cell_occ, Tensor block_occ, int64_t block,
                   c10::ArrayRef<double> lattice, int64_t degree, Tensor origins, Tensor dirs,
                   double step, double stop_transmittance, double near, double sigma_threshold, int64_t max_samples, bool contract,
                   Tensor out) {
    check_grid(data, links, cell_occ, block_occ, (int)degree);
    check_rays(origins, dirs);
    check_float_rows(out, "out");
    TORCH_CHECK(out.numel() == data.size(0), "out must have one entry per row");
    const GridView g = make_view(data, links, cell_occ, block_occ, (int)block, lattice);
    const MarchOptions opt = make_options(step, stop_transmittance, near, sigma_threshold, max_samples, contract);
    PLX_DISPATCH_DEGREE(degree, max_weights_impl<D>(g, opt, origins.data_ptr<float>(), dirs.data_ptr<float>(),
                                                    origins.size(0), out.data_ptr<float>()));
}

// (samples on the rays' lattices inside the box, samples that contributed): for benchmarks and reports.
std::tuple<int64_t, int64_t> sample_counts(Tensor data, Tensor links, Tensor cell_occ, Tensor block_occ, int64_t block,
                                           c10::ArrayRef<double> lattice, int64_t degree,
                                           Tensor origins, Tensor dirs, double step, double stop_transmittance,
                                           double near, double sigma_threshold, int64_t max_samples, bool contract) {
    check_grid(data, links, cell_occ, block_occ, (int)degree);
    check_rays(origins, dirs);
    const GridView g = make_view(data, links, cell_occ, block_occ, (int)block, lattice);
    const MarchOptions opt = make_options(step, stop_transmittance, near, sigma_threshold, max_samples, contract);
    int64_t on_lattice = 0, used = 0;
    PLX_DISPATCH_DEGREE(degree, sample_counts_impl<D>(g, opt, origins.data_ptr<float>(), dirs.data_ptr<float>(),
                                                      origins.size(0), &on_lattice, &used));
    return {on_lattice, used};
}

}  // namespace plx_cpu
