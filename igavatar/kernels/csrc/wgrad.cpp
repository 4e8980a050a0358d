// Weight gradients of fully connected layers straight from row-major activations:
//
//   out (M, N) = A^T B = sum_p A[p, :]^T B[p, :]      A (P, M), B (P, N), N a multiple of 16
//   a_sums (M,) = sum_p A[p, :], b_sums (N,) = sum_p B[p, :]   (optional: the bias gradient,
//                                                               accumulated in double)
//
// For a layer y = x W^T + b with upstream gradient g (P, out): grad_W = g^T x is out(A = g, B = x)
// when `in` is a multiple of 16, else (out(A = x, B = g))^T when `out` is. oneDNN's own
// weight-gradient primitive (igavatar/model/linear.py) first converts both (P, .) operands into
// its layout, a full copy of each through memory on every call; here the rows are read where
// they lie. Why this is fast: every row p adds an outer product, so a tile of R rows of `out` by
// L * NV columns (L floats a vector) lives in R * NV vector registers while p runs over a block of
// rows whose B slice stays in L1; each B vector loaded feeds R fused multiply-adds. The rows are split between
// threads, each with its own partial sums, added in thread order: deterministic for a given
// thread count. Each row block's partial tile starts from zero and is then added to the total,
// a two-level sum that keeps the float32 rounding of a 20k-row reduction small.
//
// GCC vector extensions, one copy per ISA (AVX-512, AVX2 + FMA, and plain SSE / NEON), each with
// vectors and tiles sized to its registers, chosen once on the CPU's features. numpy in, numpy out
// (pybind11 only).

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include "numpy_kernel.h"

#include <algorithm>
#include <cstdint>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#ifdef _OPENMP
#include <omp.h>
#endif

// a * b + c as one rounding where the ISA has FMA (the -std=c++ modes switch GCC's contraction off).
#pragma GCC optimize("fp-contract=fast")

namespace py = pybind11;
using Floats = py::array_t<float, py::array::c_style>;

namespace {

// Vectors of 16, 8 and 4 floats, each one register of AVX-512, AVX2 and SSE / NEON. Each ISA gets
// its own type: GCC keeps a vector wider than the target's registers (16 floats under AVX2) on the
// stack and moves it through general registers piece by piece, which ran 10-20x slower than
// torch's own product on an AVX2-only EPYC (tests/benchmarks/results/wgrad-avx2.md).
typedef float Vec16 __attribute__((vector_size(64)));
typedef float Vec8 __attribute__((vector_size(32)));
typedef float Vec4 __attribute__((vector_size(16)));

template <typename V> constexpr int64_t kLanes = sizeof(V) / sizeof(float);

constexpr int64_t kBlockRows = 128;  // rows per block: a 128 x 64 float slice of B is 32 KB (L1)

// Unaligned loads and stores at any float address (memcpy: an aligned(4) typedef of the vector is
// dropped when passed as a template argument, and the store became an aligned one that faulted).
template <typename V>
__attribute__((always_inline)) inline V load(const float* p) {
  V v;
  __builtin_memcpy(&v, p, sizeof(V));
  return v;
}

template <typename V>
__attribute__((always_inline)) inline void store(float* p, V v) {
  __builtin_memcpy(p, &v, sizeof(V));
}

// out[0:R, 0:L*NV] (row stride ldo) += sum_{p < rows} a[p, 0:R]^T b[p, 0:L*NV] (row strides lda,
// ldb), L = kLanes<V>: R x NV accumulators and NV loaded vectors of B held in registers.
template <typename V, int R, int NV>
__attribute__((always_inline)) inline void tile(const float* a, int64_t lda, const float* b, int64_t ldb,
                                                int64_t rows, float* out, int64_t ldo) {
  constexpr int64_t L = kLanes<V>;
  V acc[R][NV];
#pragma GCC unroll 8
  for (int r = 0; r < R; ++r)
#pragma GCC unroll 4
    for (int v = 0; v < NV; ++v) acc[r][v] = V{};
  for (int64_t p = 0; p < rows; ++p) {
    V bv[NV];
#pragma GCC unroll 4
    for (int v = 0; v < NV; ++v) bv[v] = load<V>(b + p * ldb + L * v);
#pragma GCC unroll 8
    for (int r = 0; r < R; ++r) {
      const float s = a[p * lda + r];
#pragma GCC unroll 4
      for (int v = 0; v < NV; ++v) acc[r][v] += s * bv[v];
    }
  }
#pragma GCC unroll 8
  for (int r = 0; r < R; ++r)
#pragma GCC unroll 4
    for (int v = 0; v < NV; ++v) store<V>(out + r * ldo + L * v, load<V>(out + r * ldo + L * v) + acc[r][v]);
}

// All R-row tiles of one (L * NV)-column slab: full groups of 4 rows, then the 1-3 left over.
template <typename V, int NV>
__attribute__((always_inline)) inline void slab(const float* a, int64_t M, const float* b, int64_t N,
                                                int64_t rows, float* out) {
  int64_t m = 0;
  for (; m + 4 <= M; m += 4) tile<V, 4, NV>(a + m, M, b, N, rows, out + m * N, N);
  switch (M - m) {
    case 3: tile<V, 3, NV>(a + m, M, b, N, rows, out + m * N, N); break;
    case 2: tile<V, 2, NV>(a + m, M, b, N, rows, out + m * N, N); break;
    case 1: tile<V, 1, NV>(a + m, M, b, N, rows, out + m * N, N); break;
    default: break;
  }
}

// totals[0:C] += the column sums of x (rows, C), in double: a bias gradient sums thousands of
// signed terms whose running sum can be far larger than the result (a float32 running sum lost
// 1e-6 of 0.07 in a test), and C doubles per row cost next to nothing beside the tiles.
__attribute__((always_inline)) inline void column_sums(const float* x, int64_t rows, int64_t C, double* totals) {
  for (int64_t p = 0; p < rows; ++p) {
    const float* row = x + p * C;
#pragma omp simd
    for (int64_t c = 0; c < C; ++c) totals[c] += static_cast<double>(row[c]);
  }
}

// Rows [p0, p1) of A (P, M) and B (P, N) added into out (M, N), and into the column sums of A and B
// where a_sums / b_sums are set; slabs of MaxNV vectors V, then the 1-3 vectors left over (N is a
// multiple of 16, so of every L).
template <typename V, int MaxNV>
__attribute__((always_inline)) inline void outer_sum_rows(const float* a, const float* b, int64_t M, int64_t N,
                                                          int64_t p0, int64_t p1, float* out, double* a_sums,
                                                          double* b_sums) {
  constexpr int64_t L = kLanes<V>;
  for (int64_t q0 = p0; q0 < p1; q0 += kBlockRows) {
    const int64_t rows = std::min(kBlockRows, p1 - q0);
    const float* ab = a + q0 * M;
    const float* bb = b + q0 * N;
    int64_t n = 0;
    for (; n + L * MaxNV <= N; n += L * MaxNV) slab<V, MaxNV>(ab, M, bb + n, N, rows, out + n);
    switch ((N - n) / L) {
      case 3: slab<V, 3>(ab, M, bb + n, N, rows, out + n); break;
      case 2: slab<V, 2>(ab, M, bb + n, N, rows, out + n); break;
      case 1: slab<V, 1>(ab, M, bb + n, N, rows, out + n); break;
      default: break;
    }
    if (a_sums != nullptr) column_sums(ab, rows, M, a_sums);
    if (b_sums != nullptr) column_sums(bb, rows, N, b_sums);
  }
}

using RowsFn = void (*)(const float*, const float*, int64_t, int64_t, int64_t, int64_t, float*, double*, double*);

// One copy per register file, each sized to fit it: AVX-512's 32 zmm hold a 4 x 4 tile's 16
// accumulators and 4 B vectors; AVX2's 16 ymm a 4 x 2 tile (8 + 2); SSE's 16 xmm (and NEON's 32 q) a
// 4 x 2 tile of 4-float vectors.
void outer_sum_rows_base(const float* a, const float* b, int64_t M, int64_t N, int64_t p0, int64_t p1, float* out,
                         double* a_sums, double* b_sums) {
  outer_sum_rows<Vec4, 2>(a, b, M, N, p0, p1, out, a_sums, b_sums);
}

#if defined(IGA_TARGET_V4)
IGA_TARGET_V4 void outer_sum_rows_v4(const float* a, const float* b, int64_t M, int64_t N, int64_t p0, int64_t p1,
                                     float* out, double* a_sums, double* b_sums) {
  outer_sum_rows<Vec16, 4>(a, b, M, N, p0, p1, out, a_sums, b_sums);
}

IGA_TARGET_V3 void outer_sum_rows_v3(const float* a, const float* b, int64_t M, int64_t N, int64_t p0, int64_t p1,
                                     float* out, double* a_sums, double* b_sums) {
  outer_sum_rows<Vec8, 2>(a, b, M, N, p0, p1, out, a_sums, b_sums);
}
#endif

// The copies this CPU can run, by name, the fastest first (never chosen on the CPU's model); found
// once.
const std::vector<std::pair<std::string, RowsFn>>& runnable_copies() {
  static const auto copies = [] {
    std::vector<std::pair<std::string, RowsFn>> found;
#if defined(IGA_TARGET_V4)
    __builtin_cpu_init();
    const bool v3 = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
    if (v3 && __builtin_cpu_supports("avx512f")) found.emplace_back("avx512", outer_sum_rows_v4);
    if (v3) found.emplace_back("avx2", outer_sum_rows_v3);
#endif
    found.emplace_back("base", outer_sum_rows_base);
    return found;
  }();
  return copies;
}

// The named copy ("" = the fastest this CPU runs); invalid_argument for one it cannot run.
RowsFn rows_copy(const std::string& name) {
  const auto& copies = runnable_copies();
  if (name.empty()) return copies.front().second;
  for (const auto& [copy_name, fn] : copies)
    if (copy_name == name) return fn;
  throw std::invalid_argument("wgrad: copy '" + name + "' does not run on this CPU");
}

std::vector<std::string> copy_names() {
  std::vector<std::string> names;
  for (const auto& copy : runnable_copies()) names.push_back(copy.first);
  return names;
}

const float* input(const Floats& array, const char* name) {
  if (array.ndim() != 2) throw std::invalid_argument(std::string("wgrad: ") + name + " must be 2-D (P, C)");
  return array.data();
}

float* output(const py::buffer& buffer, const std::vector<py::ssize_t>& shape, const char* name) {
  return iga::output_floats(buffer, shape, "wgrad", name);
}

// out = A^T B; a_sums / b_sums = the column sums of A / B, each skipped when passed empty.
void outer_sum(const Floats& a, const Floats& b, const py::buffer& out, const py::buffer& a_sums,
               const py::buffer& b_sums, const std::string& copy) {
  const float* ap = input(a, "a");
  const float* bp = input(b, "b");
  const int64_t P = a.shape(0), M = a.shape(1), N = b.shape(1);
  if (b.shape(0) != P) throw std::invalid_argument("wgrad: a and b must have the same number of rows");
  if (N % 16 != 0 || N == 0) throw std::invalid_argument("wgrad: b's column count must be a positive multiple of 16");
  float* op = output(out, {M, N}, "out");
  float* asp = a_sums.request().size > 0 ? output(a_sums, {M}, "a_sums") : nullptr;
  float* bsp = b_sums.request().size > 0 ? output(b_sums, {N}, "b_sums") : nullptr;
  const RowsFn rows_fn = rows_copy(copy);
  py::gil_scoped_release release;
  const int64_t blocks = (P + kBlockRows - 1) / kBlockRows;
#ifdef _OPENMP
  const int64_t max_threads = std::max<int64_t>(1, std::min<int64_t>(omp_get_max_threads(), blocks));
#else
  const int64_t max_threads = 1;
#endif
  // Thread 0 sums the product into `out`, the others into partials; the column sums go to per-thread
  // double accumulators. Everything is added in thread order afterwards.
  std::fill(op, op + M * N, 0.0f);
  std::vector<float> partial(static_cast<size_t>((max_threads - 1) * M * N), 0.0f);
  std::vector<double> sums(static_cast<size_t>(max_threads * (M + N)), 0.0);
#pragma omp parallel num_threads(max_threads)
  {
#ifdef _OPENMP
    const int64_t thread = omp_get_thread_num(), n_threads = omp_get_num_threads();
#else
    const int64_t thread = 0, n_threads = 1;
#endif
    // Contiguous row ranges in whole blocks, one per thread.
    const int64_t p0 = std::min(P, (blocks * thread / n_threads) * kBlockRows);
    const int64_t p1 = std::min(P, (blocks * (thread + 1) / n_threads) * kBlockRows);
    float* mine = thread == 0 ? op : partial.data() + (thread - 1) * M * N;
    double* my_sums = sums.data() + thread * (M + N);
    rows_fn(ap, bp, M, N, p0, p1, mine, asp != nullptr ? my_sums : nullptr, bsp != nullptr ? my_sums + M : nullptr);
  }
  for (int64_t t = 1; t < max_threads; ++t) {
    const float* part = partial.data() + (t - 1) * M * N;
    for (int64_t i = 0; i < M * N; ++i) op[i] += part[i];
  }
  for (int64_t t = 1; t < max_threads; ++t)
    for (int64_t i = 0; i < M + N; ++i) sums[i] += sums[t * (M + N) + i];
  if (asp != nullptr)
    for (int64_t m = 0; m < M; ++m) asp[m] = static_cast<float>(sums[m]);
  if (bsp != nullptr)
    for (int64_t n = 0; n < N; ++n) bsp[n] = static_cast<float>(sums[M + n]);
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "Weight gradients A^T B of fully connected layers from row-major (P, M), (P, N) float32 arrays";
  m.def("outer_sum", &outer_sum, "out (M, N) = a^T b, and the column sums of a and b unless passed empty (in place)",
        py::arg("a"), py::arg("b"), py::arg("out"), py::arg("a_sums"), py::arg("b_sums"), py::arg("copy") = "");
  m.def("copies", &copy_names, "names of the ISA copies this CPU runs, the one outer_sum uses by default first");
}
