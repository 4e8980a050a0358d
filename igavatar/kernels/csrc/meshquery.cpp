// Exact triangle-mesh queries for the geometry metrics, one point per loop iteration (OpenMP over
// points; the result of a point never depends on the thread count).
//
// * inside(vertices, faces, points): ray parity along +z. Triangles are binned by their xy bounding
//   box into a 2D grid; a point tests only the triangles of its column's cell. Points exactly on a
//   projected edge or vertex are resolved by simulation of simplicity (the point is moved by
//   (d, d^2), d -> 0+), so the two triangles sharing an edge never both count and never both miss:
//   the parity is exact on a closed mesh for every point not on the surface itself.
// * closest(vertices, faces, points): exact closest point on the mesh (Ericson, RTCD 5.1.5, the same
//   arithmetic as the numpy reference), ties to the lower face index, through a bounding volume
//   hierarchy searched nearest box first (a far point costs a few more nodes, not a volume scan).
//
// References (the semantics kept here): igavatar/metrics/geometry.py `closest_points_on_mesh`
// (numpy) and `volumetric_iou`'s inside test (trimesh + embree ray parity).
// numpy in, numpy out (pybind11 only: no ATen headers, so the build takes seconds, not a minute).

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

namespace py = pybind11;
using Doubles = py::array_t<double, py::array::c_style | py::array::forcecast>;
using Indices = py::array_t<int64_t, py::array::c_style | py::array::forcecast>;

namespace {

struct Vec3 {
  double x, y, z;
};
inline Vec3 sub(const Vec3& a, const Vec3& b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
inline Vec3 add_scaled(const Vec3& a, double t, const Vec3& d) { return {a.x + t * d.x, a.y + t * d.y, a.z + t * d.z}; }
inline double dot(const Vec3& a, const Vec3& b) { return a.x * b.x + a.y * b.y + a.z * b.z; }

void check_rows(const py::buffer_info& info, int64_t columns, const char* name) {
  if (info.ndim != 2 || info.shape[1] != columns)
    throw std::invalid_argument(std::string("meshquery: ") + name + " must be (N, " + std::to_string(columns) + ")");
}

struct Mesh {
  const double* v;
  const int64_t* f;
  int64_t n_vertices, n_faces;
  Vec3 vertex(int64_t face, int corner) const {
    const double* p = v + 3 * f[3 * face + corner];
    return {p[0], p[1], p[2]};
  }
};

Mesh make_mesh(const Doubles& vertices, const Indices& faces) {
  auto vi = vertices.request();
  auto fi = faces.request();
  check_rows(vi, 3, "vertices");
  check_rows(fi, 3, "faces");
  Mesh mesh{static_cast<const double*>(vi.ptr), static_cast<const int64_t*>(fi.ptr), vi.shape[0], fi.shape[0]};
  for (int64_t i = 0; i < 3 * mesh.n_faces; ++i)
    if (mesh.f[i] < 0 || mesh.f[i] >= mesh.n_vertices) throw std::invalid_argument("meshquery: face index out of range");
  return mesh;
}

// Cells of a uniform grid holding triangle ids (CSR: cell c owns ids[start[c] .. start[c + 1])).
struct Bins {
  std::vector<int64_t> start;
  std::vector<int64_t> ids;
};

// Bin items into cells: `cells_of(i, visit)` calls visit(cell) for every cell item i overlaps.
template <typename CellsOf>
Bins make_bins(int64_t n_items, int64_t n_cells, CellsOf cells_of) {
  Bins bins;
  bins.start.assign(n_cells + 1, 0);
  for (int64_t i = 0; i < n_items; ++i) cells_of(i, [&](int64_t c) { ++bins.start[c + 1]; });
  for (int64_t c = 0; c < n_cells; ++c) bins.start[c + 1] += bins.start[c];
  bins.ids.resize(bins.start[n_cells]);
  std::vector<int64_t> fill(bins.start.begin(), bins.start.end() - 1);
  // Items go in increasing order, so every cell lists its triangles by increasing face index.
  for (int64_t i = 0; i < n_items; ++i) cells_of(i, [&](int64_t c) { bins.ids[fill[c]++] = i; });
  return bins;
}

inline int64_t cell_index(double x, double lo, double inv_size, int64_t n) {
  const double u = (x - lo) * inv_size;
  if (!(u > 0.0)) return 0;
  return std::min<int64_t>(static_cast<int64_t>(u), n - 1);
}

// ----------------------------------------------------------------------------- inside (ray parity)

// Sign of the edge function of (a -> b) at p in the xy plane, with p moved by (d, d^2), d -> 0+:
// never 0 unless the edge is a point in xy.
inline int edge_sign(double ax, double ay, double bx, double by, double px, double py) {
  const double dx = bx - ax, dy = by - ay;
  const double e = dx * (py - ay) - dy * (px - ax);
  if (e > 0) return 1;
  if (e < 0) return -1;
  // e(p + (d, d^2)) = e(p) + dx d^2 - dy d: the d term decides, else the d^2 term.
  if (dy != 0) return dy < 0 ? 1 : -1;
  if (dx != 0) return dx > 0 ? 1 : -1;
  return 0;
}

py::array_t<bool> inside(const Doubles& vertices, const Indices& faces, const Doubles& points) {
  const Mesh mesh = make_mesh(vertices, faces);
  auto pi = points.request();
  check_rows(pi, 3, "points");
  const double* p = static_cast<const double*>(pi.ptr);
  const int64_t n_points = pi.shape[0];
  py::array_t<bool> result(n_points);
  bool* out = result.mutable_data();
  std::fill(out, out + n_points, false);
  if (mesh.n_faces == 0 || n_points == 0) return result;
  py::gil_scoped_release release;

  double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
  for (int64_t i = 0; i < 3 * mesh.n_faces; ++i) {
    const double* q = mesh.v + 3 * mesh.f[i];
    for (int a = 0; a < 3; ++a) lo[a] = std::min(lo[a], q[a]), hi[a] = std::max(hi[a], q[a]);
  }
  // About one cell per two triangles over the xy box, square cells.
  const double ex = std::max(hi[0] - lo[0], 1e-12), ey = std::max(hi[1] - lo[1], 1e-12);
  const double cell = std::sqrt(ex * ey / std::max<double>(1.0, 0.5 * mesh.n_faces));
  const int64_t nx = std::min<int64_t>(4096, std::max<int64_t>(1, static_cast<int64_t>(ex / cell) + 1));
  const int64_t ny = std::min<int64_t>(4096, std::max<int64_t>(1, static_cast<int64_t>(ey / cell) + 1));
  const double inv_x = nx / ex, inv_y = ny / ey;
  const Bins bins = make_bins(mesh.n_faces, nx * ny, [&](int64_t t, auto visit) {
    const Vec3 a = mesh.vertex(t, 0), b = mesh.vertex(t, 1), c = mesh.vertex(t, 2);
    const int64_t x0 = cell_index(std::min({a.x, b.x, c.x}), lo[0], inv_x, nx);
    const int64_t x1 = cell_index(std::max({a.x, b.x, c.x}), lo[0], inv_x, nx);
    const int64_t y0 = cell_index(std::min({a.y, b.y, c.y}), lo[1], inv_y, ny);
    const int64_t y1 = cell_index(std::max({a.y, b.y, c.y}), lo[1], inv_y, ny);
    for (int64_t y = y0; y <= y1; ++y)
      for (int64_t x = x0; x <= x1; ++x) visit(y * nx + x);
  });

#pragma omp parallel for schedule(dynamic, 1024)
  for (int64_t i = 0; i < n_points; ++i) {
    const double px = p[3 * i], py = p[3 * i + 1], pz = p[3 * i + 2];
    // Outside the xy box or above the top, the upward ray meets nothing. The bins' cells are
    // half-open; a point exactly on the box's high edge clamps into the last cell, which holds
    // every triangle touching that edge.
    if (!(px >= lo[0] && px <= hi[0] && py >= lo[1] && py <= hi[1] && pz < hi[2])) continue;
    const int64_t c = cell_index(py, lo[1], inv_y, ny) * nx + cell_index(px, lo[0], inv_x, nx);
    bool parity = false;
    for (int64_t k = bins.start[c]; k < bins.start[c + 1]; ++k) {
      const int64_t t = bins.ids[k];
      const Vec3 a = mesh.vertex(t, 0), b = mesh.vertex(t, 1), v2 = mesh.vertex(t, 2);
      const int s_ab = edge_sign(a.x, a.y, b.x, b.y, px, py);
      const int s_bc = edge_sign(b.x, b.y, v2.x, v2.y, px, py);
      const int s_ca = edge_sign(v2.x, v2.y, a.x, a.y, px, py);
      if (s_ab == 0 || s_ab != s_bc || s_bc != s_ca) continue;
      // Height of the triangle's plane above (px, py) from barycentric weights (edge functions).
      const double w_a = (v2.x - b.x) * (py - b.y) - (v2.y - b.y) * (px - b.x);
      const double w_b = (a.x - v2.x) * (py - v2.y) - (a.y - v2.y) * (px - v2.x);
      const double w_c = (b.x - a.x) * (py - a.y) - (b.y - a.y) * (px - a.x);
      const double total = w_a + w_b + w_c;
      if (total == 0) continue;
      const double z = (w_a * a.z + w_b * b.z + w_c * v2.z) / total;
      if (z > pz) parity = !parity;
    }
    out[i] = parity;
  }
  return result;
}

// ----------------------------------------------------------------------------- closest point

// Ericson's closest point on triangle (a, b, c) to p, in the numpy reference's region order.
inline Vec3 closest_on_triangle(const Vec3& p, const Vec3& a, const Vec3& b, const Vec3& c) {
  const Vec3 ab = sub(b, a), ac = sub(c, a), ap = sub(p, a);
  const double d1 = dot(ab, ap), d2 = dot(ac, ap);
  if (d1 <= 0 && d2 <= 0) return a;
  const Vec3 bp = sub(p, b);
  const double d3 = dot(ab, bp), d4 = dot(ac, bp);
  if (d3 >= 0 && d4 <= d3) return b;
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0 && d1 >= 0 && d3 <= 0) {
    const double den = d1 - d3;
    return add_scaled(a, den != 0 ? d1 / den : 0.0, ab);
  }
  const Vec3 cp = sub(p, c);
  const double d5 = dot(ab, cp), d6 = dot(ac, cp);
  if (d6 >= 0 && d5 <= d6) return c;
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0 && d2 >= 0 && d6 <= 0) {
    const double den = d2 - d6;
    return add_scaled(a, den != 0 ? d2 / den : 0.0, ac);
  }
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0) {
    const double den = (d4 - d3) + (d5 - d6);
    return add_scaled(b, den != 0 ? (d4 - d3) / den : 0.0, sub(c, b));
  }
  const double den = va + vb + vc;
  const double v = den != 0 ? vb / den : 0.0, w = den != 0 ? vc / den : 0.0;
  return {a.x + v * ab.x + w * ac.x, a.y + v * ab.y + w * ac.y, a.z + v * ab.z + w * ac.z};
}

// A bounding volume hierarchy over triangles: median split on the longest axis of the centroids,
// leaves of at most kLeafSize triangles. Node n's children are left[n] and left[n] + 1.
struct Bvh {
  static constexpr int64_t kLeafSize = 4;
  std::vector<double> box;        // (nodes, 6): lo xyz, hi xyz
  std::vector<int64_t> left;      // first child, or -1 for a leaf
  std::vector<int64_t> begin, end;  // leaf's range in `order`
  std::vector<int64_t> order;     // triangle ids, grouped by leaf
};

Bvh make_bvh(const Mesh& mesh) {
  Bvh bvh;
  const int64_t n = mesh.n_faces;
  std::vector<double> tri_lo(3 * n), tri_hi(3 * n), centre(3 * n);
  for (int64_t t = 0; t < n; ++t) {
    const Vec3 v[3] = {mesh.vertex(t, 0), mesh.vertex(t, 1), mesh.vertex(t, 2)};
    for (int a = 0; a < 3; ++a) {
      const double c0 = a == 0 ? v[0].x : a == 1 ? v[0].y : v[0].z;
      const double c1 = a == 0 ? v[1].x : a == 1 ? v[1].y : v[1].z;
      const double c2 = a == 0 ? v[2].x : a == 1 ? v[2].y : v[2].z;
      tri_lo[3 * t + a] = std::min({c0, c1, c2});
      tri_hi[3 * t + a] = std::max({c0, c1, c2});
      centre[3 * t + a] = 0.5 * (tri_lo[3 * t + a] + tri_hi[3 * t + a]);
    }
  }
  bvh.order.resize(n);
  for (int64_t t = 0; t < n; ++t) bvh.order[t] = t;
  struct Task {
    int64_t node, begin, end;
  };
  auto new_node = [&]() {
    bvh.box.insert(bvh.box.end(), 6, 0.0);
    bvh.left.push_back(-1);
    bvh.begin.push_back(0);
    bvh.end.push_back(0);
    return static_cast<int64_t>(bvh.left.size()) - 1;
  };
  std::vector<Task> tasks{{new_node(), 0, n}};
  while (!tasks.empty()) {
    const Task task = tasks.back();
    tasks.pop_back();
    double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    double c_lo[3] = {INFINITY, INFINITY, INFINITY}, c_hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    for (int64_t k = task.begin; k < task.end; ++k) {
      const int64_t t = bvh.order[k];
      for (int a = 0; a < 3; ++a) {
        lo[a] = std::min(lo[a], tri_lo[3 * t + a]), hi[a] = std::max(hi[a], tri_hi[3 * t + a]);
        c_lo[a] = std::min(c_lo[a], centre[3 * t + a]), c_hi[a] = std::max(c_hi[a], centre[3 * t + a]);
      }
    }
    for (int a = 0; a < 3; ++a) bvh.box[6 * task.node + a] = lo[a], bvh.box[6 * task.node + 3 + a] = hi[a];
    const int axis = (c_hi[0] - c_lo[0] >= c_hi[1] - c_lo[1])
                         ? (c_hi[0] - c_lo[0] >= c_hi[2] - c_lo[2] ? 0 : 2)
                         : (c_hi[1] - c_lo[1] >= c_hi[2] - c_lo[2] ? 1 : 2);
    if (task.end - task.begin <= Bvh::kLeafSize || c_hi[axis] == c_lo[axis]) {
      bvh.begin[task.node] = task.begin, bvh.end[task.node] = task.end;
      continue;
    }
    const int64_t mid = task.begin + (task.end - task.begin) / 2;
    std::nth_element(bvh.order.begin() + task.begin, bvh.order.begin() + mid, bvh.order.begin() + task.end,
                     [&](int64_t s, int64_t t) { return centre[3 * s + axis] < centre[3 * t + axis]; });
    const int64_t first = new_node();
    new_node();
    bvh.left[task.node] = first;
    tasks.push_back({first, task.begin, mid});
    tasks.push_back({first + 1, mid, task.end});
  }
  return bvh;
}

// Squared distance from p to node n's box (0 inside).
inline double box_distance2(const Bvh& bvh, int64_t n, const double* p) {
  double d2 = 0;
  for (int a = 0; a < 3; ++a) {
    const double below = bvh.box[6 * n + a] - p[a], above = p[a] - bvh.box[6 * n + 3 + a];
    const double gap = std::max({below, above, 0.0});
    d2 += gap * gap;
  }
  return d2;
}

py::tuple closest(const Doubles& vertices, const Indices& faces, const Doubles& points) {
  const Mesh mesh = make_mesh(vertices, faces);
  if (mesh.n_faces == 0) throw std::invalid_argument("meshquery.closest: the mesh has no faces");
  auto pi = points.request();
  check_rows(pi, 3, "points");
  const double* p = static_cast<const double*>(pi.ptr);
  const int64_t n_points = pi.shape[0];
  py::array_t<double> closest_out({n_points, static_cast<int64_t>(3)});
  py::array_t<double> distance_out(n_points);
  py::array_t<int64_t> face_out(n_points);
  double* q_out = closest_out.mutable_data();
  double* d_out = distance_out.mutable_data();
  int64_t* f_out = face_out.mutable_data();
  {
    py::gil_scoped_release release;
    const Bvh bvh = make_bvh(mesh);
#pragma omp parallel for schedule(dynamic, 64)
    for (int64_t i = 0; i < n_points; ++i) {
      const double* xs = p + 3 * i;
      const Vec3 x{xs[0], xs[1], xs[2]};
      double best = INFINITY;
      int64_t best_face = -1;
      Vec3 best_q{0, 0, 0};
      std::vector<int64_t> stack{0};
      stack.reserve(64);
      while (!stack.empty()) {
        const int64_t node = stack.back();
        stack.pop_back();
        // Not pruned at equality: a face exactly as far as the best may still win on its index.
        if (box_distance2(bvh, node, xs) > best * best) continue;
        if (bvh.left[node] < 0) {
          for (int64_t k = bvh.begin[node]; k < bvh.end[node]; ++k) {
            const int64_t t = bvh.order[k];
            const Vec3 q = closest_on_triangle(x, mesh.vertex(t, 0), mesh.vertex(t, 1), mesh.vertex(t, 2));
            const Vec3 d = sub(q, x);
            const double dist = std::sqrt(dot(d, d));
            if (dist < best || (dist == best && t < best_face)) best = dist, best_face = t, best_q = q;
          }
          continue;
        }
        // Nearer child last, so it is searched first and tightens the bound for the other.
        const int64_t a = bvh.left[node], b = a + 1;
        const double da = box_distance2(bvh, a, xs), db = box_distance2(bvh, b, xs);
        if (da <= db) {
          stack.push_back(b), stack.push_back(a);
        } else {
          stack.push_back(a), stack.push_back(b);
        }
      }
      q_out[3 * i] = best_q.x, q_out[3 * i + 1] = best_q.y, q_out[3 * i + 2] = best_q.z;
      d_out[i] = best;
      f_out[i] = best_face;
    }
  }
  return py::make_tuple(closest_out, distance_out, face_out);
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("inside", &inside, "ray-parity inside test (P,) bool of points (P, 3) in a closed mesh", py::arg("vertices"),
        py::arg("faces"), py::arg("points"));
  m.def("closest", &closest, "closest point (P, 3), distance (P,) and face (P,) on a mesh", py::arg("vertices"),
        py::arg("faces"), py::arg("points"));
}
