"""Rigged, optionally animated, binary glTF (GLB) of a canonical avatar mesh, and a GLB reader.

    write_rigged_glb("avatar.glb", vertices, faces, colors, names, parents, joints_canonical, weights,
                     world_to_gltf=gltf_axes("anny"))
    x_posed = pose_glb_vertices("avatar.glb", rotations_rel_canonical, root_translation)  # glTF frame

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
on the root; fps in the animation's extras). The reader side (`read_rigged_glb`,
`pose_glb_vertices`, `read_glb_animation`) decodes accessors and composes node matrices itself,
sharing no code with the writer or with igavatar.body's forward kinematics, so tests can use it
to check both.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pygltflib
import torch

from igavatar.artifacts.atomic import atomic_write_bytes
from igavatar.body.motions import body_to_world
from igavatar.body.rotations import matrix_to_quaternion
from igavatar.body.skeleton import Skeleton
from igavatar.errors import InputError
from igavatar.mesh.cleanup import vertex_normals

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


class _BinaryBuilder:
    """Accumulates 4-byte-aligned buffer views and their accessors for one GLB buffer."""

    def __init__(self) -> None:
        self.blob = bytearray()
        self.views: list[pygltflib.BufferView] = []
        self.accessors: list[pygltflib.Accessor] = []

    def add(
        self,
        array: np.ndarray,
        component_type: int,
        accessor_type: str,
        target: int | None = None,
        with_bounds: bool = False,
        normalized: bool = False,
    ) -> int:
        """Append `array` (count, components) as one view + accessor; returns the accessor index."""
        data = np.ascontiguousarray(array)
        self.blob.extend(b"\0" * (-len(self.blob) % 4))
        self.views.append(
            pygltflib.BufferView(buffer=0, byteOffset=len(self.blob), byteLength=data.nbytes, target=target)
        )
        self.blob.extend(data.tobytes())
        accessor = pygltflib.Accessor(
            bufferView=len(self.views) - 1,
            byteOffset=0,
            componentType=component_type,
            normalized=normalized,
            count=int(data.shape[0]),
            type=accessor_type,
        )
        if with_bounds:
            flat = data.reshape(data.shape[0], -1)
            accessor.min = [float(x) for x in flat.min(axis=0)]
            accessor.max = [float(x) for x in flat.max(axis=0)]
        else:
            accessor.min = None
            accessor.max = None
        self.accessors.append(accessor)
        return len(self.accessors) - 1


def _as_array(value: Any) -> np.ndarray:
    """numpy view of an array-like or a (CPU or device) tensor."""
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    return np.asarray(value)


def _quaternions_xyzw(rotations: np.ndarray) -> np.ndarray:
    """glTF quaternions (..., 4) as x, y, z, w of rotation matrices (..., 3, 3)."""
    wxyz = matrix_to_quaternion(torch.as_tensor(rotations, dtype=torch.float64)).numpy()
    return np.concatenate((wxyz[..., 1:], wxyz[..., :1]), axis=-1)


def _check_rotations(rotations: np.ndarray, what: str) -> None:
    gram = np.swapaxes(rotations, -1, -2) @ rotations
    if not np.allclose(gram, np.eye(3), atol=1e-4) or np.any(np.linalg.det(rotations) <= 0):
        raise InputError(f"{what}: not all 3x3 matrices are rotations (orthonormal, det +1)")


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
    v = _as_array(vertices).astype(np.float64)
    f = _as_array(faces)
    skeleton = Skeleton(  # validates parents, joint positions and names
        parents=_as_array(parents),
        rest_joints=_as_array(joints_canonical),
        joint_names=tuple(joint_names),
    )
    num_joints = skeleton.num_joints
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0 or not np.all(np.isfinite(v)):
        raise InputError(f"{path}: vertices have shape {v.shape}, expected finite (V, 3) with V >= 1")
    num_vertices = v.shape[0]
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0 or not np.issubdtype(f.dtype, np.integer):
        raise InputError(f"{path}: faces have shape {f.shape} and dtype {f.dtype}, expected (F, 3) integers")
    if f.min() < 0 or f.max() >= num_vertices:
        raise InputError(f"{path}: faces index [{f.min()}, {f.max()}] but there are {num_vertices} vertices")
    uv = None
    if texture is not None:
        uv, png = texture
        uv = _as_array(uv).astype(np.float64)
        if uv.shape != (num_vertices, 2) or not np.all(np.isfinite(uv)):
            raise InputError(f"{path}: texture uv have shape {uv.shape}, expected finite ({num_vertices}, 2)")
        if not isinstance(png, (bytes, bytearray)) or not bytes(png[:8]) == b"\x89PNG\r\n\x1a\n":
            raise InputError(f"{path}: the texture image must be PNG bytes")
    if colors is None and uv is None:
        raise InputError(f"{path}: give vertex colors or a texture")
    c = np.ones((num_vertices, 3)) if colors is None else _as_array(colors)
    if c.shape != (num_vertices, 3):
        raise InputError(f"{path}: colors have shape {c.shape}, expected ({num_vertices}, 3)")
    c = c / 255.0 if c.dtype == np.uint8 else c.astype(np.float64)
    if not np.all(np.isfinite(c)) or c.min() < 0 or c.max() > 1:
        raise InputError(f"{path}: float colors must lie in [0, 1] (uint8 colors are 0..255)")
    w = _as_array(skin_weights).astype(np.float64)
    if w.shape != (num_vertices, num_joints):
        raise InputError(
            f"{path}: skin_weights have shape {w.shape}, expected ({num_vertices}, {num_joints})"
        )
    if not np.all(np.isfinite(w)) or w.min() < 0:
        raise InputError(f"{path}: skin_weights must be finite and non-negative")
    if influences not in INFLUENCE_CHOICES:
        raise InputError(f"{path}: influences = {influences}, expected one of {INFLUENCE_CHOICES}")
    axes = np.asarray(world_to_gltf, dtype=np.float64)
    if axes.shape != (3, 3):
        raise InputError(f"{path}: world_to_gltf has shape {axes.shape}, expected (3, 3)")
    _check_rotations(axes, f"{path}: world_to_gltf")
    joints_idx, weights = top_k_weights(w, influences)
    # Bake glTF's axes into every position (see the module docstring for why not a root node).
    v = v @ axes.T
    joints_gltf = skeleton.rest_joints.astype(np.float64) @ axes.T
    offset = floor_origin_offset(v, joints_gltf[0])
    v, joints_gltf = v + offset, joints_gltf + offset

    normals = vertex_normals(v, f).astype(np.float64)
    # glTF requires unit normals; a vertex of degenerate faces only gets an arbitrary one.
    degenerate = np.linalg.norm(normals, axis=1) < 0.5
    normals[degenerate] = (0.0, 0.0, 1.0)

    builder = _BinaryBuilder()
    positions = builder.add(
        v.astype(np.float32), pygltflib.FLOAT, pygltflib.VEC3, pygltflib.ARRAY_BUFFER, with_bounds=True
    )
    normal_accessor = builder.add(normals.astype(np.float32), pygltflib.FLOAT, pygltflib.VEC3, pygltflib.ARRAY_BUFFER)
    surface: dict[str, int] = {}
    if uv is None:
        surface["COLOR_0"] = builder.add(
            srgb_to_linear(c).astype(np.float32), pygltflib.FLOAT, pygltflib.VEC3, pygltflib.ARRAY_BUFFER
        )
    else:
        surface["TEXCOORD_0"] = builder.add(uv.astype(np.float32), pygltflib.FLOAT, pygltflib.VEC2, pygltflib.ARRAY_BUFFER)
    joint_type, joint_dtype = (
        (pygltflib.UNSIGNED_BYTE, np.uint8) if num_joints <= 256 else (pygltflib.UNSIGNED_SHORT, np.uint16)
    )
    joint_sets = [
        builder.add(np.ascontiguousarray(joints_idx[:, k : k + 4]).astype(joint_dtype), joint_type, pygltflib.VEC4,
                    pygltflib.ARRAY_BUFFER)
        for k in range(0, influences, 4)
    ]
    weight_sets = [
        builder.add(np.ascontiguousarray(weights[:, k : k + 4]), pygltflib.FLOAT, pygltflib.VEC4, pygltflib.ARRAY_BUFFER)
        for k in range(0, influences, 4)
    ]
    indices = builder.add(
        f.astype(np.uint32).reshape(-1), pygltflib.UNSIGNED_INT, pygltflib.SCALAR,
        pygltflib.ELEMENT_ARRAY_BUFFER, with_bounds=True,
    )

    # Bind pose: identity rotations, so each joint's global bind transform is a translation to
    # its canonical position and the inverse bind matrix the opposite translation.
    rest = joints_gltf
    offsets = rest.copy()
    offsets[1:] = rest[1:] - rest[skeleton.parents[1:]]
    inverse_bind = np.tile(np.eye(4), (num_joints, 1, 1))
    inverse_bind[:, :3, 3] = -rest
    # glTF matrices are column-major.
    inverse_bind_accessor = builder.add(
        np.transpose(inverse_bind, (0, 2, 1)).reshape(num_joints, 16).astype(np.float32),
        pygltflib.FLOAT, pygltflib.MAT4,
    )

    children: list[list[int]] = [[] for _ in range(num_joints)]
    for j in range(1, num_joints):
        children[int(skeleton.parents[j])].append(j)
    nodes = [
        pygltflib.Node(
            name=skeleton.joint_names[j],
            translation=[float(x) for x in offsets[j]],
            rotation=[0.0, 0.0, 0.0, 1.0],
            children=children[j],
        )
        for j in range(num_joints)
    ]
    mesh_node = num_joints
    nodes.append(pygltflib.Node(name="avatar", mesh=0, skin=0))

    color = pygltflib.PbrMetallicRoughness(baseColorFactor=[1.0, 1.0, 1.0, 1.0], metallicFactor=0.0, roughnessFactor=1.0)
    material = pygltflib.Material(name="vertex_color" if uv is None else "texture", pbrMetallicRoughness=color,
                                  doubleSided=False)
    images, textures, samplers = [], [], []
    if uv is not None:
        builder.blob.extend(b"\0" * (-len(builder.blob) % 4))
        builder.views.append(pygltflib.BufferView(buffer=0, byteOffset=len(builder.blob), byteLength=len(png)))
        builder.blob.extend(bytes(png))
        images = [pygltflib.Image(name="base_color", mimeType="image/png", bufferView=len(builder.views) - 1)]
        # Linear filtering with mipmaps; clamp, since the atlas charts never wrap.
        samplers = [pygltflib.Sampler(magFilter=pygltflib.LINEAR, minFilter=pygltflib.LINEAR_MIPMAP_LINEAR,
                                      wrapS=pygltflib.CLAMP_TO_EDGE, wrapT=pygltflib.CLAMP_TO_EDGE)]
        textures = [pygltflib.Texture(sampler=0, source=0)]
        color.baseColorTexture = pygltflib.TextureInfo(index=0, texCoord=0)

    gltf = pygltflib.GLTF2(
        images=images, textures=textures, samplers=samplers,
        asset=pygltflib.Asset(
            version="2.0", generator="igavatar",
            extras={"igavatar": {"world_to_gltf": axes.tolist(), "world_to_gltf_offset": offset.tolist(),
                                 "influences": influences}},
        ),
        scene=0,
        scenes=[pygltflib.Scene(name="avatar", nodes=[0, mesh_node])],
        nodes=nodes,
        meshes=[
            pygltflib.Mesh(
                name="avatar",
                primitives=[
                    pygltflib.Primitive(
                        attributes=pygltflib.Attributes(
                            POSITION=positions, NORMAL=normal_accessor, **surface,
                            **{f"JOINTS_{n}": a for n, a in enumerate(joint_sets)},
                            **{f"WEIGHTS_{n}": a for n, a in enumerate(weight_sets)},
                        ),
                        indices=indices,
                        material=0,
                        mode=pygltflib.TRIANGLES,
                    )
                ],
            )
        ],
        materials=[material],
        skins=[
            pygltflib.Skin(
                name="skeleton", inverseBindMatrices=inverse_bind_accessor, skeleton=0,
                joints=list(range(num_joints)),
            )
        ],
    )

    if animation is not None:
        gltf.animations = [_add_animation(builder, animation, offsets[0], num_joints, axes, path)]

    gltf.accessors = builder.accessors
    gltf.bufferViews = builder.views
    builder.blob.extend(b"\0" * (-len(builder.blob) % 4))
    gltf.buffers = [pygltflib.Buffer(byteLength=len(builder.blob))]
    gltf.set_binary_blob(bytes(builder.blob))
    atomic_write_bytes(path, b"".join(gltf.save_to_bytes()))
    return offset


def floor_origin_offset(vertices_gltf: np.ndarray, root_gltf: np.ndarray) -> np.ndarray:
    """(3,) translation that puts the origin on the floor under the root joint: the root's ground
    projection at the lowest vertex's height (glTF frame, +Y up).

    Humanoid assets (Mixamo, VRM, Ready Player Me) stand on Y = 0 with the origin between the
    feet, so that an engine places them on the ground and turns them about their own axis; the
    capture's origin (Anny's: the pelvis) would sink the avatar 0.8 m into the floor.
    """
    return -np.array([root_gltf[0], vertices_gltf[:, 1].min(), root_gltf[2]], dtype=np.float64)


def gltf_to_world(points_gltf: np.ndarray, world_to_gltf: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """(N, 3) points of an igavatar GLB back in the capture's frame (x_gltf = R x_world + offset)."""
    return (np.asarray(points_gltf, np.float64) - np.asarray(offset, np.float64)) @ np.asarray(world_to_gltf, np.float64)


def _add_animation(
    builder: _BinaryBuilder,
    animation: tuple[np.ndarray, np.ndarray, float],
    root_offset: np.ndarray,
    num_joints: int,
    world_to_gltf: np.ndarray,
    path: Path,
) -> pygltflib.Animation:
    """Keyframe accessors and the Animation object for (rotations, root translation, fps).

    The keys come in the caller's frame and are stored in glTF's (`gltf_pose`); root_offset (3,)
    is the root node's bind translation, already in glTF's frame.
    """
    try:
        rotations, translation, fps = animation
    except (TypeError, ValueError):
        raise InputError(f"{path}: animation must be (local_rotations, root_translation, fps)") from None
    rotations = _as_array(rotations).astype(np.float64)
    translation = _as_array(translation).astype(np.float64)
    if rotations.ndim != 4 or rotations.shape[1:] != (num_joints, 3, 3) or rotations.shape[0] == 0:
        raise InputError(
            f"{path}: animation rotations have shape {rotations.shape}, expected (N, {num_joints}, 3, 3)"
        )
    num_frames = rotations.shape[0]
    if translation.shape != (num_frames, 3) or not np.all(np.isfinite(translation)):
        raise InputError(
            f"{path}: animation root_translation has shape {translation.shape}, expected finite ({num_frames}, 3)"
        )
    try:
        fps = float(fps)
    except (TypeError, ValueError):
        raise InputError(f"{path}: animation fps = {fps!r}, expected a number > 0") from None
    if not np.isfinite(fps) or fps <= 0:
        raise InputError(f"{path}: animation fps = {fps}, expected > 0")
    _check_rotations(rotations, f"{path}: animation rotations")
    rotations, translation = gltf_pose(world_to_gltf, rotations, translation)

    times = builder.add(
        (np.arange(num_frames, dtype=np.float64) / float(fps)).astype(np.float32),
        pygltflib.FLOAT, pygltflib.SCALAR, with_bounds=True,  # sampler inputs need min/max
    )
    quaternions = _quaternions_xyzw(rotations)  # (N, J, 4)
    # LINEAR rotation keyframes are slerped: keep consecutive quaternions in one hemisphere so
    # every viewer takes the short way.
    for n in range(1, num_frames):
        flip = (quaternions[n] * quaternions[n - 1]).sum(axis=-1) < 0
        quaternions[n, flip] *= -1.0
    samplers = []
    channels = []
    for j in range(num_joints):
        output = builder.add(quaternions[:, j].astype(np.float32), pygltflib.FLOAT, pygltflib.VEC4)
        samplers.append(pygltflib.AnimationSampler(input=times, output=output, interpolation="LINEAR"))
        channels.append(
            pygltflib.AnimationChannel(
                sampler=j, target=pygltflib.AnimationChannelTarget(node=j, path="rotation")
            )
        )
    root_positions = builder.add(
        (root_offset[None, :] + translation).astype(np.float32), pygltflib.FLOAT, pygltflib.VEC3
    )
    samplers.append(pygltflib.AnimationSampler(input=times, output=root_positions, interpolation="LINEAR"))
    channels.append(
        pygltflib.AnimationChannel(
            sampler=num_joints, target=pygltflib.AnimationChannelTarget(node=0, path="translation")
        )
    )
    return pygltflib.Animation(
        name="motion", samplers=samplers, channels=channels, extras={"fps": float(fps)}
    )


# --------------------------------------------------------------------------------------------
# Reader (independent of the writer and of igavatar.body)

_COMPONENT_DTYPES = {
    5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32,
}
_TYPE_SIZES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


def _load(path: str | os.PathLike[str]) -> tuple[pygltflib.GLTF2, bytes]:
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: GLB file not found")
    try:
        gltf = pygltflib.GLTF2.load_binary(str(path))
    except Exception as error:  # pygltflib raises assorted errors for bad files
        raise InputError(f"{path}: not a readable GLB file ({error})") from error
    blob = gltf.binary_blob()
    if blob is None:
        raise InputError(f"{path}: the GLB has no binary chunk")
    return gltf, blob


def read_accessor(gltf: pygltflib.GLTF2, blob: bytes, index: int) -> np.ndarray:
    """Decode accessor `index` of a GLB: (count, components) array (count,) for SCALAR.

    Handles byte offsets, byte strides and normalized integers (returned as float32 in [0, 1] or
    [-1, 1]); sparse accessors are refused.
    """
    accessor = gltf.accessors[index]
    if accessor.sparse is not None:
        raise InputError(f"GLB accessor {index} is sparse, which this reader does not support")
    dtype = np.dtype(_COMPONENT_DTYPES[accessor.componentType])
    components = _TYPE_SIZES[accessor.type]
    view = gltf.bufferViews[accessor.bufferView]
    start = (view.byteOffset or 0) + (accessor.byteOffset or 0)
    element = dtype.itemsize * components
    stride = view.byteStride or element
    raw = np.frombuffer(blob, dtype=np.uint8, count=stride * (accessor.count - 1) + element, offset=start)
    rows = np.lib.stride_tricks.as_strided(raw, shape=(accessor.count, element), strides=(stride, 1))
    data = np.ascontiguousarray(rows).view(dtype).reshape(accessor.count, components)
    if accessor.normalized:
        info = np.iinfo(dtype)
        data = np.maximum(data.astype(np.float32) / info.max, -1.0)
    return data[:, 0] if accessor.type == "SCALAR" else data


def _skinned_node(gltf: pygltflib.GLTF2, path: str | os.PathLike[str]) -> pygltflib.Node:
    for node in gltf.nodes:
        if node.mesh is not None and node.skin is not None:
            return node
    raise InputError(f"{path}: the GLB has no skinned mesh node")


def _quaternion_xyzw_to_matrix(q: np.ndarray) -> np.ndarray:
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _node_matrix(node: pygltflib.Node, rotation: np.ndarray | None, extra_translation: np.ndarray | None) -> np.ndarray:
    """Local 4x4 matrix T R S of a node, with its rotation replaced and translation offset if given."""
    if node.matrix is not None:
        local = np.asarray(node.matrix, dtype=np.float64).reshape(4, 4).T  # column-major
        if rotation is not None:
            scale = np.linalg.norm(local[:3, :3], axis=0)
            local[:3, :3] = rotation * scale[None, :]
    else:
        local = np.eye(4)
        r = rotation if rotation is not None else (
            _quaternion_xyzw_to_matrix(node.rotation) if node.rotation is not None else np.eye(3)
        )
        s = np.asarray(node.scale, dtype=np.float64) if node.scale is not None else np.ones(3)
        local[:3, :3] = r * s[None, :]
        if node.translation is not None:
            local[:3, 3] = node.translation
    if extra_translation is not None:
        local[:3, 3] += extra_translation
    return local


def _skin_root(gltf: pygltflib.GLTF2, joints: list[int]) -> int:
    """The skin joint whose node has no parent among the skin's joints."""
    joint_set = set(joints)
    child_of_joint = {c for j in joints for c in (gltf.nodes[j].children or []) if c in joint_set}
    roots = [j for j in joints if j not in child_of_joint]
    if len(roots) != 1:
        raise InputError(f"the GLB skin has {len(roots)} root joints, expected 1")
    return roots[0]


def read_rigged_glb(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The skinned mesh of a GLB written by write_rigged_glb (or any single-primitive skinned GLB).

    Returns a dict, in the file's (glTF, +Y up) frame: vertices (V, 3) float32, faces (F, 3)
    int64, normals (V, 3) or None, uv (V, 2) TEXCOORD_0 or None, colors (V, 3) float sRGB in [0, 1] or None (COLOR_0 is linear
    in the file), joint_names (J,), parents (J,) int64 in skin-joint order (-1 for the root),
    joints_bind (J, 3) joint positions from the inverse bind matrices, inverse_bind (J, 4, 4),
    joints (V, 4 S) int64 and weights (V, 4 S) float32 (JOINTS_n/WEIGHTS_n of the S sets side by
    side), world_to_gltf (3, 3) the writer's recorded axes (identity if none).
    """
    gltf, blob = _load(path)
    return _read_skinned(gltf, blob, path)


def _read_skinned(gltf: pygltflib.GLTF2, blob: bytes, path: str | os.PathLike[str]) -> dict[str, Any]:
    node = _skinned_node(gltf, path)
    mesh = gltf.meshes[node.mesh]
    if len(mesh.primitives) != 1:
        raise InputError(f"{path}: the skinned mesh has {len(mesh.primitives)} primitives, expected 1")
    primitive = mesh.primitives[0]
    attributes = primitive.attributes
    for name in ("POSITION", "JOINTS_0", "WEIGHTS_0"):
        if getattr(attributes, name) is None:
            raise InputError(f"{path}: the skinned primitive has no {name}")
    vertices = read_accessor(gltf, blob, attributes.POSITION).astype(np.float32)
    if primitive.indices is None:
        faces = np.arange(vertices.shape[0], dtype=np.int64).reshape(-1, 3)
    else:
        faces = read_accessor(gltf, blob, primitive.indices).astype(np.int64).reshape(-1, 3)
    normals = None if attributes.NORMAL is None else read_accessor(gltf, blob, attributes.NORMAL)
    uv = None if attributes.TEXCOORD_0 is None else read_accessor(gltf, blob, attributes.TEXCOORD_0)
    colors = None
    if attributes.COLOR_0 is not None:
        colors = linear_to_srgb(read_accessor(gltf, blob, attributes.COLOR_0)[:, :3])
    skin = gltf.skins[node.skin]
    joint_nodes = list(skin.joints)
    slot = {n: k for k, n in enumerate(joint_nodes)}
    parents = np.full(len(joint_nodes), -1, dtype=np.int64)
    for k, n in enumerate(joint_nodes):
        for child in gltf.nodes[n].children or []:
            if child in slot:
                parents[slot[child]] = k
    if skin.inverseBindMatrices is None:
        inverse_bind = np.tile(np.eye(4), (len(joint_nodes), 1, 1))
    else:
        inverse_bind = np.transpose(
            read_accessor(gltf, blob, skin.inverseBindMatrices).reshape(-1, 4, 4), (0, 2, 1)
        ).astype(np.float64)
    bind = np.linalg.inv(inverse_bind)
    # Every JOINTS_n/WEIGHTS_n pair, in order (n = 0, 1, ...), as one (V, 4 * sets) array.
    joint_sets, weight_sets = [], []
    while getattr(attributes, f"JOINTS_{len(joint_sets)}", None) is not None:
        if getattr(attributes, f"WEIGHTS_{len(joint_sets)}", None) is None:
            raise InputError(f"{path}: the skinned primitive has JOINTS_{len(joint_sets)} without WEIGHTS_{len(joint_sets)}")
        weight_sets.append(getattr(attributes, f"WEIGHTS_{len(joint_sets)}"))
        joint_sets.append(getattr(attributes, f"JOINTS_{len(joint_sets)}"))
    return {
        "vertices": vertices,
        "faces": faces,
        "normals": normals,
        "uv": uv,
        "colors": colors,
        "joint_names": [gltf.nodes[n].name for n in joint_nodes],
        "parents": parents,
        "joints_bind": bind[:, :3, 3],
        "inverse_bind": inverse_bind,
        "joints": np.concatenate([read_accessor(gltf, blob, a).astype(np.int64) for a in joint_sets], axis=1),
        "weights": np.concatenate([read_accessor(gltf, blob, a).astype(np.float32) for a in weight_sets], axis=1),
        "world_to_gltf": _world_to_gltf(gltf),
        "world_to_gltf_offset": _recorded(gltf, "world_to_gltf_offset", np.zeros(3)),
    }


def _world_to_gltf(gltf: pygltflib.GLTF2) -> np.ndarray:
    """The igavatar writer's recorded world -> glTF rotation (identity for other files)."""
    return _recorded(gltf, "world_to_gltf", np.eye(3))


def _recorded(gltf: pygltflib.GLTF2, key: str, default: np.ndarray) -> np.ndarray:
    """An array the igavatar writer recorded in asset.extras.igavatar (`default` for other files)."""
    extras = gltf.asset.extras or {}
    if isinstance(extras, str):
        extras = json.loads(extras)
    recorded = extras.get("igavatar", {}).get(key) if isinstance(extras, dict) else None
    return default if recorded is None else np.asarray(recorded, dtype=np.float64)


def pose_glb_vertices(
    path: str | os.PathLike[str],
    local_rotations_rel_canonical: np.ndarray,
    root_translation: np.ndarray,
) -> np.ndarray:
    """Skin a GLB's mesh the glTF way under a pose.

    Replaces every skin joint node's rotation by the given one and adds `root_translation` to
    the root joint node's translation, composes node matrices down the node hierarchy, and skins
    with jointMatrix_k = global(joint k) @ inverseBindMatrix_k and every JOINTS_n/WEIGHTS_n set
    (the skinned node's own transform is ignored, as glTF specifies). Everything is in the file's
    (glTF) frame: convert a pose of igavatar's frame with `gltf_pose` first.

    Args:
        path: a GLB with one skinned mesh (e.g. from write_rigged_glb).
        local_rotations_rel_canonical: (J, 3, 3) joint rotations in skin-joint order.
        root_translation: (3,) offset added to the root joint's translation.
    Returns:
        (V, 3) float64 posed vertices in the file's frame.
    """
    gltf, blob = _load(path)
    node = _skinned_node(gltf, path)
    skin = gltf.skins[node.skin]
    joint_nodes = list(skin.joints)
    rotations = np.asarray(local_rotations_rel_canonical, dtype=np.float64)
    if rotations.shape != (len(joint_nodes), 3, 3):
        raise InputError(
            f"{path}: pose has shape {rotations.shape}, expected ({len(joint_nodes)}, 3, 3) for its skin"
        )
    rotation_of = {n: rotations[k] for k, n in enumerate(joint_nodes)}
    root = _skin_root(gltf, joint_nodes)
    translation_of = {root: np.asarray(root_translation, dtype=np.float64).reshape(3)}

    parent_of: dict[int, int] = {}
    for index, candidate in enumerate(gltf.nodes):
        for child in candidate.children or []:
            parent_of[child] = index
    cache: dict[int, np.ndarray] = {}

    def global_matrix(index: int) -> np.ndarray:
        if index not in cache:
            local = _node_matrix(gltf.nodes[index], rotation_of.get(index), translation_of.get(index))
            parent = parent_of.get(index)
            cache[index] = local if parent is None else global_matrix(parent) @ local
        return cache[index]

    data = _read_skinned(gltf, blob, path)
    joint_matrices = np.stack([global_matrix(n) for n in joint_nodes]) @ data["inverse_bind"]
    positions = np.concatenate(
        (data["vertices"].astype(np.float64), np.ones((data["vertices"].shape[0], 1))), axis=1
    )
    posed = np.zeros((positions.shape[0], 4))
    for k in range(data["joints"].shape[1]):
        matrices = joint_matrices[data["joints"][:, k]]  # (V, 4, 4)
        posed += data["weights"][:, k : k + 1].astype(np.float64) * np.einsum("vij,vj->vi", matrices, positions)
    return posed[:, :3]


def read_glb_animation(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray, float]:
    """The keyframes of a GLB's first animation, in pose_glb_vertices' terms.

    Returns:
        local rotations (N, J, 3, 3) in skin-joint order (identity for joints without a rotation
        channel), root translation offsets (N, 3) from the root node's bind translation, and the
        frame rate (from the animation's extras, else from the first two key times).
    """
    gltf, blob = _load(path)
    if not gltf.animations:
        raise InputError(f"{path}: the GLB has no animation")
    node = _skinned_node(gltf, path)
    joint_nodes = list(gltf.skins[node.skin].joints)
    slot = {n: k for k, n in enumerate(joint_nodes)}
    root = _skin_root(gltf, joint_nodes)
    animation = gltf.animations[0]
    times: np.ndarray | None = None
    rotations: np.ndarray | None = None
    translation: np.ndarray | None = None
    for channel in animation.channels:
        sampler = animation.samplers[channel.sampler]
        key_times = read_accessor(gltf, blob, sampler.input).astype(np.float64)
        if times is None:
            times = key_times
            rotations = np.tile(np.eye(3), (key_times.shape[0], len(joint_nodes), 1, 1))
            translation = np.zeros((key_times.shape[0], 3))
        elif key_times.shape != times.shape or not np.allclose(key_times, times):
            raise InputError(f"{path}: animation channels use different key times")
        values = read_accessor(gltf, blob, sampler.output).astype(np.float64)
        target = channel.target
        if target.path == "rotation" and target.node in slot:
            rotations[:, slot[target.node]] = [_quaternion_xyzw_to_matrix(q) for q in values]
        elif target.path == "translation" and target.node == root:
            translation[:] = values - np.asarray(gltf.nodes[root].translation or [0.0, 0.0, 0.0])
    if times is None:
        raise InputError(f"{path}: the GLB's animation has no channels")
    extras = animation.extras or {}
    if isinstance(extras, str):
        extras = json.loads(extras)
    if "fps" in extras:
        fps = float(extras["fps"])
    elif times.shape[0] > 1:
        fps = 1.0 / float(times[1] - times[0])
    else:
        fps = 0.0
    return rotations, translation, fps
