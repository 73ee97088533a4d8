// Torch-facing glue for the CUDA kernels: checks tensors, picks the device and stream, and calls the
// plain launchers of kernels_cuda.cu. Compiled only in the CUDA build (setup.py defines
// PLX_WITH_CUDA there); a CPU-only build sees an empty file.
//
// These are the CUDA implementations of the operators declared in ops.cpp (torch.ops.voxfield.*).
// The CPU's per-thread scratch arguments are accepted and ignored: the kernels accumulate with
// atomics. Touched rows are tracked in grad_mask by the kernels and compacted into grad_rows here,
// so callers see the CPU's (grad_rows, num_touched) contract: rows listed exactly when their mask
// byte is set.
#ifdef PLX_WITH_CUDA

#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <torch/library.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/full.h>
#include <ATen/ops/zeros.h>

#include <cstdint>
#include <optional>
#include <string>
#include <tuple>
#include <vector>

#include "cuda_kernels.h"
#include "ops.h"
#include "plenoxels_math.h"

namespace {

using at::Tensor;

using plx::row_stride;

void check_cuda(const Tensor& t, at::ScalarType type, const char* name, const Tensor& like) {
    TORCH_CHECK(t.is_cuda() && t.device() == like.device(), name, " must be on ", like.device());
    TORCH_CHECK(t.scalar_type() == type && t.is_contiguous(), name, " must be contiguous ", at::toString(type));
}

// The kernels read and write rows as float4.
void check_aligned(const Tensor& t, const char* name) {
    TORCH_CHECK(reinterpret_cast<uintptr_t>(t.data_ptr()) % 16 == 0, name,
                " must start on a 16-byte boundary (a fresh contiguous tensor, not an offset view)");
}

void check_launch(cudaError_t err, const char* what) {
    TORCH_CHECK(err == cudaSuccess, "CUDA kernel ", what, " failed: ", cudaGetErrorString(err));
}

cudaStream_t stream() { return c10::cuda::getCurrentCUDAStream().stream(); }

plx_cuda::Grid make_grid(const Tensor& data, const Tensor& links, const Tensor& cell_occ, const Tensor& block_occ,
                         int64_t block, c10::ArrayRef<double> lattice, int64_t degree) {
    check_cuda(data, at::kFloat, "data", data);
    check_cuda(links, at::kInt, "links", data);
    check_cuda(cell_occ, at::kByte, "cell_occ", data);
    check_cuda(block_occ, at::kByte, "block_occ", data);
    TORCH_CHECK(degree >= 0 && degree <= 3, "sh_degree must be 0..3, got ", std::to_string(degree));
    TORCH_CHECK(data.dim() == 2 && data.size(1) == row_stride((int)degree),
                "data must be [N, padded row] for this SH degree");
    TORCH_CHECK(links.dim() == 3 && links.size(0) >= 2 && links.size(1) >= 2 && links.size(2) >= 2,
                "links must be [Rx,Ry,Rz] with every size >= 2");
    TORCH_CHECK(block_occ.dim() == 3 && block > 0 && (block & (block - 1)) == 0,
                "block_occ must be 3-D and block a power of two");
    check_aligned(data, "data");
    plx_cuda::Grid g;
    g.data = data.data_ptr<float>();
    g.links = links.data_ptr<int32_t>();
    g.cell_occ = cell_occ.data_ptr<uint8_t>();
    g.block_occ = block_occ.data_ptr<uint8_t>();
    g.stride = (int)data.size(1);
    g.block = (int)block;
    for (int a = 0; a < 3; ++a) {
        g.res[a] = (int)links.size(a);
        g.bres[a] = (int)block_occ.size(a);
    }
    const char* error = plx::read_lattice(lattice.data(), (long)lattice.size(), g.res, &g.lattice);
    TORCH_CHECK(error == nullptr, error);
    return g;
}

// `background_past_grid_only`: the background shows only where light gets past the grid (March.background_stop).
plx_cuda::March make_march(double step, double stop_transmittance, double near, double sigma_threshold,
                           int64_t max_samples, bool contract, bool background_past_grid_only = false) {
    return plx_cuda::March{step, (float)stop_transmittance, near, (float)sigma_threshold, (int)max_samples, contract,
                           background_past_grid_only ? (float)stop_transmittance : 0.0f};
}

plx_cuda::Rays make_rays(const Tensor& origins, const Tensor& dirs, const Tensor& like) {
    check_cuda(origins, at::kFloat, "origins", like);
    check_cuda(dirs, at::kFloat, "dirs", like);
    TORCH_CHECK(origins.dim() == 2 && origins.size(1) == 3 && dirs.sizes() == origins.sizes(),
                "origins and dirs must be [B,3]");
    return plx_cuda::Rays{origins.data_ptr<float>(), dirs.data_ptr<float>(), nullptr, origins.size(0)};
}

void check_grad_storage(const Tensor& data, const Tensor& grad_data, const Tensor& grad_mask, const Tensor& grad_rows) {
    check_cuda(grad_data, at::kFloat, "grad data", data);
    check_cuda(grad_mask, at::kByte, "grad mask", data);
    check_cuda(grad_rows, at::kInt, "grad rows", data);
    TORCH_CHECK(grad_data.sizes() == data.sizes(), "gradient storage does not match the grid");
    check_aligned(grad_data, "grad data");
    TORCH_CHECK(grad_mask.numel() == data.size(0) && grad_rows.numel() >= data.size(0),
                "grad mask and grad rows need one entry per row");
}

// Rewrites grad_rows[0..count) as the rows whose mask byte is set; returns count.
int64_t compact_touched(const Tensor& grad_mask, Tensor& grad_rows) {
    const Tensor touched = grad_mask.nonzero().reshape({-1}).to(at::kInt);
    const int64_t count = touched.numel();
    grad_rows.narrow(0, 0, count).copy_(touched);
    return count;
}

std::vector<Tensor> render(Tensor data, Tensor links, Tensor cell_occ, Tensor block_occ, int64_t block,
                           c10::ArrayRef<double> lattice, int64_t degree, Tensor origins,
                           Tensor dirs, std::optional<Tensor> background, bool past_grid_only, double step,
                           double stop_transmittance, double near, double sigma_threshold, int64_t max_samples,
                           bool contract) {
    const c10::cuda::CUDAGuard guard(data.device());
    const plx_cuda::Grid g = make_grid(data, links, cell_occ, block_occ, block, lattice, degree);
    plx_cuda::Rays rays = make_rays(origins, dirs, data);
    if (background.has_value()) {
        check_cuda(*background, at::kFloat, "background", data);
        TORCH_CHECK(background->sizes() == origins.sizes(), "background must be [B,3]");
        rays.background = background->data_ptr<float>();
    }
    const int64_t B = rays.count;
    Tensor rgb = at::empty({B, 3}, data.options());
    Tensor depth = at::empty({B}, data.options());
    Tensor opacity = at::empty({B}, data.options());
    check_launch(plx_cuda::render(g, make_march(step, stop_transmittance, near, sigma_threshold, max_samples, contract,
                                                past_grid_only),
                                  (int)degree, rays, rgb.data_ptr<float>(), depth.data_ptr<float>(),
                                  opacity.data_ptr<float>(), stream()),
                 "render");
    return {rgb, depth, opacity};
}

std::tuple<double, Tensor, int64_t> loss_and_grad(Tensor data, Tensor links, Tensor cell_occ, Tensor block_occ,
                                                  int64_t block, c10::ArrayRef<double> lattice,
                                                  int64_t degree, Tensor origins,
                                                  Tensor dirs, Tensor targets, Tensor background,
                                                  bool past_grid_only, double step, double stop_transmittance,
                                                  double near, double sigma_threshold,
                                                  int64_t max_samples, bool contract, double near_gradient,
                                                  Tensor grad_data, Tensor grad_mask, Tensor grad_rows, int64_t num_touched,
                                                  Tensor, Tensor) {
    const c10::cuda::CUDAGuard guard(data.device());
    const plx_cuda::Grid g = make_grid(data, links, cell_occ, block_occ, block, lattice, degree);
    const plx_cuda::Rays rays = make_rays(origins, dirs, data);
    check_cuda(targets, at::kFloat, "targets", data);
    check_cuda(background, at::kFloat, "background", data);
    TORCH_CHECK(targets.sizes() == origins.sizes() && background.sizes() == origins.sizes(),
                "targets and background must be [B,3]");
    check_grad_storage(data, grad_data, grad_mask, grad_rows);
    const int64_t B = rays.count;
    Tensor grad_background = at::empty({B, 3}, data.options());
    if (B == 0) return {0.0, grad_background, num_touched};
    Tensor sse = at::empty({B}, data.options().dtype(at::kDouble));
    plx_cuda::Rays with_background = rays;
    with_background.background = background.data_ptr<float>();
    const float loss_scale = 1.0f / (3.0f * (float)B);
    check_launch(plx_cuda::loss_and_grad(g, make_march(step, stop_transmittance, near, sigma_threshold, max_samples, contract,
                                                       past_grid_only),
                                         (int)degree, with_background, targets.data_ptr<float>(), loss_scale,
                                         (float)near_gradient, sse.data_ptr<double>(), grad_background.data_ptr<float>(),
                                         grad_data.data_ptr<float>(), grad_mask.data_ptr<uint8_t>(), stream()),
                 "loss_and_grad");
    const double total = sse.sum().item<double>();
    return {total, grad_background, compact_touched(grad_mask, grad_rows)};
}

void max_weights(Tensor data, Tensor links, Tensor cell_occ, Tensor block_occ, int64_t block,
                   c10::ArrayRef<double> lattice, int64_t degree, Tensor origins,
                   Tensor dirs, double step, double stop_transmittance, double near, double sigma_threshold,
                   int64_t max_samples, bool contract, Tensor out) {
    const c10::cuda::CUDAGuard guard(data.device());
    const plx_cuda::Grid g = make_grid(data, links, cell_occ, block_occ, block, lattice, degree);
    const plx_cuda::Rays rays = make_rays(origins, dirs, data);
    check_cuda(out, at::kFloat, "out", data);
    TORCH_CHECK(out.numel() == data.size(0), "out must have one entry per row");
    check_launch(plx_cuda::max_weights(g, make_march(step, stop_transmittance, near, sigma_threshold, max_samples, contract),
                                       rays, out.data_ptr<float>(), stream()),
                 "max_weights");
}

std::tuple<int64_t, int64_t> sample_counts(Tensor data, Tensor links, Tensor cell_occ, Tensor block_occ, int64_t block,
                                           c10::ArrayRef<double> lattice, int64_t degree,
                                           Tensor origins, Tensor dirs, double step, double stop_transmittance,
                                           double near, double sigma_threshold, int64_t max_samples, bool contract) {
    const c10::cuda::CUDAGuard guard(data.device());
    const plx_cuda::Grid g = make_grid(data, links, cell_occ, block_occ, block, lattice, degree);
    const plx_cuda::Rays rays = make_rays(origins, dirs, data);
    Tensor counts = at::zeros({2}, data.options().dtype(at::kLong));
    check_launch(plx_cuda::sample_counts(g, make_march(step, stop_transmittance, near, sigma_threshold, max_samples, contract),
                                         rays, reinterpret_cast<unsigned long long*>(counts.data_ptr<int64_t>()),
                                         stream()),
                 "sample_counts");
    const Tensor host = counts.cpu();
    return {host[0].item<int64_t>(), host[1].item<int64_t>()};
}

// Live-block bookkeeping arguments; coords null when none are given.
plx_cuda::LiveBlocks make_live(const Tensor& data, const std::optional<Tensor>& coords, int64_t block,
                               const std::optional<Tensor>& counts, const std::optional<Tensor>& blocks) {
    plx_cuda::LiveBlocks live{nullptr, 1, {0, 0, 0}, nullptr, nullptr};
    if (!coords.has_value()) return live;
    TORCH_CHECK(counts.has_value() && blocks.has_value() && block > 0,
                "live bookkeeping needs coords, block, counts and blocks");
    check_cuda(*coords, at::kInt, "coords", data);
    check_cuda(*counts, at::kInt, "counts", data);
    check_cuda(*blocks, at::kByte, "blocks", data);
    TORCH_CHECK(coords->dim() == 2 && coords->size(0) == data.size(0) && coords->size(1) == 3, "coords must be [N,3]");
    TORCH_CHECK(counts->dim() == 3 && blocks->sizes() == counts->sizes(), "counts must be 3-D and blocks like counts");
    live.coords = coords->data_ptr<int32_t>();
    live.block = (int)block;
    for (int a = 0; a < 3; ++a) live.nblocks[a] = (int)counts->size(a);
    live.counts = counts->data_ptr<int32_t>();
    live.blocks = blocks->data_ptr<uint8_t>();
    return live;
}

void count_live_blocks(Tensor data, Tensor coords, int64_t block, Tensor counts, Tensor blocks) {
    const c10::cuda::CUDAGuard guard(data.device());
    check_cuda(data, at::kFloat, "data", data);
    TORCH_CHECK(data.dim() == 2, "data must be [N, stride]");
    const plx_cuda::LiveBlocks live = make_live(data, coords, block, counts, blocks);
    check_launch(plx_cuda::count_live_blocks(data.data_ptr<float>(), (int)data.size(1), data.size(0), live, stream()),
                 "count_live_blocks");
}

std::tuple<double, int64_t> tv_loss_and_grad(Tensor data, Tensor links, Tensor coords, Tensor sample_rows,
                                              double weight_density, double weight_sh, int64_t degree,
                                              Tensor grad_data, Tensor grad_mask, Tensor grad_rows,
                                              int64_t num_touched, Tensor, Tensor) {
    const c10::cuda::CUDAGuard guard(data.device());
    check_cuda(data, at::kFloat, "data", data);
    check_cuda(links, at::kInt, "links", data);
    check_cuda(coords, at::kInt, "coords", data);
    check_cuda(sample_rows, at::kLong, "sample rows", data);
    check_grad_storage(data, grad_data, grad_mask, grad_rows);
    TORCH_CHECK(links.dim() == 3 && coords.dim() == 2 && coords.size(1) == 3, "links must be 3-D, coords [N,3]");
    const int64_t M = sample_rows.numel();
    if (M == 0) return {0.0, num_touched};
    plx_cuda::TVArgs a;
    a.data = data.data_ptr<float>();
    a.stride = (int)data.size(1);
    a.links = links.data_ptr<int32_t>();
    for (int axis = 0; axis < 3; ++axis) a.res[axis] = (int)links.size(axis);
    a.coords = coords.data_ptr<int32_t>();
    a.sample_rows = sample_rows.data_ptr<int64_t>();
    a.count = M;
    const int columns = 1 + 3 * (int)((degree + 1) * (degree + 1));
    a.column_begin = weight_density != 0.0 ? 0 : 1;
    a.column_end = weight_sh != 0.0 ? columns : 1;
    a.scale_density = (float)(weight_density / (double)M);
    a.scale_sh = (float)(weight_sh / (double)M);
    Tensor loss = at::empty({M}, data.options().dtype(at::kDouble));
    check_launch(plx_cuda::tv_loss_and_grad(a, loss.data_ptr<double>(), grad_data.data_ptr<float>(),
                                            grad_mask.data_ptr<uint8_t>(), stream()),
                 "tv_loss_and_grad");
    const double total = loss.sum().item<double>();
    return {total, compact_touched(grad_mask, grad_rows)};
}

void rmsprop_step(Tensor data, Tensor second_moment, Tensor grad_data, Tensor grad_mask, Tensor grad_rows,
                  int64_t num_touched, int64_t columns, double lr_density, double lr_sh, double beta, double eps,
                  std::optional<Tensor> live_coords, int64_t live_block, std::optional<Tensor> live_counts,
                  std::optional<Tensor> live_blocks) {
    const c10::cuda::CUDAGuard guard(data.device());
    check_cuda(data, at::kFloat, "data", data);
    check_cuda(second_moment, at::kFloat, "second moment", data);
    TORCH_CHECK(second_moment.sizes() == data.sizes(), "second moment must match the grid");
    check_grad_storage(data, grad_data, grad_mask, grad_rows);
    TORCH_CHECK(num_touched >= 0 && num_touched <= grad_rows.numel() && columns >= 1 && columns <= data.size(1),
                "bad touched-row count or column count");
    plx_cuda::RMSPropArgs a{data.data_ptr<float>(),
                            second_moment.data_ptr<float>(),
                            grad_data.data_ptr<float>(),
                            grad_mask.data_ptr<uint8_t>(),
                            grad_rows.data_ptr<int32_t>(),
                            num_touched,
                            (int)data.size(1),
                            (int)columns,
                            (float)lr_density,
                            (float)lr_sh,
                            (float)beta,
                            (float)(1.0 - beta),
                            (float)eps};
    const plx_cuda::LiveBlocks live = make_live(data, live_coords, live_block, live_counts, live_blocks);
    check_launch(plx_cuda::rmsprop_step(a, live, stream()), "rmsprop_step");
}

std::vector<Tensor> build_occupancy(Tensor links, int64_t block) {
    const c10::cuda::CUDAGuard guard(links.device());
    check_cuda(links, at::kInt, "links", links);
    TORCH_CHECK(links.dim() == 3 && links.size(0) >= 2 && links.size(1) >= 2 && links.size(2) >= 2 && block > 0,
                "links must be [Rx,Ry,Rz] with every size >= 2, block > 0");
    const int res[3] = {(int)links.size(0), (int)links.size(1), (int)links.size(2)};
    const int64_t cx = res[0] - 1, cy = res[1] - 1, cz = res[2] - 1;
    const auto options = links.options().dtype(at::kByte);
    Tensor cells = at::empty({cx, cy, cz}, options);
    Tensor blocks = at::empty({(cx + block - 1) / block, (cy + block - 1) / block, (cz + block - 1) / block}, options);
    check_launch(plx_cuda::build_occupancy(links.data_ptr<int32_t>(), res, (int)block, cells.data_ptr<uint8_t>(),
                                           blocks.data_ptr<uint8_t>(), stream()),
                 "build_occupancy");
    return {cells, blocks};
}

// No per-thread buffers on the GPU: empty scratch on the gradient's device.
std::vector<Tensor> grad_scratch(Tensor grad_data, int64_t /*max_slots*/) {
    return {at::empty({0, grad_data.size(0), grad_data.size(1)}, grad_data.options()),
            at::empty({0, grad_data.size(0)}, grad_data.options().dtype(at::kByte))};
}

Tensor sample(Tensor data, Tensor links, Tensor points) {
    const c10::cuda::CUDAGuard guard(data.device());
    check_cuda(data, at::kFloat, "data", data);
    check_cuda(links, at::kInt, "links", data);
    check_cuda(points, at::kFloat, "points", data);
    TORCH_CHECK(data.dim() == 2, "data must be [N, S]");
    TORCH_CHECK(links.dim() == 3 && links.size(0) >= 2 && links.size(1) >= 2 && links.size(2) >= 2,
                "links must be [Rx,Ry,Rz] with every size >= 2");
    TORCH_CHECK(points.dim() == 2 && points.size(1) == 3, "points must be [P,3]");
    const int res[3] = {(int)links.size(0), (int)links.size(1), (int)links.size(2)};
    Tensor out = at::empty({points.size(0), data.size(1)}, data.options());
    check_launch(plx_cuda::sample(data.data_ptr<float>(), (int)data.size(1), links.data_ptr<int32_t>(), res,
                                  points.data_ptr<float>(), points.size(0), out.data_ptr<float>(), stream()),
                 "sample");
    return out;
}

Tensor row_coords(Tensor links, int64_t rows) {
    const c10::cuda::CUDAGuard guard(links.device());
    check_cuda(links, at::kInt, "links", links);
    TORCH_CHECK(links.dim() == 3, "links must be [Rx,Ry,Rz]");
    const int res[3] = {(int)links.size(0), (int)links.size(1), (int)links.size(2)};
    Tensor out = at::full({rows, 3}, -1, links.options());
    check_launch(plx_cuda::row_coords(links.data_ptr<int32_t>(), res, rows, out.data_ptr<int32_t>(), stream()),
                 "row_coords");
    return out;
}

}  // namespace

plx_cuda::Background make_background(const Tensor& centre, const Tensor& radii, const Tensor& texture,
                                     const Tensor& far_colour) {
    check_cuda(centre, at::kFloat, "centre", texture);
    check_cuda(radii, at::kFloat, "radii", texture);
    check_cuda(texture, at::kFloat, "texture", texture);
    check_cuda(far_colour, at::kFloat, "far_colour", texture);
    TORCH_CHECK(centre.numel() == 3 && far_colour.numel() == 3, "centre and far_colour must hold 3 values");
    TORCH_CHECK(texture.dim() == 4 && texture.size(3) == 4 && texture.size(0) == radii.numel(),
                "texture must be [K, H, W, 4] with one sphere per radius");
    return {centre.data_ptr<float>(), radii.data_ptr<float>(), texture.data_ptr<float>(), far_colour.data_ptr<float>(),
            (int)texture.size(0), (int)texture.size(1), (int)texture.size(2)};
}

// The forward's layer record is the CPU's saving (a GPU re-intersects the spheres at no cost that matters): the
// background's optimiser asks for none on a GPU.
Tensor background_render(Tensor origins, Tensor dirs, Tensor centre, Tensor radii, Tensor texture, Tensor far_colour,
                         std::optional<Tensor> layer_texels, std::optional<Tensor> layer_weights) {
    TORCH_CHECK(!layer_texels.has_value() && !layer_weights.has_value(),
                "the background's layer record is a CPU path; a GPU re-intersects the spheres");
    const c10::cuda::CUDAGuard guard(texture.device());
    const plx_cuda::Background bg = make_background(centre, radii, texture, far_colour);
    const plx_cuda::Rays rays = make_rays(origins, dirs, texture);
    Tensor rgb = at::empty({origins.size(0), 3}, texture.options());
    check_launch(plx_cuda::background_render(bg, rays, rgb.data_ptr<float>(), stream()), "background_render");
    return rgb;
}

int64_t background_backward(Tensor origins, Tensor dirs, Tensor centre, Tensor radii, Tensor texture, Tensor far_colour,
                            Tensor rgb, Tensor grad_rgb, std::optional<Tensor> layer_texels,
                            std::optional<Tensor> layer_weights, Tensor grad_texture, Tensor grad_mask, Tensor grad_rows,
                            int64_t, Tensor, Tensor) {
    TORCH_CHECK(!layer_texels.has_value() && !layer_weights.has_value(),
                "the background's layer record is a CPU path; a GPU re-intersects the spheres");
    const c10::cuda::CUDAGuard guard(texture.device());
    const plx_cuda::Background bg = make_background(centre, radii, texture, far_colour);
    const plx_cuda::Rays rays = make_rays(origins, dirs, texture);
    check_cuda(rgb, at::kFloat, "rgb", texture);
    check_cuda(grad_rgb, at::kFloat, "grad_rgb", texture);
    check_cuda(grad_texture, at::kFloat, "grad_texture", texture);
    const int64_t texels = texture.numel() / 4;
    TORCH_CHECK(rgb.sizes() == origins.sizes() && grad_rgb.sizes() == origins.sizes() && grad_texture.numel() == 4 * texels,
                "rgb and grad_rgb must be [B, 3] and grad_texture [K*H*W, 4]");
    TORCH_CHECK(grad_mask.is_cuda() && grad_mask.scalar_type() == at::kByte && grad_mask.numel() == texels &&
                grad_rows.is_cuda() && grad_rows.scalar_type() == at::kInt && grad_rows.numel() >= texels,
                "grad mask and rows need one uint8 / int32 entry per texel on the texture's device");
    check_launch(plx_cuda::background_backward(bg, rays, rgb.data_ptr<float>(), grad_rgb.data_ptr<float>(),
                                               grad_texture.data_ptr<float>(),
                                               grad_mask.data_ptr<uint8_t>(), stream()),
                 "background_backward");
    return compact_touched(grad_mask, grad_rows);
}

TORCH_LIBRARY_IMPL(voxfield, CUDA, m) {
    PLX_IMPL_DEVICE_OPS(m);
}

#endif  // PLX_WITH_CUDA
