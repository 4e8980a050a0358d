// Shared by the numpy/pybind11 kernels (sdfhead.cpp, wgrad.cpp): CPU-feature clones and the check
// of the preallocated output arrays they write in place. A header, not a kernel: the loader hashes
// every csrc/*.h into each kernel's cache key, so editing this rebuilds the kernels that use it.

#pragma once

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <stdexcept>
#include <string>
#include <vector>

// Clones by ISA level (x86-64-v4: AVX-512, v3: AVX2 + FMA), dispatched on CPU features, never on the
// CPU model (an `arch=haswell` clone never runs on AMD). Feature-named clones ("avx2") are the
// fallback for GCC < 12; their AVX2 copy does not vectorise every loop (no blend/FMA set).
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 12
#define IGA_CLONES __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#elif defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define IGA_CLONES __attribute__((target_clones("avx512f", "avx2", "default")))
#else
#define IGA_CLONES
#endif

// Single-ISA targets for kernels that keep one hand-sized copy per register file (wgrad.cpp), chosen
// at run time with __builtin_cpu_supports; undefined where there is no such choice (not x86-64 GCC).
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && __GNUC__ >= 12
#define IGA_TARGET_V4 __attribute__((target("arch=x86-64-v4")))
#define IGA_TARGET_V3 __attribute__((target("arch=x86-64-v3")))
#elif defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define IGA_TARGET_V4 __attribute__((target("avx512f")))
#define IGA_TARGET_V3 __attribute__((target("avx2,fma")))
#endif

namespace iga {

namespace py = pybind11;

// The float32 data of an output array of exactly `shape`, C-contiguous. Outputs come as buffers,
// not array_t: a converted copy would take the writes and lose them. Errors name the kernel.
inline float* output_floats(const py::buffer& buffer, const std::vector<py::ssize_t>& shape, const char* kernel,
                            const char* name) {
  const py::buffer_info info = buffer.request(true);
  const auto fail = [&](const char* why) {
    throw std::invalid_argument(std::string(kernel) + ": output " + name + " " + why);
  };
  if (info.format != py::format_descriptor<float>::format() || info.itemsize != sizeof(float)) fail("must be float32");
  if (info.ndim != static_cast<py::ssize_t>(shape.size())) fail("has the wrong number of dimensions");
  py::ssize_t stride = sizeof(float);
  for (py::ssize_t i = info.ndim - 1; i >= 0; --i) {
    if (info.shape[i] != shape[i]) fail("has the wrong shape");
    if (info.shape[i] > 1 && info.strides[i] != stride) fail("must be C-contiguous");
    stride *= info.shape[i];
  }
  return static_cast<float*>(info.ptr);
}

}  // namespace iga
