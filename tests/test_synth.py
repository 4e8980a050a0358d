"""`igavatar synth`: garments, solid texture, ray caster and the capture it writes.

One small capture (96 px, 4 + 3 frames) is shared by the module; acceptance: every scan projected
with the saved cameras covers its saved mask with IoU >= 0.98, and the clothed surface is a closed
2-manifold without self-intersections.
"""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from igavatar.artifacts.manifest import read_artifact
from igavatar.body.anny_body import AnnyBody
from igavatar.capture.capture_v1 import load_mask, read_capture_v1
from igavatar.errors import InputError
from igavatar.synth.garments import (
    GARMENTS,
    REGIONS,
    is_closed_manifold,
    loop_subdivision,
    self_intersecting_faces,
)
from igavatar.geometry.projection import project_points
from igavatar.geometry.raycast import CameraRays, MeshRayCaster, render_mesh
from igavatar.synth.scene import frame_static_camera, look_w2c, yaw_about_vertical
from igavatar.synth.texture import make_texture
from stages.synth import (
    SynthOptions,
    build_subject,
    build_texture,
    parse_phenotype,
    pose_subject,
    run_synth,
)

OPTIONS = dict(resolution=96, train_frames=4, test_frames=3, seed=3)


class RecordingProgress:
    """A ProgressSink that remembers what the stage reported."""

    def __init__(self) -> None:
        self.statuses: list[str] = []
        self.tasks: list[tuple[str, int | None]] = []
        self.advanced = 0

    def status(self, message: str) -> None:
        self.statuses.append(message)

    @contextmanager
    def task(self, description: str, total: int | None):
        self.tasks.append((description, total))

        def advance(n: int = 1, **fields) -> None:
            self.advanced += n

        yield advance


@pytest.fixture(scope="module")
def body() -> AnnyBody:
    return AnnyBody.load()


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> tuple[Path, dict, RecordingProgress]:
    out = tmp_path_factory.mktemp("synth") / "capture"
    progress = RecordingProgress()
    summary = run_synth(SynthOptions(out=out, **OPTIONS), progress=progress)
    return out, summary, progress


def rasterise_coverage(x_pixels: np.ndarray, faces: np.ndarray, height: int, width: int, s: int) -> np.ndarray:
    """Reference silhouette, independent of Embree: (H, W) fraction of each pixel's s x s samples
    (at the renderer's sample positions) that lie inside any projected triangle."""
    grid = s * (x_pixels + 0.5) - 0.5  # sample-grid coordinates: sample (i, j) sits at integer (j, i)
    tri = grid[faces]  # (F, 3, 2)
    low = np.ceil(tri.min(axis=1)).astype(int)
    high = np.floor(tri.max(axis=1)).astype(int)
    low = np.maximum(low, 0)
    high = np.minimum(high, [width * s - 1, height * s - 1])
    size = np.maximum(high - low + 1, 0)
    count = size[:, 0] * size[:, 1]
    face = np.repeat(np.arange(len(faces)), count)
    offset = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    sx = low[face, 0] + offset % size[face, 0]
    sy = low[face, 1] + offset // size[face, 0]
    a, b, c = tri[face, 0], tri[face, 1], tri[face, 2]
    p = np.stack([sx, sy], axis=1).astype(np.float64)

    def edge(u, v, q):
        return (v[:, 0] - u[:, 0]) * (q[:, 1] - u[:, 1]) - (v[:, 1] - u[:, 1]) * (q[:, 0] - u[:, 0])

    e0, e1, e2 = edge(a, b, p), edge(b, c, p), edge(c, a, p)
    inside = ((e0 >= 0) & (e1 >= 0) & (e2 >= 0)) | ((e0 <= 0) & (e1 <= 0) & (e2 <= 0))
    samples = np.zeros((height * s, width * s), dtype=bool)
    samples[sy[inside], sx[inside]] = True
    return samples.reshape(height, s, width, s).mean(axis=(1, 3))


# ----------------------------------------------------------------------------------------------
# The capture


def test_capture_is_valid_capture_v1_and_artifact(capture):
    out, summary, progress = capture
    meta = read_capture_v1(out)
    manifest = read_artifact(out, "capture")
    assert manifest["stage"] == "synth" and manifest["data"]["body_model"] == "anny"
    assert summary["frames"] == 7 and summary["skipped"] is False
    assert meta.splits["train"] == [f"train_{i:04d}" for i in range(4)]
    assert meta.splits["test"] == ["test_walk_0000", "test_arm_raise_0000", "test_squat_0000"]
    assert sorted(meta.meta["motions"]) == ["arm_raise", "squat", "turntable", "walk"]
    assert meta.has_masks and set(meta.scans) == set(meta.frames)
    assert meta.poses["pose_parameters"].shape == (7, 104, 4, 4)
    assert meta.poses["phenotype_labels"].dtype.kind == "U"
    assert (meta.height, meta.width) == (96, 96)
    assert progress.tasks == [("rendering frames", 7)] and progress.advanced == 7


def test_scans_reproject_onto_masks(capture):
    out, _, _ = capture
    meta = read_capture_v1(out)
    for i, frame in enumerate(meta.frames):
        scan = trimesh.load(meta.scans[frame], process=False)
        x_pixels, z = project_points(meta.K[i], meta.w2c[i], np.asarray(scan.vertices))
        assert np.all(z > 0)
        mask_ref = rasterise_coverage(x_pixels, np.asarray(scan.faces), meta.height, meta.width, s=2) > 0.5
        mask = load_mask(meta.mask_path(frame), (meta.height, meta.width))
        iou = (mask & mask_ref).sum() / (mask | mask_ref).sum()
        assert iou >= 0.98, f"{frame}: IoU {iou:.4f}"
        assert mask.sum() > 200  # the subject is actually in view
        # Nothing touches the image border: the camera frames the whole subject.
        assert not (mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any())


def test_scans_are_watertight_and_match_pose_parameters(capture, body):
    out, _, _ = capture
    meta = read_capture_v1(out)
    rotations, translation = body.local_rotations_from_pose_parameters(torch.as_tensor(meta.poses["pose_parameters"]))
    subject = build_subject(body, "shirt-trousers")
    x_posed = pose_subject(subject, body, rotations, translation)
    for i, frame in enumerate(meta.frames):
        scan = trimesh.load(meta.scans[frame], process=False)
        assert scan.is_watertight
        np.testing.assert_allclose(np.asarray(scan.vertices), x_posed[i], atol=1e-5)
    # The training frames turn the subject once around: frame i at 360 * i / N degrees.
    yaw = [float(torch.atan2(r[0, 1, 0], r[0, 0, 0])) for r in rotations[:4]]
    np.testing.assert_allclose(np.unwrap(yaw), np.radians([0, 90, 180, 270]), atol=1e-6)


def test_same_config_is_skipped_and_seed_is_deterministic(capture, tmp_path):
    out, _, _ = capture
    again = run_synth(SynthOptions(out=out, **OPTIONS))
    assert again["skipped"] is True
    other = tmp_path / "again"
    run_synth(SynthOptions(out=other, **OPTIONS))

    def hashes(path: Path) -> dict[str, str]:
        return {o["path"]: o["sha256"] for o in read_artifact(path, "capture")["outputs"]}

    assert hashes(other) == hashes(out)


def test_bad_options_raise_input_error(tmp_path):
    for item, words in [("gender=1.5", "outside [0, 1]"), ("color=0.2", "valid labels"), ("gender", "label=value"),
                        ("age=old", "not a number")]:
        with pytest.raises(InputError, match=words.replace("[", r"\[").replace("]", r"\]")):
            run_synth(SynthOptions(out=tmp_path / "c", phenotype=(item,)))
    with pytest.raises(InputError, match="garment"):
        run_synth(SynthOptions(out=tmp_path / "c", garment="kilt"))
    assert not (tmp_path / "c").exists()
    (tmp_path / "precious").mkdir()
    (tmp_path / "precious" / "notes.txt").write_text("keep me")
    with pytest.raises(InputError, match="refusing"):
        run_synth(SynthOptions(out=tmp_path / "precious", resolution=32, train_frames=1, test_frames=0))
    assert parse_phenotype(("height=0.8",))["height"] == 0.8


# ----------------------------------------------------------------------------------------------
# Garments


@pytest.mark.parametrize("garment", GARMENTS)
def test_clothed_surface_is_closed_and_free_of_self_intersections(body, garment):
    subject = build_subject(body, garment)
    assert is_closed_manifold(subject.faces)
    assert trimesh.Trimesh(subject.vertices_canonical, subject.faces, process=False).is_watertight
    assert not self_intersecting_faces(subject.vertices_canonical, subject.faces).any()
    np.testing.assert_allclose(subject.weights.sum(axis=1), 1.0, atol=1e-5)
    # Clothes go outwards only, within the garment thicknesses (the dress skirt hangs further out).
    assert subject.offsets.min() >= 0.0
    body_volume = trimesh.Trimesh(body.rest_vertices.numpy(), body.faces.numpy(), process=False).volume
    clothed_volume = trimesh.Trimesh(subject.vertices_canonical, subject.faces, process=False).volume
    assert clothed_volume > body_volume * (1.05 if garment == "tight" else 1.2)


def test_loop_subdivision_is_affine_and_keeps_a_closed_surface():
    sphere = trimesh.creation.icosphere(subdivisions=1)
    operator, faces = loop_subdivision(np.asarray(sphere.faces), len(sphere.vertices))
    np.testing.assert_allclose(np.asarray(operator.sum(axis=1)).reshape(-1), 1.0)
    assert is_closed_manifold(faces) and len(faces) == 4 * len(sphere.faces)
    x = operator @ np.asarray(sphere.vertices)
    radius = np.linalg.norm(x, axis=1)
    assert radius.max() <= 1.0 + 1e-9 and radius.min() > 0.85  # Loop shrinks a coarse sphere slightly
    assert trimesh.Trimesh(x, faces, process=False).volume > 0


# ----------------------------------------------------------------------------------------------
# Texture


def test_texture_is_periodic_in_canonical_space_and_plain_is_flat(body):
    stripes = build_texture(body, "stripes", seed=0)
    top = REGIONS.index("top")
    z = np.linspace(0.1, 0.2, 41)
    x = np.stack([np.full_like(z, 0.15), np.full_like(z, 0.05), z], axis=1)  # beside the chest print
    shifted = x + [0.0, 0.0, stripes.stripe_period]
    regions = np.full(len(z), top)
    np.testing.assert_allclose(stripes.albedo(x, regions), stripes.albedo(shifted, regions), atol=1e-9)
    assert np.ptp(stripes.albedo(x, regions), axis=0).max() > 0.3  # the stripes are there
    plain = make_texture("plain", 0, stripes.landmarks)
    assert np.ptp(plain.albedo(x, regions), axis=0).max() == 0.0
    # The chest print: at least some points on the front of the chest take the print color.
    chest = stripes.landmarks.chest
    grid = np.stack(np.meshgrid(np.linspace(-0.07, 0.07, 60), np.linspace(-0.02, 0.02, 20)), -1).reshape(-1, 2)
    front = np.stack([chest[0] + grid[:, 0], np.full(len(grid), chest[1]), chest[2] + grid[:, 1]], axis=1)
    colors = stripes.albedo(front, np.full(len(front), top))
    assert np.isclose(colors, stripes.accents["print"], atol=0.02).all(axis=1).mean() > 0.1
    with pytest.raises(InputError, match="texture"):
        make_texture("polka", 0, stripes.landmarks)
    # The bold pattern: 3 cm stripes (6 cm period), near-black green on near-white, whatever the seed.
    for seed in (0, 1):
        bold = make_texture("bold", seed, stripes.landmarks)
        assert bold.stripe_period == pytest.approx(0.06)
        z = np.linspace(0.0, 0.06, 61)
        band = bold.albedo(np.stack([np.full_like(z, 0.15), np.full_like(z, 0.05), z], axis=1), np.full(len(z), top))
        assert band.mean(axis=1).max() > 0.9 and band.mean(axis=1).min() < 0.25


# ----------------------------------------------------------------------------------------------
# Ray caster and camera


def test_ray_caster_pixel_convention_depth_and_barycentrics():
    # A square 2 m in front of a camera at the origin; its left edge projects to x = 20.6 px.
    f, cx, depth = 100.0, 31.5, 2.0
    left = (20.6 - cx) * depth / f
    square = np.array([[left, -0.5, depth], [0.5, -0.5, depth], [0.5, 0.5, depth], [left, 0.5, depth]])
    faces = np.array([[0, 2, 1], [0, 3, 2]])
    K = np.array([[f, 0, cx], [0, f, cx], [0, 0, 1.0]])
    rays = CameraRays(K, np.eye(4), 64, 64, supersample=2)
    caster = MeshRayCaster(square, faces)
    frame = render_mesh(caster, rays, lambda hits, x, d: np.full((len(x), 3), 0.5))
    row = frame.mask[32]
    assert not row[20] and row[21] and row[:21].sum() == 0  # pixel 21's samples (20.75, 21.25) are inside
    np.testing.assert_allclose(frame.depth[frame.mask], depth, atol=1e-5)
    assert np.all(frame.rgb[frame.mask] == 128) and np.all(frame.rgb[~frame.mask & (frame.coverage == 0)] == 0)
    # Barycentric hit points equal the ray's own intersection point.
    origins = np.zeros((5, 3))
    targets = np.array([[0.1, 0.2, depth], [-0.05, -0.3, depth], [0.4, 0.4, depth], [0.0, 0.0, depth], [0.3, -0.1, depth]])
    directions = targets / np.linalg.norm(targets, axis=1, keepdims=True)
    hits = caster.first_hits(origins, directions)
    assert hits.hit.all()
    x_hit = np.einsum("rk,rkc->rc", hits.barycentric, square[faces[hits.face_index]])
    np.testing.assert_allclose(x_hit, targets, atol=1e-5)
    np.testing.assert_allclose(hits.distance, np.linalg.norm(targets, axis=1), atol=1e-5)


def test_static_camera_frames_points_level_and_from_the_front():
    points = np.random.default_rng(0).uniform([-0.5, -0.2, -0.9], [0.5, 0.2, 0.9], size=(500, 3))
    K, w2c = frame_static_camera(points, 120, 100, distance=3.0, margin=0.1)
    x_pixels, z = project_points(K, w2c, points)
    assert np.all(z > 2.0) and np.all(z < 4.0)
    # Principal point at the image center ((W - 1) / 2, (H - 1) / 2); 10% free border on each side,
    # reached on at least one side.
    low, high = np.array([49.5 - 40.0, 59.5 - 48.0]), np.array([49.5 + 40.0, 59.5 + 48.0])
    assert np.all(x_pixels >= low - 1e-9) and np.all(x_pixels <= high + 1e-9)
    slack = np.minimum(x_pixels.min(axis=0) - low, high - x_pixels.max(axis=0))
    assert slack.min() < 1e-6
    # Level camera looking along +Y with world +Z up the image: image "down" is world -Z.
    np.testing.assert_allclose(w2c[2, :3], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(w2c[1, :3], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(look_w2c(np.zeros(3), np.array([0, 1.0, 0]))[:3, :3] @ [1, 0, 0], [1, 0, 0])


def test_yaw_turns_the_posed_body_about_the_vertical(body):
    subject = build_subject(body, "tight")
    rotations = torch.eye(3, dtype=torch.float64).expand(1, 104, 3, 3).clone()
    translation = torch.tensor([[0.1, 0.2, 0.0]], dtype=torch.float64)
    turned_r, turned_t = yaw_about_vertical(rotations, translation, np.pi / 2)
    before = pose_subject(subject, body, rotations, translation)[0]
    after = pose_subject(subject, body, turned_r, turned_t)[0]
    root = np.asarray(body.skeleton.rest_joints)[0]
    rz = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    np.testing.assert_allclose(after - root, (before - root) @ rz.T, atol=1e-9)


def test_holdout_frames_are_an_in_distribution_turn_between_the_training_views(body):
    from stages.synth import make_sequence, sequence_poses

    parts = make_sequence(body, train_frames=8, test_frames=3, seed=0, holdout_frames=4)
    assert [p.split for p in parts[:2]] == ["train", "test"]
    holdout = parts[1]
    assert holdout.frames == tuple(f"test_holdout_{i:04d}" for i in range(4))
    assert holdout.motion.name == "turntable" and holdout.yaw == pytest.approx(np.pi / 8)
    # Other small motions than the training turn, and the novel-pose motions still follow.
    rotations, _ = sequence_poses(body, parts)
    assert not torch.allclose(rotations[8:12], rotations[0:4])
    assert {p.motion.name for p in parts[2:]} <= {"walk", "arm_raise", "squat"}
    assert len(make_sequence(body, 8, 3, 0)) == len(parts) - 1
