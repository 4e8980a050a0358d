"""Marching cubes of analytic SDFs (sphere, torus, two spheres) and pymeshlab cleanup.

    .venv/bin/python -m pytest tests/test_mesh_extract.py -q
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.spatial
import skimage.measure
import torch
import trimesh

from igavatar.errors import InputError
from igavatar.mesh.cleanup import clean_mesh, connected_components, is_watertight, vertex_normals
from igavatar.geometry.extract import extract_mesh

BOX_MIN = np.array([-1.0, -1.0, -1.0])
BOX_MAX = np.array([1.0, 1.0, 1.0])
CENTER = torch.tensor([0.11, -0.07, 0.03])
RADIUS = 0.5


def sphere_sdf(x: torch.Tensor, center: torch.Tensor = CENTER, radius: float = RADIUS) -> torch.Tensor:
    return (x - center.to(x)).norm(dim=-1) - radius


def torus_sdf(x: torch.Tensor) -> torch.Tensor:
    """Torus around z, major radius 0.5, minor 0.18, centerd off the grid lines."""
    p = x - torch.tensor([0.03, -0.02, 0.05])
    ring = torch.stack((p[:, :2].norm(dim=-1) - 0.5, p[:, 2]), dim=-1)
    return ring.norm(dim=-1) - 0.18


def two_spheres_sdf(x: torch.Tensor) -> torch.Tensor:
    big = sphere_sdf(x, torch.tensor([-0.45, 0.0, 0.0]), 0.4)
    small = sphere_sdf(x, torch.tensor([0.6, 0.05, 0.0]), 0.2)
    return torch.minimum(big, small)


def voxel_lower_bound(resolution: int, extent: float) -> float:
    """The fine voxel is at least the surface's extent over resolution - 1 (the tight box is larger)."""
    return extent / (resolution - 1)


def test_sphere_radius_watertight_outward_euler():
    resolution = 96
    vertices, faces = extract_mesh(sphere_sdf, BOX_MIN, BOX_MAX, resolution=resolution, coarse_resolution=32)
    assert vertices.dtype == np.float32 and faces.dtype == np.int64
    voxel = voxel_lower_bound(resolution, 2 * RADIUS)
    radius = np.linalg.norm(vertices - CENTER.numpy(), axis=1)
    assert np.abs(radius - RADIUS).mean() < 0.2 * voxel
    assert np.abs(radius - RADIUS).max() < 0.5 * voxel

    assert is_watertight(vertices, faces)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.euler_number == 2
    # Outward winding: positive signed volume close to the ball's, normals along the radius.
    assert mesh.volume == pytest.approx(4.0 / 3.0 * math.pi * RADIUS**3, rel=5e-3)
    real = mesh.area_faces > 1e-4 * voxel**2
    radial = (mesh.face_normals * (mesh.triangles_center - CENTER.numpy()))[real].sum(axis=1)
    assert (radial > 0).all()


def test_torus_has_genus_one():
    vertices, faces = extract_mesh(torus_sdf, BOX_MIN, BOX_MAX, resolution=96, coarse_resolution=32)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    assert is_watertight(vertices, faces)
    assert mesh.euler_number == 0
    assert mesh.volume == pytest.approx(2 * math.pi**2 * 0.5 * 0.18**2, rel=1e-2)


@pytest.mark.parametrize("sdf_fn", [torus_sdf, two_spheres_sdf], ids=["torus", "two_spheres"])
def test_narrow_band_equals_dense_fine_pass(sdf_fn):
    counts = {}
    meshes = {}
    for narrow in (True, False):
        calls = []
        meshes[narrow] = extract_mesh(
            sdf_fn, BOX_MIN, BOX_MAX, resolution=112, coarse_resolution=32, narrow_band=narrow,
            progress=lambda done, total: calls.append((done, total)),
        )
        counts[narrow] = calls[-1][1]
        dones = [d for d, _ in calls]
        assert dones == sorted(dones) and calls[-1][0] == calls[-1][1]
    # Same sign changes on the same grid: bit-identical meshes for a fraction of the evaluations.
    np.testing.assert_array_equal(meshes[True][1], meshes[False][1])
    np.testing.assert_array_equal(meshes[True][0], meshes[False][0])
    assert counts[True] < 0.5 * counts[False]


def test_wide_band_handles_steeper_than_distance_field():
    """An SDF with |grad| = 2 is not a distance; band=2 keeps the narrow band exact."""

    def steep(x: torch.Tensor) -> torch.Tensor:
        return 2.0 * torus_sdf(x)

    narrow = extract_mesh(steep, BOX_MIN, BOX_MAX, resolution=80, coarse_resolution=24, band=2.0)
    dense = extract_mesh(steep, BOX_MIN, BOX_MAX, resolution=80, coarse_resolution=24, narrow_band=False)
    np.testing.assert_array_equal(narrow[1], dense[1])


def test_coarse_to_fine_matches_single_dense_pass_over_box():
    """The two-pass mesh agrees with plain marching cubes over the whole box at the same voxel."""
    vertices, faces = extract_mesh(torus_sdf, BOX_MIN, BOX_MAX, resolution=96, coarse_resolution=32)
    # Same voxel size as the fine pass: its tight box spans the surface plus padding.
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    voxel = float((hi - lo).max()) / 95.0
    n = int(round(2.0 / voxel)) + 1
    axis = torch.linspace(-1.0, 1.0, n)
    grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1).reshape(-1, 3)
    volume = torus_sdf(grid).reshape(n, n, n).numpy()
    step = 2.0 / (n - 1)
    ref_vertices, ref_faces, _, _ = skimage.measure.marching_cubes(volume, 0.0, spacing=(step,) * 3)
    ref_vertices = ref_vertices - 1.0
    # Both lie on the surface to a small fraction of a voxel, and each covers the other (vertex
    # spacing is at most about a voxel).
    for points in (vertices, ref_vertices):
        assert torus_sdf(torch.as_tensor(points, dtype=torch.float32)).abs().max() < 0.05 * step
    distance_to_ref, _ = scipy.spatial.cKDTree(ref_vertices).query(vertices)
    distance_from_ref, _ = scipy.spatial.cKDTree(vertices).query(ref_vertices)
    assert max(distance_to_ref.max(), distance_from_ref.max()) < 1.5 * step
    mesh, ref = trimesh.Trimesh(vertices, faces), trimesh.Trimesh(ref_vertices, ref_faces)
    assert abs(mesh.volume) == pytest.approx(abs(ref.volume), rel=5e-3)
    assert mesh.area == pytest.approx(ref.area, rel=5e-3)


def test_empty_when_no_surface_and_level_shifts_surface():
    vertices, faces = extract_mesh(
        lambda x: sphere_sdf(x) + 10.0, BOX_MIN, BOX_MAX, resolution=32, coarse_resolution=16
    )
    assert vertices.shape == (0, 3) and faces.shape == (0, 3)
    # level = 0.1 is the sphere of radius 0.6.
    vertices, _ = extract_mesh(sphere_sdf, BOX_MIN, BOX_MAX, resolution=64, coarse_resolution=16, level=0.1)
    assert np.abs(np.linalg.norm(vertices - CENTER.numpy(), axis=1) - 0.6).mean() < 0.2 * 1.2 / 63


def test_box_axes_and_sdf_output_shapes():
    """A flat box gives proportional sample counts (cubic voxels); (P, 1) outputs are accepted."""
    box_min, box_max = np.array([-1.0, -1.0, -0.3]), np.array([1.0, 1.0, 0.3])
    calls = []

    def flat_sdf(x: torch.Tensor) -> torch.Tensor:
        calls.append(x.shape)
        return sphere_sdf(x, torch.tensor([0.0, 0.0, 0.0]), 0.2)[:, None]

    vertices, faces = extract_mesh(flat_sdf, box_min, box_max, resolution=48, coarse_resolution=20, chunk_points=1000)
    assert all(s[0] <= 1000 for s in calls)
    assert is_watertight(vertices, faces)
    assert np.abs(np.linalg.norm(vertices, axis=1) - 0.2).max() < 0.5 * 0.4 / 47 * 1.5


def test_bad_inputs_raise_input_error():
    with pytest.raises(InputError, match="box_min"):
        extract_mesh(sphere_sdf, BOX_MAX, BOX_MIN, resolution=16)
    with pytest.raises(InputError, match=r"\(3,\)"):
        extract_mesh(sphere_sdf, np.zeros(2), np.ones(2), resolution=16)
    with pytest.raises(InputError, match="resolution"):
        extract_mesh(sphere_sdf, BOX_MIN, BOX_MAX, resolution=1)
    with pytest.raises(InputError, match="expected a tensor of shape"):
        extract_mesh(lambda x: x, BOX_MIN, BOX_MAX, resolution=16, coarse_resolution=8)
    with pytest.raises(InputError, match="NaN"):
        extract_mesh(lambda x: x[:, 0] / 0.0 * 0.0, BOX_MIN, BOX_MAX, resolution=16, coarse_resolution=8)


def test_tensor_box_and_grad_mode_untouched():
    box_min, box_max = torch.tensor(BOX_MIN, dtype=torch.float32), torch.tensor(BOX_MAX, dtype=torch.float32)
    grad_enabled = []

    def sdf(x):
        grad_enabled.append(torch.is_grad_enabled())
        return sphere_sdf(x)

    vertices, _ = extract_mesh(sdf, box_min, box_max, resolution=32, coarse_resolution=16)
    assert vertices.shape[0] > 0 and not any(grad_enabled) and torch.is_grad_enabled()


# ------------------------------------------------------------------------------------------
# cleanup


@pytest.fixture(scope="module")
def two_spheres_mesh():
    return extract_mesh(two_spheres_sdf, BOX_MIN, BOX_MAX, resolution=96, coarse_resolution=32)


def test_keep_largest_drops_the_small_sphere(two_spheres_mesh):
    vertices, faces = two_spheres_mesh
    labels = connected_components(vertices.shape[0], faces)
    sizes = np.bincount(labels)
    assert sizes.shape == (2,) and sizes[0] > sizes[1]  # label 0 is the largest

    kept_v, kept_f, report = clean_mesh(vertices, faces, keep_largest=True)
    assert report["components"] == 2 and report["components_dropped"] == 1
    assert report["faces_after"] == sizes[0] and report["faces_dropped_in_components"] == sizes[1]
    assert report["faces_before"] == faces.shape[0]
    assert kept_v.dtype == np.float32 and kept_f.dtype == np.int64
    distance = np.linalg.norm(kept_v - np.array([-0.45, 0.0, 0.0]), axis=1)
    assert np.abs(distance - 0.4).max() < 0.01
    assert is_watertight(kept_v, kept_f)

    # Without keep_largest, a ratio threshold decides; the small sphere has ~1/4 of the faces.
    _, both_f, report = clean_mesh(vertices, faces, keep_largest=False, min_component_faces_ratio=0.1)
    assert report["components_dropped"] == 0 and both_f.shape[0] == faces.shape[0]
    _, _, report = clean_mesh(vertices, faces, keep_largest=False, min_component_faces_ratio=0.5)
    assert report["components_dropped"] == 1


def test_taubin_smooths_noise_without_shrinking():
    vertices, faces = extract_mesh(sphere_sdf, BOX_MIN, BOX_MAX, resolution=64, coarse_resolution=24)
    rng = np.random.default_rng(0)
    radial = (vertices - CENTER.numpy()) / np.linalg.norm(vertices - CENTER.numpy(), axis=1, keepdims=True)
    noisy = vertices + (0.01 * rng.standard_normal(vertices.shape[0]))[:, None] * radial
    smooth_v, smooth_f, report = clean_mesh(noisy, faces, taubin_steps=10)
    assert report["taubin_steps"] == 10 and smooth_f.shape == faces.shape
    error_before = np.abs(np.linalg.norm(noisy - CENTER.numpy(), axis=1) - RADIUS)
    radius_after = np.linalg.norm(smooth_v - CENTER.numpy(), axis=1)
    assert np.abs(radius_after - RADIUS).mean() < 0.5 * error_before.mean()
    assert abs(radius_after.mean() - RADIUS) < 0.01 * RADIUS  # Taubin, unlike Laplacian, keeps the size
    assert is_watertight(smooth_v, smooth_f)


def test_decimation_respects_face_budget():
    vertices, faces = extract_mesh(sphere_sdf, BOX_MIN, BOX_MAX, resolution=64, coarse_resolution=24)
    budget = 2000
    small_v, small_f, report = clean_mesh(vertices, faces, target_faces=budget)
    assert report["decimated"] and report["faces_after"] == small_f.shape[0]
    assert 0.9 * budget <= small_f.shape[0] <= budget
    assert is_watertight(small_v, small_f)
    radius = np.linalg.norm(small_v - CENTER.numpy(), axis=1)
    assert np.abs(radius - RADIUS).max() < 0.02 * RADIUS
    # A budget above the face count leaves the mesh alone.
    _, same_f, report = clean_mesh(vertices, faces, target_faces=faces.shape[0] + 10)
    assert not report["decimated"] and same_f.shape[0] == faces.shape[0]


def test_watertight_and_normals_helpers():
    box = trimesh.creation.box()
    assert is_watertight(box.vertices, box.faces)
    assert not is_watertight(box.vertices, box.faces[1:])
    vertices, faces = extract_mesh(sphere_sdf, BOX_MIN, BOX_MAX, resolution=48, coarse_resolution=16)
    normals = vertex_normals(vertices, faces)
    radial = (vertices - CENTER.numpy()) / np.linalg.norm(vertices - CENTER.numpy(), axis=1, keepdims=True)
    assert normals.dtype == np.float32
    assert np.einsum("ij,ij->i", normals, radial).min() > 0.98


def test_cleanup_bad_inputs_and_empty_mesh():
    with pytest.raises(InputError, match="faces index"):
        clean_mesh(np.zeros((3, 3)), np.array([[0, 1, 3]]))
    with pytest.raises(InputError, match=r"\(V, 3\)"):
        clean_mesh(np.zeros((3, 2)), np.array([[0, 1, 2]]))
    v, f, report = clean_mesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    assert v.shape == (0, 3) and f.shape == (0, 3) and report["faces_after"] == 0
