"""Rigged, optionally animated, binary glTF (GLB) of a canonical avatar mesh: the writer and the
conventions it follows (the reader is igavatar.mesh.gltf_read, the buffer and animation pieces
igavatar.mesh.gltf_parts).

    write_rigged_glb("avatar.glb", vertices, faces, colors, names, parents, joints_canonical, weights,
                     world_to_gltf=gltf_axes("anny"))

Axes: glTF is +Y up, +Z forward (the front of an asset faces +Z), +X the asset's left, meters;
every importer (Blender, three.js, Unity) converts from that. igavatar's world frame is the
capture's (Anny: +Z up, facing -Y), so the writer takes `world_to_gltf`, the (3, 3) rotation from
the caller's frame to glTF's (`gltf_axes(body_model)`: the body's left, up and forward axes become
+X, +Y and +Z), and *bakes* it into every position, normal, joint, bind matrix and keyframe. We bake
rather than add a rotated root node because a parent node above the skeleton becomes an extra
object or bone in Blender, is dropped or re-parented by engines that retarget humanoids (Unity's
importer, three.js' SkeletonUtils), and would rotate the root translation channel in a frame the
user never sees; baked, the armature's own nodes are in glTF's frame and the file is
self-explanatory. The origin is then moved to the floor under the root joint
(`floor_origin_offset`), where humanoid assets have it. Rotation and offset are recorded in
`asset.extras.igavatar` (`world_to_gltf`, `world_to_gltf_offset`: x_gltf = R x_world + offset) so
tools can map back to the capture frame (`read_rigged_glb` returns both; `gltf_to_world`). The
readers below return the file's (glTF) frame.

The bind pose is the canonical pose: every joint node has identity rotation and the translation
of its canonical offset from its parent (the root's: its canonical position), and each
inverse bind matrix is the inverse of the joint's global bind transform. The joint frames are
therefore world-aligned at bind time, so a pose given as local rotations *relative to the
canonical pose* in the parent's world-aligned canonical frame (SMPL's convention with the
canonical pose as rest) is exactly the glTF node rotations; `pose_relative_to_canonical` converts
a pose relative to the skeleton's own rest pose (what forward_kinematics takes) to that form.
Root translation is an offset added to the root node's canonical position.

Stored: POSITION (with min/max), NORMAL (unit), COLOR_0 (float RGB, linear as glTF requires; the
colors given are sRGB and converted), indices (uint32), JOINTS_0/WEIGHTS_0 (the 4 largest weights
per vertex renormalized to sum to 1; joints as uint8, or uint16 above 256 joints; with
`influences=8` also JOINTS_1/WEIGHTS_1, the 8 largest summing to 1 over both sets), one skin, and
optionally one animation (LINEAR keyframes: a rotation channel per joint, a translation channel
on the root; fps in the animation's extras). The reader (igavatar.mesh.gltf_read: `read_rigged_glb`,
`pose_glb_vertices`, `read_glb_animation`) decodes accessors and composes node matrices itself,
sharing no code with the writer or with igavatar.body's forward kinematics, so tests can use it
to check both.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pygltflib

from igavatar.artifacts.atomic import atomic_write_bytes
from igavatar.body.motions import body_to_world
from igavatar.body.skeleton import Skeleton
from igavatar.errors import InputError
from igavatar.mesh.cleanup import vertex_normals
from igavatar.mesh.gltf_parts import (
    BinaryBuilder, animation_of, as_array, check_rotations, checked_animation, material_of,
)

INFLUENCES = 4
"""Default joint influences per vertex: one JOINTS_0/WEIGHTS_0 set, what every web engine reads."""
INFLUENCE_CHOICES = (4, 8)
"""Influences the writer offers: 4 (one set) or 8 (JOINTS_0/1, WEIGHTS_0/1; Blender reads both)."""


def gltf_axes(body_model: str) -> np.ndarray:
    """(3, 3) rotation from a body model's world frame to glTF's (+X left, +Y up, +Z forward).

    Anny: +Z up, facing -Y -> (x, z, -y). SMPL is already Y-up, Z-forward (identity). A bare
    skeleton of unknown kind has no convention of its own; SMPL's is assumed, as elsewhere in
    igavatar (callers pass a bare skeleton's kind when it has one: ModelArtifact.axes_kind).
    """
    kind = body_model if body_model in ("anny", "smpl") else "smpl"
    return body_to_world(kind).T.copy()


def gltf_pose(world_to_gltf: np.ndarray, rotations: np.ndarray, translation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A pose for the GLB's nodes expressed in the caller's frame, re-expressed in glTF's.

    Joint frames are world-aligned at bind time, so a local rotation R becomes A R A^T and a root
    offset t becomes A t (A = world_to_gltf).

    Args:
        world_to_gltf: (3, 3) rotation A.
        rotations: (..., J, 3, 3) node rotations relative to the canonical pose (caller's frame).
        translation: (..., 3) root offsets (caller's frame).
    Returns:
        rotations (..., J, 3, 3) and offsets (..., 3) in glTF's frame, float64.
    """
    a = np.asarray(world_to_gltf, dtype=np.float64)
    rotations = a @ np.asarray(rotations, dtype=np.float64) @ a.T
    return rotations, np.asarray(translation, dtype=np.float64) @ a.T


# --------------------------------------------------------------------------------------------
# Color and weight helpers


def srgb_to_linear(srgb: np.ndarray) -> np.ndarray:
    """The sRGB transfer function inverted: values in [0, 1] -> linear [0, 1] (float64)."""
    c = np.clip(np.asarray(srgb, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """The sRGB transfer function: linear values in [0, 1] -> sRGB [0, 1] (float64)."""
    c = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.0031308, c * 12.92, 1.055 * c ** (1.0 / 2.4) - 0.055)


def top_k_weights(skin_weights: np.ndarray, k: int = INFLUENCES) -> tuple[np.ndarray, np.ndarray]:
    """The k largest skinning weights of each vertex, renormalized.

    Args:
        skin_weights: (V, J) non-negative weights.
        k: influences kept per vertex.
    Returns:
        joints (V, k) int64, largest weight first (unused slots: joint 0), and weights (V, k)
        float32 summing to 1 in float32 arithmetic up to one rounding (the largest weight absorbs
        the residual), zero in unused slots.
    """
    w = np.asarray(skin_weights, dtype=np.float64)
    num_vertices, num_joints = w.shape
    if num_joints < k:
        w = np.concatenate((w, np.zeros((num_vertices, k - num_joints))), axis=1)
    top = np.argpartition(-w, k - 1, axis=1)[:, :k]
    top_w = np.take_along_axis(w, top, axis=1)
    order = np.argsort(-top_w, axis=1, kind="stable")
    joints = np.take_along_axis(top, order, axis=1)
    kept = np.take_along_axis(top_w, order, axis=1)
    total = kept.sum(axis=1, keepdims=True)
    if np.any(total <= 0):
        bad = int(np.flatnonzero(total[:, 0] <= 0)[0])
        raise InputError(f"skin_weights: vertex {bad} has no positive weight; every vertex needs a joint")
    weights = (kept / total).astype(np.float32)
    joints = np.where(weights > 0, joints, 0)
    weights[:, 0] = np.float32(1.0) - weights[:, 1:].sum(axis=1, dtype=np.float32)
    return joints.astype(np.int64), weights


def pose_relative_to_canonical(
    local_rotations: np.ndarray,
    root_translation: np.ndarray,
    canonical_local_rotations: np.ndarray,
    canonical_root_translation: np.ndarray,
    parents: Sequence[int] | np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Re-express a pose relative to the canonical pose (the GLB's bind pose).

    With C_j the global rotation of joint j in the canonical pose, the rotation that the GLB's
    joint node j needs is P_j = C_parent(j) R_j Rc_j^T C_parent(j)^T: then P_0 ... P_j equals
    Q_j C_j^T, the rotation part of bone_transforms(FK(pose), FK(canonical)), and the joint
    positions agree too. The root offset becomes t - t_canonical.

    Args:
        local_rotations: (..., J, 3, 3) pose relative to the skeleton's rest pose (as FK takes).
        root_translation: (..., 3) its root translation.
        canonical_local_rotations: (J, 3, 3) the canonical pose, relative to the rest pose.
        canonical_root_translation: (3,) the canonical pose's root translation.
        parents: (J,) parent indices, parents before children.
    Returns:
        rotations (..., J, 3, 3) relative to the canonical pose and root offsets (..., 3), float64.
    """
    rotations = np.asarray(local_rotations, dtype=np.float64)
    canonical = np.asarray(canonical_local_rotations, dtype=np.float64)
    parents = np.asarray(parents, dtype=np.int64)
    num_joints = parents.shape[0]
    if rotations.shape[-3:] != (num_joints, 3, 3) or canonical.shape != (num_joints, 3, 3):
        raise InputError(
            f"pose_relative_to_canonical: rotations {rotations.shape} and canonical "
            f"{canonical.shape} must be (..., {num_joints}, 3, 3) and ({num_joints}, 3, 3)"
        )
    canonical_global = np.empty_like(canonical)
    parent_global = np.empty_like(canonical)
    for j in range(num_joints):
        parent_global[j] = np.eye(3) if parents[j] < 0 else canonical_global[parents[j]]
        canonical_global[j] = parent_global[j] @ canonical[j]
    relative = parent_global @ rotations @ np.swapaxes(canonical, -1, -2) @ np.swapaxes(parent_global, -1, -2)
    translation = np.asarray(root_translation, dtype=np.float64) - np.asarray(
        canonical_root_translation, dtype=np.float64
    )
    return relative, translation


# --------------------------------------------------------------------------------------------
# Writer


def write_rigged_glb(
    path: str | os.PathLike[str],
    vertices: np.ndarray,
    faces: np.ndarray,
    colors: np.ndarray | None,
    joint_names: Sequence[str],
    parents: Sequence[int] | np.ndarray,
    joints_canonical: np.ndarray,
    skin_weights: np.ndarray,
    *,
    world_to_gltf: np.ndarray,
    animation: tuple[np.ndarray, np.ndarray, float] | None = None,
    influences: int = INFLUENCES,
    texture: tuple[np.ndarray, bytes] | None = None,
) -> np.ndarray:
    """Write a skinned mesh whose bind pose is the canonical pose as one GLB (atomically); returns
    the (3,) offset added after the axes (`floor_origin_offset`: the origin on the floor).

    Args:
        path: the .glb file to write.
        vertices: (V, 3) canonical positions in meters.
        faces: (F, 3) vertex indices, counter-clockwise seen from outside.
        colors: (V, 3) sRGB colors, uint8 or float in [0, 1] (None with a texture).
        joint_names: J names (node names in the file).
        parents: (J,) parent indices, -1 for the root at 0, parents before children.
        joints_canonical: (J, 3) joint positions in the canonical pose.
        skin_weights: (V, J) non-negative skinning weights (top `influences` kept, renormalized).
        world_to_gltf: (3, 3) rotation from the frame of every input (vertices, joints, animation)
            to glTF's +Y-up, +Z-forward frame (`gltf_axes(body_model)`); baked into the file.
        animation: optional (local_rotations (N, J, 3, 3) relative to the canonical pose,
            root_translation (N, 3) offsets from the canonical root position, fps), in the
            caller's frame like the vertices.
        influences: 4 (JOINTS_0/WEIGHTS_0) or 8 (also JOINTS_1/WEIGHTS_1).
        texture: optional (uv (V, 2) in [0, 1] with v down from the image's top row, as glTF
            defines TEXCOORD_0; PNG bytes of the sRGB base color). The image is embedded and
            the material samples it; `colors` are then not stored (glTF would multiply them).
    """
    path = Path(path)
    skeleton = Skeleton(  # validates parents, joint positions and names
        parents=as_array(parents), rest_joints=as_array(joints_canonical), joint_names=tuple(joint_names),
    )
    mesh = _checked_mesh(path, vertices, faces, colors, skin_weights, texture, skeleton.num_joints)
    if influences not in INFLUENCE_CHOICES:
        raise InputError(f"{path}: influences = {influences}, expected one of {INFLUENCE_CHOICES}")
    axes = np.asarray(world_to_gltf, dtype=np.float64)
    if axes.shape != (3, 3):
        raise InputError(f"{path}: world_to_gltf has shape {axes.shape}, expected (3, 3)")
    check_rotations(axes, f"{path}: world_to_gltf")
    motion = None if animation is None else checked_animation(animation, skeleton.num_joints, path)
    # Bake glTF's axes into every position (see the module docstring for why not a root node),
    # then put the origin on the floor.
    vertices_gltf = mesh.vertices @ axes.T
    joints_gltf = skeleton.rest_joints.astype(np.float64) @ axes.T
    offset = floor_origin_offset(vertices_gltf, joints_gltf[0])
    vertices_gltf, joints_gltf = vertices_gltf + offset, joints_gltf + offset

    builder = BinaryBuilder()
    primitive = _primitive(builder, mesh, vertices_gltf, influences, skeleton.num_joints)
    nodes, inverse_bind = _skeleton_nodes(builder, skeleton, joints_gltf)
    material, images, textures, samplers = material_of(builder, mesh.texture_png)
    gltf = pygltflib.GLTF2(
        images=images, textures=textures, samplers=samplers,
        asset=pygltflib.Asset(version="2.0", generator="igavatar", extras={"igavatar": {
            "world_to_gltf": axes.tolist(), "world_to_gltf_offset": offset.tolist(), "influences": influences}}),
        scene=0,
        scenes=[pygltflib.Scene(name="avatar", nodes=[0, len(nodes) - 1])],
        nodes=nodes,
        meshes=[pygltflib.Mesh(name="avatar", primitives=[primitive])],
        materials=[material],
        skins=[pygltflib.Skin(name="skeleton", inverseBindMatrices=inverse_bind, skeleton=0,
                              joints=list(range(skeleton.num_joints)))],
    )
    if motion is not None:
        rotations, translation, fps = motion
        rotations_gltf, translation_gltf = gltf_pose(axes, rotations, translation)
        gltf.animations = [animation_of(builder, rotations_gltf, translation_gltf, fps, np.asarray(nodes[0].translation))]
    gltf.accessors = builder.accessors
    gltf.bufferViews = builder.views
    builder.blob.extend(b"\0" * (-len(builder.blob) % 4))
    gltf.buffers = [pygltflib.Buffer(byteLength=len(builder.blob))]
    gltf.set_binary_blob(bytes(builder.blob))
    atomic_write_bytes(path, b"".join(gltf.save_to_bytes()))
    return offset


@dataclass(frozen=True)
class _Mesh:
    """The writer's checked mesh inputs (capture frame, float64)."""

    vertices: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 3) integers
    colors: np.ndarray  # (V, 3) sRGB in [0, 1] (ones with a texture)
    weights: np.ndarray  # (V, J)
    uv: np.ndarray | None  # (V, 2) with a texture
    texture_png: bytes | None


def _checked_mesh(path: Path, vertices, faces, colors, skin_weights, texture, num_joints: int) -> _Mesh:
    """The mesh, colours, weights and texture as arrays; InputError naming `path` when malformed."""
    v = as_array(vertices).astype(np.float64)
    f = as_array(faces)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0 or not np.all(np.isfinite(v)):
        raise InputError(f"{path}: vertices have shape {v.shape}, expected finite (V, 3) with V >= 1")
    num_vertices = v.shape[0]
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0 or not np.issubdtype(f.dtype, np.integer):
        raise InputError(f"{path}: faces have shape {f.shape} and dtype {f.dtype}, expected (F, 3) integers")
    if f.min() < 0 or f.max() >= num_vertices:
        raise InputError(f"{path}: faces index [{f.min()}, {f.max()}] but there are {num_vertices} vertices")
    uv, png = None, None
    if texture is not None:
        uv, png = texture
        uv = as_array(uv).astype(np.float64)
        if uv.shape != (num_vertices, 2) or not np.all(np.isfinite(uv)):
            raise InputError(f"{path}: texture uv have shape {uv.shape}, expected finite ({num_vertices}, 2)")
        if not isinstance(png, (bytes, bytearray)) or not bytes(png[:8]) == b"\x89PNG\r\n\x1a\n":
            raise InputError(f"{path}: the texture image must be PNG bytes")
    if colors is None and uv is None:
        raise InputError(f"{path}: give vertex colors or a texture")
    c = np.ones((num_vertices, 3)) if colors is None else as_array(colors)
    if c.shape != (num_vertices, 3):
        raise InputError(f"{path}: colors have shape {c.shape}, expected ({num_vertices}, 3)")
    c = c / 255.0 if c.dtype == np.uint8 else c.astype(np.float64)
    if not np.all(np.isfinite(c)) or c.min() < 0 or c.max() > 1:
        raise InputError(f"{path}: float colors must lie in [0, 1] (uint8 colors are 0..255)")
    w = as_array(skin_weights).astype(np.float64)
    if w.shape != (num_vertices, num_joints):
        raise InputError(f"{path}: skin_weights have shape {w.shape}, expected ({num_vertices}, {num_joints})")
    if not np.all(np.isfinite(w)) or w.min() < 0:
        raise InputError(f"{path}: skin_weights must be finite and non-negative")
    return _Mesh(v, f, c, w, uv, None if png is None else bytes(png))


def _primitive(builder: BinaryBuilder, mesh: _Mesh, vertices_gltf: np.ndarray, influences: int,
               num_joints: int) -> pygltflib.Primitive:
    """POSITION, NORMAL, COLOR_0 or TEXCOORD_0, JOINTS_n/WEIGHTS_n and indices of the one primitive."""
    normals = vertex_normals(vertices_gltf, mesh.faces).astype(np.float64)
    # glTF requires unit normals; a vertex of degenerate faces only gets an arbitrary one.
    normals[np.linalg.norm(normals, axis=1) < 0.5] = (0.0, 0.0, 1.0)
    attributes = {
        "POSITION": builder.add(vertices_gltf.astype(np.float32), pygltflib.FLOAT, pygltflib.VEC3,
                                pygltflib.ARRAY_BUFFER, with_bounds=True),
        "NORMAL": builder.add(normals.astype(np.float32), pygltflib.FLOAT, pygltflib.VEC3, pygltflib.ARRAY_BUFFER),
    }
    if mesh.uv is None:
        attributes["COLOR_0"] = builder.add(srgb_to_linear(mesh.colors).astype(np.float32), pygltflib.FLOAT,
                                            pygltflib.VEC3, pygltflib.ARRAY_BUFFER)
    else:
        attributes["TEXCOORD_0"] = builder.add(mesh.uv.astype(np.float32), pygltflib.FLOAT, pygltflib.VEC2,
                                               pygltflib.ARRAY_BUFFER)
    joints_idx, weights = top_k_weights(mesh.weights, influences)
    joint_type, joint_dtype = (pygltflib.UNSIGNED_BYTE, np.uint8) if num_joints <= 256 else (pygltflib.UNSIGNED_SHORT, np.uint16)
    sets = list(enumerate(range(0, influences, 4)))
    for n, k in sets:  # every JOINTS_n first, then every WEIGHTS_n: the buffer layout files have had
        attributes[f"JOINTS_{n}"] = builder.add(np.ascontiguousarray(joints_idx[:, k:k + 4]).astype(joint_dtype),
                                                joint_type, pygltflib.VEC4, pygltflib.ARRAY_BUFFER)
    for n, k in sets:
        attributes[f"WEIGHTS_{n}"] = builder.add(np.ascontiguousarray(weights[:, k:k + 4]), pygltflib.FLOAT,
                                                 pygltflib.VEC4, pygltflib.ARRAY_BUFFER)
    indices = builder.add(mesh.faces.astype(np.uint32).reshape(-1), pygltflib.UNSIGNED_INT, pygltflib.SCALAR,
                          pygltflib.ELEMENT_ARRAY_BUFFER, with_bounds=True)
    return pygltflib.Primitive(attributes=pygltflib.Attributes(**attributes), indices=indices, material=0,
                               mode=pygltflib.TRIANGLES)


def _skeleton_nodes(builder: BinaryBuilder, skeleton: Skeleton, joints_gltf: np.ndarray) -> tuple[list, int]:
    """The joint nodes (bind pose: identity rotations, canonical offsets) plus the mesh node last,
    and the accessor of the inverse bind matrices."""
    num_joints = skeleton.num_joints
    offsets = joints_gltf.copy()
    offsets[1:] = joints_gltf[1:] - joints_gltf[skeleton.parents[1:]]
    # Identity rotations: each joint's global bind transform is a translation to its canonical
    # position, and the inverse bind matrix the opposite translation.
    inverse_bind = np.tile(np.eye(4), (num_joints, 1, 1))
    inverse_bind[:, :3, 3] = -joints_gltf
    inverse_bind_accessor = builder.add(  # glTF matrices are column-major
        np.transpose(inverse_bind, (0, 2, 1)).reshape(num_joints, 16).astype(np.float32), pygltflib.FLOAT, pygltflib.MAT4,
    )
    children: list[list[int]] = [[] for _ in range(num_joints)]
    for j in range(1, num_joints):
        children[int(skeleton.parents[j])].append(j)
    nodes = [pygltflib.Node(name=skeleton.joint_names[j], translation=[float(x) for x in offsets[j]],
                            rotation=[0.0, 0.0, 0.0, 1.0], children=children[j]) for j in range(num_joints)]
    nodes.append(pygltflib.Node(name="avatar", mesh=0, skin=0))
    return nodes, inverse_bind_accessor


def floor_origin_offset(vertices_gltf: np.ndarray, root_gltf: np.ndarray) -> np.ndarray:
    """(3,) translation that puts the origin on the floor under the root joint: the root's ground
    projection at the lowest vertex's height (glTF frame, +Y up).

    Humanoid assets (Mixamo, VRM, Ready Player Me) stand on Y = 0 with the origin between the
    feet, so that an engine places them on the ground and turns them about their own axis; the
    capture's origin (Anny's: the pelvis) would sink the avatar 0.8 m into the floor.
    """
    return -np.array([root_gltf[0], vertices_gltf[:, 1].min(), root_gltf[2]], dtype=np.float64)
