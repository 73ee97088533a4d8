// The multi-sphere background on the CPU: its colour along rays and the gradient into its texture.
#include "cpu_kernels.h"

namespace plx_cpu {

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

}  // namespace plx_cpu
