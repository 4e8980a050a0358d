"""A game-ready canonical mesh: decimated (pymeshlab quadric), unwrapped (xatlas), color baked.

    mesh = textured_mesh(vertices, faces, color_fn, target_faces=30_000, texture_size=1024)
    obj_text, mtl_text = textured_obj(mesh.vertices, mesh.faces, mesh.uv, "avatar.mtl", "avatar.png")

Decimation is quadric edge collapse with the boundary, face orientation and topology kept
(`clean_mesh`): no collapse may change the genus or flip a face, so thin limbs and fingers are
not pinched shut, and the budget goes where the curvature is. The color is then baked from the
color field at full detail (one query per texel), not from the decimated vertices.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from igavatar.mesh.cleanup import clean_mesh
from igavatar.mesh.texture import bake_texture, obj_uv, unwrap


@dataclass(frozen=True)
class TexturedMesh:
    """The decimated mesh with its atlas and texture.

    Attributes:
        vertices: (V', 3) float32 positions (seam vertices duplicated); faces: (F, 3) int64.
        uv: (V', 2) float32 TEXCOORD_0 (v down); image: (S, S, 3) uint8 sRGB texture.
        coverage: fraction of texels inside a chart (the rest are seam dilation).
        decimated_vertices: vertex count of the decimated mesh before the UV seams split it.
    """

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    image: np.ndarray
    coverage: float
    decimated_vertices: int


#: paint(atlas_vertices (V', 3), faces (F, 3), uv (V', 2), size) -> (image (S, S, 3) uint8, covered (S, S) bool):
#: another source of the texture than the color field (igavatar.mesh.texture_fusion, the images).
Painter = Callable[[np.ndarray, np.ndarray, np.ndarray, int], tuple[np.ndarray, np.ndarray]]


def textured_mesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    color_fn: Callable[[np.ndarray], np.ndarray],
    target_faces: int,
    texture_size: int,
    paint: Painter | None = None,
) -> TexturedMesh:
    """Decimate to at most `target_faces`, unwrap, and bake `color_fn` ((P, 3) -> (P, 3) sRGB in
    [0, 1]) into the atlas, or let `paint` make the texture over it."""
    decimated, decimated_faces, _ = clean_mesh(vertices, faces, keep_largest=False, target_faces=target_faces)
    atlas = unwrap(decimated, decimated_faces, texture_size)
    atlas_vertices = atlas.vertices(decimated).astype(np.float32)
    if paint is None:
        image, covered = bake_texture(atlas_vertices, atlas.faces, atlas.uv, color_fn, texture_size)
    else:
        image, covered = paint(atlas_vertices, atlas.faces, atlas.uv, texture_size)
    return TexturedMesh(
        vertices=atlas_vertices, faces=atlas.faces, uv=atlas.uv, image=image, coverage=float(covered.mean()),
        decimated_vertices=int(decimated.shape[0]),
    )


def textured_obj(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray, mtl_name: str, png_name: str
                 ) -> tuple[str, str]:
    """Wavefront OBJ text (v, vt, f v/vt) and its MTL text for a texture-mapped mesh.

    Args:
        vertices: (V, 3); faces: (F, 3) 0-based; uv: (V, 2) glTF-style (v down; flipped for OBJ).
        mtl_name, png_name: file names the OBJ and MTL refer to (same directory).
    """
    vt = obj_uv(uv)
    lines = [f"# igavatar textured avatar: {len(vertices)} vertices, {len(faces)} faces", f"mtllib {mtl_name}"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in np.asarray(vertices, np.float64)]
    lines += [f"vt {u:.6f} {v:.6f}" for u, v in vt]
    lines.append("usemtl avatar")
    lines += [f"f {a}/{a} {b}/{b} {c}/{c}" for a, b, c in np.asarray(faces, np.int64) + 1]
    mtl = "\n".join([
        "newmtl avatar", "Ka 0 0 0", "Kd 1 1 1", "Ks 0 0 0", "d 1", "illum 1", f"map_Kd {png_name}", "",
    ])
    return "\n".join(lines) + "\n", mtl
