// The operator schema of the Plenoxels core, declared once: torch.ops.voxfield.<name>. The CPU
// kernels (kernels_cpu.cpp) and the CUDA kernels (bindings_cuda.cpp, CUDA build only) register
// implementations of these same operators, and torch's dispatcher picks one from the tensors' device.
// plenoxels/native.py is the Python side.
//
// Shared conventions: `data` [N, S] packed rows (S = padded_stride(1 + 3K)), `links` [Rx, Ry, Rz]
// int32 (row or -1), occupancy as uint8; gradients in the layout of `data` with a touched mask [N]
// and touched-row list [N] of which the first `num_touched` entries are valid (every kernel that
// adds gradient returns the new count). `scratch_grad` / `scratch_mask` come from grad_scratch: the
// CPU's per-thread buffers, empty on a GPU (whose kernels accumulate with atomics).
#include <omp.h>
#include <torch/extension.h>
#include <torch/library.h>

#include "plenoxels_math.h"

namespace {

#define PLX_GRID "Tensor data, Tensor links, Tensor cell_occ, Tensor block_occ, int block, float[] lattice, " \
                 "int sh_degree"
#define PLX_MARCH "float step, float stop_transmittance, float near, float sigma_threshold, int max_samples, " \
                  "bool contract"
#define PLX_GRAD "Tensor(a!) grad_data, Tensor(b!) grad_mask, Tensor(c!) grad_rows, int num_touched, " \
                 "Tensor(d!) scratch_grad, Tensor(e!) scratch_mask"

}  // namespace

TORCH_LIBRARY(voxfield, m) {
    // Device-free facts, one kernel for every device.
    m.def("padded_stride(int columns) -> int", [](int64_t columns) -> int64_t { return plx::padded_stride((int)columns); });
    m.def("num_threads() -> int", []() -> int64_t { return omp_get_max_threads(); });
    // Asks for 2 MiB pages behind a contiguous CPU tensor; true when advised.
    m.def("advise_huge_pages(Tensor t) -> bool");
    // Per-thread gradient scratch for a gradient table: (float [T-1, N, S], uint8 [T-1, N]), zero, with T - 1 at
    // most max_slots: the kernels that add gradient run on as many threads as there are slots, plus one.
    m.def("grad_scratch(Tensor grad_data, int max_slots) -> Tensor[]");
    // (cells [Rx-1, Ry-1, Rz-1], blocks) uint8: any corner allocated / any cell of the block occupied.
    m.def("build_occupancy(Tensor links, int block) -> Tensor[]");
    // Live-vertex counts and flags per occupancy block, recounted from scratch.
    m.def("count_live_blocks(Tensor data, Tensor coords, int block, Tensor(a!) counts, Tensor(b!) blocks) -> ()");
    // int32 [rows, 3]: the vertex of every allocated row.
    m.def("row_coords(Tensor links, int rows) -> Tensor");
    // Trilinear interpolation of every column at grid-frame points [P, 3] -> [P, S]; zeros outside the box.
    m.def("sample(Tensor data, Tensor links, Tensor points) -> Tensor");
    // [rgb [B, 3], depth [B], opacity [B]]; past_grid_only: the background shows only on rays the grid lets light
    // past, none on a ray stopped below stop_transmittance (plx::light_past_grid), here and in the loss.
    m.def("render(" PLX_GRID ", Tensor origins, Tensor dirs, Tensor? background, bool past_grid_only, " PLX_MARCH
          ") -> Tensor[]");
    // (sum of squared errors, d loss / d background [B, 3], touched count); adds d(mse)/d(data), each sample's
    // share scaled down nearer the camera than near_gradient (plx::near_gradient_scale; 0: none).
    m.def("loss_and_grad(" PLX_GRID ", Tensor origins, Tensor dirs, Tensor targets, Tensor background, "
          "bool past_grid_only, " PLX_MARCH
          ", float near_gradient, " PLX_GRAD ") -> (float, Tensor, int)");
    // loss_and_grad with the background spheres (background_render's arguments, on the rays sphere_origins and
    // sphere_dirs, with its layer record) drawn in the same pass, only on the rays that light gets past the grid on
    // (CPU only: a GPU draws them all beforehand): (sse, d loss / d background, the background [B, 3], touched count).
    m.def("loss_and_grad_spheres(" PLX_GRID ", Tensor origins, Tensor dirs, Tensor targets, Tensor sphere_origins, "
          "Tensor sphere_dirs, Tensor centre, Tensor radii, Tensor texture, Tensor far_colour, Tensor(f!) layer_texels, "
          "Tensor(g!) layer_weights, " PLX_MARCH ", float near_gradient, " PLX_GRAD ") -> (float, Tensor, Tensor, int)");
    // out[row] = max(out[row], largest weight of a sample that reads the row).
    m.def("max_weights(" PLX_GRID ", Tensor origins, Tensor dirs, " PLX_MARCH ", Tensor(a!) out) -> ()");
    // (samples on the rays' lattices inside the box, samples that contributed).
    m.def("sample_counts(" PLX_GRID ", Tensor origins, Tensor dirs, " PLX_MARCH ") -> (int, int)");
    // (TV loss at the sampled rows, touched count); adds its gradient.
    m.def("tv_loss_and_grad(Tensor data, Tensor links, Tensor coords, Tensor sample_rows, float weight_density, "
          "float weight_sh, int sh_degree, " PLX_GRAD ") -> (float, int)");
    // The multi-sphere background: colour [B, 3] of rays (origins, any-length dirs) through spheres of `radii`
    // around `centre`, textures [K, H, W, 4] (raw density, colour logits), far_colour [3].
    // With layer_texels [B, K, 4] int32 and layer_weights [B, K, 4] (CPU), it also records where each ray met each
    // sphere (texel rows, -1 for none; bilinear weights), which background_backward then reads instead of
    // intersecting the spheres again.
    m.def("background_render(Tensor origins, Tensor dirs, Tensor centre, Tensor radii, Tensor texture, "
          "Tensor far_colour, Tensor(a!)? layer_texels=None, Tensor(b!)? layer_weights=None) -> Tensor");
    // Adds d loss / d texture into the gradient table [K*H*W, 4] (its texel rows, as the grid's) from the rays'
    // colours (background_render's) and d loss / d colour [B, 3]; returns the new touched count.
    m.def("background_backward(Tensor origins, Tensor dirs, Tensor centre, Tensor radii, Tensor texture, "
          "Tensor far_colour, Tensor rgb, Tensor grad_rgb, Tensor? layer_texels, Tensor? layer_weights, " PLX_GRAD
          ") -> int");
    // RMSProp on the touched rows; clears their gradient. With live coords/counts/blocks, keeps them current.
    m.def("rmsprop_step(Tensor(a!) data, Tensor(b!) second_moment, Tensor(c!) grad_data, Tensor(d!) grad_mask, "
          "Tensor grad_rows, int num_touched, int columns, float lr_density, float lr_sh, float beta, float eps, "
          "Tensor? live_coords, int live_block, Tensor(e!)? live_counts, Tensor(f!)? live_blocks) -> ()");
    // Adam on distinct rows of a table [N, D] (CPU only, as the splats' distillation): moments [N, D], per-row step
    // counts [N] (float), grad [R, D] of those rows; column c's rate is rates[c], times row_factor[row] on the columns
    // [scaled_begin, scaled_end).
    m.def("adam_rows(Tensor(a!) data, Tensor(b!) first, Tensor(c!) second, Tensor(d!) steps, Tensor rows, "
          "Tensor grad, Tensor rates, Tensor row_factor, int scaled_begin, int scaled_end, float beta1, float beta2, "
          "float eps) -> ()");
    // A training batch's rays (CPU only: a GPU makes them from the ray set's tables in a few launches): [order [B],
    // image [B], origins [B, 3], unit dirs [B, 3], colours [B, 3]] of the photos' pixels at flat indices `pixel` [B]
    // into pixels uint8 [P, 3] (the photos side by side from offsets [N + 1], of sizes [N, 2] (h, w)), with
    // intrinsics [N, 4] (fl_x, fl_y, cx, cy) and c2w [N, 4, 4]; output i is pixel order[i]: the pixels' order, or with
    // coherent the Morton order of each ray's point closest to the origin within [-extent, extent]^3 (stable).
    m.def("pixel_rays(Tensor pixel, Tensor intrinsics, Tensor c2w, Tensor pixels, Tensor offsets, Tensor sizes, "
          "bool coherent, float extent) -> Tensor[]");
    // Splats composited over the window (x0, y0, w, h) of an image (CPU only: splats are distilled on the CPU), from
    // their projections (means2d [M, 2] in pixel-index coordinates, conics [M, 3], colours [M, 3], opacities [M],
    // radii [M] of their 3 sigma boxes) and order [M] (front to back): [rgb [h*w, 3], opacity [h*w], ends [h*w]
    // (int32, how far down its tile's list each pixel went) and light [h*w] (float64, what light each pixel kept),
    // which the backward pass reads].
    m.def("splat_composite(Tensor means2d, Tensor conics, Tensor colours, Tensor opacities, Tensor radii, "
          "Tensor order, int x0, int y0, int w, int h, Tensor background) -> Tensor[]");
    // d loss / d (means2d, conics, colours, opacities) from d loss / d (rgb, opacity) of splat_composite.
    m.def("splat_composite_backward(Tensor means2d, Tensor conics, Tensor colours, Tensor opacities, Tensor radii, "
          "Tensor order, int x0, int y0, int w, int h, Tensor background, Tensor ends, Tensor light, Tensor grad_rgb, "
          "Tensor grad_opacity) -> Tensor[]");
}

// `import plenoxels._C` loads this library, which registers the operators above; the module itself is empty.
PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {}
