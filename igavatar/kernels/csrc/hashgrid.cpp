// Multiresolution hash-grid encoding on the CPU: forward (features + closed-form spatial Jacobian)
// and backward (table gradient + point gradient), float32, OpenMP.
//
// Same semantics as HashGridEncoding._encode_reference (igavatar/model/hashgrid.py):
//   u = clamp((x - box_min) / extent, 0, 1); pos = u * N_l; cell = min(floor(pos), N_l - 1);
//   frac = pos - cell; corner rows: dense levels  i*m0 + j*m1 + k*m2 + offset,
//   hashed levels ((i*p0) ^ (j*p1) ^ (k*p2)) & (T - 1) + offset in uint32 arithmetic;
//   trilinear interpolation as three nested lerps (z, then y, then x) in the reference's order;
//   jacobian_a = (inside_a / extent_a * N_l) * d(trilinear) / d frac_a, inside_a = box_min_a <= x_a <= box_min_a + extent_a
//   (the reference's bound: box_min + extent can differ from box_max by an ulp in float32).
// Backward: every output is linear in the 8 corner rows, so
//   grad_table[corner] += g * w_c + sum_a gJ_a * s_a * dw_c / dfrac_a,
//   grad_x_a = clamp_a / extent_a * sum_l N_l * sum_ch (g * dv/dfrac_a + sum_{b != a} gJ_b * s_b * d2v / dfrac_a dfrac_b)
//   with clamp_a = (0 <= (x_a - box_min_a) / extent_a <= 1), the mask of the reference's clamp backward
//   (it equals inside_a except possibly on the box faces, by rounding).
// The table-gradient pass is parallel over levels (each level owns a disjoint row range, no races);
// the point gradient is accumulated in per-thread (P, 3) buffers and reduced in parallel over points.
// Both passes compute the corner rows of a small group (levels of a point / points of a level) first
// and prefetch them, so the random table accesses' cache misses overlap (about 2x on random points).

#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#ifdef _OPENMP
#include <omp.h>
#endif

namespace {

constexpr int64_t kLevelGroup = 8;   // forward: levels whose corner rows are prefetched together
constexpr int64_t kPointGroup = 8;   // backward: points whose corner rows are prefetched together

struct Grid {
    const float* table;
    const int64_t* offsets;
    const int32_t* resolutions;
    const int32_t* multipliers;  // (L, 3), int32 bit patterns of uint32 multipliers
    int64_t n_levels;
    int64_t n_features;
    int64_t n_dense;
    uint32_t hash_mask;
    float box_min[3];
    float extent[3];
};

// Per (point, level) geometry: fractions, the Jacobian scale per axis and the 8 corner rows
// (corner c = dx * 4 + dy * 2 + dz).
struct Cell {
    float t[3];
    float s[3];
    int64_t row[8];
};

// u: the clamped unit coordinates; inside: the Jacobian's box test; unclamped: the clamp's gradient mask.
inline void point_unit(const Grid& g, const float* x, float u[3], bool inside[3], bool* unclamped = nullptr) {
    for (int a = 0; a < 3; ++a) {
        const float v = (x[a] - g.box_min[a]) / g.extent[a];
        u[a] = std::min(std::max(v, 0.0f), 1.0f);
        inside[a] = (x[a] >= g.box_min[a]) && (x[a] <= g.box_min[a] + g.extent[a]);
        if (unclamped) unclamped[a] = (v >= 0.0f) && (v <= 1.0f);
    }
}

inline void level_cell(const Grid& g, int64_t level, const float u[3], const bool inside[3], bool with_scale,
                       Cell& cell) {
    const int32_t n_int = g.resolutions[level];
    const float n = static_cast<float>(n_int);
    uint32_t code[3][2];
    const bool dense = level < g.n_dense;
    for (int a = 0; a < 3; ++a) {
        const float pos = u[a] * n;
        // pos is in [0, N] (NaN only for a NaN point: cell 0 then keeps every row in bounds).
        int32_t c = pos >= 0.0f ? static_cast<int32_t>(std::floor(pos)) : 0;
        c = std::min(c, n_int - 1);
        cell.t[a] = pos - static_cast<float>(c);
        if (with_scale) cell.s[a] = (inside[a] ? 1.0f : 0.0f) / g.extent[a] * n;
        const uint32_t m = static_cast<uint32_t>(g.multipliers[level * 3 + a]);
        uint32_t lo = static_cast<uint32_t>(c) * m;
        uint32_t hi = lo + m;
        if (!dense) {
            lo &= g.hash_mask;
            hi &= g.hash_mask;
        }
        code[a][0] = lo;
        code[a][1] = hi;
    }
    const int64_t offset = g.offsets[level];
    for (int dx = 0; dx < 2; ++dx)
        for (int dy = 0; dy < 2; ++dy)
            for (int dz = 0; dz < 2; ++dz) {
                const uint32_t combined = dense ? code[0][dx] + code[1][dy] + code[2][dz]
                                                : code[0][dx] ^ code[1][dy] ^ code[2][dz];
                cell.row[dx * 4 + dy * 2 + dz] = offset + static_cast<int64_t>(combined);
            }
}

// Derivatives of one channel's trilinear interpolation wrt the fractions, the reference's nested lerps.
struct Lerps {
    float value;
    float d[3];    // d v / d t_a
    float dd[3];   // d2 v / dt_x dt_y, dt_x dt_z, dt_y dt_z
};

inline Lerps interpolate(const float c[8], const float t[3], bool second) {
    const float tx = t[0], ty = t[1], tz = t[2];
    float diff_z[4], ly[4];
    for (int q = 0; q < 4; ++q) {  // q = dx * 2 + dy
        diff_z[q] = c[2 * q + 1] - c[2 * q];
        ly[q] = c[2 * q] + tz * diff_z[q];
    }
    float diff_yz[2], lx[2], diff_z_x[2];
    for (int dx = 0; dx < 2; ++dx) {
        diff_yz[dx] = ly[2 * dx + 1] - ly[2 * dx];
        lx[dx] = ly[2 * dx] + ty * diff_yz[dx];
        diff_z_x[dx] = diff_z[2 * dx] + ty * (diff_z[2 * dx + 1] - diff_z[2 * dx]);
    }
    Lerps out;
    const float diff_xyz = lx[1] - lx[0];
    out.value = lx[0] + tx * diff_xyz;
    out.d[0] = diff_xyz;
    out.d[1] = diff_yz[0] + tx * (diff_yz[1] - diff_yz[0]);
    out.d[2] = diff_z_x[0] + tx * (diff_z_x[1] - diff_z_x[0]);
    if (second) {
        out.dd[0] = diff_yz[1] - diff_yz[0];
        out.dd[1] = diff_z_x[1] - diff_z_x[0];
        const float dzy0 = diff_z[1] - diff_z[0];
        const float dzy1 = diff_z[3] - diff_z[2];
        out.dd[2] = dzy0 + tx * (dzy1 - dzy0);
    }
    return out;
}

Grid make_grid(const torch::Tensor& table, const torch::Tensor& offsets, const torch::Tensor& resolutions,
               const torch::Tensor& multipliers, int64_t n_dense, int64_t hashmap_size,
               const torch::Tensor& box_min, const torch::Tensor& box_max) {
    auto check_cpu = [](const torch::Tensor& t, const char* name, c10::ScalarType dtype) {
        TORCH_CHECK(t.device().is_cpu(), "hashgrid: ", name, " must be a CPU tensor, got ", t.device());
        TORCH_CHECK(t.scalar_type() == dtype, "hashgrid: ", name, " must have dtype ", dtype, ", got ",
                    t.scalar_type());
        TORCH_CHECK(t.is_contiguous(), "hashgrid: ", name, " must be contiguous");
    };
    check_cpu(table, "table", torch::kFloat32);
    check_cpu(offsets, "offsets", torch::kInt64);
    check_cpu(resolutions, "resolutions", torch::kInt32);
    check_cpu(multipliers, "multipliers", torch::kInt32);
    check_cpu(box_min, "box_min", torch::kFloat32);
    check_cpu(box_max, "box_max", torch::kFloat32);
    TORCH_CHECK(table.dim() == 2, "hashgrid: table must have shape (R, F), got ", table.sizes());
    const int64_t n_levels = offsets.numel();
    TORCH_CHECK(offsets.dim() == 1 && n_levels >= 1, "hashgrid: offsets must have shape (L,), got ", offsets.sizes());
    TORCH_CHECK(resolutions.dim() == 1 && resolutions.numel() == n_levels,
                "hashgrid: resolutions must have shape (", n_levels, ",), got ", resolutions.sizes());
    TORCH_CHECK(multipliers.dim() == 2 && multipliers.size(0) == n_levels && multipliers.size(1) == 3,
                "hashgrid: multipliers must have shape (", n_levels, ", 3), got ", multipliers.sizes());
    TORCH_CHECK(box_min.numel() == 3 && box_max.numel() == 3, "hashgrid: box_min and box_max must have 3 elements");
    TORCH_CHECK(0 <= n_dense && n_dense <= n_levels, "hashgrid: n_dense must be in [0, ", n_levels, "], got ", n_dense);
    TORCH_CHECK(hashmap_size >= 1 && hashmap_size <= (int64_t(1) << 31) && (hashmap_size & (hashmap_size - 1)) == 0,
                "hashgrid: hashmap_size must be a power of two <= 2^31, got ", hashmap_size);
    const int64_t n_features = table.size(1);
    TORCH_CHECK(n_features >= 1, "hashgrid: table must have at least one feature column, got ", table.sizes());

    Grid g;
    g.table = table.data_ptr<float>();
    g.offsets = offsets.data_ptr<int64_t>();
    g.resolutions = resolutions.data_ptr<int32_t>();
    g.multipliers = multipliers.data_ptr<int32_t>();
    g.n_levels = n_levels;
    g.n_features = n_features;
    g.n_dense = n_dense;
    g.hash_mask = static_cast<uint32_t>(hashmap_size - 1);
    const float* lo = box_min.data_ptr<float>();
    const float* hi = box_max.data_ptr<float>();
    for (int a = 0; a < 3; ++a) {
        g.box_min[a] = lo[a];
        g.extent[a] = hi[a] - lo[a];
    }
    // Every corner row must lie inside the table (a wrong offsets/resolutions buffer would read out of bounds).
    const int64_t rows = table.size(0);
    for (int64_t l = 0; l < n_levels; ++l) {
        const int64_t n = g.resolutions[l];
        TORCH_CHECK(n >= 1, "hashgrid: resolutions must be >= 1, got ", n, " at level ", l);
        const int64_t size = l < n_dense ? (n + 1) * (n + 1) * (n + 1) : hashmap_size;
        TORCH_CHECK(g.offsets[l] >= 0 && g.offsets[l] + size <= rows, "hashgrid: level ", l, " rows [", g.offsets[l],
                    ", ", g.offsets[l] + size, ") exceed the table's ", rows, " rows");
        if (l < n_dense) {
            const int64_t m0 = g.multipliers[3 * l], m1 = g.multipliers[3 * l + 1], m2 = g.multipliers[3 * l + 2];
            TORCH_CHECK(m0 >= 0 && m1 >= 0 && m2 >= 0 && (m0 + m1 + m2) * n <= size - 1,
                        "hashgrid: dense level ", l, " multipliers overflow its ", size, " rows");
        }
    }
    return g;
}

void check_points(const torch::Tensor& x) {
    TORCH_CHECK(x.device().is_cpu(), "hashgrid: x must be a CPU tensor, got ", x.device());
    TORCH_CHECK(x.scalar_type() == torch::kFloat32, "hashgrid: x must be float32, got ", x.scalar_type());
    TORCH_CHECK(x.dim() == 2 && x.size(1) == 3, "hashgrid: x must have shape (P, 3), got ", x.sizes());
    TORCH_CHECK(x.is_contiguous(), "hashgrid: x must be contiguous");
}

// Channel count as a compile-time constant for the common F (loops over channels unroll), else runtime.
template <int kF>
void forward_points(const Grid& g, const float* xp, float* fp, float* jp, int64_t n_points, bool with_jacobian) {
    const int64_t L = g.n_levels, F = kF > 0 ? kF : g.n_features, C = L * F;
#pragma omp parallel for schedule(static)
    for (int64_t p = 0; p < n_points; ++p) {
        float u[3];
        bool inside[3];
        point_unit(g, xp + 3 * p, u, inside);
        // Two phases per group of levels: all corner rows first (prefetched, so the cache misses of
        // the group overlap), then the interpolation.
        Cell cells[kLevelGroup];
        for (int64_t l0 = 0; l0 < L; l0 += kLevelGroup) {
            const int64_t nl = std::min<int64_t>(kLevelGroup, L - l0);
            for (int64_t i = 0; i < nl; ++i) {
                level_cell(g, l0 + i, u, inside, with_jacobian, cells[i]);
                for (int k = 0; k < 8; ++k) __builtin_prefetch(g.table + cells[i].row[k] * F);
            }
            for (int64_t i = 0; i < nl; ++i) {
                const Cell& cell = cells[i];
                const int64_t l = l0 + i;
                for (int64_t f = 0; f < F; ++f) {
                    float c[8];
                    for (int k = 0; k < 8; ++k) c[k] = g.table[cell.row[k] * F + f];
                    const Lerps v = interpolate(c, cell.t, false);
                    const int64_t ch = p * C + l * F + f;
                    fp[ch] = v.value;
                    if (with_jacobian) {
                        for (int a = 0; a < 3; ++a) jp[3 * ch + a] = v.d[a] * cell.s[a];
                    }
                }
            }
        }
    }
}

// One level's contribution: its table rows (owned by this level) and this thread's point-gradient buffer.
template <int kF>
void backward_level(const Grid& g, int64_t l, const float* xp, const float* gfp, const float* gjp, float* gtp,
                    float* gx_local, int64_t n_points) {
    const int64_t L = g.n_levels, F = kF > 0 ? kF : g.n_features, C = L * F;
    const bool has_gf = gfp != nullptr, has_gj = gjp != nullptr;
    const bool need_grad_table = gtp != nullptr, need_grad_x = gx_local != nullptr;
    Cell cells[kPointGroup];
    for (int64_t p0 = 0; p0 < n_points; p0 += kPointGroup) {
        // Corner rows of a group of points first (prefetched: the group's cache misses overlap).
        const int64_t np = std::min<int64_t>(kPointGroup, n_points - p0);
        for (int64_t i = 0; i < np; ++i) {
            float u[3];
            bool inside[3];
            point_unit(g, xp + 3 * (p0 + i), u, inside);
            level_cell(g, l, u, inside, true, cells[i]);
            for (int k = 0; k < 8; ++k) {
                if (need_grad_table) __builtin_prefetch(gtp + cells[i].row[k] * F, 1);
                if (need_grad_x) __builtin_prefetch(g.table + cells[i].row[k] * F);
            }
        }
        for (int64_t i = 0; i < np; ++i) {
            const int64_t p = p0 + i;
            const Cell& cell = cells[i];
            const float tx = cell.t[0], ty = cell.t[1], tz = cell.t[2];
            const float w[3][2] = {{1.0f - tx, tx}, {1.0f - ty, ty}, {1.0f - tz, tz}};
            float acc[3] = {0.0f, 0.0f, 0.0f};  // sum over channels of d loss / d t_a
            for (int64_t f = 0; f < F; ++f) {
                const int64_t ch = p * C + l * F + f;
                const float gv = has_gf ? gfp[ch] : 0.0f;
                float gj[3] = {0.0f, 0.0f, 0.0f};  // gJ_a * s_a
                if (has_gj)
                    for (int a = 0; a < 3; ++a) gj[a] = gjp[3 * ch + a] * cell.s[a];
                if (need_grad_table) {
                    for (int dx = 0; dx < 2; ++dx)
                        for (int dy = 0; dy < 2; ++dy)
                            for (int dz = 0; dz < 2; ++dz) {
                                const float wx = w[0][dx], wy = w[1][dy], wz = w[2][dz];
                                const float sx = dx ? 1.0f : -1.0f, sy = dy ? 1.0f : -1.0f,
                                            sz = dz ? 1.0f : -1.0f;
                                const float grad = gv * wx * wy * wz + gj[0] * sx * wy * wz +
                                                   gj[1] * wx * sy * wz + gj[2] * wx * wy * sz;
                                gtp[cell.row[dx * 4 + dy * 2 + dz] * F + f] += grad;
                            }
                }
                if (need_grad_x) {
                    float c[8];
                    for (int k = 0; k < 8; ++k) c[k] = g.table[cell.row[k] * F + f];
                    const Lerps v = interpolate(c, cell.t, has_gj);
                    for (int a = 0; a < 3; ++a) acc[a] += gv * v.d[a];
                    if (has_gj) {
                        acc[0] += gj[1] * v.dd[0] + gj[2] * v.dd[1];
                        acc[1] += gj[0] * v.dd[0] + gj[2] * v.dd[2];
                        acc[2] += gj[0] * v.dd[1] + gj[1] * v.dd[2];
                    }
                }
            }
            if (need_grad_x) {
                const float n = static_cast<float>(g.resolutions[l]);
                for (int a = 0; a < 3; ++a) gx_local[3 * p + a] += acc[a] * n;
            }
        }
    }
}

}  // namespace

std::vector<torch::Tensor> hashgrid_forward(torch::Tensor x, torch::Tensor table, torch::Tensor offsets,
                                            torch::Tensor resolutions, torch::Tensor multipliers, int64_t n_dense,
                                            int64_t hashmap_size, torch::Tensor box_min, torch::Tensor box_max,
                                            bool with_jacobian) {
    check_points(x);
    const Grid g = make_grid(table, offsets, resolutions, multipliers, n_dense, hashmap_size, box_min, box_max);
    const int64_t n_points = x.size(0), L = g.n_levels, F = g.n_features, C = L * F;
    auto features = torch::empty({n_points, C}, x.options());
    auto jacobian = with_jacobian ? torch::empty({n_points, C, 3}, x.options()) : torch::empty({0}, x.options());
    const float* xp = x.data_ptr<float>();
    float* fp = features.data_ptr<float>();
    float* jp = with_jacobian ? jacobian.data_ptr<float>() : nullptr;

    switch (F) {
        case 1: forward_points<1>(g, xp, fp, jp, n_points, with_jacobian); break;
        case 2: forward_points<2>(g, xp, fp, jp, n_points, with_jacobian); break;
        case 4: forward_points<4>(g, xp, fp, jp, n_points, with_jacobian); break;
        case 8: forward_points<8>(g, xp, fp, jp, n_points, with_jacobian); break;
        default: forward_points<0>(g, xp, fp, jp, n_points, with_jacobian);
    }
    return {features, jacobian};
}

std::vector<torch::Tensor> hashgrid_backward(torch::Tensor grad_features, torch::Tensor grad_jacobian, torch::Tensor x,
                                             torch::Tensor table, torch::Tensor offsets, torch::Tensor resolutions,
                                             torch::Tensor multipliers, int64_t n_dense, int64_t hashmap_size,
                                             torch::Tensor box_min, torch::Tensor box_max, bool need_grad_x,
                                             bool need_grad_table) {
    check_points(x);
    const Grid g = make_grid(table, offsets, resolutions, multipliers, n_dense, hashmap_size, box_min, box_max);
    const int64_t n_points = x.size(0), L = g.n_levels, F = g.n_features, C = L * F;
    // Either upstream gradient may be empty (that output unused): it then contributes nothing.
    const bool has_gf = grad_features.numel() > 0;
    const bool has_gj = grad_jacobian.numel() > 0;
    if (has_gf) {
        TORCH_CHECK(grad_features.device().is_cpu() && grad_features.scalar_type() == torch::kFloat32 &&
                        grad_features.is_contiguous(),
                    "hashgrid: grad_features must be a contiguous float32 CPU tensor");
        TORCH_CHECK(grad_features.dim() == 2 && grad_features.size(0) == n_points && grad_features.size(1) == C,
                    "hashgrid: grad_features must have shape (", n_points, ", ", C, "), got ", grad_features.sizes());
    }
    if (has_gj) {
        TORCH_CHECK(grad_jacobian.device().is_cpu() && grad_jacobian.scalar_type() == torch::kFloat32 &&
                        grad_jacobian.is_contiguous(),
                    "hashgrid: grad_jacobian must be a contiguous float32 CPU tensor");
        TORCH_CHECK(grad_jacobian.dim() == 3 && grad_jacobian.size(0) == n_points && grad_jacobian.size(1) == C &&
                        grad_jacobian.size(2) == 3,
                    "hashgrid: grad_jacobian must have shape (", n_points, ", ", C, ", 3) or be empty, got ",
                    grad_jacobian.sizes());
    }
    auto grad_table = need_grad_table ? torch::zeros_like(table) : torch::empty({0}, table.options());
    auto grad_x = need_grad_x ? torch::zeros({n_points, 3}, x.options()) : torch::empty({0}, x.options());
    if ((!need_grad_table && !need_grad_x) || (!has_gf && !has_gj) || n_points == 0) return {grad_table, grad_x};

    const float* xp = x.data_ptr<float>();
    const float* gfp = has_gf ? grad_features.data_ptr<float>() : nullptr;
    const float* gjp = has_gj ? grad_jacobian.data_ptr<float>() : nullptr;
    float* gtp = need_grad_table ? grad_table.data_ptr<float>() : nullptr;
    float* gxp = need_grad_x ? grad_x.data_ptr<float>() : nullptr;

    int n_threads = 1;
#ifdef _OPENMP
    n_threads = std::max(1, std::min<int>(omp_get_max_threads(), static_cast<int>(L)));
#endif
    // Per-thread (P, 3) partial point gradients (thread 0 writes straight into grad_x).
    std::vector<float> partial(need_grad_x && n_threads > 1 ? (n_threads - 1) * n_points * 3 : 0, 0.0f);

#pragma omp parallel num_threads(n_threads)
    {
        int thread = 0;
#ifdef _OPENMP
        thread = omp_get_thread_num();
#endif
        float* gx_local = need_grad_x ? (thread == 0 ? gxp : partial.data() + (thread - 1) * n_points * 3) : nullptr;

        // Level-parallel: every level's corner rows lie in its own row range of the table. The static
        // level -> thread assignment keeps grad_x's summation order, hence the result, reproducible
        // for a given thread count (training runs are compared bit for bit).
#pragma omp for schedule(static, 1)
        for (int64_t l = 0; l < L; ++l) {
            switch (F) {
                case 1: backward_level<1>(g, l, xp, gfp, gjp, gtp, gx_local, n_points); break;
                case 2: backward_level<2>(g, l, xp, gfp, gjp, gtp, gx_local, n_points); break;
                case 4: backward_level<4>(g, l, xp, gfp, gjp, gtp, gx_local, n_points); break;
                case 8: backward_level<8>(g, l, xp, gfp, gjp, gtp, gx_local, n_points); break;
                default: backward_level<0>(g, l, xp, gfp, gjp, gtp, gx_local, n_points);
            }
        }
        if (need_grad_x) {
            // The implicit barrier of the loop above has passed: reduce the partials over points,
            // then chain through the clamp (its gradient mask) and the division by the extent.
#pragma omp for schedule(static)
            for (int64_t p = 0; p < n_points; ++p) {
                float u[3];
                bool inside[3], unclamped[3];
                point_unit(g, xp + 3 * p, u, inside, unclamped);
                for (int a = 0; a < 3; ++a) {
                    const int64_t i = 3 * p + a;
                    float sum = gxp[i];
                    for (int t = 1; t < n_threads; ++t) sum += partial[(t - 1) * n_points * 3 + i];
                    gxp[i] = unclamped[a] ? sum / g.extent[a] : 0.0f;
                }
            }
        }
    }
    return {grad_table, grad_x};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
    m.doc() = "Multiresolution hash-grid encoding (forward + spatial Jacobian + backward), float32 CPU, OpenMP";
    m.def("forward", &hashgrid_forward, "features (P, L*F) and jacobian (P, L*F, 3) or empty",
          py::arg("x"), py::arg("table"), py::arg("offsets"), py::arg("resolutions"), py::arg("multipliers"),
          py::arg("n_dense"), py::arg("hashmap_size"), py::arg("box_min"), py::arg("box_max"),
          py::arg("with_jacobian"));
    m.def("backward", &hashgrid_backward, "grad_table (R, F) or empty, grad_x (P, 3) or empty",
          py::arg("grad_features"), py::arg("grad_jacobian"), py::arg("x"), py::arg("table"), py::arg("offsets"),
          py::arg("resolutions"), py::arg("multipliers"), py::arg("n_dense"), py::arg("hashmap_size"),
          py::arg("box_min"), py::arg("box_max"), py::arg("need_grad_x"), py::arg("need_grad_table") = true);
}
