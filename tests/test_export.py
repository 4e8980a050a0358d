"""`igavatar export`: analytic spheres, a tiny model's canonical/posed meshes, GLB round trip, maps, bad inputs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pygltflib
import pytest
import torch
import trimesh

from igavatar.artifacts.manifest import read_artifact
from igavatar.body.rotations import axis_angle_to_matrix, rigid_matrix
from igavatar.body.skeleton import SMPL_JOINT_NAMES, SMPL_PARENTS, Skeleton
from igavatar.capture.subject import pose_frames
from igavatar.errors import InputError, NotAvailableError
from igavatar.mesh.cleanup import is_watertight
from igavatar.mesh.exr import read_exr
from igavatar.mesh.gltf import gltf_axes, gltf_pose, linear_to_srgb, pose_relative_to_canonical
from igavatar.mesh.gltf_read import gltf_to_world, pose_glb_vertices, read_glb_animation, read_rigged_glb
from igavatar.body.pose_files import local_pose_from_bone_transforms, read_pose_sequence, sequence_local_pose
from igavatar.model.avatar import Avatar
from igavatar.model.fields import silhouette_offset
from igavatar.training.config import preset
from igavatar_cli.main import app
from igavatar.avatar.model import load_model
from igavatar.avatar.surfaces import canonical_surface, posed_surface
from igavatar.mesh.maps import frontal_camera, mesh_maps
from igavatar.model.posed import PosedAvatar
from stages.export import ExportOptions, run_export

RESOLUTION = 40  # marching cubes samples: small so the module stays fast on two cores


class SphereSDF(torch.nn.Module):
    """An exact sphere SDF with the SDFField interface (zero features), to test extraction exactly."""

    def __init__(self, center: tuple[float, float, float], radius: float, feature_dim: int) -> None:
        super().__init__()
        self.register_buffer("centre", torch.tensor(center))
        self.radius = radius
        self.feature_dim = feature_dim

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        sdf = (x - self.centre).norm(dim=-1) - self.radius
        return sdf, torch.cat((sdf[:, None], torch.zeros(x.shape[0], self.feature_dim - 1)), dim=1)

    def forward_with_gradient(self, x: torch.Tensor):
        sdf, feature = self.forward(x)
        return sdf, feature, torch.nn.functional.normalize(x - self.centre, dim=-1)


def sphere_avatar(half_size: float, radius: float, center=(0.0, 0.0, 0.0)) -> Avatar:
    """A one-bone avatar whose canonical SDF is an exact sphere inside a cubic canonical box."""
    config = preset("tiny").avatar
    box = torch.tensor([[-half_size] * 3, [half_size] * 3])
    avatar = Avatar(config, box, torch.ones(1, 4, 4, 4), box[0] - 0.2, box[1] + 0.2, pose_dim=3, init_bones=(0,))
    avatar.sdf_field = SphereSDF(center, radius, config.sdf.feature_dim)
    return avatar.eval()  # mesh it at surface_level="zero": the sphere itself


@pytest.fixture(scope="module")
def posed_export(small_run, tiny_model, tmp_path_factory) -> Path:
    """Every frame of the capture, non-rigid offsets on, maps on."""
    out = tmp_path_factory.mktemp("mesh") / "mesh"
    run_export(ExportOptions(model=tiny_model, out=out, resolution=RESOLUTION, pose=small_run / "capture",
                             all_frames=True, exr=True, exr_size=48, device="cpu"))
    return out


# ------------------------------------------------------------------------------------------------
# Analytic spheres


def test_sphere_canonical_mesh_has_the_radius_and_is_watertight():
    radius, center = 0.45, np.array([0.05, -0.1, 0.02])
    avatar = sphere_avatar(0.7, radius, tuple(center))
    vertices, faces = canonical_surface(avatar, resolution=48, coarse_resolution=24, surface_level="zero")
    distance = np.linalg.norm(vertices - center, axis=1)
    # Linear interpolation along grid edges cuts chords: about h^2 / (8 r) inside, h ~ 2.5 cm here.
    assert np.abs(distance - radius).max() < 5e-4
    assert is_watertight(vertices, faces)
    # Outward winding: the signed volume is the sphere's (to the discretisation's precision).
    assert trimesh.Trimesh(vertices, faces, process=False).volume == pytest.approx(4 / 3 * np.pi * radius**3, rel=0.02)


def test_the_silhouette_level_mesh_is_the_sphere_grown_by_the_silhouette_offset():
    radius = 0.3
    avatar = sphere_avatar(0.6, radius)
    avatar.density.set_ceiling(0.002)  # beta = 2 mm
    offset = silhouette_offset(0.002)
    assert avatar.surface_level("silhouette") == pytest.approx(offset) and 0.0045 < offset < 0.0065  # ~2.7 beta at r = 10 cm
    vertices, _ = canonical_surface(avatar, resolution=48, coarse_resolution=24, surface_level="silhouette")
    assert np.abs(np.linalg.norm(vertices, axis=1) - (radius + offset)).max() < 5e-4
    vertices, _ = canonical_surface(avatar, resolution=48, coarse_resolution=24, surface_level="zero")
    assert np.abs(np.linalg.norm(vertices, axis=1) - radius).max() < 5e-4


def test_a_surface_reaching_the_canonical_box_is_capped_closed():
    avatar = sphere_avatar(0.4, 0.5)
    vertices, faces = canonical_surface(avatar, resolution=40, coarse_resolution=20, surface_level="zero")
    assert is_watertight(vertices, faces)
    assert np.abs(vertices).max() <= 0.4 + 1e-5
    on_box = np.isclose(np.abs(vertices), 0.4, atol=1e-4).any(axis=1)
    assert on_box.sum() > 100 and (~on_box).sum() > 100  # box faces and sphere caps both present


def test_posed_marching_and_lbs_posing_of_a_rigid_sphere_agree():
    radius = 0.3
    avatar = sphere_avatar(0.5, radius)
    transform = rigid_matrix(axis_angle_to_matrix(torch.tensor([0.3, -0.2, 0.5])), torch.tensor([0.2, 0.1, -0.3]))
    posed_avatar = PosedAvatar.of(avatar, transform[None], torch.zeros(3))
    vertices, faces = canonical_surface(avatar, resolution=32, coarse_resolution=16, surface_level="zero")
    posed = posed_avatar.pose_vertices(vertices)
    expected = vertices @ transform[:3, :3].numpy().T + transform[:3, 3].numpy()
    np.testing.assert_allclose(posed, expected, atol=1e-5)
    marched, marched_faces = posed_surface(posed_avatar, np.full(3, -0.7), np.full(3, 0.6), resolution=32,
                                           coarse_resolution=16, surface_level="zero")
    assert is_watertight(marched, marched_faces)
    assert np.abs(np.linalg.norm(marched - transform[:3, 3].numpy(), axis=1) - radius).max() < 2e-3


def test_depth_and_normal_maps_of_a_sphere_from_the_frontal_camera():
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.5)
    vertices = np.asarray(sphere.vertices) + [0.1, 0.2, 1.0]
    colors = np.full((vertices.shape[0], 3), 255, np.uint8)
    axes = np.stack(([1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]), axis=1)  # Anny: left +X, up +Z, forward -Y
    K, w2c = frontal_camera(vertices, axes, size=65)
    maps = mesh_maps(vertices, np.asarray(sphere.faces), colors, K, w2c, 65)
    center_camera = w2c[:3, :3] @ np.array([0.1, 0.2, 1.0]) + w2c[:3, 3]
    assert center_camera[:2] == pytest.approx([0, 0], abs=1e-9)  # looks at the center
    camera_position = -w2c[:3, :3].T @ w2c[:3, 3]
    assert (camera_position - [0.1, 0.2, 1.0]) @ [0, -1, 0] > 0  # in front of the face (-Y)
    assert maps["A"][32, 32] == 1 and maps["A"][0, 0] == 0
    assert maps["Z"][32, 32] == pytest.approx(center_camera[2] - 0.5, abs=2e-3)
    np.testing.assert_allclose(maps["N"][32, 32], [0, -1, 0], atol=0.02)  # facing the camera
    hit = maps["A"] > 0
    assert np.allclose(np.linalg.norm(maps["N"][hit], axis=-1), 1, atol=1e-4)
    assert np.allclose(maps["RGB"][hit], 1.0, atol=1e-5) and (maps["Z"][~hit] == 0).all()
    # The whole silhouette fits in the image with a margin.
    rows, cols = np.nonzero(hit)
    assert rows.min() > 0 and cols.min() > 0 and rows.max() < 64 and cols.max() < 64


# ------------------------------------------------------------------------------------------------
# Pose files


def test_smpl_formats_are_read_and_refused_for_an_anny_skeleton(tmp_path):
    rng = np.random.default_rng(0)
    poses72, trans = rng.normal(0, 0.2, (3, 72)), rng.normal(0, 1, (3, 3))
    np.savez(tmp_path / "aist.npz", poses=poses72, trans=trans)
    np.savez(tmp_path / "split.npz", global_orient=poses72[:, :3], body_pose=poses72[:, 3:], transl=trans, betas=np.zeros((1, 10)))
    amass = np.concatenate((poses72[:, :66], rng.normal(0, 0.2, (3, 90))), axis=1)
    np.savez(tmp_path / "amass.npz", poses=amass, trans=trans, mocap_framerate=np.array(120.0), gender=np.array("male"))
    sequences = {name: read_pose_sequence(tmp_path / f"{name}.npz") for name in ("aist", "split", "amass")}
    assert [s.format for s in sequences.values()] == ["smpl-poses", "smpl-split", "smpl-amass"]
    np.testing.assert_array_equal(sequences["split"].rotvecs, sequences["aist"].rotvecs)
    np.testing.assert_array_equal(sequences["amass"].rotvecs[:, :22], sequences["aist"].rotvecs[:, :22])
    assert (sequences["amass"].rotvecs[:, 22:] == 0).all() and sequences["amass"].fps == 120.0

    # An avatar with SMPL's tree takes them as they are; Anny avatars get a retarget
    # (tests/test_retarget.py), which needs Anny's joint names; other skeletons are refused.
    smpl = Skeleton(np.array(SMPL_PARENTS), np.random.default_rng(1).normal(size=(24, 3)), SMPL_JOINT_NAMES)
    rotations, translation = sequence_local_pose(sequences["aist"], smpl, "smpl")
    np.testing.assert_allclose(rotations.numpy(), axis_angle_to_matrix(torch.tensor(poses72).reshape(3, 24, 3)).numpy(), atol=1e-6)
    np.testing.assert_allclose(translation.numpy(), trans, atol=1e-6)
    parents = np.array([-1] + [max(0, j - 1) for j in range(1, 104)])
    anny_like = Skeleton(parents, np.zeros((104, 3)), tuple(f"bone{j}" for j in range(104)))
    with pytest.raises(InputError, match=r"cannot retarget .* to Anny \(104 joints\): .*target skeleton lacks 20 of the anny joints"):
        sequence_local_pose(sequences["amass"], anny_like, "anny", phenotype={})
    with pytest.raises(NotAvailableError, match=r"SMPL pose sequence .* skeleton is a bare skeleton \(104 joints\).*only to anny"):
        sequence_local_pose(sequences["amass"], anny_like, "skeleton")


def test_skeleton_sequences_need_the_same_tree(tmp_path):
    parents = np.array([-1, 0, 1])
    rest = np.array([[0, 0, 0], [0, 0.3, 0], [0, 0.6, 0]])
    rotvecs = np.random.default_rng(2).normal(0, 0.3, (4, 3, 3))
    np.savez(tmp_path / "s.npz", parents=parents, rest_joints=rest, rotvecs=rotvecs, transl=np.ones((4, 3)))
    sequence = read_pose_sequence(tmp_path / "s.npz").select([3, 1])
    assert sequence.frame_names == ("00003", "00001")
    rotations, translation = sequence_local_pose(sequence, Skeleton(parents, rest * 2, ("a", "b", "c")), "skeleton")
    np.testing.assert_allclose(rotations.numpy(), axis_angle_to_matrix(torch.tensor(rotvecs[[3, 1]])).numpy(), atol=1e-6)
    with pytest.raises(InputError, match="another skeleton"):
        sequence_local_pose(sequence, Skeleton(np.array([-1, 0, 0]), rest, ("a", "b", "c")), "skeleton")
    with pytest.raises(InputError, match=r"frame 9 is out of range; the sequence has 4 frames"):
        read_pose_sequence(tmp_path / "s.npz").select([9])


@pytest.mark.parametrize("arrays, message", [
    ({"pose_parameters": np.zeros((2, 104, 4, 3))}, r"key 'pose_parameters' has shape \(2, 104, 4, 3\)"),
    ({"poses": np.zeros((2, 165)), "trans": np.zeros((2, 3))}, r"key 'poses' has shape \(2, 165\)"),
    ({"global_orient": np.zeros((2, 3)), "body_pose": np.zeros((3, 69)), "transl": np.zeros((2, 3))}, "key 'body_pose'"),
    ({"poses": np.zeros((2, 72))}, "key 'trans' missing"),
    ({"weird": np.zeros(3)}, "not a pose sequence igavatar knows"),
])
def test_malformed_pose_files_name_the_key_and_shape(tmp_path, arrays, message):
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(InputError, match=message):
        read_pose_sequence(tmp_path / "bad.npz")


def test_local_pose_from_bone_transforms_inverts_pose_frames():
    rng = np.random.default_rng(3)
    parents = np.array([-1, 0, 1, 1, 3])
    rest = torch.tensor(rng.normal(size=(5, 3)))
    canonical = axis_angle_to_matrix(torch.tensor(rng.normal(0, 0.3, (5, 3))))
    rotations = axis_angle_to_matrix(torch.tensor(rng.normal(0, 0.5, (6, 5, 3))))
    translation = torch.tensor(rng.normal(size=(6, 3)))
    frames = pose_frames(parents, rest, canonical, rotations, translation)
    got_rotations, got_translation = local_pose_from_bone_transforms(frames.bone_transforms, parents, rest, canonical)
    np.testing.assert_allclose(got_rotations.numpy(), rotations.numpy(), atol=1e-9)
    np.testing.assert_allclose(got_translation.numpy(), translation.numpy(), atol=1e-9)


# ------------------------------------------------------------------------------------------------
# A trained tiny model


def test_export_writes_a_valid_closed_colored_mesh_artifact(posed_export, small_run):
    manifest = read_artifact(posed_export, expected="mesh")
    data = manifest["data"]
    canonical = data["canonical"]
    assert canonical["watertight"] and canonical["resolution"] == RESOLUTION and canonical["vertices"] > 100
    assert set(canonical["files"]) == {"canonical.ply", "canonical.obj", "canonical.glb"}
    ply = trimesh.load(posed_export / "canonical.ply", process=False)
    obj = trimesh.load(posed_export / "canonical.obj", process=False)
    assert len(ply.vertices) == canonical["vertices"] and len(ply.faces) == canonical["faces"]
    np.testing.assert_allclose(obj.vertices, ply.vertices, atol=1e-5)
    np.testing.assert_array_equal(obj.visual.vertex_colors[:, :3], ply.visual.vertex_colors[:, :3])
    frames = json.loads((small_run / "capture" / "capture.json").read_text())["frames"]
    assert [f["name"] for f in data["posed"]["frames"]] == frames and data["posed"]["nonrigid"]
    assert {"extract_s", "cleanup_s", "posing_s", "maps_s", "total_s"} <= set(manifest["timings"])


def test_posed_vertices_are_in_world_space_and_map_back_to_their_canonical_vertex(posed_export, small_run, tiny_model):
    """Root finding from each posed vertex recovers its canonical vertex (plus the non-rigid offset).

    Checked near the body (within 10 cm of the template), where the skinning field is the body's:
    a 6-step model's surface is a blob, and far from the body LBS can fold, which root finding
    from the major bones does not always invert."""
    import scipy.spatial

    model = load_model(tiny_model)
    canonical = np.asarray(trimesh.load(posed_export / "canonical.ply", process=False).vertices, np.float32)
    template = np.asarray(trimesh.load(small_run / "dataset" / "template.ply", process=False).vertices)
    near_body = scipy.spatial.cKDTree(template).query(canonical)[0] < 0.1
    box = model.avatar.canonical_box.numpy()
    near_body &= ~np.any(np.isclose(canonical, box[0], atol=1e-3) | np.isclose(canonical, box[1], atol=1e-3), axis=1)
    assert near_body.sum() > 100
    frames = np.load(small_run / "dataset" / "frames.npz")
    names = [str(n) for n in frames["frame_names"]]
    for k in (0, len(names) - 1):  # a training frame and a novel-pose test frame
        posed = np.asarray(trimesh.load(posed_export / "posed" / f"{names[k]}.ply", process=False).vertices)
        box = frames["posed_boxes"][k]
        assert np.all(posed.mean(axis=0) > box[0]) and np.all(posed.mean(axis=0) < box[1]), "not in world space"
        frame = model.avatar.deformer.prepare(torch.from_numpy(frames["bone_transforms"][k]))
        pose = torch.from_numpy(frames["pose_condition"][k])
        candidates, valid = model.avatar.deformer.canonicalize(torch.from_numpy(posed[near_body]).float(), frame)
        with torch.no_grad():
            offset = model.avatar.offset_points(candidates.reshape(-1, 3), pose).reshape(candidates.shape)
        error = (offset - torch.from_numpy(canonical[near_body])[:, None]).norm(dim=-1)
        error = torch.where(valid, error, torch.inf).amin(dim=1)
        assert (error < 1e-3).float().mean() > 0.97, float((error < 1e-3).float().mean())


def test_glb_round_trip_and_posing_its_skeleton_matches_export_pose(small_run, tiny_model, posed_export, tmp_path):
    """GLB re-read by pygltflib/trimesh; its skeleton posed with a capture pose gives the vertices of
    `export --pose` (dataset route, no non-rigid offset) up to the top-4 truncation the manifest reports,
    and exactly the LBS with its own top-4 weights."""
    from igavatar.body.anny_body import AnnyBody
    from igavatar.capture.capture_v1 import read_capture_v1

    k = 5
    out = tmp_path / "mesh"
    run_export(ExportOptions(model=tiny_model, out=out, formats=("ply", "glb"), resolution=RESOLUTION,
                             pose=small_run / "dataset", frame=k, nonrigid=False, device="cpu"))
    data = read_artifact(out, expected="mesh")["data"]
    model = load_model(tiny_model)
    canonical = trimesh.load(out / "canonical.ply", process=False)
    np.testing.assert_array_equal(canonical.vertices, trimesh.load(posed_export / "canonical.ply", process=False).vertices)

    gltf = pygltflib.GLTF2().load(str(out / "canonical.glb"))
    assert [gltf.nodes[j].name for j in gltf.skins[0].joints] == model.joint_names
    scene = trimesh.load(out / "canonical.glb", process=False)
    geometry = next(iter(scene.geometry.values()))
    assert len(geometry.vertices) == len(canonical.vertices) and len(geometry.faces) == len(canonical.faces)
    axes = gltf_axes("anny")  # the GLB is Y-up: canonical vertices rotated from the capture's Z-up frame
    # ... and moved so that the origin is on the floor under the root joint.
    offset_gltf = np.asarray(data["glb"]["world_to_gltf_offset"])
    assert geometry.vertices[:, 1].min() == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose(geometry.vertices, canonical.vertices @ axes.T + offset_gltf, atol=1e-5)
    # With a material, trimesh keeps COLOR_0 (linear, as glTF stores it) as a vertex attribute.
    colors = np.round(linear_to_srgb(geometry.visual.vertex_attributes["color"]) * 255)
    assert np.abs(colors - np.asarray(canonical.visual.vertex_colors)[:, :3]).max() <= 1

    # The known pose: frame k of the capture, through the Anny adapter, relative to the canonical pose.
    capture = read_capture_v1(small_run / "capture")
    body = AnnyBody.load(model.manifest["data"]["subject"]["phenotype"])
    rotations, translation = body.local_rotations_from_pose_parameters(torch.tensor(capture.poses["pose_parameters"][k:k + 1]))
    relative, offset = pose_relative_to_canonical(rotations[0].double().numpy(), translation[0].double().numpy(),
                                                  model.subject.canonical_rotations, np.zeros(3), model.subject.parents)
    glb_posed_gltf = pose_glb_vertices(out / "canonical.glb", *gltf_pose(axes, relative, offset))
    animation_rotations, animation_offset, _ = read_glb_animation(out / "canonical.glb")
    np.testing.assert_allclose(pose_glb_vertices(out / "canonical.glb", animation_rotations[0], animation_offset[0]),
                               glb_posed_gltf, atol=1e-4)
    glb_posed = gltf_to_world(glb_posed_gltf, axes, offset_gltf)  # back to the capture's world frame

    # Same vertices as LBS with the GLB's own top-4 weights under the model's bone transforms: < 0.1 mm.
    transforms = model.pose(rotations, translation).bone_transforms[0].double().numpy()
    joints = _accessor(gltf, out / "canonical.glb", "JOINTS_0").astype(np.int64)
    weights = _accessor(gltf, out / "canonical.glb", "WEIGHTS_0").astype(np.float64)
    blended = np.einsum("vk,vkrc->vrc", weights, transforms[joints][:, :, :3, :])
    lbs = np.einsum("vrc,vc->vr", blended[:, :, :3], canonical.vertices) + blended[:, :, 3]
    assert np.abs(glb_posed - lbs).max() < 1e-4

    # `export --pose` uses every skinning weight: it differs from the GLB by what the manifest reports.
    posed = np.asarray(trimesh.load(out / "posed" / f"{capture.frames[k]}.ply", process=False).vertices)
    gap = np.linalg.norm(glb_posed - posed, axis=1) * 1e3
    reported = data["posed"]["frames"][0]["glb_top4_gap_mm"]
    assert gap.max() == pytest.approx(reported["max"], abs=0.05) and gap.mean() == pytest.approx(reported["mean"], abs=0.05)
    # Without the non-rigid offset, igavatar's posing is full-weight LBS: the drift is that gap.
    drift = data["posed"]["frames"][0]["glb_drift_mm"]
    assert drift["4"]["max"] == pytest.approx(reported["max"], abs=0.05)
    assert drift["8"]["max"] <= drift["4"]["max"] + 1e-6
    assert data["glb"]["drift_mm"] == {"4": drift["4"]["max"], "8": drift["8"]["max"]}
    assert data["glb"]["up_axis"] == "+Y" and np.allclose(data["glb"]["world_to_gltf"], axes)
    # And, the same posing with every weight, from the model directly (no non-rigid offset).
    model.avatar.nonrigid.set_enabled(False)
    bone_transforms = torch.from_numpy(np.load(small_run / "dataset" / "frames.npz")["bone_transforms"][k])
    expected = model.posed(bone_transforms, torch.zeros(model.pose_dim)).pose_vertices(np.asarray(canonical.vertices))
    assert np.abs(posed - expected).max() < 1e-4


def test_exported_glb_is_y_up_with_the_head_above_the_feet(posed_export):
    """Our GLB read back (pygltflib via read_rigged_glb): the head joint and the top of the mesh lie
    above the feet along glTF's +Y, and the feet are at the bottom of the mesh."""
    data = read_rigged_glb(posed_export / "canonical.glb")
    names = [n.lower() for n in data["joint_names"]]
    y = data["joints_bind"][:, 1]
    head = next(i for i, n in enumerate(names) if n == "head")
    feet = [i for i, n in enumerate(names) if n.startswith("foot")]
    assert feet, names
    assert y[head] - y[feet].max() > 1.0  # an adult: > 1 m from the feet to the head, along +Y
    # The tiny model's surface is a rough blob around the body that fills its box in depth (the
    # template's depth + 6 cm on each side): it still stands along Y, half again taller than deep.
    vertices = data["vertices"]
    extent = vertices.max(axis=0) - vertices.min(axis=0)
    assert extent[1] > 1.5 * extent[2], extent
    assert y[feet].max() < vertices[:, 1].mean() < y[head]


def test_eight_influences_and_drift_per_frame(small_run, tiny_model, tmp_path):
    out = tmp_path / "mesh8"
    run_export(ExportOptions(model=tiny_model, out=out, formats=("glb",), resolution=RESOLUTION, influences=8,
                             pose=small_run / "capture", frame=4, device="cpu"))
    data = read_artifact(out, expected="mesh")["data"]
    glb = read_rigged_glb(out / "canonical.glb")
    assert glb["weights"].shape[1] == 8 and data["glb"]["influences"] == 8
    np.testing.assert_allclose(glb["weights"].sum(axis=1, dtype=np.float64), 1.0, atol=1e-6)
    (frame,) = data["posed"]["frames"]
    # The non-rigid offset is on: both truncations drift from igavatar's posing, 8 no more than 4 + offset.
    assert 0 < frame["glb_drift_mm"]["8"]["mean"] and frame["glb_drift_mm"]["4"]["max"] < 100
    assert data["glb"]["drift_mm"]["4"] == frame["glb_drift_mm"]["4"]["max"]
    # Measured from the files: the GLB's own 8-weight skinning against posed/<frame>.ply.
    rotations, offset, _ = read_glb_animation(out / "canonical.glb")
    posed_glb = gltf_to_world(pose_glb_vertices(out / "canonical.glb", rotations[0], offset[0]),
                              data["glb"]["world_to_gltf"], data["glb"]["world_to_gltf_offset"])
    posed = np.asarray(trimesh.load(out / "posed" / f"{frame['name']}.ply", process=False).vertices)
    gap = np.linalg.norm(posed_glb - posed, axis=1) * 1e3
    assert gap.max() == pytest.approx(frame["glb_drift_mm"]["8"]["max"], abs=0.05)


def test_textured_export_bakes_the_color_field_and_rigs_the_decimated_mesh(small_run, tiny_model, tmp_path):
    import cv2

    from igavatar.avatar.surfaces import surface_colors

    out = tmp_path / "mesh"
    run_export(ExportOptions(model=tiny_model, out=out, resolution=RESOLUTION, texture_size=128, textured_faces=800,
                             texture_from="field", pose=small_run / "capture", frame=2, device="cpu"))
    data = read_artifact(out, expected="mesh")["data"]
    textured = data["textured"]
    assert set(textured["files"]) == {f"textured/avatar.{ext}" for ext in ("png", "obj", "mtl", "glb")}
    assert textured["faces"] <= 800 and textured["texture_size"] == 128
    assert data["canonical"]["faces"] > textured["faces"]  # the full-resolution mesh stays as it was

    glb = read_rigged_glb(out / "textured" / "avatar.glb")
    assert glb["uv"] is not None and glb["colors"] is None and glb["faces"].shape[0] == textured["faces"]
    gltf = pygltflib.GLTF2().load(str(out / "textured" / "avatar.glb"))
    assert gltf.materials[0].pbrMetallicRoughness.baseColorTexture.index == 0
    assert gltf.images[0].mimeType == "image/png" and len(gltf.animations) == 1
    # The texture at each vertex's UV is the color field at that (canonical) vertex.
    image = cv2.cvtColor(cv2.imread(str(out / "textured" / "avatar.png")), cv2.COLOR_BGR2RGB).astype(np.float32) / 255
    texel = glb["uv"] * 128 - 0.5
    sampled = cv2.remap(image, texel[:, 0].astype(np.float32)[None], texel[:, 1].astype(np.float32)[None],
                        cv2.INTER_LINEAR)[0]
    canonical = gltf_to_world(glb["vertices"], glb["world_to_gltf"], glb["world_to_gltf_offset"])  # capture frame
    expected = surface_colors(load_model(tiny_model).avatar, canonical)
    assert np.median(np.abs(sampled - expected)) < 0.03
    np.testing.assert_allclose(glb["weights"].sum(axis=1), 1.0, atol=1e-6)
    # The OBJ (with its MTL and PNG) is the same Y-up mesh.
    obj = trimesh.load(out / "textured" / "avatar.obj", process=False)
    assert len(obj.faces) == textured["faces"] and obj.visual.uv is not None
    assert np.abs(np.asarray(obj.vertices).max(axis=0) - glb["vertices"].max(axis=0)).max() < 1e-4


def test_texture_from_images_uses_the_training_frames_only(small_run, tiny_model, tmp_path):
    out = tmp_path / "mesh"
    run_export(ExportOptions(model=tiny_model, out=out, resolution=RESOLUTION, texture_size=128, textured_faces=800,
                             texture_from="images", dataset=small_run / "dataset", device="cpu"))
    manifest = read_artifact(out, expected="mesh")
    fusion = manifest["data"]["textured"]["texture_from"]
    assert fusion["source"] == "images" and fusion["views"] == 4  # the 4 training frames, not the 3 test frames
    assert 0 < fusion["seen_fraction"] <= 1 and fusion["texels"] > 0
    assert any(i.get("artifact") == "dataset" for i in manifest["inputs"])
    assert manifest["config"]["texture_from"] == "images"
    # The same export from the field is another artifact (the option is part of the config).
    field = run_export(ExportOptions(model=tiny_model, out=out, resolution=RESOLUTION, texture_size=128,
                                     textured_faces=800, texture_from="field", device="cpu"))
    assert "skipped" not in field
    assert read_artifact(out, expected="mesh")["data"]["textured"]["texture_from"] == {"source": "field"}


@pytest.mark.parametrize("options, message", [
    ({"dataset": Path("elsewhere")}, "--dataset .* needs --texture-size"),
    ({"texture_from": "photos", "texture_size": 64}, "--texture-from 'photos': choose one of images, field"),
    ({"texture_size": 64, "dataset": Path("no-such-dataset")}, "no-such-dataset the model was trained on is not there"),
])
def test_texture_from_bad_options_are_one_line(tiny_model, tmp_path, options, message):
    with pytest.raises(InputError, match=message):
        run_export(ExportOptions(model=tiny_model, out=tmp_path / "mesh", resolution=RESOLUTION, device="cpu", **options))


def _accessor(gltf: pygltflib.GLTF2, path: Path, attribute: str) -> np.ndarray:
    """An attribute of the GLB's skinned primitive decoded with pygltflib (independent of igavatar's reader)."""
    accessor = gltf.accessors[getattr(gltf.meshes[0].primitives[0].attributes, attribute)]
    view = gltf.bufferViews[accessor.bufferView]
    dtype = {pygltflib.UNSIGNED_BYTE: np.uint8, pygltflib.UNSIGNED_SHORT: np.uint16, pygltflib.FLOAT: np.float32}[accessor.componentType]
    blob = gltf.binary_blob()
    start = view.byteOffset + (accessor.byteOffset or 0)
    return np.frombuffer(blob, dtype=dtype, count=accessor.count * 4, offset=start).reshape(accessor.count, 4)


def test_exr_maps_back_project_onto_the_exported_mesh(posed_export):
    from igavatar.metrics.geometry import closest_points_on_mesh

    data = read_artifact(posed_export, expected="mesh")["data"]
    cameras = np.load(posed_export / "maps" / "cameras.npz")
    names = [str(n) for n in cameras["names"]]
    assert names == [v["name"] for v in data["maps"]["views"]] and names[0] == "canonical"
    for index in (0, len(names) - 1):
        maps = read_exr(posed_export / "maps" / f"{names[index]}.exr")
        assert set(maps) == {"Z", "N", "A", "RGB"}
        mesh_file = "canonical.ply" if index == 0 else f"posed/{names[index]}.ply"
        mesh = trimesh.load(posed_export / mesh_file, process=False)
        rows, cols = np.nonzero(maps["A"] > 0)
        assert rows.size > 50
        pick = np.random.default_rng(0).choice(rows.size, 40, replace=False)
        pixels = np.stack((cols[pick], rows[pick], np.ones(40)), axis=1)
        z = maps["Z"][rows[pick], cols[pick]]
        x_camera = (np.linalg.inv(cameras["K"][index]) @ pixels.T).T * z[:, None]
        w2c = cameras["w2c"][index]
        x_world = (x_camera - w2c[:3, 3]) @ w2c[:3, :3]
        _, distance, _ = closest_points_on_mesh(x_world, mesh.vertices, mesh.faces)
        assert distance.max() < 1e-4


def test_cli_export_json_and_skip_when_unchanged(small_run, tiny_model, cli_runner, tmp_path):
    args = ["export", "--model", str(tiny_model), "--out", str(tmp_path / "mesh"), "--resolution", "24",
            "--formats", "ply", "--device", "cpu", "--json"]
    result = cli_runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    assert summary["watertight"] and summary["files"] == [str(tmp_path / "mesh" / "canonical.ply")]
    again = cli_runner.invoke(app, args)
    assert again.exit_code == 0 and "unchanged" in json.loads(again.output)["skipped"]
    # Another kind of artifact is never replaced by a mesh.
    refused = cli_runner.invoke(app, ["export", "--model", str(tiny_model), "--out", str(small_run / "dataset"), "-q"])
    assert refused.exit_code == 2 and "holds a dataset artifact" in refused.output
    read_artifact(small_run / "dataset", expected="dataset")


@pytest.mark.parametrize("case", ["dataset-as-model", "bad-shape", "other-skeleton", "frame-range", "frame-without-pose", "no-pose-file",
                                  "influences", "texture-size", "surface-level"])
def test_bad_inputs_are_one_line_and_write_nothing(small_run, tiny_model, cli_runner, tmp_path, case):
    np.savez(tmp_path / "bad.npz", pose_parameters=np.zeros((2, 104, 4, 3)))
    # A bare 3-joint skeleton: no retarget exists onto Anny (SMPL sequences are retargeted).
    np.savez(tmp_path / "chain.npz", parents=np.array([-1, 0, 1]), rest_joints=np.eye(3), rotvecs=np.zeros((2, 3, 3)),
             transl=np.zeros((2, 3)))
    model, extra, code, message = {
        "dataset-as-model": (small_run / "dataset", [], 3, "needs a model artifact"),
        "bad-shape": (tiny_model, ["--pose", str(tmp_path / "bad.npz")], 2, "key 'pose_parameters' has shape (2, 104, 4, 3)"),
        "other-skeleton": (tiny_model, ["--pose", str(tmp_path / "chain.npz")], 2, "Anny (104 joints)"),
        "frame-range": (tiny_model, ["--pose", str(small_run / "capture"), "--frame", "99"], 2, "--frame 99"),
        "frame-without-pose": (tiny_model, ["--frame", "1"], 2, "--frame needs --pose"),
        "no-pose-file": (tiny_model, ["--pose", str(tmp_path / "missing.npz")], 2, "no such file"),
        "influences": (tiny_model, ["--influences", "6"], 2, "--influences 6: expected 4"),
        "texture-size": (tiny_model, ["--texture-size", "8"], 2, "--texture-size 8: expected 0"),
        "surface-level": (tiny_model, ["--surface-level", "outer"], 2, "--surface-level 'outer': choose one of silhouette, zero"),
    }[case]
    out = tmp_path / "mesh"
    result = cli_runner.invoke(app, ["export", "--model", str(model), "--out", str(out), "--resolution", "16", *extra])
    assert result.exit_code == code, result.output
    assert message in " ".join(result.output.split()) and "Traceback" not in result.output
    assert not out.exists() and not list(tmp_path.glob(".mesh*"))


def test_posed_marching_is_recorded_beside_the_lbs_posed_mesh(small_run, tiny_model, tmp_path):
    out = tmp_path / "mesh"
    run_export(ExportOptions(model=tiny_model, out=out, formats=("ply",), resolution=24, pose=small_run / "capture",
                             frame=6, posed_marching=True, device="cpu"))
    manifest = read_artifact(out, expected="mesh")
    (marched,) = manifest["data"]["posed_marching"]
    assert marched["name"] == "test_squat_0000" and marched["faces"] > 100 and "posed_marching_s" in manifest["timings"]
    mesh = trimesh.load(out / marched["file"], process=False)
    assert len(mesh.faces) == marched["faces"] and marched["watertight"] == is_watertight(mesh.vertices, mesh.faces)
    # Both are the same surface where LBS is invertible: on average within a few marching-cubes cells.
    cell_mm = 1e3 * np.ptp(mesh.vertices, axis=0).max() / 23
    assert marched["mean_distance_to_posed_mm"] < 3 * cell_mm


def test_the_default_glb_is_decimated_for_engines_and_stands_on_the_floor(small_run, tiny_model, tmp_path):
    """canonical.glb: at most --glb-faces faces (the PLY keeps the full mesh), its measured distance
    to the full mesh in the manifest, the origin on the floor under the root joint, and its drift
    measured on its own vertices."""
    from igavatar.mesh.engine_mesh import surface_deviation_mm

    out = tmp_path / "mesh"
    run_export(ExportOptions(model=tiny_model, out=out, formats=("ply", "glb"), resolution=RESOLUTION, glb_faces=300,
                             pose=small_run / "dataset", frame=1, device="cpu"))
    data = read_artifact(out, expected="mesh")["data"]
    full = trimesh.load(out / "canonical.ply", process=False)
    glb = read_rigged_glb(out / "canonical.glb")
    record = data["glb"]["mesh"]
    assert record["decimated"] and record["full_faces"] == len(full.faces) == data["canonical"]["faces"] > 300
    assert glb["faces"].shape[0] == record["faces"] <= 300 and data["glb"]["bytes"] == (out / "canonical.glb").stat().st_size
    # The reported deviation is the distance between the two surfaces, measured again here.
    world = gltf_to_world(glb["vertices"], glb["world_to_gltf"], glb["world_to_gltf_offset"])
    again = surface_deviation_mm((np.asarray(full.vertices), np.asarray(full.faces)), (world, glb["faces"]), 100_000)
    assert 0 < record["deviation_mm"]["mean"] < 20 and again["mean"] == pytest.approx(record["deviation_mm"]["mean"], rel=0.05)
    # On the floor: the lowest vertex at Y = 0, the root joint straight above the origin.
    assert glb["vertices"][:, 1].min() == pytest.approx(0.0, abs=1e-6)
    root = glb["joints_bind"][0]
    assert abs(root[0]) < 1e-6 and abs(root[2]) < 1e-6 and root[1] > 0.3
    # The drift is of the GLB's own vertices: as many as it has.
    frame = data["posed"]["frames"][0]
    assert set(frame["glb_drift_mm"]) == {"4", "8"} and frame["glb_drift_mm"]["4"]["max"] < 100

    # --glb-faces 0 keeps the full mesh.
    run_export(ExportOptions(model=tiny_model, out=tmp_path / "full", formats=("glb",), resolution=RESOLUTION,
                             glb_faces=0, device="cpu"))
    whole = read_artifact(tmp_path / "full", expected="mesh")["data"]["glb"]["mesh"]
    assert not whole["decimated"] and whole["faces"] == whole["full_faces"] and whole["deviation_mm"]["max"] == 0.0
