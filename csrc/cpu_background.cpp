// The multi-sphere background on the CPU: its colour along rays and the gradient into its texture.
#include "cpu_kernels.h"

namespace plx_cpu {

Spheres spheres_view(const Tensor& origins, const Tensor& dirs, const Tensor& centre, const Tensor& radii,
                     const Tensor& texture, const Tensor& far_colour, const std::optional<Tensor>& layer_texels,
                     const std::optional<Tensor>& layer_weights) {
    check_rays(origins, dirs);
    check_float_rows(centre, "centre");
    check_float_rows(radii, "radii");
    check_float_rows(texture, "texture");
    check_float_rows(far_colour, "far_colour");
    TORCH_CHECK(centre.numel() == 3 && far_colour.numel() == 3, "centre and far_colour must hold 3 values");
    TORCH_CHECK(texture.dim() == 4 && texture.size(3) == 4 && texture.size(0) == radii.numel() && texture.size(1) >= 1 &&
                texture.size(2) >= 1, "texture must be [K, H, W, 4] with one sphere per radius");
    Spheres s{origins.data_ptr<float>(), dirs.data_ptr<float>(), centre.data_ptr<float>(), radii.data_ptr<float>(),
              texture.data_ptr<float>(), far_colour.data_ptr<float>(), (int)texture.size(0), (int)texture.size(1),
              (int)texture.size(2)};
    TORCH_CHECK(layer_texels.has_value() == layer_weights.has_value(), "the background's layer record needs texels and weights");
    if (!layer_texels.has_value()) return s;
    const int64_t n = origins.size(0) * s.count * 4;
    TORCH_CHECK(layer_texels->scalar_type() == at::kInt && layer_texels->is_contiguous() && layer_texels->numel() == n,
                "layer texels must be int32 [B, K, 4]");
    check_float_rows(*layer_weights, "layer weights");
    TORCH_CHECK(layer_weights->numel() == n, "layer weights must be float32 [B, K, 4]");
    s.texels = layer_texels->data_ptr<int32_t>();
    s.weights = layer_weights->data_ptr<float>();
    return s;
}

void sphere_colour(const Spheres& s, int64_t b, bool drawn, float rgb[3]) {
    const int K = s.count;
    if (!drawn) {
        rgb[0] = rgb[1] = rgb[2] = 0.0f;
        if (s.texels)
            for (int k = 0; k < K; ++k) s.texels[(b * K + k) * 4] = -1;
        return;
    }
    double rel[3], unit[3];
    plx::bg_ray(s.origins + 3 * b, s.dirs + 3 * b, s.centre, rel, unit);
    if (!s.texels) {
        plx::bg_forward(s.texture, s.radii, K, s.height, s.width, rel, unit, s.far_colour, rgb);
        return;
    }
    int32_t* texels = s.texels + b * K * 4;
    float* weights = s.weights + b * K * 4;
    for (int k = 0; k < K; ++k) texels[4 * k] = -1;
    const auto layer = [&](int k, plx::BgLayer* l) {
        if (!plx::bg_layer(s.texture, k, s.height, s.width, rel, unit, s.radii[k], l)) return false;
        for (int i = 0; i < 4; ++i) {
            texels[4 * k + i] = l->texel[i];
            weights[4 * k + i] = l->w[i];
        }
        return true;
    };
    plx::bg_composite(K, layer, s.far_colour, rgb);
}

Tensor background_render(Tensor origins, Tensor dirs, Tensor centre, Tensor radii, Tensor texture, Tensor far_colour,
                         std::optional<Tensor> layer_texels, std::optional<Tensor> layer_weights) {
    const Spheres spheres = spheres_view(origins, dirs, centre, radii, texture, far_colour, layer_texels, layer_weights);
    const int64_t B = origins.size(0);
    Tensor rgb = at::empty({B, 3}, origins.options());
    float* out = rgb.data_ptr<float>();
#pragma omp parallel for schedule(static)
    for (int64_t b = 0; b < B; ++b) sphere_colour(spheres, b, true, out + 3 * b);
    return rgb;
}

int64_t background_backward(Tensor origins, Tensor dirs, Tensor centre, Tensor radii, Tensor texture, Tensor far_colour,
                             Tensor rgb, Tensor grad_rgb, std::optional<Tensor> layer_texels,
                             std::optional<Tensor> layer_weights, Tensor grad_texture, Tensor grad_mask, Tensor grad_rows,
                             int64_t num_touched, Tensor scratch_grad, Tensor scratch_mask) {
    // With the forward's record of the layers, the backward reads the same texels and weights back instead of
    // intersecting every sphere again (the square roots and arc functions that are most of a ray's cost).
    const Spheres s = spheres_view(origins, dirs, centre, radii, texture, far_colour, layer_texels, layer_weights);
    check_float_rows(grad_rgb, "grad_rgb");
    check_float_rows(grad_texture, "grad_texture");
    const int64_t B = origins.size(0);
    const int K = s.count;
    const int64_t texels = (int64_t)K * s.height * s.width;
    check_float_rows(rgb, "rgb");
    TORCH_CHECK(grad_rgb.sizes() == origins.sizes() && rgb.sizes() == origins.sizes(), "rgb and grad_rgb must be [B, 3] like the rays");
    TORCH_CHECK(grad_texture.dim() == 2 && grad_texture.size(0) == texels && grad_texture.size(1) == 4,
                "grad_texture must be [K*H*W, 4]");
    TORCH_CHECK(grad_mask.scalar_type() == at::kByte && grad_mask.is_contiguous() && grad_mask.numel() == texels &&
                grad_rows.scalar_type() == at::kInt && grad_rows.is_contiguous() && grad_rows.numel() >= texels,
                "grad mask and rows need one uint8 / int32 entry per texel");
    // Every ray reads the same few spheres, so many rays share each texel: each thread adds into its own table (the
    // grid's per-thread scheme, merged after), where atomic adds would fight over the same cache lines.
    ThreadGrads scratch(grad_texture, scratch_grad, scratch_mask);
    GradTarget target{grad_texture.data_ptr<float>(), grad_mask.data_ptr<uint8_t>(), grad_rows.data_ptr<int32_t>(),
                      num_touched};
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
            if (s.texels) {
                const int32_t* texels = s.texels + b * K * 4;
                const float* weights = s.weights + b * K * 4;
                const auto layer = [&](int k, plx::BgLayer* l) {
                    if (texels[4 * k] < 0) return false;
                    for (int i = 0; i < 4; ++i) {
                        l->texel[i] = texels[4 * k + i];
                        l->w[i] = weights[4 * k + i];
                    }
                    plx::bg_read(s.texture, l);
                    return true;
                };
                plx::bg_composite_backward(K, layer, colour + 3 * b, g + 3 * b, add);
                continue;
            }
            double rel[3], unit[3];
            plx::bg_ray(s.origins + 3 * b, s.dirs + 3 * b, s.centre, rel, unit);
            plx::bg_backward(s.texture, s.radii, K, s.height, s.width, rel, unit, colour + 3 * b, g + 3 * b, add);
        }
    }
    merge(&target, &scratch, threads);
    return target.count;
}

}  // namespace plx_cpu
