// The C++ signature of each operator of ops.cpp, stated once for both backends. Torch refuses, when
// the library loads, a second kernel whose C++ signature differs from the first's in any way (a
// `const Tensor&` against a `Tensor`), and that refusal aborts the process. Registering through
// PLX_IMPL turns such a drift into a compile error in the backend that drifted.
//
// Both backends put numbers into their error messages as std::to_string(n), never as the number
// itself: on one GPU machine (Ubuntu 24.04, g++ 13.3, torch 2.11+cu130) streaming an integer in any
// extension's TORCH_CHECK message segfaulted (a three-line extension showed it), so a refusal
// became a crash. Strings stream there as they should.
#pragma once

#include <ATen/core/Tensor.h>
#include <c10/util/ArrayRef.h>

#include <cstdint>
#include <optional>
#include <tuple>
#include <vector>

namespace plx::op {

using at::Tensor;
using Doubles = c10::ArrayRef<double>;
using MaybeTensor = std::optional<Tensor>;

using grad_scratch = std::vector<Tensor>(Tensor grad_data, int64_t max_slots);
using build_occupancy = std::vector<Tensor>(Tensor links, int64_t block);
using count_live_blocks = void(Tensor data, Tensor coords, int64_t block, Tensor counts, Tensor blocks);
using row_coords = Tensor(Tensor links, int64_t rows);
using sample = Tensor(Tensor data, Tensor links, Tensor points);
using render = std::vector<Tensor>(Tensor data, Tensor links, Tensor cell_occ, Tensor block_occ, int64_t block,
                                   Doubles lattice, int64_t degree, Tensor origins, Tensor dirs,
                                   MaybeTensor background, bool past_grid_only, double step,
                                   double stop_transmittance, double near, double sigma_threshold, int64_t max_samples,
                                   bool contract);
using loss_and_grad = std::tuple<double, Tensor, int64_t>(
    Tensor data, Tensor links, Tensor cell_occ, Tensor block_occ, int64_t block, Doubles lattice,
    int64_t degree, Tensor origins, Tensor dirs, Tensor targets, Tensor background, bool past_grid_only, double step,
    double stop_transmittance, double near, double sigma_threshold, int64_t max_samples, bool contract,
    double near_gradient, Tensor grad_data, Tensor grad_mask, Tensor grad_rows, int64_t num_touched, Tensor scratch_grad,
    Tensor scratch_mask);
using loss_and_grad_spheres = std::tuple<double, Tensor, Tensor, int64_t>(
    Tensor data, Tensor links, Tensor cell_occ, Tensor block_occ, int64_t block, Doubles lattice,
    int64_t degree, Tensor origins, Tensor dirs, Tensor targets, Tensor sphere_origins, Tensor sphere_dirs,
    Tensor centre, Tensor radii, Tensor texture, Tensor far_colour, Tensor layer_texels, Tensor layer_weights,
    double step, double stop_transmittance, double near, double sigma_threshold, int64_t max_samples, bool contract,
    double near_gradient, Tensor grad_data, Tensor grad_mask, Tensor grad_rows, int64_t num_touched, Tensor scratch_grad,
    Tensor scratch_mask);
using max_weights = void(Tensor data, Tensor links, Tensor cell_occ, Tensor block_occ, int64_t block, Doubles lattice,
                         int64_t degree, Tensor origins, Tensor dirs, double step,
                         double stop_transmittance, double near, double sigma_threshold, int64_t max_samples,
                         bool contract, Tensor out);
using sample_counts = std::tuple<int64_t, int64_t>(Tensor data, Tensor links, Tensor cell_occ, Tensor block_occ,
                                                   int64_t block, Doubles lattice, int64_t degree,
                                                   Tensor origins, Tensor dirs, double step,
                                                   double stop_transmittance, double near, double sigma_threshold,
                                                   int64_t max_samples, bool contract);
using tv_loss_and_grad = std::tuple<double, int64_t>(Tensor data, Tensor links, Tensor coords, Tensor sample_rows,
                                                     double weight_density, double weight_sh, int64_t degree,
                                                     Tensor grad_data, Tensor grad_mask, Tensor grad_rows,
                                                     int64_t num_touched, Tensor scratch_grad, Tensor scratch_mask);
using rmsprop_step = void(Tensor data, Tensor second_moment, Tensor grad_data, Tensor grad_mask, Tensor grad_rows,
                          int64_t num_touched, int64_t columns, double lr_density, double lr_sh, double beta,
                          double eps, MaybeTensor live_coords, int64_t live_block, MaybeTensor live_counts,
                          MaybeTensor live_blocks);
using background_render = Tensor(Tensor origins, Tensor dirs, Tensor centre, Tensor radii, Tensor texture,
                                 Tensor far_colour, MaybeTensor layer_texels, MaybeTensor layer_weights);
using background_backward = int64_t(Tensor origins, Tensor dirs, Tensor centre, Tensor radii, Tensor texture,
                                    Tensor far_colour, Tensor rgb, Tensor grad_rgb, MaybeTensor layer_texels,
                                    MaybeTensor layer_weights, Tensor grad_texture, Tensor grad_mask,
                                    Tensor grad_rows, int64_t num_touched, Tensor scratch_grad,
                                    Tensor scratch_mask);

using adam_rows = void(Tensor data, Tensor first, Tensor second, Tensor steps, Tensor rows, Tensor grad, Tensor rates,
                       Tensor row_factor, int64_t scaled_begin, int64_t scaled_end, double beta1, double beta2,
                       double eps);
using pixel_rays = std::vector<Tensor>(Tensor pixel, Tensor intrinsics, Tensor c2w, Tensor pixels, Tensor offsets,
                                         Tensor sizes, bool coherent, double extent);
using splat_composite = std::vector<Tensor>(Tensor means2d, Tensor conics, Tensor colours, Tensor opacities,
                                            Tensor radii, Tensor order, int64_t x0, int64_t y0, int64_t w, int64_t h,
                                            Tensor background);
using splat_composite_backward = std::vector<Tensor>(Tensor means2d, Tensor conics, Tensor colours, Tensor opacities,
                                                     Tensor radii, Tensor order, int64_t x0, int64_t y0, int64_t w,
                                                     int64_t h, Tensor background, Tensor ends, Tensor light,
                                                     Tensor grad_rgb, Tensor grad_opacity);
}  // namespace plx::op

// Registers the function `name` of the current scope as the kernel of operator `name`; it must have
// exactly the signature plx::op::name (a static_cast between function pointer types does not compile).
#define PLX_IMPL(library, name) (library).impl(#name, static_cast<plx::op::name*>(&name))

// Every operator that runs on a device, each backend's kernels registered with the functions of the same names
// in the scope of its TORCH_LIBRARY_IMPL block: a backend that lacks one does not compile. (The CPU's block also
// registers advise_huge_pages, a host-memory helper, the loss with the background spheres drawn in its pass, and the
// splat rasterizer's compositing.)
#define PLX_IMPL_DEVICE_OPS(library) \
    PLX_IMPL(library, grad_scratch); \
    PLX_IMPL(library, build_occupancy); \
    PLX_IMPL(library, count_live_blocks); \
    PLX_IMPL(library, row_coords); \
    PLX_IMPL(library, sample); \
    PLX_IMPL(library, render); \
    PLX_IMPL(library, loss_and_grad); \
    PLX_IMPL(library, max_weights); \
    PLX_IMPL(library, sample_counts); \
    PLX_IMPL(library, tv_loss_and_grad); \
    PLX_IMPL(library, rmsprop_step); \
    PLX_IMPL(library, background_render); \
    PLX_IMPL(library, background_backward)
