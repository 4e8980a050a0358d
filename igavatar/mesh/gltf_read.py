"""Reading igavatar's GLBs back, independently of the writer and of igavatar.body's kinematics, so
that tests and interop checks can use it to check both.

    data = read_rigged_glb("avatar.glb")          # vertices, faces, joints, weights... in glTF's frame
    world = gltf_to_world(data["vertices"], data["world_to_gltf"], data["world_to_gltf_offset"])
    x_posed = pose_glb_vertices("avatar.glb", rotations_rel_canonical, root_translation)
    rotations, translations, fps = read_glb_animation("avatar.glb")

Accessors are decoded and node matrices composed here, by the glTF 2.0 rules alone.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import pygltflib

from igavatar.errors import InputError
from igavatar.mesh.gltf import linear_to_srgb


def gltf_to_world(points_gltf: np.ndarray, world_to_gltf: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """(N, 3) points of an igavatar GLB back in the capture's frame (x_gltf = R x_world + offset)."""
    return (np.asarray(points_gltf, np.float64) - np.asarray(offset, np.float64)) @ np.asarray(world_to_gltf, np.float64)


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
