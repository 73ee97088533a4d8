// Per-pair math of the splat rasterizer (one splat seen at one pixel centre), for any backend: plain inline functions
// on scalars, as plenoxels_math.h. The PyTorch reference is plenoxels/splats/rasterize.py (_alphas, composite); the
// rule, as in 3D Gaussian Splatting and glTF's KHR_gaussian_splatting:
//   d = pixel - mean2d, power = -(a dx^2 + 2 b dx dy + c dy^2) / 2 with (a, b, c) the inverse 2D covariance,
//   alpha = min(ALPHA_MAX, opacity exp(min(power, 0))); a pair under ALPHA_MIN is skipped, and a pixel stops before
//   the pair that would leave it less than STOP_TRANSMITTANCE of its light.
#pragma once

#include <math.h>

#include "plenoxels_math.h"

namespace plx::splat {

constexpr float kAlphaMin = 1.0f / 255.0f;
constexpr float kAlphaMax = 0.99f;
constexpr double kStopTransmittance = 1e-4;

// A splat's 3 sigma box on the pixel lattice, clipped to the window [x0, x1] x [y0, y1] (inclusive): empty when
// lo > hi. Rounded as the reference rounds (ceil of the low edge, floor of the high one, in float).
struct Box {
    int lo_x, hi_x, lo_y, hi_y;
};

PLX_HD Box box_of(float mx, float my, float radius, int x0, int y0, int x1, int y1) {
    Box b;
    b.lo_x = (int)fmaxf(ceilf(mx - radius), (float)x0);
    b.hi_x = (int)fminf(floorf(mx + radius), (float)x1);
    b.lo_y = (int)fmaxf(ceilf(my - radius), (float)y0);
    b.hi_y = (int)fminf(floorf(my + radius), (float)y1);
    return b;
}

PLX_HD bool box_holds(const Box& b, int x, int y) { return x >= b.lo_x && x <= b.hi_x && y >= b.lo_y && y <= b.hi_y; }

// power at offset (dx, dy); the Gaussian's value is exp(min(power, 0)).
PLX_HD float power_at(const float* conic, float dx, float dy) {
    return -0.5f * (conic[0] * (dx * dx) + 2.0f * conic[1] * dx * dy + conic[2] * (dy * dy));
}

// A power under which opacity exp(power) is surely under ALPHA_MIN (a margin below the exact bound, so that rounding
// never skips a pair the reference keeps): pairs below it need no exp.
PLX_HD float faint_power(float opacity) { return opacity > 0.0f ? logf(kAlphaMin / opacity) - 1e-3f : -INFINITY; }

// alpha of the pair; *gauss receives exp(min(power, 0)) for the backward pass.
PLX_HD float alpha_at(float opacity, const float* conic, float dx, float dy, float* gauss) {
    *gauss = expf(fminf(power_at(conic, dx, dy), 0.0f));
    return fminf(opacity * *gauss, kAlphaMax);
}

// Adds to g_mean [2], g_conic [3] and *g_opacity what d loss / d alpha = g_alpha gives them (no gradient where alpha
// is held at ALPHA_MAX, as the reference's clamp gives none).
PLX_HD void alpha_backward(float opacity, const float* conic, float dx, float dy, float gauss, float g_alpha,
                           float* g_mean, float* g_conic, float* g_opacity) {
    if (opacity * gauss > kAlphaMax) return;
    *g_opacity += g_alpha * gauss;
    if (power_at(conic, dx, dy) > 0.0f) return;
    const float g_power = g_alpha * opacity * gauss;
    g_conic[0] += -0.5f * g_power * dx * dx;
    g_conic[1] += -g_power * dx * dy;
    g_conic[2] += -0.5f * g_power * dy * dy;
    g_mean[0] += g_power * (conic[0] * dx + conic[1] * dy);
    g_mean[1] += g_power * (conic[1] * dx + conic[2] * dy);
}

}  // namespace plx::splat
