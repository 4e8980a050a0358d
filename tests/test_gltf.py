"""Rigged GLB export: round trips (pygltflib, trimesh), glTF-side skinning vs our FK + LBS, structure.

    .venv/bin/python -m pytest tests/test_gltf.py -q
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pygltflib
import pytest
import torch
import trimesh

from igavatar.body.rotations import axis_angle_to_matrix
from igavatar.body.skeleton import bone_transforms, forward_kinematics, linear_blend_skinning
from igavatar.errors import InputError
from igavatar.mesh.gltf import gltf_axes, floor_origin_offset, gltf_pose, linear_to_srgb, pose_relative_to_canonical, srgb_to_linear, top_k_weights, write_rigged_glb
from igavatar.mesh.gltf_read import gltf_to_world, pose_glb_vertices, read_glb_animation, read_rigged_glb

# A small humanoid-like tree: pelvis, spine, head, two arms of two joints, two legs of two joints.
PARENTS = np.array([-1, 0, 1, 1, 3, 1, 5, 0, 7, 0, 9])
NAMES = [
    "pelvis", "spine", "head", "l_shoulder", "l_elbow", "r_shoulder", "r_elbow",
    "l_hip", "l_knee", "r_hip", "r_knee",
]
REST = np.array([
    [0.0, 0.0, 0.9], [0.0, 0.0, 1.2], [0.0, 0.0, 1.55], [0.18, 0.0, 1.4], [0.45, 0.0, 1.4],
    [-0.18, 0.0, 1.4], [-0.45, 0.0, 1.4], [0.1, 0.0, 0.85], [0.1, 0.0, 0.45], [-0.1, 0.0, 0.85],
    [-0.1, 0.0, 0.45],
])


# The test subject is Z-up like Anny's frame; every GLB is written in glTF's Y-up frame.
AXES = gltf_axes("anny")


def to_gltf(points: np.ndarray, avatar: Avatar) -> np.ndarray:
    """Points of the (Z-up) test frame in the GLB's (Y-up) frame, origin on the floor under the root."""
    return np.asarray(points, dtype=np.float64) @ AXES.T + avatar.floor_offset


def glb_posed(path: Path, rotations: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """pose_glb_vertices of a pose given in the test frame, mapped back to the test frame."""
    offset = read_rigged_glb(path)["world_to_gltf_offset"]
    return gltf_to_world(pose_glb_vertices(path, *gltf_pose(AXES, rotations, translation)), AXES, offset)


def random_rotations(rng: np.random.Generator, shape: tuple[int, ...], scale: float) -> np.ndarray:
    rotvecs = torch.as_tensor(rng.normal(scale=scale, size=shape + (3,)), dtype=torch.float64)
    return axis_angle_to_matrix(rotvecs).numpy()


def fk(rotations: np.ndarray, translation: np.ndarray) -> torch.Tensor:
    return forward_kinematics(
        torch.as_tensor(rotations, dtype=torch.float64), REST, PARENTS,
        torch.as_tensor(translation, dtype=torch.float64),
    )


class Avatar:
    """A canonical (Da-pose-like) subject: points around the bones, smooth Gaussian weights."""

    def __init__(self, sigma: float = 0.06, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        self.canonical_rotations = random_rotations(rng, (len(PARENTS),), 0.25)
        self.canonical_translation = np.array([0.02, -0.01, 0.03])
        self.G_canonical = fk(self.canonical_rotations, self.canonical_translation)
        self.joints_canonical = self.G_canonical[:, :3, 3].numpy()
        # Points on the canonical bones plus noise: a stand-in for a body surface.
        child = np.arange(1, len(PARENTS))
        t = rng.random((600, 1))
        bone = rng.integers(0, child.shape[0], 600)
        a, b = self.joints_canonical[PARENTS[child[bone]]], self.joints_canonical[child[bone]]
        self.vertices = (a + t * (b - a) + rng.normal(scale=0.04, size=(600, 3))).astype(np.float32)
        distance = np.linalg.norm(self.vertices[:, None, :] - self.joints_canonical[None], axis=-1)
        weights = np.exp(-0.5 * (distance / sigma) ** 2) + 1e-12
        self.weights = weights / weights.sum(axis=1, keepdims=True)
        self.faces = rng.integers(0, 600, size=(900, 3))  # any valid index triples
        self.colors = rng.integers(0, 256, size=(600, 3)).astype(np.uint8)

    @property
    def floor_offset(self) -> np.ndarray:
        """The translation the writer adds after the axes: the origin on the floor under the root."""
        return floor_origin_offset(self.vertices.astype(np.float64) @ AXES.T, self.joints_canonical[0] @ AXES.T)

    def write(self, path: Path, **kwargs) -> Path:
        write_rigged_glb(
            path, self.vertices, self.faces, self.colors, NAMES, PARENTS, self.joints_canonical,
            self.weights, world_to_gltf=AXES, **kwargs,
        )
        return path

    def our_posed(self, rotations: np.ndarray, translation: np.ndarray, weights: np.ndarray) -> np.ndarray:
        transforms = bone_transforms(fk(rotations, translation), self.G_canonical)
        return linear_blend_skinning(
            torch.as_tensor(self.vertices, dtype=torch.float64),
            torch.as_tensor(weights, dtype=torch.float64), transforms,
        ).numpy()

    def top4_dense(self) -> np.ndarray:
        joints, weights = top_k_weights(self.weights)
        dense = np.zeros_like(self.weights)
        np.put_along_axis(dense, joints, weights.astype(np.float64), axis=1)
        return dense


@pytest.fixture(scope="module")
def avatar() -> Avatar:
    return Avatar()


# ------------------------------------------------------------------------------------------
# An independent structural validator (a subset of the Khronos validator's checks)

_SIZES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
_BYTES = {5121: 1, 5123: 2, 5125: 4, 5126: 4}


def validate_glb(path: Path) -> dict:
    data = path.read_bytes()
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    assert magic == b"glTF" and version == 2 and length == len(data)
    json_length, json_type = struct.unpack_from("<I4s", data, 12)
    assert json_type == b"JSON" and json_length % 4 == 0
    doc = json.loads(data[20 : 20 + json_length])
    bin_offset = 20 + json_length
    bin_length, bin_type = struct.unpack_from("<I4s", data, bin_offset)
    assert bin_type == b"BIN\0" and bin_length % 4 == 0 and (bin_offset + 8) % 4 == 0
    assert bin_offset + 8 + bin_length == len(data)
    blob = data[bin_offset + 8 :]

    assert doc["asset"]["version"] == "2.0"
    assert len(doc["buffers"]) == 1 and doc["buffers"][0]["byteLength"] <= bin_length
    for view in doc["bufferViews"]:
        assert view.get("byteOffset", 0) % 4 == 0
        assert view.get("byteOffset", 0) + view["byteLength"] <= doc["buffers"][0]["byteLength"]
    for accessor in doc["accessors"]:
        view = doc["bufferViews"][accessor["bufferView"]]
        size = _SIZES[accessor["type"]] * _BYTES[accessor["componentType"]]
        assert accessor.get("byteOffset", 0) % 4 == 0
        assert accessor.get("byteOffset", 0) + accessor["count"] * size <= view["byteLength"]
        assert "byteStride" not in view or view["byteStride"] % 4 == 0

    def read(index: int) -> np.ndarray:
        accessor = doc["accessors"][index]
        view = doc["bufferViews"][accessor["bufferView"]]
        dtype = {5121: np.uint8, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}[accessor["componentType"]]
        start = view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
        count = accessor["count"] * _SIZES[accessor["type"]]
        return np.frombuffer(blob, dtype=dtype, count=count, offset=start).reshape(accessor["count"], -1)

    nodes = doc["nodes"]
    names = [n.get("name") for n in nodes]
    assert len(set(names)) == len(names)
    parent_count = np.zeros(len(nodes), int)
    for node in nodes:
        for child in node.get("children", []):
            parent_count[child] += 1
    assert parent_count.max() <= 1  # a forest: no node with two parents
    assert all(node.get("children", [0]) for node in nodes)  # children, if present, is non-empty
    assert all(parent_count[n] == 0 for n in doc["scenes"][doc["scene"]]["nodes"])

    (primitive,) = doc["meshes"][0]["primitives"]
    assert primitive.get("mode", 4) == 4
    attributes = primitive["attributes"]
    position = doc["accessors"][attributes["POSITION"]]
    values = read(attributes["POSITION"])
    assert position["min"] == pytest.approx(values.min(axis=0).tolist())
    assert position["max"] == pytest.approx(values.max(axis=0).tolist())
    num_vertices = position["count"]
    for name in ("NORMAL", "COLOR_0", "JOINTS_0", "WEIGHTS_0"):
        assert doc["accessors"][attributes[name]]["count"] == num_vertices
        assert doc["bufferViews"][doc["accessors"][attributes[name]]["bufferView"]].get("target") == 34962
    indices = read(primitive["indices"])
    assert doc["bufferViews"][doc["accessors"][primitive["indices"]]["bufferView"]]["target"] == 34963
    assert indices.max() < num_vertices and indices.shape[0] % 3 == 0
    np.testing.assert_allclose(np.linalg.norm(read(attributes["NORMAL"]), axis=1), 1.0, atol=1e-5)
    colors = read(attributes["COLOR_0"])
    assert colors.min() >= 0 and colors.max() <= 1

    skin = doc["skins"][0]
    num_joints = len(skin["joints"])
    assert all(0 <= j < len(nodes) for j in skin["joints"])
    inverse_bind = read(skin["inverseBindMatrices"]).reshape(-1, 4, 4).transpose(0, 2, 1)
    assert inverse_bind.shape[0] == num_joints
    np.testing.assert_array_equal(inverse_bind[:, 3], np.tile([0, 0, 0, 1], (num_joints, 1)))
    sets = 1 + ("JOINTS_1" in attributes)
    for name in ("JOINTS_1", "WEIGHTS_1")[: 2 * (sets - 1)]:
        assert doc["accessors"][attributes[name]]["count"] == num_vertices
    joints = np.concatenate([read(attributes[f"JOINTS_{n}"]) for n in range(sets)], axis=1)
    weights = np.concatenate([read(attributes[f"WEIGHTS_{n}"]) for n in range(sets)], axis=1)
    assert joints.max() < num_joints and weights.min() >= 0
    # The validator's tolerance: |sum - 1| <= 2e-7 x the number of non-zero weights.
    assert np.all(np.abs(weights.sum(axis=1, dtype=np.float32) - 1) <= 2e-7 * (weights > 0).sum(axis=1))
    assert np.all(joints[weights == 0] == 0)

    for animation in doc.get("animations", []):
        for sampler in animation["samplers"]:
            times = doc["accessors"][sampler["input"]]
            assert "min" in times and "max" in times
            assert np.all(np.diff(read(sampler["input"])[:, 0]) > 0)
        for channel in animation["channels"]:
            assert channel["target"]["path"] in ("rotation", "translation")
            if channel["target"]["path"] == "rotation":
                q = read(animation["samplers"][channel["sampler"]]["output"])
                np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)
    return doc


# ------------------------------------------------------------------------------------------


def test_round_trip_pygltflib_and_trimesh(tmp_path, avatar):
    path = avatar.write(tmp_path / "avatar.glb")
    doc = validate_glb(path)
    assert doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["JOINTS_0"]]["componentType"] == 5121

    data = read_rigged_glb(path)
    np.testing.assert_allclose(data["vertices"], to_gltf(avatar.vertices, avatar), atol=1e-6)
    np.testing.assert_array_equal(data["world_to_gltf"], AXES)
    np.testing.assert_array_equal(data["faces"], avatar.faces)
    assert data["joint_names"] == NAMES
    np.testing.assert_array_equal(data["parents"], PARENTS)
    np.testing.assert_allclose(data["joints_bind"], to_gltf(avatar.joints_canonical, avatar), atol=1e-6)
    # Colors are stored linear (glTF) and come back as the sRGB values written.
    np.testing.assert_array_equal(np.round(data["colors"] * 255).astype(np.uint8), avatar.colors)
    np.testing.assert_allclose(data["weights"].sum(axis=1), 1.0, atol=3e-7)
    joints, weights = top_k_weights(avatar.weights)
    np.testing.assert_array_equal(data["joints"], joints)
    np.testing.assert_array_equal(data["weights"], weights)

    gltf = pygltflib.GLTF2.load(str(path))
    assert [gltf.nodes[j].name for j in gltf.skins[0].joints] == NAMES
    assert gltf.materials[0].pbrMetallicRoughness.metallicFactor == 0.0

    scene = trimesh.load(path, process=False)
    (mesh,) = scene.geometry.values()
    assert mesh.vertices.shape == avatar.vertices.shape and mesh.faces.shape == avatar.faces.shape
    np.testing.assert_array_equal(mesh.faces, avatar.faces)
    np.testing.assert_allclose(mesh.vertices, to_gltf(avatar.vertices, avatar), atol=1e-6)
    plain = trimesh.load(path, process=False, skip_materials=True)
    (plain_mesh,) = plain.geometry.values()
    linear = srgb_to_linear(avatar.colors / 255.0)
    assert np.abs(plain_mesh.visual.vertex_colors[:, :3] / 255.0 - linear).max() < 1.0 / 255 + 1e-6
    assert {gltf.nodes[n].name for n in range(len(NAMES))} <= set(scene.graph.nodes)


def test_glb_is_y_up_head_above_the_feet(tmp_path, avatar):
    """Read back with pygltflib alone: the head joint and the head's vertices lie above the knees
    along +Y (glTF's up), and the body's height is not along Z (as a Z-up file would have it)."""
    path = avatar.write(tmp_path / "avatar.glb")
    gltf = pygltflib.GLTF2.load(str(path))
    translations = {n.name: np.array(n.translation) for n in gltf.nodes if n.translation is not None}
    pelvis = translations["pelvis"]
    head = pelvis + translations["spine"] + translations["head"]
    knee = pelvis + translations["l_knee"] + translations["l_hip"]
    up = head - knee  # ~1.1 m in the rest pose, tilted by the random canonical rotations
    assert up[1] > 0.7 and up[1] > 3 * max(abs(up[0]), abs(up[2]))
    accessor = gltf.accessors[gltf.meshes[0].primitives[0].attributes.POSITION]
    extent = np.array(accessor.max) - np.array(accessor.min)
    assert extent[1] > extent[0] and extent[1] > 2 * extent[2]  # tall along Y, thin along Z
    # The subject faces +Z: the glTF frame's forward; the Anny frame's forward was -Y.
    np.testing.assert_allclose(AXES @ np.array([0.0, -1.0, 0.0]), [0.0, 0.0, 1.0])


def test_eight_influences_sum_to_one_and_skin_closer_than_four(tmp_path):
    avatar = Avatar(sigma=0.2, seed=6)  # wide weights: the 5th..8th joints matter
    path4 = avatar.write(tmp_path / "four.glb")
    path8 = avatar.write(tmp_path / "eight.glb", influences=8)
    doc = validate_glb(path8)
    attributes = doc["meshes"][0]["primitives"][0]["attributes"]
    assert {"JOINTS_0", "JOINTS_1", "WEIGHTS_0", "WEIGHTS_1"} <= set(attributes)
    assert "JOINTS_1" not in validate_glb(path4)["meshes"][0]["primitives"][0]["attributes"]
    data = read_rigged_glb(path8)
    assert data["joints"].shape == (600, 8) and data["weights"].shape == (600, 8)
    np.testing.assert_allclose(data["weights"].sum(axis=1, dtype=np.float64), 1.0, atol=1e-6)
    joints, weights = top_k_weights(avatar.weights, 8)
    np.testing.assert_array_equal(data["joints"], joints)
    np.testing.assert_array_equal(data["weights"], weights)
    assert np.all(np.diff(data["weights"], axis=1) <= 0)  # largest first, across both sets

    rng = np.random.default_rng(7)
    rotations = random_rotations(rng, (len(PARENTS),), 0.5)
    translation = rng.normal(scale=0.2, size=3)
    full = avatar.our_posed(rotations, translation, avatar.weights)
    relative, offset = pose_relative_to_canonical(
        rotations, translation, avatar.canonical_rotations, avatar.canonical_translation, PARENTS
    )
    gap4 = np.abs(glb_posed(path4, relative, offset) - full).max()
    gap8 = np.abs(glb_posed(path8, relative, offset) - full).max()
    assert gap8 < 0.5 * gap4, (gap4, gap8)
    dense8 = np.zeros_like(avatar.weights)
    np.put_along_axis(dense8, joints, weights.astype(np.float64), axis=1)
    np.testing.assert_allclose(glb_posed(path8, relative, offset), avatar.our_posed(rotations, translation, dense8), atol=1e-4)


def test_srgb_transfer_round_trip():
    x = np.linspace(0.0, 1.0, 1001)
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(x)), x, atol=1e-12)
    assert srgb_to_linear(np.array(0.5)) == pytest.approx(0.21404, abs=1e-5)


def test_top_k_weights():
    weights = np.array([[0.1, 0.5, 0.0, 0.2, 0.15, 0.05], [0.0, 0.0, 1.0, 0.0, 0.0, 0.0]])
    joints, top = top_k_weights(weights)
    np.testing.assert_array_equal(joints, [[1, 3, 4, 0], [2, 0, 0, 0]])
    np.testing.assert_allclose(top[0], np.array([0.5, 0.2, 0.15, 0.1]) / 0.95, rtol=1e-6)
    np.testing.assert_array_equal(top[1], [1.0, 0.0, 0.0, 0.0])
    assert top.dtype == np.float32 and np.all(top.sum(axis=1, dtype=np.float32) == pytest.approx(1.0, abs=2e-7))
    with pytest.raises(InputError, match="vertex 0"):
        top_k_weights(np.zeros((1, 6)))
    joints, top = top_k_weights(np.array([[0.3, 0.7]]))  # fewer joints than influences
    np.testing.assert_array_equal(joints, [[1, 0, 0, 0]])
    np.testing.assert_allclose(top, [[0.7, 0.3, 0.0, 0.0]], rtol=1e-6)


def test_identity_pose_is_the_canonical_mesh(tmp_path, avatar):
    path = avatar.write(tmp_path / "avatar.glb")
    posed = pose_glb_vertices(path, np.tile(np.eye(3), (len(PARENTS), 1, 1)), np.zeros(3))
    np.testing.assert_allclose(posed, to_gltf(avatar.vertices, avatar), atol=1e-6)


def test_glb_skinning_matches_forward_kinematics(tmp_path, avatar):
    path = avatar.write(tmp_path / "avatar.glb")
    rng = np.random.default_rng(1)
    weights4 = avatar.top4_dense()
    for _ in range(3):
        rotations = random_rotations(rng, (len(PARENTS),), 0.6)
        translation = rng.normal(scale=0.3, size=3)
        ours = avatar.our_posed(rotations, translation, weights4)
        relative, offset = pose_relative_to_canonical(
            rotations, translation, avatar.canonical_rotations, avatar.canonical_translation, PARENTS
        )
        glb = glb_posed(path, relative, offset)
        assert np.abs(glb - ours).max() < 1e-4
        assert np.abs(ours - avatar.vertices).max() > 0.05  # a real pose, not a no-op
        # The conversion matters: rest-relative rotations fed straight to the GLB are wrong.
        naive = glb_posed(path, rotations, translation)
        assert np.abs(naive - ours).max() > 0.01
        # So do the axes: the pose's own frame fed to the Y-up file is wrong too.
        assert np.abs(pose_glb_vertices(path, relative, offset) @ AXES - ours).max() > 0.01


def test_top4_is_close_to_full_weights_for_smooth_weights(tmp_path):
    avatar = Avatar(sigma=0.04, seed=3)
    joints, _ = top_k_weights(avatar.weights)
    mass = np.take_along_axis(avatar.weights, joints, axis=1).sum(axis=1)
    assert mass.min() > 0.999  # the premise: the top 4 hold nearly all the weight
    path = avatar.write(tmp_path / "avatar.glb")
    rng = np.random.default_rng(4)
    rotations = random_rotations(rng, (len(PARENTS),), 0.4)
    translation = rng.normal(scale=0.2, size=3)
    full = avatar.our_posed(rotations, translation, avatar.weights)
    relative, offset = pose_relative_to_canonical(
        rotations, translation, avatar.canonical_rotations, avatar.canonical_translation, PARENTS
    )
    glb = glb_posed(path, relative, offset)
    assert np.abs(glb - full).max() < 1e-3


def test_animation_keyframes_round_trip_and_pose(tmp_path, avatar):
    rng = np.random.default_rng(5)
    frames = 4
    rotations = random_rotations(rng, (frames, len(PARENTS)), 0.5)
    translation = rng.normal(scale=0.2, size=(frames, 3))
    relative, offset = pose_relative_to_canonical(
        rotations, translation, avatar.canonical_rotations, avatar.canonical_translation, PARENTS
    )
    path = avatar.write(tmp_path / "animated.glb", animation=(relative, offset, 24.0))
    doc = validate_glb(path)
    assert len(doc["animations"][0]["channels"]) == len(PARENTS) + 1

    keys_rotations, keys_translation, fps = read_glb_animation(path)
    assert fps == 24.0
    expected_rotations, expected_offset = gltf_pose(AXES, relative, offset)
    np.testing.assert_allclose(keys_rotations, expected_rotations, atol=1e-6)
    np.testing.assert_allclose(keys_translation, expected_offset, atol=1e-6)
    weights4 = avatar.top4_dense()
    for n in range(frames):
        ours = avatar.our_posed(rotations[n], translation[n], weights4)
        glb = pose_glb_vertices(path, keys_rotations[n], keys_translation[n])
        assert np.abs(glb - to_gltf(ours, avatar)).max() < 1e-4


def test_quaternion_hemisphere_is_continuous(tmp_path, avatar):
    # Rotations about z by 0 .. 330 degrees: w changes sign past 180, stored keys must not flip.
    angles = np.deg2rad(np.arange(0, 360, 30))
    per_frame = axis_angle_to_matrix(torch.tensor([[0.0, 0.0, a] for a in angles], dtype=torch.float64)).numpy()
    rotations = np.tile(np.eye(3), (angles.shape[0], len(PARENTS), 1, 1))
    rotations[:, 2] = per_frame
    path = avatar.write(tmp_path / "spin.glb", animation=(rotations, np.zeros((angles.shape[0], 3)), 10.0))
    gltf = pygltflib.GLTF2.load(str(path))
    animation = gltf.animations[0]
    channel = next(c for c in animation.channels if c.target.node == 2 and c.target.path == "rotation")
    accessor = gltf.accessors[animation.samplers[channel.sampler].output]
    view = gltf.bufferViews[accessor.bufferView]
    q = np.frombuffer(gltf.binary_blob(), np.float32, accessor.count * 4, view.byteOffset).reshape(-1, 4)
    assert np.all((q[1:] * q[:-1]).sum(axis=1) > 0)
    keys, _, _ = read_glb_animation(path)
    np.testing.assert_allclose(keys[:, 2], AXES @ per_frame @ AXES.T, atol=1e-6)


def test_many_joints_use_unsigned_short(tmp_path):
    num_joints = 300
    parents = np.arange(-1, num_joints - 1)  # a chain
    joints = np.stack([np.zeros(num_joints), np.zeros(num_joints), np.linspace(0, 3, num_joints)], axis=1)
    vertices = (joints + np.array([0.05, 0.0, 0.0])).astype(np.float32)
    weights = np.eye(num_joints)
    faces = np.stack([np.arange(num_joints - 2), np.arange(1, num_joints - 1), np.arange(2, num_joints)], 1)
    path = tmp_path / "chain.glb"
    write_rigged_glb(
        path, vertices, faces, np.full((num_joints, 3), 0.5), [f"j{i}" for i in range(num_joints)],
        parents, joints, weights, world_to_gltf=np.eye(3),
    )
    doc = validate_glb(path)
    assert doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["JOINTS_0"]]["componentType"] == 5123
    data = read_rigged_glb(path)
    np.testing.assert_array_equal(data["joints"][:, 0], np.arange(num_joints))
    # Bend the last joint by 90 degrees about y: the last vertex swings around it.
    rotations = np.tile(np.eye(3), (num_joints, 1, 1))
    rotations[-1] = axis_angle_to_matrix(torch.tensor([0.0, np.pi / 2, 0.0], dtype=torch.float64)).numpy()
    posed = pose_glb_vertices(path, rotations, np.zeros(3))
    np.testing.assert_allclose(posed[:-1], vertices[:-1], atol=1e-6)
    np.testing.assert_allclose(posed[-1], joints[-1] + np.array([0.0, 0.0, -0.05]), atol=1e-6)


def test_bad_inputs_raise_input_error(tmp_path, avatar):
    def write(**changes):
        arguments = dict(
            vertices=avatar.vertices, faces=avatar.faces, colors=avatar.colors, joint_names=NAMES,
            parents=PARENTS, joints_canonical=avatar.joints_canonical, skin_weights=avatar.weights,
            world_to_gltf=AXES,
        )
        arguments.update(changes)
        write_rigged_glb(tmp_path / "bad.glb", **arguments)

    with pytest.raises(InputError, match="colors"):
        write(colors=np.full((600, 3), 1.5))
    with pytest.raises(InputError, match="skin_weights"):
        write(skin_weights=avatar.weights[:, :5])
    with pytest.raises(InputError, match="faces index"):
        write(faces=np.array([[0, 1, 600]]))
    with pytest.raises(InputError, match="joint_names"):
        write(joint_names=NAMES[:-1])
    with pytest.raises(InputError, match="vertex 0"):
        write(skin_weights=np.zeros_like(avatar.weights))
    with pytest.raises(InputError, match="rotations"):
        write(animation=(np.ones((2, len(PARENTS), 3, 3)), np.zeros((2, 3)), 30.0))
    with pytest.raises(InputError, match="influences"):
        write(influences=6)
    with pytest.raises(InputError, match="world_to_gltf"):
        write(world_to_gltf=np.diag([1.0, 1.0, -1.0]))  # a mirror, not a rotation
    with pytest.raises(InputError, match="fps"):
        write(animation=(np.tile(np.eye(3), (2, len(PARENTS), 1, 1)), np.zeros((2, 3)), 0.0))
    assert not (tmp_path / "bad.glb").exists()
    with pytest.raises(InputError, match="not found"):
        read_rigged_glb(tmp_path / "missing.glb")
