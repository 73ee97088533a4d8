// The CPU core's shared machinery (cpu_kernels.h): the grid view, huge pages, per-thread gradient scratch and
// its merge, and the checks of the operators' arguments.
#include <sys/mman.h>

#include "cpu_kernels.h"

namespace plx_cpu {

GridView make_view(const at::Tensor& data, const at::Tensor& links, const at::Tensor& cell_occ,
                   const at::Tensor& block_occ, int block, c10::ArrayRef<double> lattice) {
    TORCH_CHECK(block > 0 && (block & (block - 1)) == 0, "the occupancy block must be a power of two, got ",
                std::to_string(block));
    GridView g;
    g.data = data.data_ptr<float>();
    g.links = links.data_ptr<int32_t>();
    g.cell_occ = cell_occ.data_ptr<uint8_t>();
    g.block_occ = block_occ.data_ptr<uint8_t>();
    g.block = block;
    for (int a = 0; a < 3; ++a) {
        g.res[a] = (int)links.size(a);
        g.bres[a] = (int)block_occ.size(a);
    }
    const char* error = plx::read_lattice(lattice.data(), (long)lattice.size(), g.res, &g.lattice);
    TORCH_CHECK(error == nullptr, error);
    const int origin[3] = {0, 0, 0};
    for (int c = 0; c < 8; ++c) g.corner_offset[c] = plx::corner_index(origin, g.res, c);
    return g;
}

// Asks the kernel to back [ptr, ptr + bytes) with 2 MiB pages where the system allows it
// (transparent huge pages in `madvise` mode). Random row access over hundreds of MiB otherwise
// misses the TLB on nearly every load. Only whole 2 MiB pages inside the range are advised.
bool advise_huge_pages(void* ptr, size_t bytes) {
    constexpr uintptr_t kHuge = 2u << 20;
    const uintptr_t begin = ((uintptr_t)ptr + kHuge - 1) & ~(kHuge - 1);
    const uintptr_t end = ((uintptr_t)ptr + bytes) & ~(kHuge - 1);
    if (end <= begin) return false;
    return madvise((void*)begin, end - begin, MADV_HUGEPAGE) == 0;
}

// Zeroed per-thread scratch for a gradient table: slots for threads 1..T-1 of T = omp_get_max_threads(), at most
// max_slots of them (the caller's memory share: random rays soon touch every page of a slot).
// Anonymous mappings are zero pages mapped lazily, so a thread's slot costs memory only for the rows it ever
// touches, and they start on a page, so rows stay whole cache lines (calloc's large blocks start 16 bytes in,
// which split every row across one more line).
std::vector<at::Tensor> grad_scratch(at::Tensor grad_data, int64_t max_slots) {
    TORCH_CHECK(grad_data.device().is_cpu() && grad_data.dim() == 2, "grad data must be a CPU [N, S] table");
    TORCH_CHECK(max_slots >= 0, "max_slots must be >= 0");
    const int64_t slots = std::min<int64_t>(std::max(omp_get_max_threads() - 1, 0), max_slots);
    const int64_t rows = grad_data.size(0), stride = grad_data.size(1);
    const auto zeroed = [](int64_t count, size_t size, at::IntArrayRef shape, at::ScalarType type, bool huge) {
        if (count == 0) return at::zeros(shape, at::TensorOptions().dtype(type));
        const size_t bytes = (size_t)count * size;
        void* p = mmap(nullptr, bytes, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
        TORCH_CHECK(p != MAP_FAILED, "out of memory for per-thread gradient buffers");
        if (huge) advise_huge_pages(p, bytes);
        return at::from_blob(p, shape, [bytes](void* q) { munmap(q, bytes); }, at::TensorOptions().dtype(type));
    };
    return {zeroed(slots * rows * stride, sizeof(float), {slots, rows, stride}, at::kFloat, true),
            zeroed(slots * rows, 1, {slots, rows}, at::kByte, false)};
}

// How many rows ahead merge prefetches.
constexpr int kMergeLookahead = 8;

// Adds every other thread's gradients into the caller's tensors and clears their masks. Rows new to the caller's
// list are gathered by each worker as it merges them (a row is in a thread's list once, so no two workers meet at
// a mask byte) and appended after, in no set order.
void merge(GradTarget* target, ThreadGrads* scratch, int threads) {
    const int S = scratch->stride();
    for (int t = 1; t < threads; ++t) {
        std::vector<int32_t>& list = scratch->list(t);
        if (list.empty()) continue;
        float* buf = scratch->buffer(t);
        uint8_t* mask = scratch->mask(t);
        const int64_t n = (int64_t)list.size();
#pragma omp parallel
        {
            thread_local std::vector<int32_t> fresh;
            fresh.clear();
#pragma omp for schedule(static) nowait
            for (int64_t j = 0; j < n; ++j) {
                // The rows lie scattered over the tables: ask for those a few iterations ahead.
                if (j + kMergeLookahead < n) {
                    const int64_t ahead = list[j + kMergeLookahead];
                    for (int k = 0; k < S; k += 16) {
                        __builtin_prefetch(buf + ahead * S + k, 0, 3);
                        __builtin_prefetch(target->data + ahead * S + k, 1, 3);
                    }
                    __builtin_prefetch(target->mask + ahead, 1, 3);
                }
                const int64_t row = list[j];
                const float* src = buf + row * S;
                float* dst = target->data + row * S;
#pragma omp simd
                for (int k = 0; k < S; ++k) dst[k] += src[k];
                mask[row] = 0;
                if (!target->mask[row]) {
                    target->mask[row] = 1;
                    fresh.push_back((int32_t)row);
                }
            }
#pragma omp critical(plx_merge_rows)
            {
                std::copy(fresh.begin(), fresh.end(), target->rows + target->count);
                target->count += (int64_t)fresh.size();
            }
        }
        list.clear();
    }
}

void check_float_rows(const at::Tensor& t, const char* name) {
    TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == at::kFloat && t.is_contiguous(), name,
                " must be a contiguous float32 CPU tensor");
}

void check_grid(const Tensor& data, const Tensor& links, const Tensor& cell_occ, const Tensor& block_occ, int degree) {
    check_float_rows(data, "data");
    TORCH_CHECK(degree >= 0 && degree <= 3, "sh_degree must be 0..3");
    TORCH_CHECK(data.dim() == 2 && data.size(1) == row_stride(degree),
                "data must be [N, padded row] for this SH degree");
    TORCH_CHECK(links.scalar_type() == at::kInt && links.is_contiguous() && links.dim() == 3, "links must be int32 [Rx,Ry,Rz]");
    TORCH_CHECK(links.size(0) >= 2 && links.size(1) >= 2 && links.size(2) >= 2, "grid resolution must be >= 2 per axis");
    TORCH_CHECK(cell_occ.scalar_type() == at::kByte && cell_occ.is_contiguous(), "cell_occ must be uint8");
    TORCH_CHECK(block_occ.scalar_type() == at::kByte && block_occ.is_contiguous() && block_occ.dim() == 3, "block_occ must be uint8 3-D");
}

void check_rays(const Tensor& origins, const Tensor& dirs) {
    check_float_rows(origins, "origins");
    check_float_rows(dirs, "dirs");
    TORCH_CHECK(origins.dim() == 2 && origins.size(1) == 3 && dirs.sizes() == origins.sizes(), "origins and dirs must be [B,3]");
}

}  // namespace plx_cpu
