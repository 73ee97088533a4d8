// Per-sample math of the multi-sphere background, shared by the CPU and CUDA kernels.
// Included by plenoxels_math.h, after the definitions it uses; include that header, not this one.
#pragma once

namespace plx {

// ---- The multi-sphere background (plenoxels/background.py; its twin is reference.background_colour) ------------
// Concentric spheres, each an equirectangular texture of 4 channels (raw density, then colour logits R, G, B) laid
// out as rows [sphere][row][column][4]. A ray reads each sphere where it leaves it; a layer's opacity is
// 1 - exp(-relu(density)) and its colour sigmoid(logits); spheres composite front (small radius) to back, and the
// transmittance left sees far_colour.

// Where a ray (origin relative to the centre `rel`, unit direction `unit`) leaves the sphere of `radius`, as a unit
// direction from the centre; false when it misses or the exit lies behind the origin. Double precision so that
// spheres at a million times the foreground's size still meet the ray where they should.
PLX_HD bool bg_exit(const double rel[3], const double unit[3], double radius, double p[3]) {
    const double b = rel[0] * unit[0] + rel[1] * unit[1] + rel[2] * unit[2];
    const double c = rel[0] * rel[0] + rel[1] * rel[1] + rel[2] * rel[2] - radius * radius;
    const double disc = b * b - c;
    if (disc < 0.0) return false;
    const double t = -b + sqrt(disc);
    if (!(t > 0.0)) return false;
    // The exit point lies on the sphere, so dividing by the radius makes it a unit vector (to rounding, which the
    // texel lookup's clamp absorbs).
    const double inv = 1.0 / radius;
    for (int a = 0; a < 3; ++a) p[a] = (rel[a] + t * unit[a]) * inv;
    return true;
}

// The 4 texels (row * width + column, within one sphere) and bilinear weights at unit direction p: texel centres
// at (i + 0.5) / W of the azimuth from -pi and (j + 0.5) / H of the polar angle from +z; azimuth wraps, rows clamp.
PLX_HD void bg_texels(const double p[3], int height, int width, int texel[4], float w[4]) {
    // Single precision from here: the direction is already exact to ~1e-7 rad, far finer than any texel.
    const float kPi = 3.14159265358979323846f;
    const float z = (float)p[2];
    const float azimuth = atan2f((float)p[1], (float)p[0]);
    const float elevation = asinf(z < -1.0f ? -1.0f : (z > 1.0f ? 1.0f : z));
    const float u = (azimuth + kPi) / (2.0f * kPi) * width - 0.5f;
    float v = (0.5f * kPi - elevation) / kPi * height - 0.5f;
    v = v < 0.0f ? 0.0f : (v > height - 1.0f ? height - 1.0f : v);
    const float fu = floorf(u), fv = floorf(v);
    const float au = u - fu, av = v - fv;
    int c0 = (int)fu % width;
    if (c0 < 0) c0 += width;
    const int c1 = (c0 + 1) % width;
    const int r0 = (int)fv < height - 1 ? (int)fv : height - 1;
    const int r1 = r0 + 1 < height ? r0 + 1 : height - 1;
    texel[0] = r0 * width + c0;
    texel[1] = r0 * width + c1;
    texel[2] = r1 * width + c0;
    texel[3] = r1 * width + c1;
    w[0] = (1.0f - au) * (1.0f - av);
    w[1] = au * (1.0f - av);
    w[2] = (1.0f - au) * av;
    w[3] = au * av;
}

// One sphere's interpolated channels for a ray: false when the ray does not meet it.
struct BgLayer {
    int texel[4];    // rows of the texture table (sphere offset included)
    float w[4];
    float raw[4];    // interpolated raw density and colour logits
};

// The interpolated channels of the texels `layer` names (texel rows and bilinear weights already set).
PLX_HD void bg_read(const float* texture, BgLayer* layer) {
    for (int c = 0; c < 4; ++c) layer->raw[c] = 0.0f;
    for (int i = 0; i < 4; ++i) {
        const float* row = texture + 4 * (int64_t)layer->texel[i];
        for (int c = 0; c < 4; ++c) layer->raw[c] += layer->w[i] * row[c];
    }
}

// Where a ray meets sphere k: its texels and weights (sphere offset included) and their channels.
PLX_HD bool bg_layer(const float* texture, int k, int height, int width, const double rel[3], const double unit[3],
                     double radius, BgLayer* layer) {
    double p[3];
    if (!bg_exit(rel, unit, radius, p)) return false;
    bg_texels(p, height, width, layer->texel, layer->w);
    const int64_t base = (int64_t)k * height * width;
    for (int i = 0; i < 4; ++i) layer->texel[i] += (int)base;
    bg_read(texture, layer);
    return true;
}

PLX_HD float bg_sigmoid(float x) { return 1.0f / (1.0f + expf(-x)); }

// Ray set-up shared by forward and backward: origin relative to the centre, unit direction.
PLX_HD void bg_ray(const float* o, const float* d, const float* centre, double rel[3], double unit[3]) {
    double n = 0.0;
    for (int a = 0; a < 3; ++a) {
        rel[a] = (double)o[a] - (double)centre[a];
        unit[a] = d[a];
        n += unit[a] * unit[a];
    }
    n = sqrt(n) > 1e-30 ? sqrt(n) : 1e-30;
    for (int a = 0; a < 3; ++a) unit[a] /= n;
}

// A ray stops compositing spheres once this little light gets through (as the grid's rays stop at
// stop_transmittance): the spheres behind an opaque one cost nothing. reference.background_colour does the same.
#define PLX_BG_STOP_TRANSMITTANCE 1e-4f

// The compositing below takes each sphere's layer from `layer(k, &out)` (false: the ray does not meet sphere k), so
// one statement of the math serves rays that intersect the spheres as they go (bg_layer) and a backward pass that
// reads back the layers its forward pass recorded.

// Colour of one ray: front-to-back composite of the spheres, then far_colour.
#ifdef __CUDACC__
#pragma nv_exec_check_disable  // `layer` is a device functor on the GPU, a host one on the CPU
#endif
template <typename Layer>
PLX_HD void bg_composite(int spheres, Layer layer, const float* far_colour, float rgb[3]) {
    float transmittance = 1.0f;
    rgb[0] = rgb[1] = rgb[2] = 0.0f;
    for (int k = 0; k < spheres && transmittance >= PLX_BG_STOP_TRANSMITTANCE; ++k) {
        BgLayer l;
        if (!layer(k, &l)) continue;
        const float alpha = 1.0f - expf(-(l.raw[0] > 0.0f ? l.raw[0] : 0.0f));
        const float weight = transmittance * alpha;
        for (int c = 0; c < 3; ++c) rgb[c] += weight * bg_sigmoid(l.raw[1 + c]);
        transmittance *= 1.0f - alpha;
    }
    for (int c = 0; c < 3; ++c) rgb[c] += transmittance * far_colour[c];
}

PLX_HD void bg_forward(const float* texture, const float* radii, int spheres, int height, int width, const double rel[3],
                       const double unit[3], const float* far_colour, float rgb[3]) {
    bg_composite(spheres, [&](int k, BgLayer* l) { return bg_layer(texture, k, height, width, rel, unit, radii[k], l); },
                 far_colour, rgb);
}

// d loss / d texel channels of one ray given its colour `total` (bg_forward's) and d loss / d colour `g`, handed
// texel by texel to `add(row, grad[4])`. With A_k the colour composited up to and including sphere k and C the
// ray's colour, d C / d sigma_k = T_k (1 - alpha_k) c_k - (C - A_k) for sigma_k > 0: no division by 1 - alpha, so
// opaque layers stay finite.
#ifdef __CUDACC__
#pragma nv_exec_check_disable  // `layer` and `add` are device functors on the GPU, host ones on the CPU
#endif
template <typename Layer, typename Add>
PLX_HD void bg_composite_backward(int spheres, Layer layer, const float total[3], const float g[3], Add add) {
    float transmittance = 1.0f, acc[3] = {0.0f, 0.0f, 0.0f};
    for (int k = 0; k < spheres && transmittance >= PLX_BG_STOP_TRANSMITTANCE; ++k) {
        BgLayer l;
        if (!layer(k, &l)) continue;
        const bool positive = l.raw[0] > 0.0f;
        const float alpha = 1.0f - expf(-(positive ? l.raw[0] : 0.0f));
        const float weight = transmittance * alpha;
        float colour[3], grad[4];
        float dsigma = 0.0f;
        for (int c = 0; c < 3; ++c) {
            colour[c] = bg_sigmoid(l.raw[1 + c]);
            acc[c] += weight * colour[c];
            grad[1 + c] = g[c] * weight * colour[c] * (1.0f - colour[c]);
            dsigma += g[c] * (transmittance * (1.0f - alpha) * colour[c] - (total[c] - acc[c]));
        }
        grad[0] = positive ? dsigma : 0.0f;
        for (int i = 0; i < 4; ++i) {
            float texel_grad[4];
            for (int c = 0; c < 4; ++c) texel_grad[c] = l.w[i] * grad[c];
            add(l.texel[i], texel_grad);
        }
        transmittance *= 1.0f - alpha;
    }
}

#ifdef __CUDACC__
#pragma nv_exec_check_disable  // `add` is a device functor on the GPU, a host one on the CPU
#endif
template <typename Add>
PLX_HD void bg_backward(const float* texture, const float* radii, int spheres, int height, int width,
                        const double rel[3], const double unit[3], const float total[3], const float g[3], Add add) {
    bg_composite_backward(
        spheres, [&](int k, BgLayer* l) { return bg_layer(texture, k, height, width, rel, unit, radii[k], l); }, total,
        g, add);
}

}  // namespace plx
