"""The C++ mesh-query kernel (igavatar/kernels/csrc/meshquery.cpp) against its references.

The inside test must agree with trimesh's embree ray parity on closed meshes (and with the analytic
answer where a point's column runs exactly through projected edges and vertices); the closest point
must equal the numpy reference `closest_points_on_mesh_reference` to float64 rounding, with the
same tie rule (lower face index) and zero-area faces ignored.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from igavatar.kernels import set_kernels_enabled
from igavatar.metrics.geometry import (
    closest_point_on_triangles,
    closest_points_on_mesh,
    closest_points_on_mesh_reference,
    contains_points,
    volumetric_iou,
)
from tests.conftest import built_kernel

# Every test here runs with the kernels forced on (whatever IGAVATAR_KERNELS says).
pytestmark = pytest.mark.usefixtures("kernels_on")


@pytest.fixture(scope="module")
def kernel():
    return built_kernel("meshquery")


def _closed_meshes() -> dict[str, trimesh.Trimesh]:
    """A convex sphere, a torus (a hole: columns cross it 0, 2 or 4 times) and a rotated box."""
    box = trimesh.creation.box(extents=(0.6, 0.3, 0.9))
    box.apply_transform(trimesh.transformations.rotation_matrix(0.4, (1, 2, 3)))
    return {
        "sphere": trimesh.creation.icosphere(subdivisions=3, radius=0.5),
        "torus": trimesh.creation.torus(major_radius=0.5, minor_radius=0.2, major_sections=48, minor_sections=24),
        "box": box,
    }


@pytest.mark.parametrize("name", ["sphere", "torus", "box"])
def test_inside_equals_embree_parity_off_the_surface(kernel, name):
    mesh = _closed_meshes()[name]
    assert mesh.is_watertight
    rng = np.random.default_rng(0)
    points = mesh.bounds[0] - 0.1 + rng.random((20_000, 3)) * (mesh.extents + 0.2)
    inside = kernel.inside(mesh.vertices, mesh.faces, points)
    assert inside.dtype == bool and inside.shape == (len(points),)
    # Points within 1e-9 of the surface have no defined answer; none are expected at random.
    _, distance, _ = closest_points_on_mesh_reference(points, mesh.vertices, mesh.faces)
    off_surface = distance > 1e-9
    assert off_surface.all()
    np.testing.assert_array_equal(inside, mesh.contains(points))
    assert 0.05 < inside.mean() < 0.95  # both answers occur


def test_inside_is_exact_where_columns_hit_edges_and_vertices(kernel):
    # An axis-aligned unit cube: its top and bottom faces are split by diagonals, so a column at
    # x == y (or through a corner) runs exactly through projected edges and vertices of 4 triangles.
    cube = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    t = np.linspace(-0.45, 0.45, 19)
    columns = np.concatenate([np.stack([t, t], 1), np.stack([t, -t], 1), [[0.0, 0.0]]])
    heights = np.array([-0.7, -0.25, 0.0, 0.3, 0.8])
    points = np.array([[x, y, z] for x, y in columns for z in heights])
    expected = np.abs(points[:, 2]) < 0.5
    np.testing.assert_array_equal(kernel.inside(cube.vertices, cube.faces, points), expected)
    # Columns on the cube's own vertical edges' x (the side faces project to lines) stay outside.
    side = np.array([[0.5, 0.1, 0.0], [-0.5, -0.5, 0.0], [0.7, 0.0, 0.0]])
    assert not kernel.inside(cube.vertices, cube.faces, side + [[1e-9, 0, 0], [-1e-9, 0, 0], [0, 0, 0]]).any()


def test_closest_equals_numpy_reference(kernel):
    rng = np.random.default_rng(1)
    mesh = _closed_meshes()["torus"]
    # Near the surface, deep inside the hole, and far away (a long way through the hierarchy).
    points = np.vstack([
        mesh.sample(2000, seed=1) + rng.normal(scale=0.02, size=(2000, 3)),
        rng.normal(scale=0.1, size=(300, 3)),
        rng.normal(scale=20.0, size=(300, 3)),
    ])
    closest, distance, face = kernel.closest(mesh.vertices, mesh.faces, points)
    ref_closest, ref_distance, ref_face = closest_points_on_mesh_reference(points, mesh.vertices, mesh.faces)
    np.testing.assert_allclose(distance, ref_distance, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(closest - points, axis=1), distance, rtol=1e-12, atol=1e-15)
    # A different face only where both are equally close (a shared edge or vertex, to rounding).
    tri = mesh.vertices[mesh.faces[face]]
    own = np.linalg.norm(closest_point_on_triangles(points, tri[:, 0], tri[:, 1], tri[:, 2]) - points, axis=1)
    np.testing.assert_allclose(own, ref_distance, rtol=1e-12, atol=1e-15)
    assert np.mean(face == ref_face) > 0.95
    np.testing.assert_allclose(closest[face == ref_face], ref_closest[face == ref_face], atol=1e-12)


def test_closest_ties_go_to_the_lower_face_and_zero_area_faces_are_ignored(kernel):
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 2, 2]])
    # Face 3 is face 1 again (an exact tie), face 0 is a zero-area sliver, face 2 is far away.
    faces = np.array([[0, 1, 1], [0, 1, 2], [3, 3, 3], [0, 1, 2]])
    points = np.array([[0.2, 0.2, 0.5], [0.2, 0.2, -0.5]])
    for path in (closest_points_on_mesh, closest_points_on_mesh_reference):
        _, distance, face = path(points, vertices, faces)
        np.testing.assert_allclose(distance, [0.5, 0.5])
        np.testing.assert_array_equal(face, [1, 1])


def test_fast_paths_dispatch_and_keep_the_reference(kernel):
    mesh = _closed_meshes()["sphere"]
    rng = np.random.default_rng(2)
    points = rng.uniform(-0.6, 0.6, size=(3000, 3))
    fast = closest_points_on_mesh(points, mesh.vertices, mesh.faces)
    inside_fast = contains_points(mesh, points, watertight=True)
    set_kernels_enabled(False)
    reference = closest_points_on_mesh(points, mesh.vertices, mesh.faces)
    inside_reference = contains_points(mesh, points, watertight=True)
    set_kernels_enabled(True)
    np.testing.assert_allclose(fast[1], reference[1], rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(inside_fast, inside_reference)


def test_volumetric_iou_counts_are_the_same_on_both_paths(kernel):
    meshes = _closed_meshes()
    fast = volumetric_iou(meshes["torus"], meshes["sphere"], n_points=50_000, seed=4)
    set_kernels_enabled(False)
    reference = volumetric_iou(meshes["torus"], meshes["sphere"], n_points=50_000, seed=4)
    set_kernels_enabled(True)
    for key in ("n_inside_pred", "n_inside_gt", "n_intersection", "n_union", "iou"):
        assert fast[key] == reference[key], key


def test_bad_arrays_raise_a_clear_error(kernel):
    vertices = np.zeros((3, 3))
    with pytest.raises(ValueError, match="faces must be"):
        kernel.inside(vertices, np.zeros((2, 4), np.int64), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="face index out of range"):
        kernel.closest(vertices, np.array([[0, 1, 5]]), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="points must be"):
        kernel.closest(vertices, np.array([[0, 1, 2]]), np.zeros((4,)))
