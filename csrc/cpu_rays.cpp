// A training batch's rays on the CPU: each drawn pixel's world ray and colour and, where asked, the coherent order,
// in one pass over the batch (the PyTorch path, plenoxels/core/ray_set.py, takes a dozen operators and passes).
#include "cpu_kernels.h"

namespace plx_cpu {

namespace {

// Bits per axis of the coherent order's Morton code, and its cells per axis less one.
constexpr int kMortonBits = 10;
constexpr float kMortonTop = (float)((1 << kMortonBits) - 1);
// How many pixels ahead the pass loads the colour it will read (drawn pixels lie scattered over the photos' tens or
// hundreds of MB), and the batch size from which it runs on every thread.
constexpr int64_t kPixelsAhead = 8;
constexpr int64_t kParallelRays = 2048;

// Bit i of a 10-bit value moved to bit 3i (four shifts and masks).
inline uint32_t every_third_bit(uint32_t v) {
    v = (v | (v << 16)) & 0x030000FFu;
    v = (v | (v << 8)) & 0x0300F00Fu;
    v = (v | (v << 4)) & 0x030C30C3u;
    return (v | (v << 2)) & 0x09249249u;
}

// The Morton code of a ray's point closest to the origin, that point clamped to [-extent, extent]^3: the order
// ray_set.coherent_order draws, written as its operators are so that the two agree but for rounding.
inline uint32_t closest_point_code(const float o[3], const float d[3], float extent) {
    const float length = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
    float unit[3], along = 0.0f;
    for (int a = 0; a < 3; ++a) unit[a] = d[a] / length;
    for (int a = 0; a < 3; ++a) along += o[a] * unit[a];
    uint32_t code = 0;
    for (int a = 0; a < 3; ++a) {
        const float closest = std::min(std::max(o[a] - unit[a] * along, -extent), extent);
        code |= every_third_bit((uint32_t)((closest + extent) / (2.0f * extent) * kMortonTop)) << a;
    }
    return code;
}

// The stable order of 30-bit keys: a least-significant-digit radix sort in three passes of 10 bits.
std::vector<int64_t> stable_order(const std::vector<uint32_t>& keys) {
    const int64_t n = (int64_t)keys.size();
    std::vector<int64_t> order(n), swap(n);
    for (int64_t i = 0; i < n; ++i) order[i] = i;
    std::vector<int64_t> start(1 << kMortonBits);
    for (int shift = 0; shift < 3 * kMortonBits; shift += kMortonBits) {
        std::fill(start.begin(), start.end(), 0);
        for (int64_t i = 0; i < n; ++i) ++start[(keys[i] >> shift) & ((1u << kMortonBits) - 1)];
        int64_t sum = 0;
        for (auto& s : start) sum += std::exchange(s, sum);
        for (int64_t i = 0; i < n; ++i) {
            const int64_t j = order[i];
            swap[start[(keys[j] >> shift) & ((1u << kMortonBits) - 1)]++] = j;
        }
        order.swap(swap);
    }
    return order;
}

}  // namespace

// [order int64 [B], image int64 [B], origins [B, 3], unit dirs [B, 3], colours [B, 3] in [0, 1]] of the photos'
// pixels at the flat indices `pixel` [B] into their table pixels uint8 [P, 3] (the photos side by side from offsets
// [N + 1], each sizes [N, 2] (h, w)), with intrinsics [N, 4] (fl_x, fl_y, cx, cy) and c2w [N, 4, 4]
// (plenoxels.core.cameras convention: x right, y up, looking down -z). Output i is pixel order[i]: the pixels' own
// order with coherent false, else by the Morton code of each ray's point closest to the origin within
// [-extent, extent]^3, ties in the pixels' order.
std::vector<Tensor> pixel_rays(Tensor pixel, Tensor intrinsics, Tensor c2w, Tensor pixels, Tensor offsets,
                               Tensor sizes, bool coherent, double extent) {
    for (auto [t, name] : {std::pair{&pixel, "pixel"}, {&offsets, "offsets"}, {&sizes, "sizes"}})
        TORCH_CHECK(t->device().is_cpu() && t->scalar_type() == at::kLong && t->is_contiguous(),
                    "pixel_rays: ", name, " must be a contiguous int64 CPU tensor");
    TORCH_CHECK(intrinsics.scalar_type() == at::kFloat && intrinsics.is_contiguous() && intrinsics.dim() == 2 &&
                intrinsics.size(1) == 4, "pixel_rays: intrinsics must be float [N, 4]");
    TORCH_CHECK(c2w.scalar_type() == at::kFloat && c2w.is_contiguous() && c2w.dim() == 3 && c2w.size(1) >= 3 &&
                c2w.size(2) == 4 && c2w.size(0) == intrinsics.size(0), "pixel_rays: c2w must be float [N, 4, 4]");
    TORCH_CHECK(pixels.scalar_type() == at::kByte && pixels.is_contiguous() && pixels.dim() == 2 && pixels.size(1) == 3,
                "pixel_rays: pixels must be uint8 [P, 3]");
    const int64_t n_images = intrinsics.size(0), b = pixel.numel();
    TORCH_CHECK(offsets.numel() == n_images + 1 && sizes.numel() == 2 * n_images,
                "pixel_rays: offsets [N + 1] and sizes [N, 2] of the N photos");
    const int64_t *flat = pixel.data_ptr<int64_t>(), *start = offsets.data_ptr<int64_t>();
    const int64_t* hw = sizes.data_ptr<int64_t>();
    for (int64_t i = 0; i < b; ++i)
        TORCH_CHECK(flat[i] >= 0 && flat[i] < start[n_images], "pixel_rays: a pixel outside the photos");
    const float* k = intrinsics.data_ptr<float>();
    const float* pose = c2w.data_ptr<float>();
    const int64_t pose_stride = c2w.size(1) * 4;
    const uint8_t* rgb8 = pixels.data_ptr<uint8_t>();
    const auto f32 = intrinsics.options();
    Tensor images = at::empty({b}, pixel.options());
    Tensor origins = at::empty({b, 3}, f32), dirs = at::empty({b, 3}, f32), colours = at::empty({b, 3}, f32);
    int64_t* im = images.data_ptr<int64_t>();
    float *o = origins.data_ptr<float>(), *d = dirs.data_ptr<float>(), *rgb = colours.data_ptr<float>();
    std::vector<uint32_t> keys(coherent ? b : 0);
#pragma omp parallel for schedule(static) if (b >= kParallelRays)
    for (int64_t i = 0; i < b; ++i) {
        if (i + kPixelsAhead < b) __builtin_prefetch(rgb8 + 3 * flat[i + kPixelsAhead], 0, 0);
        const int64_t n = std::upper_bound(start, start + n_images + 1, flat[i]) - start - 1;
        const int64_t local = flat[i] - start[n], w = hw[2 * n + 1];
        const float* ki = k + 4 * n;
        const float* m = pose + pose_stride * n;
        const float cam[3] = {((float)(local % w) + 0.5f - ki[2]) / ki[0], -(((float)(local / w) + 0.5f - ki[3]) / ki[1]),
                              -1.0f};
        float* di = d + 3 * i;
        for (int a = 0; a < 3; ++a) di[a] = m[4 * a] * cam[0] + m[4 * a + 1] * cam[1] + m[4 * a + 2] * cam[2];
        const float length = std::sqrt(di[0] * di[0] + di[1] * di[1] + di[2] * di[2]);
        for (int a = 0; a < 3; ++a) {
            di[a] /= length;
            o[3 * i + a] = m[4 * a + 3];
            rgb[3 * i + a] = (float)rgb8[3 * flat[i] + a] / 255.0f;
        }
        im[i] = n;
        if (coherent) keys[i] = closest_point_code(o + 3 * i, di, (float)extent);
    }
    Tensor order = at::arange(b, pixel.options());
    if (!coherent) return {order, images, origins, dirs, colours};
    const std::vector<int64_t> sorted = stable_order(keys);
    Tensor ordered_images = at::empty_like(images), ordered_origins = at::empty_like(origins),
           ordered_dirs = at::empty_like(dirs), ordered_colours = at::empty_like(colours);
    int64_t *out_order = order.data_ptr<int64_t>(), *out_im = ordered_images.data_ptr<int64_t>();
    float *out_o = ordered_origins.data_ptr<float>(), *out_d = ordered_dirs.data_ptr<float>(),
          *out_rgb = ordered_colours.data_ptr<float>();
    for (int64_t i = 0; i < b; ++i) {
        const int64_t j = sorted[i];
        out_order[i] = j;
        out_im[i] = im[j];
        for (int a = 0; a < 3; ++a) {
            out_o[3 * i + a] = o[3 * j + a];
            out_d[3 * i + a] = d[3 * j + a];
            out_rgb[3 * i + a] = rgb[3 * j + a];
        }
    }
    return {order, ordered_images, ordered_origins, ordered_dirs, ordered_colours};
}

}  // namespace plx_cpu
