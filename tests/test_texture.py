"""UV atlas (xatlas) and texture baking: an analytic color gradient comes out in the texture.

    .venv/bin/python -m pytest tests/test_texture.py -q
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import trimesh

from igavatar.errors import InputError
from igavatar.artifacts.png import png_bytes
from igavatar.mesh.texture import bake_texture, dilate, obj_uv, rasterize_uv, unwrap

SIZE = 256


def gradient(points: np.ndarray) -> np.ndarray:
    """A known color field: R, G, B linear in x, y, z over the unit sphere's box."""
    return np.clip((np.asarray(points) + 1.0) / 2.0, 0.0, 1.0)


@pytest.fixture(scope="module")
def sphere_bake():
    mesh = trimesh.creation.icosphere(subdivisions=3)
    atlas = unwrap(mesh.vertices, mesh.faces, SIZE)
    vertices = atlas.vertices(mesh.vertices)
    image, covered = bake_texture(vertices, atlas.faces, atlas.uv, gradient, SIZE)
    return mesh, atlas, vertices, image, covered


def test_atlas_keeps_the_faces_and_fits_the_square(sphere_bake):
    mesh, atlas, vertices, _, covered = sphere_bake
    assert atlas.faces.shape == mesh.faces.shape
    # Same triangles, in order: the atlas only splits vertices along seams.
    np.testing.assert_array_equal(atlas.vertex_map[atlas.faces], mesh.faces)
    assert atlas.uv.min() >= 0 and atlas.uv.max() <= 1
    assert 0.3 < covered.mean() < 1.0  # charts cover a good part of the texture, not all of it


def test_rasterized_barycentrics_reproduce_the_texel_centers(sphere_bake):
    _, atlas, _, _, _ = sphere_bake
    face, bary = rasterize_uv(atlas.uv, atlas.faces, SIZE)
    rows, cols = np.nonzero(face >= 0)
    uv = np.einsum("pk,pkd->pd", bary[rows, cols], atlas.uv[atlas.faces[face[rows, cols]]].astype(np.float64))
    np.testing.assert_allclose(uv * SIZE - 0.5, np.stack((cols, rows), axis=1), atol=1e-3)


def test_a_known_gradient_comes_out_in_the_texture(sphere_bake):
    """Random points on the surface: the texture sampled at their UV (bilinear, as a viewer does)
    gives the gradient's color at the point, to within quantisation and a texel of gradient."""
    _, atlas, vertices, image, _ = sphere_bake
    rng = np.random.default_rng(0)
    faces = rng.integers(0, atlas.faces.shape[0], 2000)
    bary = rng.dirichlet(np.ones(3), size=2000)
    points = np.einsum("pk,pkd->pd", bary, vertices[atlas.faces[faces]])
    uv = np.einsum("pk,pkd->pd", bary, atlas.uv[atlas.faces[faces]].astype(np.float64))
    texel = uv * SIZE - 0.5
    sampled = cv2.remap(image.astype(np.float32), texel[:, 0].astype(np.float32)[None],
                        texel[:, 1].astype(np.float32)[None], cv2.INTER_LINEAR)[0] / 255.0
    expected = gradient(points)
    error = np.abs(sampled - expected)
    # The field changes by ~|grad| x (a texel in 3D) ~ 0.5 x 0.02 between texels; quantisation 1/510.
    assert error.mean() < 0.01 and error.max() < 0.05, (error.mean(), error.max())
    # Not trivially right: a texture of one color would be far off.
    assert np.abs(expected - expected.mean(axis=0)).mean() > 0.1


def test_dilation_fills_seams_with_the_neighbouring_color():
    image = np.zeros((8, 8, 3))
    covered = np.zeros((8, 8), dtype=bool)
    image[2:4, 2:4] = (1.0, 0.5, 0.25)
    covered[2:4, 2:4] = True
    out = dilate(image, covered, rings=1)
    np.testing.assert_allclose(out[1, 1], (1.0, 0.5, 0.25))  # one ring: the chart's color
    np.testing.assert_allclose(out[2:4, 2:4], image[2:4, 2:4])  # covered texels are untouched
    # Beyond the rings: the mean of the covered colors, never the black background.
    np.testing.assert_allclose(out[7, 7], (1.0, 0.5, 0.25))


def test_seam_texels_of_the_bake_are_not_black(sphere_bake):
    _, _, _, image, covered = sphere_bake
    ring = cv2.dilate(covered.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & ~covered
    assert ring.any()
    assert image[ring].astype(float).sum(axis=1).min() > 60  # the gradient is at least ~0.1 per channel


def test_obj_uv_flips_v_and_png_round_trips(sphere_bake):
    _, atlas, _, image, _ = sphere_bake
    np.testing.assert_allclose(obj_uv(atlas.uv)[:, 1], 1.0 - atlas.uv[:, 1], atol=1e-7)
    decoded = cv2.cvtColor(cv2.imdecode(np.frombuffer(png_bytes(image), np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(decoded, image)


def test_bad_inputs_raise_input_error():
    mesh = trimesh.creation.icosphere(subdivisions=1)
    with pytest.raises(InputError, match="at least 16"):
        unwrap(mesh.vertices, mesh.faces, 8)
    with pytest.raises(InputError, match="faces"):
        unwrap(mesh.vertices, np.zeros((0, 3), int), 64)
