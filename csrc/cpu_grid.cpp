// The sparse grid's bookkeeping on the CPU: occupancy for empty-space skipping, live-vertex counts per block,
// trilinear samples at arbitrary points, and the coordinates of the allocated rows.
#include "cpu_kernels.h"

namespace plx_cpu {

// Live-vertex counts per block from scratch: a vertex is live when its raw density is > 0. A block
// with no live vertex can hold no sample with density > 0 (interpolation is a convex combination
// and empty corners count as 0), so the march skips it whatever sigma_threshold (>= 0) is.
void count_live_blocks(Tensor data, Tensor coords, int64_t block, Tensor counts, Tensor blocks) {
    check_float_rows(data, "data");
    TORCH_CHECK(coords.scalar_type() == at::kInt && coords.is_contiguous(), "coords must be int32 [N,3]");
    TORCH_CHECK(counts.scalar_type() == at::kInt && counts.is_contiguous() && counts.dim() == 3, "counts must be int32 3-D");
    TORCH_CHECK(blocks.scalar_type() == at::kByte && blocks.is_contiguous() && blocks.sizes() == counts.sizes(), "blocks must be uint8 like counts");
    counts.zero_();
    const int64_t n = data.size(0), S = data.size(1), nblocks = counts.numel();
    const int nb[3] = {(int)counts.size(0), (int)counts.size(1), (int)counts.size(2)};
    const float* d = data.data_ptr<float>();
    const int32_t* xyz = coords.data_ptr<int32_t>();
    int32_t* c = counts.data_ptr<int32_t>();
    uint8_t* bl = blocks.data_ptr<uint8_t>();
#pragma omp parallel
    {
#pragma omp for schedule(static)
        for (int64_t r = 0; r < n; ++r)
            if (d[r * S] > 0.0f) add_live_vertex(xyz + 3 * r, (int)block, nb, c, 1, nullptr);
#pragma omp for schedule(static)
        for (int64_t b = 0; b < nblocks; ++b) bl[b] = c[b] > 0;
    }
}

// Occupancy for empty-space skipping: a cell is occupied when any of its corners is allocated, a
// block when any of its cells is.
std::vector<Tensor> build_occupancy(Tensor links, int64_t block) {
    TORCH_CHECK(links.scalar_type() == at::kInt && links.is_contiguous() && links.dim() == 3, "links must be int32 [Rx,Ry,Rz]");
    const int64_t rx = links.size(0), ry = links.size(1), rz = links.size(2);
    TORCH_CHECK(rx >= 2 && ry >= 2 && rz >= 2, "grid resolution must be >= 2 per axis");
    const int64_t cx = rx - 1, cy = ry - 1, cz = rz - 1;
    const int64_t bx = (cx + block - 1) / block, by = (cy + block - 1) / block, bz = (cz + block - 1) / block;
    Tensor cells = at::zeros({cx, cy, cz}, at::kByte);
    Tensor blocks = at::zeros({bx, by, bz}, at::kByte);
    const int32_t* l = links.data_ptr<int32_t>();
    uint8_t* c = cells.data_ptr<uint8_t>();
    uint8_t* bl = blocks.data_ptr<uint8_t>();
#pragma omp parallel for schedule(static)
    for (int64_t x = 0; x < cx; ++x) {
        for (int64_t y = 0; y < cy; ++y) {
            const int32_t* l00 = l + (x * ry + y) * rz;
            const int32_t* l01 = l00 + rz;
            const int32_t* l10 = l00 + ry * rz;
            const int32_t* l11 = l10 + rz;
            uint8_t* row = c + (x * cy + y) * cz;
            // The AND of the eight corners has its sign bit set exactly when every corner is < 0
            // (unallocated); no branch, so the loop vectorises (a 512^3 index is 134M cells).
            for (int64_t z = 0; z < cz; ++z)
                row[z] = (l00[z] & l00[z + 1] & l01[z] & l01[z + 1] & l10[z] & l10[z + 1] & l11[z] & l11[z + 1]) >= 0;
        }
    }
#pragma omp parallel for schedule(static)
    for (int64_t x = 0; x < bx; ++x) {
        for (int64_t y = 0; y < by; ++y) {
            for (int64_t z = 0; z < bz; ++z) {
                bool any = false;
                for (int64_t i = x * block; i < std::min((x + 1) * block, cx) && !any; ++i)
                    for (int64_t j = y * block; j < std::min((y + 1) * block, cy) && !any; ++j)
                        for (int64_t k = z * block; k < std::min((z + 1) * block, cz) && !any; ++k)
                            any = c[(i * cy + j) * cz + k];
                bl[(x * by + y) * bz + z] = any;
            }
        }
    }
    return {cells, blocks};
}

// Trilinear interpolation of every packed column at grid-frame points [P, 3]: [P, S], zeros outside the box.
Tensor sample(Tensor data, Tensor links, Tensor points) {
    check_float_rows(data, "data");
    check_float_rows(points, "points");
    TORCH_CHECK(data.dim() == 2, "data must be [N, S]");
    TORCH_CHECK(links.scalar_type() == at::kInt && links.is_contiguous() && links.dim() == 3, "links must be int32 [Rx,Ry,Rz]");
    TORCH_CHECK(links.size(0) >= 2 && links.size(1) >= 2 && links.size(2) >= 2, "grid resolution must be >= 2 per axis");
    TORCH_CHECK(points.dim() == 2 && points.size(1) == 3, "points must be [P,3]");
    const int64_t P = points.size(0);
    const int S = (int)data.size(1);
    const int res[3] = {(int)links.size(0), (int)links.size(1), (int)links.size(2)};
    Tensor out = at::empty({P, S}, data.options());
    const float* d = data.data_ptr<float>();
    const int32_t* l = links.data_ptr<int32_t>();
    const float* g = points.data_ptr<float>();
    float* o = out.data_ptr<float>();
#pragma omp parallel for schedule(static)
    for (int64_t p = 0; p < P; ++p) plx::interpolate_point(d, S, l, res, g + 3 * p, o + p * S);
    return out;
}

// Grid coordinates (x, y, z) of every allocated row.
Tensor row_coords(Tensor links, int64_t rows) {
    TORCH_CHECK(links.scalar_type() == at::kInt && links.is_contiguous() && links.dim() == 3, "links must be int32 [Rx,Ry,Rz]");
    Tensor out = at::full({rows, 3}, -1, at::kInt);
    const int64_t ry = links.size(1), rz = links.size(2), total = links.numel();
    const int32_t* l = links.data_ptr<int32_t>();
    int32_t* o = out.data_ptr<int32_t>();
#pragma omp parallel for schedule(static)
    for (int64_t i = 0; i < total; ++i) {
        const int32_t r = l[i];
        if (r < 0 || r >= rows) continue;
        o[3 * (int64_t)r] = (int32_t)(i / (ry * rz));
        o[3 * (int64_t)r + 1] = (int32_t)((i / rz) % ry);
        o[3 * (int64_t)r + 2] = (int32_t)(i % rz);
    }
    return out;
}

}  // namespace plx_cpu
