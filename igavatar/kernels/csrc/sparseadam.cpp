// Adam on a hash table with tiny-cuda-nn's rule: an entry whose gradient is exactly zero this step
// is skipped, its value, moments and step count all unchanged (reference and the why:
// igavatar/training/optim.py, SparseAdam). Per reached entry i:
//
//   n_i += 1;  m_i = b1 m_i + (1 - b1) g_i;  v_i = b2 v_i + (1 - b2) g_i^2
//   x_i -= lr * c(n_i) * m_i / (sqrt(v_i) + eps),   c(n) = sqrt(1 - b2^n) / (1 - b1^n)
//
// c comes as a table indexed by n (c[0] unused), its last value standing for every larger n (it
// is 1 in float32 long before): no pow per entry. One pass over the five arrays, split between
// threads; elementwise, so the result does not depend on the thread count. numpy in, in place.

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include "numpy_kernel.h"

#include <cmath>
#include <cstdint>
#include <stdexcept>
#include <string>

namespace py = pybind11;
using Floats = py::array_t<float, py::array::c_style>;

namespace {

int32_t* output_ints(const py::buffer& buffer, py::ssize_t size) {
  const py::buffer_info info = buffer.request(true);
  if (info.format != py::format_descriptor<int32_t>::format() || info.itemsize != sizeof(int32_t))
    throw std::invalid_argument("sparseadam: steps must be int32");
  if (info.size != size) throw std::invalid_argument("sparseadam: steps has the wrong size");
  if (info.ndim > 0 && info.strides[info.ndim - 1] != sizeof(int32_t) && info.size > 1)
    throw std::invalid_argument("sparseadam: steps must be C-contiguous");
  return static_cast<int32_t*>(info.ptr);
}

void step(py::buffer param, const Floats& grad, py::buffer exp_avg, py::buffer exp_avg_sq, py::buffer steps,
          const Floats& correction, float lr, float beta1, float beta2, float eps) {
  const py::ssize_t n = grad.size();
  const std::vector<py::ssize_t> flat{n};
  float* x = iga::output_floats(param, flat, "sparseadam", "param");
  float* m = iga::output_floats(exp_avg, flat, "sparseadam", "exp_avg");
  float* v = iga::output_floats(exp_avg_sq, flat, "sparseadam", "exp_avg_sq");
  int32_t* count = output_ints(steps, n);
  const float* g = grad.data();
  const float* c = correction.data();
  const int32_t last = static_cast<int32_t>(correction.size()) - 1;
  if (last < 1) throw std::invalid_argument("sparseadam: the correction table needs at least 2 entries");
  {
    py::gil_scoped_release release;
#pragma omp parallel for schedule(static)
    for (py::ssize_t i = 0; i < n; ++i) {
      const float gi = g[i];
      if (gi == 0.0f) continue;
      const float mi = m[i] = beta1 * m[i] + (1.0f - beta1) * gi;
      const float vi = v[i] = beta2 * v[i] + (1.0f - beta2) * gi * gi;
      const int32_t k = ++count[i];
      x[i] -= lr * c[k < last ? k : last] * mi / (std::sqrt(vi) + eps);
    }
  }
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "Adam that skips entries with a zero gradient (tiny-cuda-nn's hash-table rule), in place on flat float32 arrays";
  m.def("step", &step, "one SparseAdam step in place", py::arg("param"), py::arg("grad"), py::arg("exp_avg"),
        py::arg("exp_avg_sq"), py::arg("steps"), py::arg("correction"), py::arg("lr"), py::arg("beta1"),
        py::arg("beta2"), py::arg("eps"));
}
