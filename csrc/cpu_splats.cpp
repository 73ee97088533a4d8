// The splat rasterizer's compositing on the CPU, forward and backward (splat_composite, splat_composite_backward):
// the per-pixel loop of plenoxels/splats/rasterize.py's composite without its (splat, pixel) pair tensors. The window
// is cut into tiles of kTile pixels a side; each tile lists, front to back, the splats whose box reaches it, and each
// pixel walks its tile's list. The per-pair math is splats_math.h's.
#include "cpu_kernels.h"
#include "splats_math.h"

namespace plx_cpu {

namespace {

constexpr int kTile = 2;

struct Window {
    int x0, y0, w, h, tiles_x, tiles_y;
};

// One splat as the pixels read it, the splats stored front to back: a pixel's walk down its tile's list reads
// memory in one direction.
struct Splat {
    float mean[2], conic[3], opacity, colour[3];
    float faint;  // the power below which the pair's alpha is under ALPHA_MIN, found without exp
    plx::splat::Box box;
    int32_t index;  // its row in the inputs
};

struct SplatInputs {
    std::vector<Splat> splats;        // the splats that reach the window, front to back
    std::vector<int64_t> tile_start;  // [tiles + 1]
    std::vector<int32_t> tile_splats; // positions in `splats`
};

void check_splats(const Tensor& means2d, const Tensor& conics, const Tensor& colours, const Tensor& opacities,
                  const Tensor& radii, const Tensor& order, const Tensor& background) {
    for (auto [t, name, columns] : {std::tuple{&means2d, "means2d", 2}, {&conics, "conics", 3}, {&colours, "colours", 3}}) {
        check_float_rows(*t, name);
        TORCH_CHECK(t->dim() == 2 && t->size(0) == means2d.size(0) && t->size(1) == columns, name,
                    " must be [M, " + std::to_string(columns) + "]");
    }
    check_float_rows(opacities, "opacities");
    check_float_rows(radii, "radii");
    check_float_rows(background, "background");
    TORCH_CHECK(opacities.numel() == means2d.size(0) && radii.numel() == means2d.size(0), "opacities and radii must be [M]");
    TORCH_CHECK(order.scalar_type() == at::kLong && order.is_contiguous() && order.numel() == means2d.size(0),
                "order must be int64 [M]: the splats front to back");
    TORCH_CHECK(background.numel() == 3, "background must be [3]");
}

// Each tile's splats, front to back.
SplatInputs bin(const Tensor& means2d, const Tensor& conics, const Tensor& colours, const Tensor& opacities,
                const Tensor& radii, const Tensor& order, const Window& win) {
    SplatInputs in;
    const int64_t m = means2d.size(0);
    const float *mean = means2d.data_ptr<float>(), *conic = conics.data_ptr<float>();
    const float *colour = colours.data_ptr<float>(), *opacity = opacities.data_ptr<float>(), *r = radii.data_ptr<float>();
    const int64_t* front_to_back = order.data_ptr<int64_t>();
    in.splats.reserve(m);
    for (int64_t i = 0; i < m; ++i) {
        const int64_t s = front_to_back[i];
        const auto b = plx::splat::box_of(mean[2 * s], mean[2 * s + 1], r[s], win.x0, win.y0, win.x0 + win.w - 1,
                                          win.y0 + win.h - 1);
        if (b.lo_x > b.hi_x || b.lo_y > b.hi_y) continue;
        in.splats.push_back(Splat{{mean[2 * s], mean[2 * s + 1]}, {conic[3 * s], conic[3 * s + 1], conic[3 * s + 2]},
                                  opacity[s], {colour[3 * s], colour[3 * s + 1], colour[3 * s + 2]},
                                  plx::splat::faint_power(opacity[s]), b, (int32_t)s});
    }
    const int tiles = win.tiles_x * win.tiles_y;
    std::vector<int64_t> counts(tiles + 1, 0);
    for (const auto& sp : in.splats)
        for (int ty = (sp.box.lo_y - win.y0) / kTile; ty <= (sp.box.hi_y - win.y0) / kTile; ++ty)
            for (int tx = (sp.box.lo_x - win.x0) / kTile; tx <= (sp.box.hi_x - win.x0) / kTile; ++tx)
                ++counts[ty * win.tiles_x + tx + 1];
    for (int t = 0; t < tiles; ++t) counts[t + 1] += counts[t];
    in.tile_start = counts;
    in.tile_splats.resize(counts[tiles]);
    std::vector<int64_t> at(counts.begin(), counts.end() - 1);
    for (int32_t i = 0; i < (int32_t)in.splats.size(); ++i) {
        const auto& b = in.splats[i].box;
        for (int ty = (b.lo_y - win.y0) / kTile; ty <= (b.hi_y - win.y0) / kTile; ++ty)
            for (int tx = (b.lo_x - win.x0) / kTile; tx <= (b.hi_x - win.x0) / kTile; ++tx)
                in.tile_splats[at[ty * win.tiles_x + tx]++] = i;
    }
    return in;
}

Window window_of(int64_t x0, int64_t y0, int64_t w, int64_t h) {
    TORCH_CHECK(w >= 1 && h >= 1, "a window must be at least one pixel");
    return Window{(int)x0, (int)y0, (int)w, (int)h, (int)((w + kTile - 1) / kTile), (int)((h + kTile - 1) / kTile)};
}

}  // namespace

std::vector<Tensor> splat_composite(Tensor means2d, Tensor conics, Tensor colours, Tensor opacities, Tensor radii,
                                    Tensor order, int64_t x0, int64_t y0, int64_t w, int64_t h, Tensor background) {
    check_splats(means2d, conics, colours, opacities, radii, order, background);
    const Window win = window_of(x0, y0, w, h);
    const SplatInputs in = bin(means2d, conics, colours, opacities, radii, order, win);
    auto rgb = at::empty({h * w, 3}, means2d.options());
    auto opacity = at::empty({h * w}, means2d.options());
    auto ends = at::empty({h * w}, means2d.options().dtype(at::kInt));
    auto light = at::empty({h * w}, means2d.options().dtype(at::kDouble));
    double* out_light = light.data_ptr<double>();

    float* out_rgb = rgb.data_ptr<float>();
    float* out_opacity = opacity.data_ptr<float>();
    int32_t* out_ends = ends.data_ptr<int32_t>();
    const float* bg = background.data_ptr<float>();
#pragma omp parallel for schedule(dynamic, 16)
    for (int64_t p = 0; p < h * w; ++p) {
        const int px = win.x0 + (int)(p % w), py = win.y0 + (int)(p / w);
        const int tile = ((py - win.y0) / kTile) * win.tiles_x + (px - win.x0) / kTile;
        double t = 1.0, c[3] = {0.0, 0.0, 0.0}, weights = 0.0;
        int64_t e = in.tile_start[tile], end = e;
        for (; e < in.tile_start[tile + 1]; ++e) {
            const Splat& sp = in.splats[in.tile_splats[e]];
            if (!plx::splat::box_holds(sp.box, px, py) ||
                plx::splat::power_at(sp.conic, (float)px - sp.mean[0], (float)py - sp.mean[1]) < sp.faint) continue;
            float gauss;
            const float a = plx::splat::alpha_at(sp.opacity, sp.conic, (float)px - sp.mean[0], (float)py - sp.mean[1], &gauss);
            if (a < plx::splat::kAlphaMin) continue;
            if (t * (1.0 - a) < plx::splat::kStopTransmittance) break;
            const double weight = a * t;
            for (int ch = 0; ch < 3; ++ch) c[ch] += weight * sp.colour[ch];
            weights += weight;
            t *= 1.0 - a;
            end = e + 1;
        }
        for (int ch = 0; ch < 3; ++ch) out_rgb[3 * p + ch] = (float)(c[ch] + (1.0 - weights) * bg[ch]);
        out_opacity[p] = (float)weights;
        out_ends[p] = (int32_t)(end - in.tile_start[tile]);
        out_light[p] = t;
    }
    return {rgb, opacity, ends, light};
}

std::vector<Tensor> splat_composite_backward(Tensor means2d, Tensor conics, Tensor colours, Tensor opacities,
                                             Tensor radii, Tensor order, int64_t x0, int64_t y0, int64_t w, int64_t h,
                                             Tensor background, Tensor ends, Tensor light, Tensor grad_rgb,
                                             Tensor grad_opacity) {
    check_splats(means2d, conics, colours, opacities, radii, order, background);
    check_float_rows(grad_rgb, "grad_rgb");
    check_float_rows(grad_opacity, "grad_opacity");
    TORCH_CHECK(grad_rgb.numel() == h * w * 3 && grad_opacity.numel() == h * w && ends.numel() == h * w &&
                ends.scalar_type() == at::kInt && ends.is_contiguous() && light.numel() == h * w &&
                light.scalar_type() == at::kDouble && light.is_contiguous(),
                "gradients, ends and light must be per window pixel, as splat_composite gave them");
    const Window win = window_of(x0, y0, w, h);
    const SplatInputs in = bin(means2d, conics, colours, opacities, radii, order, win);
    const int64_t m = means2d.size(0), n = (int64_t)in.splats.size();
    const float* g_rgb = grad_rgb.data_ptr<float>();
    const float* g_opacity = grad_opacity.data_ptr<float>();
    const int32_t* pixel_ends = ends.data_ptr<int32_t>();
    const double* pixel_light = light.data_ptr<double>();
    const float* bg = background.data_ptr<float>();
    // Per thread: d loss / d (mean2d 2, conic 3, colour 3, opacity 1) of every splat that reaches the window (by its
    // position front to back), summed after.
    constexpr int kG = 9;
    const int threads = std::max(1, omp_get_max_threads());
    std::vector<float> grads((size_t)threads * n * kG, 0.0f);
#pragma omp parallel for schedule(dynamic, 16)
    for (int64_t p = 0; p < h * w; ++p) {
        float* g = grads.data() + (size_t)omp_get_thread_num() * n * kG;
        const int px = win.x0 + (int)(p % w), py = win.y0 + (int)(p / w);
        const int tile = ((py - win.y0) / kTile) * win.tiles_x + (px - win.x0) / kTile;
        const int64_t first = in.tile_start[tile], last = first + pixel_ends[p];
        const double t_final = pixel_light[p];
        // Back to front: behind[] is what the pairs behind the current one and the background add to the pixel
        // (colour, then opacity), so that d pixel / d alpha_i = T_i c_i - behind / (1 - alpha_i).
        double t = t_final, behind[4] = {t_final * bg[0], t_final * bg[1], t_final * bg[2], 0.0};
        const double g_pixel[4] = {g_rgb[3 * p], g_rgb[3 * p + 1], g_rgb[3 * p + 2], g_opacity[p]};
        for (int64_t e = last - 1; e >= first; --e) {
            const int32_t i = in.tile_splats[e];
            const Splat& sp = in.splats[i];
            const float dx = (float)px - sp.mean[0], dy = (float)py - sp.mean[1];
            if (!plx::splat::box_holds(sp.box, px, py) || plx::splat::power_at(sp.conic, dx, dy) < sp.faint) continue;
            float gauss;
            const float a = plx::splat::alpha_at(sp.opacity, sp.conic, dx, dy, &gauss);
            if (a < plx::splat::kAlphaMin) continue;
            t /= 1.0 - a;
            const double own[4] = {sp.colour[0], sp.colour[1], sp.colour[2], 1.0};
            double g_alpha = 0.0;
            float* gs = g + (size_t)i * kG;
            for (int ch = 0; ch < 4; ++ch) {
                g_alpha += g_pixel[ch] * (t * own[ch] - behind[ch] / (1.0 - a));
                behind[ch] += own[ch] * a * t;
                if (ch < 3) gs[5 + ch] += (float)(g_pixel[ch] * a * t);
            }
            plx::splat::alpha_backward(sp.opacity, sp.conic, dx, dy, gauss, (float)g_alpha, gs, gs + 2, gs + 8);
        }
    }
    auto out = at::zeros({m, kG}, means2d.options());
    float* sum = out.data_ptr<float>();
    for (int th = 0; th < threads; ++th)
        for (int64_t i = 0; i < n; ++i)
            for (int j = 0; j < kG; ++j) sum[in.splats[i].index * kG + j] += grads[((size_t)th * n + i) * kG + j];
    return {out.slice(1, 0, 2).contiguous(), out.slice(1, 2, 5).contiguous(), out.slice(1, 5, 8).contiguous(),
            out.select(1, 8).contiguous()};
}

}  // namespace plx_cpu
