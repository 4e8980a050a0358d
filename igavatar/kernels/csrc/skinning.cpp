// Fast-SNARF skinning on CPU: forward LBS through a channel-last voxel grid, each start's own
// bone weight (start selection) and the per-start Broyden root finding, one start per loop
// iteration with everything in registers.
//
// Reference (and the semantics every function here must keep): igavatar/skinning/grid.py
// (`sample_grid`: grid_sample, trilinear, padding "border", align_corners=True) and
// igavatar/model/deformer.py (`_broyden_reference`, `FastSnarfDeformer.initial_points`).
// Grids are (D, H, W, C) float32, contiguous: the C values of a voxel are adjacent, so a lookup
// reads 8 short runs instead of 8 * C scattered floats. Points are (x, y, z) = (W, H, D) axes.

#include <torch/extension.h>

#include <cmath>
#include <cstdint>

namespace {

struct Grid {
  const float* data;
  int64_t depth, height, width, channels;
  float box_min[3];
  float scale[3];  // 2 / (box_max - box_min), as grid.py's _normalised_coordinates
};

Grid make_grid(const torch::Tensor& grid, const torch::Tensor& box_min, const torch::Tensor& box_max) {
  TORCH_CHECK(grid.dim() == 4, "skinning kernel: grid must be (D, H, W, C), got ", grid.sizes());
  TORCH_CHECK(grid.scalar_type() == torch::kFloat32 && grid.is_contiguous() && grid.device().is_cpu(),
              "skinning kernel: grid must be a contiguous float32 CPU tensor");
  TORCH_CHECK(box_min.numel() == 3 && box_max.numel() == 3, "skinning kernel: box_min/box_max must have 3 values");
  auto lo = box_min.to(torch::kFloat32).contiguous();
  auto hi = box_max.to(torch::kFloat32).contiguous();
  Grid g;
  g.data = grid.data_ptr<float>();
  g.depth = grid.size(0);
  g.height = grid.size(1);
  g.width = grid.size(2);
  g.channels = grid.size(3);
  for (int a = 0; a < 3; ++a) {
    g.box_min[a] = lo.data_ptr<float>()[a];
    g.scale[a] = 2.0f / (hi.data_ptr<float>()[a] - g.box_min[a]);
  }
  return g;
}

// One axis of grid_sample's align_corners=True, padding "border" unnormalisation: the voxel index
// i0 of the lower corner, i1 of the upper one, and the upper corner's weight t.
inline void axis_corners(float x, float box_min, float scale, int64_t size, int64_t& i0, int64_t& i1, float& t) {
  const float normalised = (x - box_min) * scale - 1.0f;
  float index = ((normalised + 1.0f) / 2.0f) * static_cast<float>(size - 1);
  if (!(index > 0.0f)) index = 0.0f;  // also maps nan to the border, like clip_coordinates
  if (index > static_cast<float>(size - 1)) index = static_cast<float>(size - 1);
  const float floor_index = std::floor(index);
  i0 = static_cast<int64_t>(floor_index);
  t = index - floor_index;
  i1 = i0 + 1 < size ? i0 + 1 : i0;  // t == 0 whenever i0 is the last voxel
}

struct Corners {
  int64_t offset[8];  // element offsets of the 8 voxels (channel 0)
  float weight[8];
};

inline void corners(const Grid& g, const float* x, Corners& c) {
  int64_t x0, x1, y0, y1, z0, z1;
  float tx, ty, tz;
  axis_corners(x[0], g.box_min[0], g.scale[0], g.width, x0, x1, tx);
  axis_corners(x[1], g.box_min[1], g.scale[1], g.height, y0, y1, ty);
  axis_corners(x[2], g.box_min[2], g.scale[2], g.depth, z0, z1, tz);
  const int64_t zs[2] = {z0, z1}, ys[2] = {y0, y1}, xs[2] = {x0, x1};
  const float wz[2] = {1.0f - tz, tz}, wy[2] = {1.0f - ty, ty}, wx[2] = {1.0f - tx, tx};
  int k = 0;
  for (int dz = 0; dz < 2; ++dz)
    for (int dy = 0; dy < 2; ++dy)
      for (int dx = 0; dx < 2; ++dx, ++k) {
        c.offset[k] = ((zs[dz] * g.height + ys[dy]) * g.width + xs[dx]) * g.channels;
        c.weight[k] = wz[dz] * wy[dy] * wx[dx];
      }
}

// The 12 entries (row-major 3x4) of the blended transform at x.
inline void blended_transform(const Grid& g, const float* x, float* transform) {
  Corners c;
  corners(g, x, c);
  for (int e = 0; e < 12; ++e) transform[e] = 0.0f;
  for (int k = 0; k < 8; ++k) {
    const float* v = g.data + c.offset[k];
    const float w = c.weight[k];
    for (int e = 0; e < 12; ++e) transform[e] += w * v[e];
  }
}

inline void apply(const float* transform, const float* x, float* out) {
  for (int r = 0; r < 3; ++r)
    out[r] = transform[4 * r] * x[0] + transform[4 * r + 1] * x[1] + transform[4 * r + 2] * x[2] + transform[4 * r + 3];
}

// Inverse of the 3x3 block of a 3x4 transform by the adjugate; identity when |det| <= 1e-12.
inline void inverse3(const float* t, float* inv) {
  const float a = t[0], b = t[1], c = t[2], d = t[4], e = t[5], f = t[6], g = t[8], h = t[9], i = t[10];
  const float ca = e * i - f * h, cb = f * g - d * i, cc = d * h - e * g;
  const float det = a * ca + b * cb + c * cc;
  if (!(std::fabs(det) > 1e-12f)) {
    for (int k = 0; k < 9; ++k) inv[k] = (k % 4 == 0) ? 1.0f : 0.0f;
    return;
  }
  const float adj[9] = {ca, c * h - b * i, b * f - c * e, cb, a * i - c * g, c * d - a * f, cc, b * g - a * h, a * e - b * d};
  for (int k = 0; k < 9; ++k) inv[k] = adj[k] / det;
}

inline float norm3(const float* v) { return std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]); }

void check_points(const torch::Tensor& x, const char* name) {
  TORCH_CHECK(x.dim() == 2 && x.size(1) == 3, "skinning kernel: ", name, " must be (N, 3), got ", x.sizes());
  TORCH_CHECK(x.scalar_type() == torch::kFloat32 && x.is_contiguous() && x.device().is_cpu(),
              "skinning kernel: ", name, " must be a contiguous float32 CPU tensor");
}

}  // namespace

// Channel i of the grid at x[:, i]: (N, C, 3) -> (N, C) (each start's own bone weight).
torch::Tensor sample_diagonal(torch::Tensor grid, torch::Tensor box_min, torch::Tensor box_max, torch::Tensor x) {
  const Grid g = make_grid(grid, box_min, box_max);
  TORCH_CHECK(x.dim() == 3 && x.size(1) == g.channels && x.size(2) == 3,
              "skinning kernel: x must be (N, C, 3) with C = grid channels, got ", x.sizes());
  TORCH_CHECK(x.scalar_type() == torch::kFloat32 && x.is_contiguous(), "skinning kernel: x must be contiguous float32");
  const int64_t n = x.size(0), channels = g.channels;
  auto out = torch::empty({n, channels}, x.options());
  const float* xp = x.data_ptr<float>();
  float* op = out.data_ptr<float>();
#pragma omp parallel for schedule(static)
  for (int64_t p = 0; p < n; ++p) {
    for (int64_t ch = 0; ch < channels; ++ch) {
      Corners c;
      corners(g, xp + 3 * (p * channels + ch), c);
      float value = 0.0f;
      for (int k = 0; k < 8; ++k) value += c.weight[k] * g.data[c.offset[k] + ch];
      op[p * channels + ch] = value;
    }
  }
  return out;
}

// Forward LBS with the blended transform grid (D, H, W, 12): canonical (N, 3) -> posed (N, 3).
torch::Tensor lbs(torch::Tensor blended, torch::Tensor box_min, torch::Tensor box_max, torch::Tensor x) {
  const Grid g = make_grid(blended, box_min, box_max);
  TORCH_CHECK(g.channels == 12, "skinning kernel: blended grid must have 12 channels, got ", g.channels);
  check_points(x, "x");
  const int64_t n = x.size(0);
  auto out = torch::empty_like(x);
  const float* xp = x.data_ptr<float>();
  float* op = out.data_ptr<float>();
#pragma omp parallel for schedule(static)
  for (int64_t p = 0; p < n; ++p) {
    float transform[12];
    blended_transform(g, xp + 3 * p, transform);
    apply(transform, xp + 3 * p, op + 3 * p);
  }
  return out;
}

// Broyden's good method for LBS(x) = x_target from x_init, per start (deformer._broyden_reference):
// returns the iterate with the smallest residual (N, 3) and that residual's norm (N,).
std::vector<torch::Tensor> broyden(torch::Tensor blended, torch::Tensor box_min, torch::Tensor box_max,
                                   torch::Tensor x_target, torch::Tensor x_init, int64_t max_iterations,
                                   double converge_threshold, double diverge_threshold) {
  const Grid g = make_grid(blended, box_min, box_max);
  TORCH_CHECK(g.channels == 12, "skinning kernel: blended grid must have 12 channels, got ", g.channels);
  check_points(x_target, "x_target");
  check_points(x_init, "x_init");
  TORCH_CHECK(x_target.size(0) == x_init.size(0), "skinning kernel: x_target and x_init differ in length");
  const int64_t n = x_init.size(0);
  auto x_best = torch::empty_like(x_init);
  auto residual_best = torch::empty({n}, x_init.options());
  const float* target_ptr = x_target.data_ptr<float>();
  const float* init_ptr = x_init.data_ptr<float>();
  float* best_ptr = x_best.data_ptr<float>();
  float* norm_ptr = residual_best.data_ptr<float>();
  const float converge = static_cast<float>(converge_threshold);
  const float diverge = static_cast<float>(diverge_threshold);

#pragma omp parallel for schedule(dynamic, 256)
  for (int64_t p = 0; p < n; ++p) {
    const float* target = target_ptr + 3 * p;
    float x[3] = {init_ptr[3 * p], init_ptr[3 * p + 1], init_ptr[3 * p + 2]};
    float transform[12], posed[3], residual[3], h[9];
    blended_transform(g, x, transform);
    apply(transform, x, posed);
    for (int r = 0; r < 3; ++r) residual[r] = posed[r] - target[r];
    inverse3(transform, h);
    float best[3] = {x[0], x[1], x[2]};
    float norm_best = norm3(residual);
    if (norm_best > converge) {
      for (int64_t iteration = 0; iteration < max_iterations; ++iteration) {
        float step[3];
        for (int r = 0; r < 3; ++r) step[r] = -(h[3 * r] * residual[0] + h[3 * r + 1] * residual[1] + h[3 * r + 2] * residual[2]);
        for (int r = 0; r < 3; ++r) x[r] += step[r];
        blended_transform(g, x, transform);
        apply(transform, x, posed);
        float change[3];
        for (int r = 0; r < 3; ++r) {
          const float updated = posed[r] - target[r];
          change[r] = updated - residual[r];
          residual[r] = updated;
        }
        const float norm = norm3(residual);
        if (norm < norm_best) {
          norm_best = norm;
          best[0] = x[0], best[1] = x[1], best[2] = x[2];
        }
        if (!(norm_best > converge && norm < diverge)) break;
        // Good Broyden: H += (dx - H dg) (dx^T H) / (dx^T H dg); skipped when the secant pair
        // carries no information (denominator far below |dx|^2).
        float v[3];
        for (int c = 0; c < 3; ++c) v[c] = step[0] * h[c] + step[1] * h[3 + c] + step[2] * h[6 + c];
        const float denominator = v[0] * change[0] + v[1] * change[1] + v[2] * change[2];
        const float step_sq = step[0] * step[0] + step[1] * step[1] + step[2] * step[2];
        if (std::fabs(denominator) > 1e-6f * step_sq) {
          const float inv_den = 1.0f / denominator;
          float numerator[3];
          for (int r = 0; r < 3; ++r)
            numerator[r] = step[r] - (h[3 * r] * change[0] + h[3 * r + 1] * change[1] + h[3 * r + 2] * change[2]);
          for (int r = 0; r < 3; ++r)
            for (int c = 0; c < 3; ++c) h[3 * r + c] += numerator[r] * inv_den * v[c];
        }
      }
    }
    best_ptr[3 * p] = best[0];
    best_ptr[3 * p + 1] = best[1];
    best_ptr[3 * p + 2] = best[2];
    norm_ptr[p] = norm_best;
  }
  return {x_best, residual_best};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("sample_diagonal", &sample_diagonal, "channel i at x[:, i]: (N, C, 3) -> (N, C)");
  m.def("lbs", &lbs, "forward LBS through a (D, H, W, 12) blended transform grid");
  m.def("broyden", &broyden, "Broyden root finding of LBS(x) = x_target per start");
}
