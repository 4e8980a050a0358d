"""`igavatar animate`: frames + video round trip, camera helpers in closed form, motions, bounded OOD poses."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import imageio
import numpy as np
import pytest
import trimesh
import torch

from igavatar.artifacts.manifest import read_artifact
import pygltflib

from igavatar.body.rotations import axis_angle_to_matrix
from igavatar.capture.images import scale_intrinsics
from igavatar.errors import InputError
from igavatar.mesh.gltf import gltf_axes, gltf_pose, pose_relative_to_canonical
from igavatar.mesh.gltf_read import gltf_to_world, pose_glb_vertices, read_rigged_glb
from igavatar.model.render_avatar import render_avatar_view
from igavatar.render.cameras import (
    box_corners,
    camera_centers,
    fit_intrinsics,
    look_at_w2c,
    orbit_w2c,
    resize_intrinsics,
    turntable_cameras,
)
from igavatar_cli.main import app
from igavatar.avatar.boxes import posed_boxes, skinned_cells
from igavatar.avatar.cameras import FRAMING_MARGIN
from igavatar.avatar.model import load_model
from stages.animate import AnimateOptions, resolve_motion, run_animate

# Tiny renders keep the file well under a minute on two shared cores.
FAST = dict(resolution=24, samples=8)


def _project(K: torch.Tensor, w2c: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    x_camera = x @ w2c[:3, :3].T + w2c[:3, 3]
    uv = x_camera @ K.T
    return uv[:, :2] / uv[:, 2:]


# ------------------------------------------------------------------------------ camera helpers
def test_look_at_centers_the_target_and_keeps_up_upright():
    eye, target, up = torch.tensor([1.0, -3.0, 0.5]), torch.tensor([0.2, 0.1, 0.3]), torch.tensor([0.0, 0.0, 1.0])
    w2c = look_at_w2c(eye, target, up)
    rotation = w2c[:3, :3].double()
    assert torch.allclose(rotation @ rotation.T, torch.eye(3, dtype=torch.float64), atol=1e-6)
    assert torch.linalg.det(rotation) == pytest.approx(1.0, abs=1e-6)
    assert torch.allclose(camera_centers(w2c), eye, atol=1e-5)
    target_camera = w2c[:3, :3] @ target + w2c[:3, 3]
    assert target_camera[:2].abs().max() < 1e-5 and target_camera[2] > 0  # on the optical axis, ahead
    up_camera = w2c[:3, :3] @ up
    assert up_camera[1] < 0 and abs(float(up_camera[0])) < 1e-6  # world up is image up, no roll


def test_orbit_keeps_distance_elevation_and_starts_in_front():
    center, up, front = torch.tensor([0.5, 0.0, 1.0]), torch.tensor([0.0, 0.0, 1.0]), torch.tensor([0.0, -1.0, 0.0])
    elevation = math.radians(20.0)
    azimuths = torch.linspace(0, 2 * math.pi, 7)[:-1]
    w2c = orbit_w2c(center, 2.5, azimuths, up=up, front=front, elevation=elevation)
    eyes = camera_centers(w2c)
    assert torch.allclose((eyes - center).norm(dim=-1), torch.full((6,), 2.5), atol=1e-5)
    assert torch.allclose(eyes[:, 2] - center[2], torch.full((6,), 2.5 * math.sin(elevation)), atol=1e-5)
    horizontal = (eyes[0] - center) * torch.tensor([1.0, 1.0, 0.0])
    assert torch.allclose(horizontal / horizontal.norm(), front, atol=1e-6)
    # Counter-clockwise seen from above: the second camera is a sixth of a turn towards +x here.
    assert eyes[1, 0] > center[0]


def test_fit_intrinsics_frames_the_box_tightly_in_every_view():
    low, high = torch.tensor([-0.4, -0.3, -1.0]), torch.tensor([0.4, 0.3, 0.9])
    K, w2c = turntable_cameras(low, high, 5, 40, 60, up=torch.tensor([0.0, 0.0, 1.0]), front=torch.tensor([0.0, -1.0, 0.0]), margin=0.1)
    corners = box_corners(low, high)
    assert corners.shape == (8, 3)
    worst_gap = float("inf")
    for view in w2c:
        uv = _project(K, view, corners)
        gap_x = torch.minimum(uv[:, 0] + 0.5, 60 - 0.5 - uv[:, 0]) / 60
        gap_y = torch.minimum(uv[:, 1] + 0.5, 40 - 0.5 - uv[:, 1]) / 40
        # +-0.5: the image spans [-0.5, W - 0.5] with pixel centers at integers.
        assert (gap_x >= 0.1 - 1e-3).all() and (gap_y >= 0.1 - 1e-3).all()
        worst_gap = min(worst_gap, float(gap_x.min()), float(gap_y.min()))
    assert worst_gap == pytest.approx(0.1, abs=2e-3)  # tight: some corner touches the margin
    with pytest.raises(Exception, match="behind a camera"):
        fit_intrinsics(torch.tensor([[0.0, 0.0, -1.0]]), torch.eye(4), 10, 10)


def test_resize_intrinsics_matches_the_pixel_center_rule():
    K = torch.tensor([[300.0, 0.0, 255.5], [0.0, 310.0, 200.0], [0.0, 0.0, 1.0]])
    resized = resize_intrinsics(K, (400, 512), (100, 128))
    assert np.allclose(resized.numpy(), scale_intrinsics(K.numpy(), (128 / 512, 100 / 400)), atol=1e-5)
    assert torch.allclose(resize_intrinsics(resized, (100, 128), (400, 512)), K, atol=1e-4)


# -------------------------------------------------------------------------------- the stage
@pytest.fixture(scope="module")
def walk_animation(tiny_model, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("anim") / "animation"
    run_animate(AnimateOptions(model=tiny_model, out=out, motion="walk", frames=4, device="cpu", meshes=True,
                               mesh_resolution=24, glb=True, **FAST))
    return out


def test_animate_writes_n_frames_and_a_video_that_decodes_to_n_frames(walk_animation):
    manifest = read_artifact(walk_animation, expected="animation")
    data = manifest["data"]
    assert data["frames"] == 4 and data["resolution"] == [24, 24] and data["camera"]["kind"] == "turntable"
    assert data["speed"]["frames_per_second"] > 0
    frames = sorted((walk_animation / "frames").glob("*.png"))
    assert [f.name for f in frames] == ["0000.png", "0001.png", "0002.png", "0003.png"]
    for path in frames:
        assert cv2.imread(str(path)).shape == (24, 24, 3)
    reader = imageio.get_reader(str(walk_animation / "video.mp4"))
    # Iterate, not list(reader): the reader reports len() = inf and list() would preallocate it.
    video = [frame for frame in reader]
    assert reader.count_frames() == 4 and len(video) == 4 and video[0].shape == (24, 24, 3)
    assert reader.get_meta_data()["fps"] == pytest.approx(30.0)
    # H.264 is lossy but a decoded frame must still be close to its PNG.
    png = cv2.cvtColor(cv2.imread(str(frames[2])), cv2.COLOR_BGR2RGB).astype(np.float32)
    assert np.abs(video[2].astype(np.float32) - png).mean() < 12.0


def test_animation_records_cameras_poses_and_meshes_that_agree(walk_animation, tiny_model):
    with np.load(walk_animation / "cameras.npz") as cameras:
        K, w2c = torch.from_numpy(cameras["K"]), torch.from_numpy(cameras["w2c"])
        assert K.shape == (4, 3, 3) and w2c.shape == (4, 4, 4) and int(cameras["height"]) == 24
    with np.load(walk_animation / "boxes.npz") as boxes_file:
        boxes = torch.from_numpy(boxes_file["posed_boxes"])
    # poses.npz re-poses the model to the very boxes the frames were rendered in.
    model = load_model(tiny_model)
    with np.load(walk_animation / "poses.npz") as poses:
        rotations = axis_angle_to_matrix(torch.from_numpy(poses["rotvecs"]).double()).float()
        posed = model.pose(rotations, torch.from_numpy(poses["transl"]))
        assert list(poses["joint_names"]) == model.joint_names
        # In place: no horizontal root travel (Anny: +Z up).
        assert np.abs(poses["transl"][:, :2]).max() < 1e-6
    assert torch.allclose(posed_boxes(model, posed.bone_transforms, posed.posed_joints), boxes, atol=1e-4)
    # The turntable keeps the body (its skinned occupied cells) inside every frame, with the margin.
    body = skinned_cells(model, posed.bone_transforms)
    low, high = FRAMING_MARGIN * 24 - 0.5 - 1e-3, (1 - FRAMING_MARGIN) * 24 - 0.5 + 1e-3
    for i in range(4):
        uv = _project(K[i], w2c[i], body[i])
        assert (uv >= low).all() and (uv <= high).all()
        assert (boxes[i, 0] < body[i].amin(0)).all() and (body[i].amax(0) < boxes[i, 1]).all()
    # Each posed mesh lies inside its frame's posed box.
    meshes = sorted((walk_animation / "meshes").glob("*.ply"))
    assert len(meshes) == 4
    import trimesh

    vertices = np.asarray(trimesh.load(meshes[1], process=False).vertices)
    assert len(vertices) > 0
    assert (vertices >= boxes[1, 0].numpy() - 1e-4).all() and (vertices <= boxes[1, 1].numpy() + 1e-4).all()


def _pygltflib_keys(path: Path) -> tuple[dict, dict]:
    """Every animation channel of a GLB decoded with pygltflib alone: {(node name, path): keys}, and the times."""
    gltf = pygltflib.GLTF2.load(str(path))
    blob = gltf.binary_blob()

    def read(index: int) -> np.ndarray:
        accessor = gltf.accessors[index]
        view = gltf.bufferViews[accessor.bufferView]
        width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[accessor.type]
        data = np.frombuffer(blob, np.float32, accessor.count * width, view.byteOffset + (accessor.byteOffset or 0))
        return data.reshape(accessor.count, width)

    (animation,) = gltf.animations
    keys, times = {}, {}
    for channel in animation.channels:
        sampler = animation.samplers[channel.sampler]
        name = gltf.nodes[channel.target.node].name
        keys[(name, channel.target.path)] = read(sampler.output)
        times[(name, channel.target.path)] = read(sampler.input)[:, 0]
        assert sampler.interpolation == "LINEAR"
    return keys, times


def _quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """(N, 4) x, y, z, w -> (N, 3, 3), written out here so the test shares no code with the writer."""
    x, y, z, w = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def test_animated_glb_channels_round_trip_the_motion(walk_animation, tiny_model):
    """animation.glb read back with pygltflib: a rotation channel per joint and the root translation,
    one key per frame at the motion's fps, equal to the driving motion (poses.npz) re-expressed
    relative to the canonical bind pose in glTF's Y-up frame."""
    data = read_artifact(walk_animation, expected="animation")["data"]
    glb = data["glb"]
    assert glb["file"] == "animation.glb" and glb["animation_frames"] == 4 and glb["fps"] == 30.0
    model = load_model(tiny_model)
    keys, times = _pygltflib_keys(walk_animation / "animation.glb")
    names = model.joint_names
    assert set(keys) == {(n, "rotation") for n in names} | {(names[0], "translation")}
    for key_times in times.values():
        np.testing.assert_allclose(key_times, np.arange(4) / 30.0, atol=1e-6)

    with np.load(walk_animation / "poses.npz") as poses:
        rotations = axis_angle_to_matrix(torch.from_numpy(poses["rotvecs"]).double()).numpy()
        translation = poses["transl"].astype(np.float64)
    relative, offset = pose_relative_to_canonical(rotations, translation, model.subject.canonical_rotations,
                                                  np.zeros(3), model.subject.parents)
    axes = gltf_axes("anny")
    expected_rotations, expected_offset = gltf_pose(axes, relative, offset)
    for j, name in enumerate(names):
        np.testing.assert_allclose(_quaternion_matrix(keys[(name, "rotation")]), expected_rotations[:, j], atol=2e-5)
    floor = read_rigged_glb(walk_animation / "animation.glb")["world_to_gltf_offset"]
    root_bind = np.asarray(model.subject.canonical_joints, np.float64)[0] @ axes.T + floor
    np.testing.assert_allclose(keys[(names[0], "translation")], root_bind + expected_offset, atol=1e-5)

    # The clip's frame 1, skinned the glTF way, lands on igavatar's posed mesh within the reported drift.
    posed_glb = gltf_to_world(pose_glb_vertices(walk_animation / "animation.glb", expected_rotations[1], expected_offset[1]),
                              axes, read_rigged_glb(walk_animation / "animation.glb")["world_to_gltf_offset"])
    import trimesh

    posed = np.asarray(trimesh.load(walk_animation / "meshes" / "0001.ply", process=False).vertices)
    gap = np.linalg.norm(posed_glb - posed, axis=1).max() * 1e3
    assert gap == pytest.approx(glb["drift_mm_per_frame"]["4"][1], abs=0.05)
    assert glb["drift_mm"]["4"] == max(glb["drift_mm_per_frame"]["4"]) and len(glb["drift_mm_per_frame"]["8"]) == 4
    assert read_rigged_glb(walk_animation / "animation.glb")["vertices"].shape[0] == data["mesh_vertices"]


@pytest.mark.parametrize("source", ["capture/poses.npz", "capture", "dataset"])
def test_pose_sources_reproduce_the_dataset_bone_transforms(tiny_model, small_run, source):
    model = load_model(tiny_model)
    options = AnimateOptions(model=tiny_model, out=small_run / "unused", motion=str(small_run / source), frames=3)
    motion = resolve_motion(model, options)
    assert motion.local_rotations.shape[0] == 3 and motion.source == str(small_run / source)
    assert motion.fps == 30.0 and motion.inputs
    posed = model.pose(motion.local_rotations, motion.root_translation)
    with np.load(small_run / "dataset" / "frames.npz") as frames:
        expected = torch.from_numpy(frames["bone_transforms"][:3])
    assert torch.allclose(posed.bone_transforms, expected, atol=1e-4)


def test_pose_file_of_another_skeleton_is_refused(tiny_model, tmp_path):
    model = load_model(tiny_model)
    path = tmp_path / "three_joints.npz"
    np.savez(path, parents=np.array([-1, 0, 1]), rest_joints=np.zeros((3, 3)), rotvecs=np.zeros((2, 3, 3)), transl=np.zeros((2, 3)))
    with pytest.raises(Exception, match="another skeleton"):
        resolve_motion(model, AnimateOptions(model=tiny_model, out=tmp_path / "out", motion=str(path)))


def test_walk_travels_forward_only_when_asked(tiny_model):
    model = load_model(tiny_model)
    base = dict(model=tiny_model, out=Path("unused"), motion="walk", seconds=2.0, fps=10.0)
    in_place = resolve_motion(model, AnimateOptions(**base))
    travel = resolve_motion(model, AnimateOptions(**base, travel=True))
    assert in_place.local_rotations.shape[0] == 20 and in_place.in_place and not travel.in_place
    assert in_place.root_translation[:, :2].abs().max() < 1e-6
    # Anny faces -Y: forward travel is towards -Y, roughly 0.5-1 m/s after the ramp-in.
    distance = -float(travel.root_translation[-1, 1] - travel.root_translation[0, 1])
    assert 0.5 < distance < 2.0


def test_out_of_distribution_poses_stay_bounded_and_render_finite(tiny_model):
    model = load_model(tiny_model)
    num_joints = len(model.joint_names)
    generator = torch.Generator().manual_seed(0)
    # Every joint turned by up to 180 degrees about a random axis: far outside any training pose.
    rotvecs = torch.nn.functional.normalize(torch.randn(2, num_joints, 3, generator=generator), dim=-1)
    rotvecs = rotvecs * torch.rand(2, num_joints, 1, generator=generator) * math.pi
    posed = model.pose(axis_angle_to_matrix(rotvecs.double()).float(), torch.zeros(2, 3))
    boxes = posed_boxes(model, posed.bone_transforms, posed.posed_joints)
    assert torch.isfinite(boxes).all() and (boxes[:, 1] > boxes[:, 0]).all()
    # Rigid bone transforms move points by at most the joint chain's reach: the box stays body-sized.
    canonical_extent = float((model.avatar.canonical_box[1] - model.avatar.canonical_box[0]).norm())
    assert float((boxes[:, 1] - boxes[:, 0]).norm(dim=-1).max()) < 2.5 * canonical_extent
    K, w2c = turntable_cameras(boxes[0, 0], boxes[0, 1], 1, 16, 16, up=torch.tensor([0.0, 0.0, 1.0]), front=torch.tensor([0.0, -1.0, 0.0]))
    # With the non-rigid offset on, boxes grow by exactly its bound (each component is bounded).
    model.avatar.nonrigid.set_enabled(False)
    rigid = posed_boxes(model, posed.bone_transforms, posed.posed_joints)
    model.avatar.nonrigid.set_enabled(True)
    bound = math.sqrt(3.0) * model.avatar.nonrigid.config.max_offset
    padded = posed_boxes(model, posed.bone_transforms, posed.posed_joints)
    assert torch.allclose(padded[:, 0], rigid[:, 0] - bound, atol=1e-5)
    assert torch.allclose(padded[:, 1], rigid[:, 1] + bound, atol=1e-5)
    offsets = model.avatar.nonrigid(torch.rand(512, 3, generator=generator), posed.pose_condition[0] * 100.0)
    assert offsets.abs().max() <= model.avatar.nonrigid.config.max_offset
    image = render_avatar_view(model.avatar, model.canonical_grid, posed.bone_transforms[0], posed.pose_condition[0],
                               K, w2c[0], 16, 16, padded[0], num_samples=8, occupancy_resolution=16)
    assert torch.isfinite(image.rgb).all() and image.rgb.min() >= 0 and image.rgb.max() <= 1


# ------------------------------------------------------------------------------------ the CLI
def test_cli_animate_capture_camera_and_json_summary(cli_runner, tiny_model, small_run, tmp_path):
    out = tmp_path / "animation"
    result = cli_runner.invoke(app, [
        "animate", "squat", "--model", str(tiny_model), "--out", str(out), "--frames", "2", "--camera", "capture",
        "--resolution", "16", "--samples", "4", "--device", "cpu", "--json",
    ])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    assert summary["frames"] == 2 and summary["camera"] == "capture" and summary["motion"] == "squat"
    # The dataset's camera, rescaled from 64x64 to 16x16 by the pixel-center rule.
    with np.load(small_run / "dataset" / "frames.npz") as frames:
        expected_K = scale_intrinsics(frames["K"][0], (0.25, 0.25))
        expected_w2c = frames["w2c"][0]
    with np.load(out / "cameras.npz") as cameras:
        assert np.allclose(cameras["K"][1], expected_K, atol=1e-4) and np.allclose(cameras["w2c"][0], expected_w2c)


def test_cli_camera_file_round_trip_and_bad_camera_file(cli_runner, walk_animation, tiny_model, tmp_path):
    out = tmp_path / "again"
    args = ["animate", "--motion", "walk", "--model", str(tiny_model), "--frames", "4", "--samples", "8",
            "--resolution", "24", "--device", "cpu", "-q"]
    result = cli_runner.invoke(app, [*args, "--out", str(out), "--camera-file", str(walk_animation / "cameras.npz")])
    assert result.exit_code == 0, result.output
    # Same cameras, same poses, same renderer: the same frames.
    for name in ("0000.png", "0003.png"):
        assert np.array_equal(cv2.imread(str(out / "frames" / name)), cv2.imread(str(walk_animation / "frames" / name)))

    bad = tmp_path / "bad_camera.npz"
    np.savez(bad, K=np.eye(3), w2c=np.eye(3), height=16, width=16)
    result = cli_runner.invoke(app, [*args, "--out", str(tmp_path / "never"), "--camera-file", str(bad)])
    assert result.exit_code == 2
    assert "'w2c'" in result.output and "(3, 3)" in result.output and "Traceback" not in result.output
    assert not (tmp_path / "never").exists() and not list(tmp_path.glob(".never*"))


def test_cli_glb_with_eight_influences_from_capture_poses(cli_runner, tiny_model, small_run, tmp_path):
    out = tmp_path / "animation"
    result = cli_runner.invoke(app, [
        "animate", str(small_run / "capture"), "--model", str(tiny_model), "--out", str(out), "--frames", "3",
        "--resolution", "16", "--samples", "4", "--mesh-resolution", "24", "--glb", "--influences", "8",
        "--device", "cpu", "--json",
    ])
    assert result.exit_code == 0, result.output
    assert json.loads(result.output)["glb"] == str(out / "animation.glb")
    glb = read_rigged_glb(out / "animation.glb")
    assert glb["weights"].shape[1] == 8
    np.testing.assert_allclose(glb["weights"].sum(axis=1, dtype=np.float64), 1.0, atol=1e-6)
    data = read_artifact(out, expected="animation")["data"]["glb"]
    assert data["influences"] == 8 and data["animation_frames"] == 3
    assert all(d >= 0 for d in data["drift_mm_per_frame"]["8"]) and len(data["drift_mm_per_frame"]["4"]) == 3
    assert not (out / "meshes").exists()  # --glb alone writes no per-frame meshes


def test_cli_bad_inputs_fail_with_one_line(cli_runner, tiny_model, tmp_path):
    cases = [
        (["animate", "--model", str(tiny_model), "--glb", "--influences", "6"], "--influences 6"),
        (["animate", "moonwalk", "--model", str(tiny_model)], "neither a procedural motion"),
        (["animate", "--model", str(tmp_path / "missing")], "run `igavatar train` first"),
        (["animate", "--model", str(tiny_model), "--camera", "capture", "--dataset", str(tmp_path / "nope")], "--dataset"),
        (["animate", "--model", str(tiny_model), "--camera", "orbit"], "--camera 'orbit'"),
    ]
    for args, message in cases:
        result = cli_runner.invoke(app, [*args, "--out", str(tmp_path / "out"), "--frames", "1", "--device", "cpu"])
        assert result.exit_code != 0, args
        assert message in result.output and "Traceback" not in result.output, result.output
        assert not (tmp_path / "out").exists()


def test_meshes_follow_the_surface_level_as_export_makes_them(tiny_model, tmp_path, walk_animation):
    """--surface-level zero meshes the SDF's zero level, inside the default silhouette level's mesh,
    and the default is export's: the same canonical surface, posed."""
    from igavatar.avatar.model import load_model
    from igavatar.avatar.surfaces import canonical_surface

    out = tmp_path / "zero"
    run_animate(AnimateOptions(model=tiny_model, out=out, motion="walk", frames=4, device="cpu", meshes=True,
                               mesh_resolution=24, surface_level="zero", **FAST))
    zero = trimesh.load(out / "meshes" / "0000.ply", process=False)
    silhouette = trimesh.load(walk_animation / "meshes" / "0000.ply", process=False)
    assert zero.volume < silhouette.volume
    model = load_model(tiny_model)
    vertices, _ = canonical_surface(model.avatar, resolution=24, surface_level="silhouette")
    assert abs(len(silhouette.vertices) - len(vertices)) <= 0.05 * len(vertices)  # the largest component of it
    with pytest.raises(InputError, match="--surface-level 'middle'"):
        run_animate(AnimateOptions(model=tiny_model, out=tmp_path / "bad", surface_level="middle", meshes=True, **FAST))
