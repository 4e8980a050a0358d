"""The visual-hull shape prior of captures with no template, and the static (root-only) subject.

Analytic: the hull mesh of two spheres seen by a turntable is closed, outward, holds both spheres
and leaves the gap between them; crushed space walled in by a "skirt" is kept, a crushed gap
open to free space is not; a rigid turn written as one root joint reproduces every frame.
End to end: `synth --skeleton root` -> `preprocess` gives a hull prior that holds the true surface
and is not much larger than it, and tiny training runs on a skeleton of one joint.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from igavatar.artifacts.manifest import read_artifact
from igavatar.body.rotations import axis_angle_to_matrix
from igavatar.body.skeleton import forward_kinematics
from igavatar.capture.visual_hull import MaskViews, enclosed_cells, hull_cells, hull_prior_mesh, search_box
from igavatar.render.cameras import turntable_cameras
from igavatar.synth.skeleton_capture import root_only_poses
from igavatar_cli.main import app
from stages.preprocess import PreprocessOptions, run_preprocess
from stages.synth import SynthOptions, run_synth
from stages.train import TrainOptions, run_train
from test_visual_hull import BOX, CENTERS, FRONT, RADIUS, UP, camera_rays, sphere_masks


def test_hull_mesh_of_two_spheres_is_closed_holds_them_and_leaves_the_gap():
    n_views, size = 24, 64
    K, w2c = turntable_cameras(BOX[0], BOX[1], n_views, size, size, up=UP, front=FRONT, elevation=math.radians(5.0))
    K = K.expand(n_views, 3, 3) if K.ndim == 2 else K
    masks = sphere_masks(K, w2c, size)
    views = MaskViews(masks=[m.numpy() for m in masks], K=K.numpy(), w2c=w2c.numpy(), frames=list(range(n_views)))
    hull = hull_prior_mesh(hull_cells(BOX, lambda frame, x: x, views, cell_size=0.02, mask_dilation_px=1))
    assert hull is not None and hull.views == n_views and not hull.touches_box
    mesh = trimesh.Trimesh(hull.vertices.numpy(), hull.faces.numpy(), process=False)
    assert mesh.is_watertight and mesh.volume > 0  # closed, normals outwards
    # The largest part only: the two spheres are two parts, so the hull keeps one of them whole.
    kept = [bool(mesh.contains(c[None].numpy())[0]) for c in CENTERS]
    assert sum(kept) == 1
    sphere_volume = 4.0 / 3.0 * math.pi * RADIUS**3
    assert sphere_volume * 0.9 < mesh.volume < sphere_volume * 2.5
    # Every point of the kept sphere's surface lies inside the hull or within a cell of it.
    center = CENTERS[kept.index(True)]
    directions = torch.nn.functional.normalize(torch.randn(500, 3, generator=torch.Generator().manual_seed(0)), dim=1)
    surface = (center + RADIUS * directions).numpy()
    outside = ~mesh.contains(surface)
    distance = np.abs(trimesh.proximity.signed_distance(mesh, surface[outside])) if outside.any() else np.zeros(0)
    assert (distance < 0.02).all()
    gap = np.array([[0.0, 0.0, 0.0]])
    assert not mesh.contains(gap)[0]


def cylinder_masks(K: torch.Tensor, w2c: torch.Tensor, size: int, radius: float, half_height: float) -> torch.Tensor:
    """(N, size, size) bool silhouettes of a solid cylinder around the z axis, |z| <= half_height."""
    masks = []
    for origin, d in camera_rays(K, w2c, size):
        o = origin.expand_as(d)
        # The ray's span inside the infinite cylinder (a quadratic in t), then its z range there.
        a = d[:, :2].square().sum(-1)
        b = 2.0 * (o[:, :2] * d[:, :2]).sum(-1)
        c = o[:, :2].square().sum(-1) - radius**2
        disc = b.square() - 4.0 * a * c
        root = disc.clamp_min(0.0).sqrt()
        t0, t1 = (-b - root) / (2.0 * a), (-b + root) / (2.0 * a)
        z0, z1 = o[:, 2] + t0 * d[:, 2], o[:, 2] + t1 * d[:, 2]
        hit = (disc > 0) & (t1 > 0) & (torch.minimum(z0, z1) <= half_height) & (torch.maximum(z0, z1) >= -half_height)
        masks.append(hit.reshape(size, size))
    return torch.stack(masks)


def test_crushed_space_walled_in_by_a_skirt_is_kept():
    # A solid cylinder (a skirt and what it hides) whose core skinning crushes to a tenth of its
    # width in every frame, as the space between spread canonical legs under a skirt is crushed
    # when the legs close: the core is inside every mask, crushed, and walled in by the skirt.
    radius, core, half_height = 0.2, 0.12, 0.15
    box = torch.tensor([[-0.4, -0.4, -0.3], [0.4, 0.4, 0.3]])
    n_views, size = 24, 64
    K, w2c = turntable_cameras(box[0], box[1], n_views, size, size, up=UP, front=FRONT, elevation=math.radians(5.0))
    K = K.expand(n_views, 3, 3) if K.ndim == 2 else K
    masks = cylinder_masks(K, w2c, size, radius, half_height)
    views = MaskViews(masks=[m.numpy() for m in masks], K=K.numpy(), w2c=w2c.numpy(), frames=list(range(n_views)))

    def skin(frame: int, x: torch.Tensor) -> torch.Tensor:
        inner = x[:, :2].norm(dim=1, keepdim=True) < core
        return torch.where(inner, x * torch.tensor([0.1, 0.1, 1.0]), x)

    hull = hull_prior_mesh(hull_cells(box, skin, views, cell_size=0.02, mask_dilation_px=1))
    mesh = trimesh.Trimesh(hull.vertices.numpy(), hull.faces.numpy(), process=False)
    assert mesh.is_watertight
    axis = np.array([[0.0, 0.0, z] for z in (-0.1, -0.05, 0.0, 0.05, 0.1)])
    assert mesh.contains(axis).all()  # the crushed core is kept: the skirt walls it in
    full = math.pi * radius**2 * 2 * half_height
    assert full * 0.8 < mesh.volume < full * 1.6


def test_enclosed_cells_fill_a_walled_in_core_and_leave_an_open_gap():
    kept = np.zeros((6, 12, 12), bool)
    candidates = np.zeros_like(kept)
    # A ring of kept cells around a core of candidates, in every horizontal (first-axis) plane.
    kept[:, 2:10, 2:10] = True
    kept[:, 4:8, 4:8] = False
    candidates[:, 4:8, 4:8] = True
    added = enclosed_cells(kept, candidates)
    # All of the core but its top and bottom layers, whose outer neighbours are not kept.
    assert added[1:-1, 4:8, 4:8].all() and not added[[0, -1]].any() and added.sum() == 4 * 16
    # Two "legs" with a candidate gap between them that opens to the grid's edge in every plane.
    legs = np.zeros_like(kept)
    legs[:, 2:10, 1:4] = True
    legs[:, 2:10, 8:11] = True
    gap = np.zeros_like(kept)
    gap[:, 2:10, 4:8] = True
    assert not enclosed_cells(legs, gap).any()
    # Only candidates are added: a walled-in cell that is not one stays out.
    assert not enclosed_cells(kept, np.zeros_like(kept)).any()


def test_search_box_gives_a_lone_root_room_for_a_standing_person():
    box = search_box(torch.tensor([[0.1, 0.2, 0.9]]))
    assert torch.allclose(box[0], torch.tensor([0.1, 0.2, 0.9]) - 1.1) and torch.allclose(box[1], torch.tensor([0.1, 0.2, 0.9]) + 1.1)
    joints = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 3.0]])  # taller than 2 x 1.1 m: the margin rules
    box = search_box(joints)
    assert float(box[0, 2]) == pytest.approx(-0.35) and float(box[1, 2]) == pytest.approx(3.35)


def test_root_only_poses_reproduce_a_rigid_turn_and_refuse_motion():
    rng = np.random.default_rng(0)
    first = rng.normal(size=(200, 3)) * [0.3, 0.2, 0.8] + [0.0, 0.0, 1.0]
    angles = np.linspace(0.0, 2.0 * np.pi, 7, endpoint=False)
    frames = []
    for k, angle in enumerate(angles):
        rotation = axis_angle_to_matrix(torch.tensor([0.0, 0.0, angle])).numpy()
        frames.append(first @ rotation.T + [0.05 * k, -0.02 * k, 0.0])
    arrays = root_only_poses(np.stack(frames))
    assert arrays["parents"].tolist() == [-1] and arrays["rotvecs"].shape == (7, 1, 3)
    rest = torch.as_tensor(arrays["rest_joints"])
    global_posed = forward_kinematics(axis_angle_to_matrix(torch.as_tensor(arrays["rotvecs"])), rest,
                                      arrays["parents"], torch.as_tensor(arrays["transl"]))
    for frame, transform in zip(frames, global_posed[:, 0]):
        # bone transform = G_posed @ inverse(G_rest), G_rest = [I | rest joint]
        moved = (torch.as_tensor(first) - rest) @ transform[:3, :3].T + transform[:3, 3]
        assert np.abs(moved.numpy() - frame).max() < 1e-9
    bent = np.stack(frames)
    bent[3, :50] += 0.05  # part of the body moved: not a static subject
    with pytest.raises(ValueError, match="frame 3 is not a rigid copy"):
        root_only_poses(bent)


def test_synth_root_refuses_novel_pose_frames(cli_runner, tmp_path):
    result = cli_runner.invoke(app, ["synth", "--out", str(tmp_path / "c"), "--skeleton", "root", "--test-frames", "3"])
    assert result.exit_code == 2
    assert "static subject" in result.output and "--test-frames 0" in result.output and "Traceback" not in result.output


@pytest.fixture(scope="module")
def static_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("static")
    run_synth(SynthOptions(out=run / "capture", resolution=96, train_frames=12, test_frames=0, holdout_frames=2,
                           skeleton="root", seed=3))
    run_preprocess(PreprocessOptions(capture=run / "capture", out=run / "dataset", max_size=96))
    return run


def test_static_capture_gets_a_hull_prior_that_holds_the_subject(static_run):
    capture = read_artifact(static_run / "capture", expected="capture")["data"]
    assert capture["body_model"] == "skeleton"
    data = read_artifact(static_run / "dataset", expected="dataset")["data"]
    assert data["shape_prior"] == "visual_hull" and data["joint_names"] == ["root"]
    prior = trimesh.load(static_run / "dataset" / "template.ply", process=False)
    truth = trimesh.load(static_run / "capture" / "scans" / "train_0000.ply", process=False)  # canonical = frame 0
    assert prior.is_watertight
    # The hull bounds the subject: nearly all of the true surface is inside it or within 2 cm
    # (masks of 96 px are ~3 cm a pixel at 3 m), and it is not a box around the whole scene.
    points = np.asarray(truth.vertices)[np.random.default_rng(0).choice(len(truth.vertices), 3000, replace=False)]
    outside = ~prior.contains(points)
    far = (np.abs(trimesh.proximity.signed_distance(prior, points[outside])) > 0.02).sum() if outside.any() else 0
    assert far / len(points) < 0.01
    assert truth.volume < prior.volume < 3.5 * truth.volume
    canonical_box = np.asarray(data["canonical_box"])
    assert (canonical_box[0] <= prior.bounds[0] + 1e-4).all() and (canonical_box[1] >= prior.bounds[1] - 1e-4).all()


def test_tiny_training_on_a_single_joint(static_run):
    run_train(TrainOptions(dataset=static_run / "dataset", out=static_run / "model", preset="tiny", steps=8, device="cpu"))
    from igavatar.avatar.model import load_model

    model = load_model(static_run / "model")
    truth = trimesh.load(static_run / "capture" / "scans" / "train_0000.ply", process=False)
    chest = torch.tensor(np.asarray(truth.vertices).mean(0)[None], dtype=torch.float32)
    beside = chest + torch.tensor([[0.0, 0.0, 1.5]])  # above the head
    with torch.no_grad():
        sdf = model.avatar.sdf_field(torch.cat((chest, beside)))[0].reshape(-1)
    assert float(sdf[0]) < 0 < float(sdf[1]), "the avatar of a lone root has no body inside its hull"


def test_volume_ratio_is_one_for_rigid_motion_and_small_where_space_is_crushed():
    from igavatar.capture.visual_hull import grid_points, grid_spacing, volume_ratio

    box = torch.tensor([[-0.2, -0.1, -0.3], [0.2, 0.1, 0.3]])
    points, shape = grid_points(box[0], box[1], 0.02)
    spacing = grid_spacing(box[0], box[1], shape)
    rotation = axis_angle_to_matrix(torch.tensor([0.3, -0.2, 1.1]))
    rigid = points @ rotation.T + torch.tensor([1.0, 2.0, 3.0])
    assert torch.allclose(volume_ratio(rigid, shape, spacing), torch.ones(len(points), dtype=torch.float64), atol=1e-5)
    squeezed = points * torch.tensor([0.1, 1.0, 1.0])  # a gap closed to a tenth of its width
    assert torch.allclose(volume_ratio(squeezed, shape, spacing), torch.full((len(points),), 0.1, dtype=torch.float64), atol=1e-5)
    mirrored = points * torch.tensor([-1.0, 1.0, 1.0])  # folded over: orientation reversed
    assert (volume_ratio(mirrored, shape, spacing) < 0).all()


def test_bare_skeleton_capture_gets_a_hull_prior_around_its_posed_truth(tmp_path):
    """Anny's joints without a template and without a body fitted to them: the prior comes from the masks
    and holds the subject."""
    from igavatar.avatar.canonical_report import canonical_truth
    from igavatar.avatar.subject import SubjectArrays

    run_synth(SynthOptions(out=tmp_path / "capture", resolution=96, train_frames=10, test_frames=0, skeleton="bare", seed=5))
    run_preprocess(PreprocessOptions(capture=tmp_path / "capture", out=tmp_path / "dataset", max_size=96, body_fit="none"))
    data = read_artifact(tmp_path / "dataset", expected="dataset")
    assert data["data"]["shape_prior"] == "visual_hull" and data["config"]["hull_prior"]["version"] >= 2
    prior = trimesh.load(tmp_path / "dataset" / "template.ply", process=False)
    vertices, faces = canonical_truth(tmp_path / "capture", SubjectArrays.read(tmp_path / "dataset" / "subject.npz"))
    truth = trimesh.Trimesh(vertices, faces, process=False)
    assert prior.is_watertight and truth.volume < prior.volume < 3.5 * truth.volume
    points = vertices[np.random.default_rng(0).choice(len(vertices), 2000, replace=False)]
    inside_or_near = prior.contains(points)
    if (~inside_or_near).any():
        near = np.abs(trimesh.proximity.signed_distance(prior, points[~inside_or_near])) < 0.03
        inside_or_near[~inside_or_near] = near
    # Skinning errors of bone weights at 96 px: most, not all, of the truth is within 3 cm.
    assert inside_or_near.mean() > 0.95


def test_shape_prior_option_is_checked(cli_runner, small_run, tmp_path):
    result = cli_runner.invoke(app, ["preprocess", "--capture", str(small_run / "capture"), "--out", str(tmp_path / "d"),
                                     "--shape-prior", "hull"])
    assert result.exit_code == 2 and "--shape-prior 'hull'" in result.output and "visual-hull" in result.output
    # small_run has 4 training frames: too few views for a hull, and the user asked for one.
    result = cli_runner.invoke(app, ["preprocess", "--capture", str(small_run / "capture"), "--out", str(tmp_path / "d"),
                                     "--shape-prior", "visual-hull"])
    assert result.exit_code == 2 and "4 training frames" in result.output and "at least 8" in result.output
    assert not (tmp_path / "d").exists()


def test_a_template_subject_with_a_hull_prior_keeps_its_naked_template_for_the_limb_check(tmp_path):
    """`--shape-prior visual-hull` on a body-model capture: template.ply is the hull, body_template.ply
    the naked template, and the canonical report's limb check reads the latter."""
    from igavatar.avatar.canonical_report import canonical_section
    from igavatar.avatar.dataset import read_dataset

    run_synth(SynthOptions(out=tmp_path / "capture", resolution=96, train_frames=10, test_frames=0, seed=5))
    run_preprocess(PreprocessOptions(capture=tmp_path / "capture", out=tmp_path / "dataset", max_size=96,
                                     shape_prior="visual-hull"))
    dataset = read_dataset(tmp_path / "dataset")
    assert dataset.shape_prior == "visual_hull"
    hull = trimesh.load(tmp_path / "dataset" / "template.ply", process=False)
    body = trimesh.load(tmp_path / "dataset" / "body_template.ply", process=False)
    assert body.is_watertight and hull.volume > 1.2 * body.volume  # the hull bounds the naked body loosely
    section, picture = canonical_section(dataset, tmp_path / "capture", (np.asarray(body.vertices), np.asarray(body.faces)),
                                         n_iou=20_000)
    assert section["limb_check"]["passed"] and len(section["limb_check"]["parts"]) == 14
    shrunk = np.asarray(body.vertices) * 0.8  # a body 20 % too small misses its hands and feet
    section, _ = canonical_section(dataset, tmp_path / "capture", (shrunk, np.asarray(body.faces)), n_iou=20_000)
    assert not section["limb_check"]["passed"]
    assert picture is not None and picture.shape[0] == 3 * 320  # prediction, truth, prior
