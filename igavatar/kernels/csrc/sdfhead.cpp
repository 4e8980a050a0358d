// Element-wise passes of the SDF MLP's fused forward/backward with its analytic gradient
// (igavatar/model/sdf_head.py): the network's matrix products run on oneDNN in Python, and the
// passes between them run here, each one sweep over memory instead of a dozen torch ops.
//
//   activation_forward:  a = softplus_beta(z), u = slope(z) * w0          (R, H) each
//   softplus:            a alone (no gradient wanted)
//   activation_backward: grad_z = grad_a * s + grad_u * w0 * s'(z);  grad_w0 = sum_rows grad_u * s
//   gradient_forward:    grad_sdf = gin[:, :3] * k[:3] + sum_c gin[:, 3 + c] k[3 + c] J[:, c, :]
//   gradient_backward:   grad_gin[:, d] = k[d] * (d < 3 ? g[:, d] : J[:, d - 3, :] . g),
//                        grad_J[:, c, :] = gin[:, 3 + c] k[3 + c] g
//
// softplus_beta(z) = log(1 + exp(beta z)) / beta and slope(z) = sigmoid(beta z) are torch's
// F.softplus(z, beta, threshold) and its derivative, both switching to the identity (slope 1,
// s' = 0) where beta z > threshold, exactly as the PyTorch reference SDFField.forward_with_gradient.
// One exp per element, e = exp(-|beta z|), gives both: softplus = (max(beta z, 0) + log1p(e)) / beta,
// sigmoid = 1 / (1 + e) or e / (1 + e), and s (1 - s) = e / (1 + e)^2 without cancellation.
// exp and log1p are written out (Cephes-style polynomials; tests hold them to 2e-6 relative
// against float64) so the loops vectorise. target_clones picks the AVX-512 / AVX2 / plain copy by
// CPU feature when the library loads (IGA_CLONES in numpy_kernel.h), so the cached library runs on any x86-64.
//
// numpy in, numpy out (pybind11 only, no ATen headers: builds in seconds). Outputs are
// preallocated by the caller (torch tensors seen through .numpy()) and written in place.

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include "numpy_kernel.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <stdexcept>
#include <string>
#include <vector>

#ifdef _OPENMP
#include <omp.h>
#endif

namespace py = pybind11;
using Floats = py::array_t<float, py::array::c_style>;

namespace {

// exp(x) for x <= 0 (x < -87 gives 0): 2^n * p(r), r = x - n ln2 in [-ln2/2, ln2/2].
__attribute__((always_inline)) inline float exp_nonpositive(float x) {
  x = x > -87.0f ? x : -87.0f;
  // Round to nearest by the 1.5 * 2^23 trick (|x log2 e| < 2^22): vectorises without SSE4.1.
  const float n = (x * 1.44269504088896341f + 12582912.0f) - 12582912.0f;
  const float r = (x - n * 0.693359375f) + n * 2.12194440e-4f;
  float p = 1.9875691500e-4f;
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  p = p * r * r + r + 1.0f;
  const int32_t scale = (static_cast<int32_t>(n) + 127) << 23;
  float two_n;
  std::memcpy(&two_n, &scale, sizeof(two_n));
  return p * two_n;
}

// log(1 + e) for e in [0, 1]: 2 atanh(t), t = e / (2 + e) in [0, 1/3] (odd series to t^15).
__attribute__((always_inline)) inline float log1p_unit(float e) {
  const float t = e / (2.0f + e);
  const float t2 = t * t;
  float p = 1.0f / 15.0f;
  p = p * t2 + 1.0f / 13.0f;
  p = p * t2 + 1.0f / 11.0f;
  p = p * t2 + 1.0f / 9.0f;
  p = p * t2 + 1.0f / 7.0f;
  p = p * t2 + 1.0f / 5.0f;
  p = p * t2 + 1.0f / 3.0f;
  p = p * t2 + 1.0f;
  return 2.0f * t * p;
}

const float* input(const Floats& array, const std::vector<py::ssize_t>& shape, const char* name) {
  if (array.ndim() != static_cast<py::ssize_t>(shape.size()))
    throw std::invalid_argument(std::string("sdfhead: ") + name + " has the wrong number of dimensions");
  for (size_t i = 0; i < shape.size(); ++i)
    if (array.shape(i) != shape[i]) throw std::invalid_argument(std::string("sdfhead: ") + name + " has the wrong shape");
  return array.data();
}

float* output(const py::buffer& buffer, const std::vector<py::ssize_t>& shape, const char* name) {
  return iga::output_floats(buffer, shape, "sdfhead", name);
}

// The shared per-element terms at beta z (see the header comment): e = exp(-|beta z|); `linear`:
// beta z > threshold (identity, slope 1, s' = 0). Scalars, not a struct, so GCC still vectorises.
__attribute__((always_inline)) inline float softplus_value(float zn, float bz, float e, bool linear, float inv_beta) {
  // Both sides evaluated, then selected: a branch here would stop the AVX2 copy vectorising.
  const float soft = ((bz > 0.0f ? bz : 0.0f) + log1p_unit(e)) * inv_beta;
  return linear ? zn : soft;
}

// sigmoid(beta z) from e and inv = 1 / (1 + e); 1 where linear.
__attribute__((always_inline)) inline float slope_value(float bz, float e, float inv, bool linear) {
  return linear ? 1.0f : (bz >= 0.0f ? inv : e * inv);
}

// Rows [r0, r1) of a = softplus(z) and u = slope(z) * w0.
IGA_CLONES void activation_forward_rows(const float* z, const float* w0, float beta, float threshold, float* a,
                                        float* u, int64_t r0, int64_t r1, int64_t H) {
  const float inv_beta = 1.0f / beta;
  for (int64_t r = r0; r < r1; ++r) {
    const int64_t base = r * H;
#pragma omp simd
    for (int64_t h = 0; h < H; ++h) {
      const float bz = beta * z[base + h];
      const float e = exp_nonpositive(-__builtin_fabsf(bz));
      const bool linear = bz > threshold;
      a[base + h] = softplus_value(z[base + h], bz, e, linear, inv_beta);
      u[base + h] = slope_value(bz, e, 1.0f / (1.0f + e), linear) * w0[h];
    }
  }
}

// Rows [r0, r1) of a = softplus(z) alone (the SDF without its gradient: queries, meshing).
IGA_CLONES void softplus_rows(const float* z, float beta, float threshold, float* a, int64_t r0, int64_t r1,
                              int64_t H) {
  const float inv_beta = 1.0f / beta;
  for (int64_t r = r0; r < r1; ++r) {
    const int64_t base = r * H;
#pragma omp simd
    for (int64_t h = 0; h < H; ++h) {
      const float bz = beta * z[base + h];
      a[base + h] = softplus_value(z[base + h], bz, exp_nonpositive(-__builtin_fabsf(bz)), bz > threshold, inv_beta);
    }
  }
}

// Rows [r0, r1) of grad_z = grad_a * s + grad_u * w0 * s'; gw0 (H,) accumulates grad_u * s.
IGA_CLONES void activation_backward_rows(const float* z, const float* ga, const float* gu, const float* w0,
                                         float beta, float threshold, float* gz, float* gw0, int64_t r0,
                                         int64_t r1, int64_t H) {
  for (int64_t r = r0; r < r1; ++r) {
    const int64_t base = r * H;
#pragma omp simd
    for (int64_t h = 0; h < H; ++h) {
      const float bz = beta * z[base + h];
      const float e = exp_nonpositive(-__builtin_fabsf(bz));
      const float inv = 1.0f / (1.0f + e);
      const bool linear = bz > threshold;
      const float s = slope_value(bz, e, inv, linear);
      const float ds = linear ? 0.0f : beta * e * inv * inv;  // d slope / dz = beta s (1 - s)
      gz[base + h] = ga[base + h] * s + gu[base + h] * w0[h] * ds;
      gw0[h] += gu[base + h] * s;
    }
  }
}

// Rows [0, R) split into contiguous blocks, one per thread, in thread order (deterministic sums).
template <typename Body>
void parallel_rows(int64_t R, Body body) {
#pragma omp parallel
  {
#ifdef _OPENMP
    const int64_t n_threads = omp_get_num_threads(), thread = omp_get_thread_num();
#else
    const int64_t n_threads = 1, thread = 0;
#endif
    const int64_t r0 = R * thread / n_threads, r1 = R * (thread + 1) / n_threads;
    body(r0, r1, thread, n_threads);
  }
}

void activation_forward(const Floats& z, const Floats& w0, float beta, float threshold, const py::buffer& a, const py::buffer& u) {
  const int64_t R = z.ndim() == 2 ? z.shape(0) : -1, H = z.ndim() == 2 ? z.shape(1) : -1;
  if (R < 0) throw std::invalid_argument("sdfhead: z must be (R, H)");
  if (!(beta > 0.0f)) throw std::invalid_argument("sdfhead: beta must be > 0");
  const float* zp = input(z, {R, H}, "z");
  const float* wp = input(w0, {H}, "w0");
  float* ap = output(a, {R, H}, "a");
  float* up = output(u, {R, H}, "u");
  py::gil_scoped_release release;
  parallel_rows(R, [&](int64_t r0, int64_t r1, int64_t, int64_t) {
    activation_forward_rows(zp, wp, beta, threshold, ap, up, r0, r1, H);
  });
}

void softplus(const Floats& z, float beta, float threshold, const py::buffer& a) {
  const int64_t R = z.ndim() == 2 ? z.shape(0) : -1, H = z.ndim() == 2 ? z.shape(1) : -1;
  if (R < 0) throw std::invalid_argument("sdfhead: z must be (R, H)");
  if (!(beta > 0.0f)) throw std::invalid_argument("sdfhead: beta must be > 0");
  const float* zp = input(z, {R, H}, "z");
  float* ap = output(a, {R, H}, "a");
  py::gil_scoped_release release;
  parallel_rows(R, [&](int64_t r0, int64_t r1, int64_t, int64_t) { softplus_rows(zp, beta, threshold, ap, r0, r1, H); });
}

void activation_backward(const Floats& z, const Floats& grad_a, const Floats& grad_u, const Floats& w0, float beta,
                         float threshold, const py::buffer& grad_z, const py::buffer& grad_w0) {
  const int64_t R = z.ndim() == 2 ? z.shape(0) : -1, H = z.ndim() == 2 ? z.shape(1) : -1;
  if (R < 0) throw std::invalid_argument("sdfhead: z must be (R, H)");
  const float* zp = input(z, {R, H}, "z");
  const float* gap = input(grad_a, {R, H}, "grad_a");
  const float* gup = input(grad_u, {R, H}, "grad_u");
  const float* wp = input(w0, {H}, "w0");
  float* gzp = output(grad_z, {R, H}, "grad_z");
  float* gwp = output(grad_w0, {H}, "grad_w0");
  py::gil_scoped_release release;
#ifdef _OPENMP
  const int64_t max_threads = omp_get_max_threads();
#else
  const int64_t max_threads = 1;
#endif
  // One partial sum of grad_w0 per thread, added in thread order: the same result on every run.
  std::vector<float> partial(static_cast<size_t>(max_threads * H), 0.0f);
  parallel_rows(R, [&](int64_t r0, int64_t r1, int64_t thread, int64_t) {
    activation_backward_rows(zp, gap, gup, wp, beta, threshold, gzp, partial.data() + thread * H, r0, r1, H);
  });
  std::fill(gwp, gwp + H, 0.0f);
  for (int64_t t = 0; t < max_threads; ++t)
    for (int64_t h = 0; h < H; ++h) gwp[h] += partial[t * H + h];
}

void gradient_forward(const Floats& gin, const Floats& jacobian, const Floats& scale, const py::buffer& out) {
  if (gin.ndim() != 2 || jacobian.ndim() != 3) throw std::invalid_argument("sdfhead: gin (R, D), jacobian (P, C, 3)");
  const int64_t R = gin.shape(0), D = gin.shape(1), P = jacobian.shape(0), C = jacobian.shape(1);
  if (D != 3 + C || P > R) throw std::invalid_argument("sdfhead: gin must be (R >= P, 3 + C) for a (P, C, 3) jacobian");
  const float* gp = input(gin, {R, D}, "gin");
  const float* jp = input(jacobian, {P, C, 3}, "jacobian");
  const float* kp = input(scale, {D}, "scale");
  float* op = output(out, {P, 3}, "out");
  py::gil_scoped_release release;
#pragma omp parallel for schedule(static)
  for (int64_t p = 0; p < P; ++p) {
    const float* g = gp + p * D;
    const float* j = jp + p * C * 3;
    float o[3] = {g[0] * kp[0], g[1] * kp[1], g[2] * kp[2]};
    for (int64_t c = 0; c < C; ++c) {
      const float v = g[3 + c] * kp[3 + c];
      o[0] += v * j[3 * c];
      o[1] += v * j[3 * c + 1];
      o[2] += v * j[3 * c + 2];
    }
    op[3 * p] = o[0];
    op[3 * p + 1] = o[1];
    op[3 * p + 2] = o[2];
  }
}

void gradient_backward(const Floats& grad_out, const Floats& gin, const Floats& jacobian, const Floats& scale,
                       const py::buffer& grad_gin, const py::buffer& grad_jacobian) {
  if (gin.ndim() != 2 || jacobian.ndim() != 3) throw std::invalid_argument("sdfhead: gin (R, D), jacobian (P, C, 3)");
  const int64_t R = gin.shape(0), D = gin.shape(1), P = jacobian.shape(0), C = jacobian.shape(1);
  if (D != 3 + C || P > R) throw std::invalid_argument("sdfhead: gin must be (R >= P, 3 + C) for a (P, C, 3) jacobian");
  const float* gop = input(grad_out, {P, 3}, "grad_out");
  const float* gp = input(gin, {R, D}, "gin");
  const float* jp = input(jacobian, {P, C, 3}, "jacobian");
  const float* kp = input(scale, {D}, "scale");
  float* ggp = output(grad_gin, {R, D}, "grad_gin");
  // A (0, C, 3) grad_jacobian: the Jacobian needs no gradient.
  float* gjp = grad_jacobian.request().size == 0 ? nullptr : output(grad_jacobian, {P, C, 3}, "grad_jacobian");
  py::gil_scoped_release release;
#pragma omp parallel for schedule(static)
  for (int64_t p = 0; p < R; ++p) {
    float* q = ggp + p * D;
    if (p >= P) {  // padding rows of the MLP: no gradient
      std::fill(q, q + D, 0.0f);
      continue;
    }
    const float* go = gop + 3 * p;
    const float* j = jp + p * C * 3;
    const float* g = gp + p * D;
    for (int a = 0; a < 3; ++a) q[a] = kp[a] * go[a];
    for (int64_t c = 0; c < C; ++c) {
      q[3 + c] = kp[3 + c] * (j[3 * c] * go[0] + j[3 * c + 1] * go[1] + j[3 * c + 2] * go[2]);
      if (gjp) {
        const float v = g[3 + c] * kp[3 + c];
        float* gj = gjp + (p * C + c) * 3;
        gj[0] = v * go[0];
        gj[1] = v * go[1];
        gj[2] = v * go[2];
      }
    }
  }
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("activation_forward", &activation_forward, "a = softplus(z), u = slope(z) * w0 (in place)", py::arg("z"),
        py::arg("w0"), py::arg("beta"), py::arg("threshold"), py::arg("a"), py::arg("u"));
  m.def("softplus", &softplus, "a = softplus(z) (in place)", py::arg("z"), py::arg("beta"), py::arg("threshold"),
        py::arg("a"));
  m.def("activation_backward", &activation_backward, "grad_z and grad_w0 of activation_forward (in place)",
        py::arg("z"), py::arg("grad_a"), py::arg("grad_u"), py::arg("w0"), py::arg("beta"), py::arg("threshold"),
        py::arg("grad_z"), py::arg("grad_w0"));
  m.def("gradient_forward", &gradient_forward, "grad_sdf from the MLP input gradient and the grid Jacobian",
        py::arg("gin"), py::arg("jacobian"), py::arg("scale"), py::arg("out"));
  m.def("gradient_backward", &gradient_backward, "grad_gin and grad_jacobian of gradient_forward (in place)",
        py::arg("grad_out"), py::arg("gin"), py::arg("jacobian"), py::arg("scale"), py::arg("grad_gin"),
        py::arg("grad_jacobian"));
}
