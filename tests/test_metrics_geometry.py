"""Geometry metrics against closed forms (spheres, cubes) and brute-force references.

    .venv/bin/python -m pytest tests/test_metrics_geometry.py -q
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from igavatar.errors import InputError
from igavatar.metrics.geometry import (
    GeometryMetrics,
    MeshInputError,
    NotWatertightError,
    chamfer_l2_vertices_cm2,
    closest_point_on_triangles,
    closest_points_on_mesh,
    closest_points_on_mesh_reference,
    evaluate_meshes,
    evenly_spaced_vertices,
    keep_largest_component,
    normal_consistency_vertices,
    sample_surface_uniform,
    surface_metrics,
    volumetric_iou,
)


def icosphere(radius: float, subdivisions: int = 3, center=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    mesh.apply_translation(center)
    return mesh


def unit_cube(offset_x: float = 0.0) -> trimesh.Trimesh:
    cube = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    cube.apply_translation((0.5 + offset_x, 0.5, 0.5))
    return cube


def random_mesh(rng: np.random.Generator, n_vertices: int, n_faces: int, scale: float = 1.0):
    vertices = rng.normal(size=(n_vertices, 3)) * scale
    faces = np.stack([rng.choice(n_vertices, 3, replace=False) for _ in range(n_faces)])
    return vertices, faces


# --------------------------------------------------------------------------- reference (test-only)


def point_triangle_distance_reference(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
    """Independent algorithm: plane projection if inside (barycentric), else nearest of 3 segments."""
    n = np.cross(b - a, c - a)
    n = n / np.linalg.norm(n)
    q = p - np.dot(p - a, n) * n
    # Barycentric coordinates of q by solving the 2x2 normal equations.
    e0, e1, e2 = b - a, c - a, q - a
    gram = np.array([[e0 @ e0, e0 @ e1], [e0 @ e1, e1 @ e1]])
    v, w = np.linalg.solve(gram, np.array([e2 @ e0, e2 @ e1]))
    if v >= 0 and w >= 0 and v + w <= 1:
        return float(np.linalg.norm(p - q))

    def seg(u, s):
        t = np.clip(np.dot(p - u, s - u) / np.dot(s - u, s - u), 0, 1)
        return np.linalg.norm(p - (u + t * (s - u)))

    return float(min(seg(a, b), seg(b, c), seg(c, a)))


# --------------------------------------------------------------------------- pre-filter


def test_keep_largest_component_drops_small_pieces_and_reindexes():
    big = icosphere(0.5, 2)
    small = icosphere(0.1, 1, center=(2.0, 0, 0))
    tri = trimesh.Trimesh([[5, 0, 0], [5, 1, 0], [5, 0, 1]], [[0, 1, 2]])
    soup = trimesh.util.concatenate([small, big, tri])  # the big one is not first
    vertices, faces, n_dropped = keep_largest_component(soup.vertices, soup.faces)
    assert n_dropped == 2
    assert len(faces) == len(big.faces) and len(vertices) == len(big.vertices)
    assert faces.min() == 0 and faces.max() == len(vertices) - 1
    np.testing.assert_allclose(np.sort(vertices, axis=0), np.sort(big.vertices, axis=0))
    # Faces keep their geometry (same triangles, same winding).
    np.testing.assert_allclose(vertices[faces], big.vertices[big.faces])


def test_keep_largest_component_welds_duplicate_positions():
    # An unwelded soup (every face has its own 3 vertices) is still one connected piece.
    sphere = icosphere(0.3, 1)
    soup_v = sphere.vertices[sphere.faces].reshape(-1, 3)
    soup_f = np.arange(len(soup_v)).reshape(-1, 3)
    vertices, faces, n_dropped = keep_largest_component(soup_v, soup_f)
    assert n_dropped == 0 and len(faces) == len(sphere.faces)


# --------------------------------------------------------------------------- paper protocol


def test_vertex_chamfer_concentric_spheres_closed_form():
    r1, r2 = 0.50, 0.53  # meters; same subdivision -> vertices radially aligned
    inner, outer = icosphere(r1, 3), icosphere(r2, 3)
    result = chamfer_l2_vertices_cm2(inner.vertices, outer.vertices)
    expected_cm2 = ((r2 - r1) * 100) ** 2  # 9 cm^2: the nearest vertex is the radial partner
    assert result["chamfer_l2_cm2"] == pytest.approx(expected_cm2, rel=1e-9)
    assert result["pred_to_gt_cm2"] == pytest.approx(expected_cm2, rel=1e-9)
    assert result["gt_to_pred_cm2"] == pytest.approx(expected_cm2, rel=1e-9)


def test_vertex_chamfer_matches_bruteforce_and_is_averaged_not_summed():
    rng = np.random.default_rng(3)
    pred = rng.normal(size=(300, 3)) * 0.3
    gt = rng.normal(size=(200, 3)) * 0.3 + 0.05
    d2 = ((pred[:, None] - gt[None]) ** 2).sum(-1) * 1e4  # brute force, cm^2
    p2g, g2p = d2.min(axis=1).mean(), d2.min(axis=0).mean()
    result = chamfer_l2_vertices_cm2(pred, gt)
    assert result["pred_to_gt_cm2"] == pytest.approx(p2g, rel=1e-10)
    assert result["gt_to_pred_cm2"] == pytest.approx(g2p, rel=1e-10)
    assert result["chamfer_l2_cm2"] == pytest.approx((p2g + g2p) / 2, rel=1e-10)


def test_vertex_normal_consistency_identical_flipped_noisy():
    sphere = icosphere(0.5, 3)
    v, n = sphere.vertices, sphere.vertex_normals
    assert normal_consistency_vertices(v, n, v, n) == pytest.approx(1.0, abs=1e-12)
    # Flipped prediction normals: |(-n) - n| = 2 everywhere -> 1 - 2 = -1 (orientation-sensitive).
    assert normal_consistency_vertices(v, -n, v, n) == pytest.approx(-1.0, abs=1e-12)
    noisy = n + np.random.default_rng(0).normal(scale=0.3, size=n.shape)
    nc_noisy = normal_consistency_vertices(v, noisy, v, n)
    assert 0.0 < nc_noisy < 0.9
    # Unnormalized input normals are normalized first: scaling changes nothing.
    assert normal_consistency_vertices(v, 7.0 * n, v, 0.2 * n) == pytest.approx(1.0, abs=1e-12)


# --------------------------------------------------------------------------- point-to-face


def test_closest_point_on_triangles_matches_two_references():
    rng = np.random.default_rng(1)
    n = 400
    a, b, c = (rng.normal(size=(n, 3)) for _ in range(3))
    p = rng.normal(size=(n, 3)) * 1.5
    q = closest_point_on_triangles(p, a, b, c)
    ours = np.linalg.norm(q - p, axis=1)
    reference = np.array([point_triangle_distance_reference(p[i], a[i], b[i], c[i]) for i in range(n)])
    np.testing.assert_allclose(ours, reference, rtol=1e-9, atol=1e-12)
    q_trimesh = trimesh.triangles.closest_point(np.stack([a, b, c], axis=1), p)
    np.testing.assert_allclose(q, q_trimesh, atol=1e-9)


def test_closest_point_on_degenerate_triangle_uses_edges():
    a = np.array([[0.0, 0, 0]])
    b = np.array([[1.0, 0, 0]])
    c = np.array([[2.0, 0, 0]])  # collinear: a segment from 0 to 2 on x
    p = np.array([[1.5, 1.0, 0.0]])
    np.testing.assert_allclose(closest_point_on_triangles(p, a, b, c), [[1.5, 0, 0]], atol=1e-12)


@pytest.mark.parametrize("closest_points", [closest_points_on_mesh, closest_points_on_mesh_reference])
def test_closest_points_on_mesh_matches_bruteforce(closest_points):
    rng = np.random.default_rng(2)
    vertices, faces = random_mesh(rng, 60, 120, scale=0.5)
    # A huge triangle exercises the "big faces" path; points far away exercise large search balls.
    vertices = np.vstack([vertices, [[-5, -5, 0.2], [5, -5, 0.2], [0, 6, 0.2]]])
    faces = np.vstack([faces, [[60, 61, 62]]])
    points = np.vstack([rng.normal(size=(150, 3)) * 0.6, rng.normal(size=(30, 3)) * 4.0])
    _, distance, face_index = closest_points(points, vertices, faces, max_pairs=500)
    brute = np.array([
        [point_triangle_distance_reference(p, *vertices[f]) for f in faces] for p in points
    ])
    np.testing.assert_allclose(distance, brute.min(axis=1), rtol=1e-9, atol=1e-12)
    # The reported face is one that achieves the minimum.
    np.testing.assert_allclose(brute[np.arange(len(points)), face_index], distance, rtol=1e-9, atol=1e-12)


def test_point_to_face_not_point_to_vertex():
    # A point 1 cm above the center of a 1 m triangle: face distance 1 cm, vertex distance ~0.58 m.
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0.5, np.sqrt(3) / 2, 0]])
    point = np.array([[0.5, np.sqrt(3) / 6, 0.01]])
    _, distance, face_index = closest_points_on_mesh(point, vertices, np.array([[0, 1, 2]]))
    assert distance[0] == pytest.approx(0.01) and face_index[0] == 0


def test_sample_surface_is_area_uniform_and_on_faces():
    # Two faces, areas 1:3 -> 25% / 75% of samples.
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 2, 0], [5, 0, 0], [8, 0, 0], [5, 2, 0]], float)
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    points, face_index = sample_surface_uniform(vertices, faces, 20000, np.random.default_rng(0))
    assert np.mean(face_index == 0) == pytest.approx(0.25, abs=0.015)
    _, distance, _ = closest_points_on_mesh(points, vertices, faces)
    assert distance.max() < 1e-12
    # Uniform within a face: the mean is the centroid.
    np.testing.assert_allclose(points[face_index == 1].mean(0), vertices[3:].mean(0), atol=0.03)


# --------------------------------------------------------------------------- surface protocol


def test_surface_protocol_concentric_spheres_closed_form():
    r1, r2 = 0.50, 0.52
    inner, outer = icosphere(r1, 4), icosphere(r2, 4)
    result = surface_metrics(inner.vertices, inner.faces, outer.vertices, outer.faces, n_points=2000, seed=0)
    # Aligned facets are parallel at (r2 - r1) * cos(facet angle); cos > 0.999 at 4 subdivisions.
    assert result["chamfer_l1_mm"] == pytest.approx((r2 - r1) * 1000, rel=2e-3)
    assert result["pred_to_gt_mm"] == pytest.approx(20.0, rel=2e-3)
    assert result["gt_to_pred_mm"] == pytest.approx(20.0, rel=2e-3)
    assert result["normal_consistency"] > 0.999


def test_surface_protocol_identical_and_noisy_meshes():
    sphere = icosphere(0.5, 3)
    same = surface_metrics(sphere.vertices, sphere.faces, sphere.vertices, sphere.faces, n_points=1000)
    assert same["chamfer_l1_mm"] < 1e-9
    assert same["normal_consistency"] == pytest.approx(1.0, abs=1e-9)
    # Flipping every face's winding leaves |cos| (and distances) unchanged: orientation-blind.
    flipped = surface_metrics(sphere.vertices, sphere.faces[:, ::-1], sphere.vertices, sphere.faces, n_points=1000)
    assert flipped["normal_consistency"] == pytest.approx(1.0, abs=1e-9)
    rng = np.random.default_rng(0)
    noisy_v = sphere.vertices + rng.normal(scale=0.01, size=sphere.vertices.shape)
    noisy = surface_metrics(noisy_v, sphere.faces, sphere.vertices, sphere.faces, n_points=1000)
    assert noisy["normal_consistency"] < 0.97
    assert noisy["chamfer_l1_mm"] > 1.0


def test_surface_protocol_matches_bruteforce_on_small_meshes():
    rng = np.random.default_rng(5)
    pred_v, pred_f = random_mesh(rng, 30, 40, scale=0.3)
    gt_v, gt_f = random_mesh(rng, 25, 35, scale=0.3)
    n, seed = 200, 7
    result = surface_metrics(pred_v, pred_f, gt_v, gt_f, n_points=n, seed=seed)
    pred_x, _ = sample_surface_uniform(pred_v, pred_f, n, np.random.default_rng([seed, 0]))
    gt_x, _ = sample_surface_uniform(gt_v, gt_f, n, np.random.default_rng([seed, 1]))
    p2g = np.mean([min(point_triangle_distance_reference(p, *gt_v[f]) for f in gt_f) for p in pred_x])
    g2p = np.mean([min(point_triangle_distance_reference(p, *pred_v[f]) for f in pred_f) for p in gt_x])
    assert result["pred_to_gt_mm"] == pytest.approx(p2g * 1000, rel=1e-9)
    assert result["gt_to_pred_mm"] == pytest.approx(g2p * 1000, rel=1e-9)
    assert result["chamfer_l1_mm"] == pytest.approx((p2g + g2p) * 500, rel=1e-9)


def test_surface_protocol_is_seeded():
    sphere, other = icosphere(0.5, 2), icosphere(0.55, 2)
    a = surface_metrics(sphere.vertices, sphere.faces, other.vertices, other.faces, n_points=300, seed=4)
    b = surface_metrics(sphere.vertices, sphere.faces, other.vertices, other.faces, n_points=300, seed=4)
    assert a == b


# --------------------------------------------------------------------------- volumetric IoU


@pytest.mark.parametrize("d", [0.25, 0.6])
def test_iou_offset_unit_cubes_closed_form(d):
    n = 200_000
    result = volumetric_iou(unit_cube(0.0), unit_cube(d), n_points=n, seed=1)
    expected = (1 - d) / (1 + d)
    # The union fills the union box, so the estimate is binomial: 5 standard errors.
    tolerance = 5 * np.sqrt(expected * (1 - expected) / n)
    assert result["iou"] == pytest.approx(expected, abs=tolerance)
    assert result["n_union"] == n  # every point of the union box lies in one cube or the other


def test_iou_identical_and_nested_spheres():
    sphere = icosphere(0.5, 3)
    assert volumetric_iou(sphere, sphere, n_points=100_000)["iou"] == 1.0
    inner = icosphere(0.4, 3)
    result = volumetric_iou(inner, sphere, n_points=200_000, seed=3)
    expected = inner.volume / sphere.volume  # nested: intersection = inner, union = outer
    fraction_in_union = sphere.volume / np.prod(sphere.extents)
    tolerance = 5 * np.sqrt(expected * (1 - expected) / (200_000 * fraction_in_union))
    assert result["iou"] == pytest.approx(expected, abs=tolerance)


def test_iou_rejects_open_mesh_naming_it():
    sphere = icosphere(0.5, 2)
    open_mesh = trimesh.Trimesh(sphere.vertices, sphere.faces[:-3], process=False)
    with pytest.raises(NotWatertightError, match="gt mesh is not watertight") as info:
        volumetric_iou(sphere, open_mesh, n_points=1000)
    assert isinstance(info.value, ValueError) and isinstance(info.value, InputError)
    loose = volumetric_iou(sphere, open_mesh, n_points=1000, require_watertight=False)
    assert loose["gt_watertight"] is False and loose["pred_watertight"] is True


def test_iou_accepts_unwelded_soup():
    cube = unit_cube()
    soup = (cube.vertices[cube.faces].reshape(-1, 3), np.arange(len(cube.faces) * 3).reshape(-1, 3))
    assert volumetric_iou(soup, cube, n_points=20_000)["iou"] == 1.0


def test_iou_keeps_a_closed_indexed_mesh_unwelded_when_two_vertices_nearly_meet():
    """A posed prediction can bring two distinct vertices within trimesh's 1e-8 merge tolerance
    (a crease compressed by a deep pose); welding them made its edges non-manifold and the frame
    lost its IoU. An indexed mesh that is closed as given is taken as given."""
    sphere = icosphere(0.5, 3)
    vertices = np.asarray(sphere.vertices, np.float64).copy()
    a = int(sphere.faces[0, 0])
    b = int(sphere.faces[0, 1])  # an edge neighbour of a
    vertices[b] = vertices[a]  # float32 posing can land them on the very same position
    welded = trimesh.Trimesh(vertices, sphere.faces, process=True)
    assert len(welded.vertices) == len(vertices) - 1 and not welded.is_watertight  # what welding did
    result = volumetric_iou((vertices, sphere.faces), sphere, n_points=20_000)
    assert result["pred_watertight"] is True and result["iou"] > 0.98


# --------------------------------------------------------------------------- bundle and validation


def test_evaluate_meshes_prefilters_and_bundles():
    r1, r2 = 0.50, 0.51
    pred = trimesh.util.concatenate([icosphere(r1, 3), icosphere(0.05, 1, center=(2, 0, 0))])
    gt = icosphere(r2, 3)
    # The scan's vertices as given (no even spacing), for the closed form below.
    metrics = evaluate_meshes(pred, gt, n_surface=1000, n_iou=100_000, seed=0, paper_max_edge=None)
    assert isinstance(metrics, GeometryMetrics)
    assert metrics.n_dropped_components == 1
    # With the floater removed, the vertex Chamfer is the closed form of aligned spheres.
    assert metrics.chamfer_l2_vertices_cm2 == pytest.approx(1.0, rel=1e-9)
    assert metrics.normal_consistency_vertices == pytest.approx(1.0, abs=1e-9)
    assert metrics.chamfer_l1_surface_mm == pytest.approx(10.0, rel=5e-3)
    assert metrics.volumetric_iou == pytest.approx(icosphere(r1, 3).volume / gt.volume, abs=0.01)
    report = metrics.to_dict()
    assert report["paper_protocol"]["chamfer_l2_cm2"] == metrics.chamfer_l2_vertices_cm2
    assert "averaged, not summed" in report["paper_protocol"]["description"]
    assert "vertices as given" in report["paper_protocol"]["description"] and report["paper_protocol"]["max_edge_mm"] is None
    assert report["surface_protocol"]["units"]["chamfer_l1"] == "mm"
    assert report["prefilter"]["n_dropped_components"] == 1
    skipped = evaluate_meshes(pred, gt, n_surface=200, n_iou=0)
    assert skipped.volumetric_iou is None and skipped.to_dict()["volumetric_iou"]["iou"] == "not computed"


def _cube_with_one_dense_side(half: float, levels: int) -> trimesh.Trimesh:
    """A cube whose +z side alone is split `levels` times (the same surface, tessellated unevenly)."""
    cube = trimesh.creation.box(extents=(2 * half,) * 3)
    top = np.flatnonzero(cube.triangles_center[:, 2] > half - 1e-9)
    vertices, faces = cube.vertices, cube.faces
    for _ in range(levels):
        vertices, faces = trimesh.remesh.subdivide(vertices, faces, face_index=top)
        top = np.flatnonzero(trimesh.Trimesh(vertices, faces, process=False).triangles_center[:, 2] > half - 1e-9)
    return trimesh.Trimesh(vertices, faces)


def test_evenly_spaced_vertices_split_long_edges_only_and_keep_the_surface():
    dense = icosphere(0.05, 4)  # edges ~4 mm
    v, f, n = evenly_spaced_vertices(dense.vertices, dense.faces, 0.01)
    assert np.array_equal(v, dense.vertices) and np.array_equal(f, dense.faces)
    np.testing.assert_allclose(n, dense.vertex_normals)
    cube = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    v, f, n = evenly_spaced_vertices(cube.vertices, cube.faces, 0.01)
    even = trimesh.Trimesh(v, f, process=False)
    edges = np.linalg.norm(v[even.edges_unique[:, 0]] - v[even.edges_unique[:, 1]], axis=1)
    assert edges.max() <= 0.01 and even.is_watertight
    assert even.area == pytest.approx(cube.area, rel=1e-9)  # midpoint splits do not move the surface
    assert np.allclose(np.abs(v).max(axis=1), 0.05)  # every new vertex lies on a side of the cube
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0)


def test_paper_protocol_does_not_depend_on_how_the_scan_is_tessellated():
    """The same cube as scan, tessellated evenly or with one side 256 times denser: the vertex
    protocol on the scan as given measures mostly that side; on evenly spaced vertices it does not."""
    pred = icosphere(0.12, 4)
    plain, uneven = _cube_with_one_dense_side(0.1, 0), _cube_with_one_dense_side(0.1, 4)
    assert len(uneven.vertices) > 20 * len(plain.vertices)
    raw = [evaluate_meshes(pred, scan, n_surface=2000, n_iou=0, paper_max_edge=None) for scan in (plain, uneven)]
    even = [evaluate_meshes(pred, scan, n_surface=2000, n_iou=0) for scan in (plain, uneven)]
    assert abs(raw[0].normal_consistency_vertices - raw[1].normal_consistency_vertices) > 0.5
    # What is left is the uneven side's seam, where vertex normals average differently.
    assert abs(even[0].normal_consistency_vertices - even[1].normal_consistency_vertices) < 0.02
    assert abs(even[0].chamfer_l2_vertices_cm2 - even[1].chamfer_l2_vertices_cm2) < 0.05 * even[0].chamfer_l2_vertices_cm2  # 2.45 against 2.53 (the raw: 56.5 against 30.1)
    assert even[0].paper_max_edge_mm == pytest.approx(10.0)
    # A prediction equal to its scan is perfect on evenly spaced vertices too.
    same = evaluate_meshes(plain, plain, n_surface=500, n_iou=0)
    assert same.chamfer_l2_vertices_cm2 == 0.0 and same.normal_consistency_vertices == pytest.approx(1.0)
    assert "split at their midpoints" in even[0].to_dict()["paper_protocol"]["description"]
    # The surface protocol samples by area, so it never depended on the tessellation.
    assert even[1].chamfer_l1_surface_mm == pytest.approx(raw[1].chamfer_l1_surface_mm)


def test_bad_inputs_name_the_problem():
    with pytest.raises(MeshInputError, match=r"pred_vertices: shape \(4, 2\)"):
        chamfer_l2_vertices_cm2(np.zeros((4, 2)), np.zeros((4, 3)))
    with pytest.raises(MeshInputError, match="indices span"):
        keep_largest_component(np.zeros((3, 3)), np.array([[0, 1, 3]]))
    with pytest.raises(MeshInputError, match="NaN"):
        chamfer_l2_vertices_cm2(np.full((2, 3), np.nan), np.zeros((2, 3)))
