// The CPU kernels of the Plenoxels core, registered for torch.ops.voxfield (the schema is declared once in
// ops.cpp). They are split by concern like the CUDA side: cpu_render.cpp (render, loss and gradient, max weights),
// cpu_grid.cpp (occupancy, live blocks, samples, row coordinates), cpu_regularizers.cpp (total variation),
// cpu_optim.cpp (sparse RMSProp; the splats' row Adam), cpu_background.cpp (the background spheres), cpu_rays.cpp (a
// training batch's rays), cpu_splats.cpp (the splat rasterizer's compositing), on the shared machinery of
// cpu_kernels.h and cpu_common.cpp. The batch's rays and the splat kernels are the CPU's alone: a GPU makes its
// batches from the ray set's tables in a few launches, and splats are distilled and scored on the CPU.
#include <torch/library.h>

#include "cpu_kernels.h"

TORCH_LIBRARY_IMPL(voxfield, CPU, m) {
    using namespace plx_cpu;
    m.impl("advise_huge_pages", [](const Tensor& t) {
        TORCH_CHECK(t.is_contiguous(), "advise_huge_pages needs a contiguous CPU tensor");
        return advise_huge_pages(t.data_ptr(), (size_t)t.nbytes());
    });
    PLX_IMPL_DEVICE_OPS(m);
    PLX_IMPL(m, loss_and_grad_spheres);
    PLX_IMPL(m, adam_rows);
    PLX_IMPL(m, pixel_rays);
    PLX_IMPL(m, splat_composite);
    PLX_IMPL(m, splat_composite_backward);
}
