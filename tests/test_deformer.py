"""Tests of the Fast-SNARF deformer on a synthetic articulated stick figure."""

import time

import pytest
import torch

from igavatar.errors import InputError
from igavatar.model.deformer import (
    DeformerConfig,
    FastSnarfDeformer,
    _remove_duplicates,
    init_parts,
    select_candidates,
)
from igavatar.skinning.grid import canonical_grid_box, grid_point_positions

# A 17-joint star-pose stick figure in igavatar's body frame (+Z up, facing -Y, x lateral).
JOINTS = torch.tensor(
    [
        [0.00, 0.0, 0.95],  # 0 pelvis
        [0.00, 0.0, 1.15],  # 1 spine
        [0.00, 0.0, 1.35],  # 2 chest
        [0.00, 0.0, 1.55],  # 3 neck
        [0.00, 0.0, 1.68],  # 4 head
        [0.18, 0.0, 1.48],  # 5 left shoulder
        [0.45, 0.0, 1.40],  # 6 left elbow
        [0.70, 0.0, 1.32],  # 7 left wrist
        [-0.18, 0.0, 1.48],  # 8 right shoulder
        [-0.45, 0.0, 1.40],  # 9 right elbow
        [-0.70, 0.0, 1.32],  # 10 right wrist
        [0.10, 0.0, 0.90],  # 11 left hip
        [0.22, 0.0, 0.50],  # 12 left knee
        [0.32, 0.0, 0.10],  # 13 left ankle
        [-0.10, 0.0, 0.90],  # 14 right hip
        [-0.22, 0.0, 0.50],  # 15 right knee
        [-0.32, 0.0, 0.10],  # 16 right ankle
    ]
)
PARENTS = [-1, 0, 1, 2, 3, 2, 5, 6, 2, 8, 9, 0, 11, 12, 0, 14, 15]
CHILD = [1, 2, 3, 4, None, 6, 7, None, 9, 10, None, 12, 13, None, 15, 16, None]
INIT_BONES = (0, 1, 2, 3, 4, 5, 6, 8, 9, 11, 12, 14, 15)  # 13 starts, like SMPL's major bones
RADIUS = 0.05


def _bone_segments() -> tuple[torch.Tensor, torch.Tensor]:
    """(J, 3) start and end of each bone; leaf bones extend along their parent's direction."""
    starts, ends = [], []
    for joint, child in enumerate(CHILD):
        start = JOINTS[joint]
        if child is not None:
            end = JOINTS[child]
        else:
            direction = start - JOINTS[PARENTS[joint]]
            end = start + 0.15 * direction / direction.norm()
        starts.append(start)
        ends.append(end)
    return torch.stack(starts), torch.stack(ends)


def _segment_distance(points: torch.Tensor, starts: torch.Tensor, ends: torch.Tensor) -> torch.Tensor:
    """(P, 3) points -> (P, J) distances to the bone segments."""
    axis = ends - starts
    t = ((points[:, None, :] - starts) * axis).sum(-1) / axis.square().sum(-1)
    closest = starts + t.clamp(0.0, 1.0)[..., None] * axis
    return (points[:, None, :] - closest).norm(dim=-1)


def _stick_figure_grid(dtype=torch.float32, resolution=(40, 12, 40)):
    """Smooth weights (softmax of -distance^2 to bones) sampled on a Fast-SNARF style grid."""
    starts, ends = _bone_segments()
    body = torch.cat([starts, ends]).double()
    box_min, box_max = canonical_grid_box(body, squeeze_axis=1)
    positions = grid_point_positions(box_min.double(), box_max.double(), resolution).reshape(-1, 3)
    logits = -_segment_distance(positions, starts.double(), ends.double()).square() / (2 * 0.06**2)
    weights = torch.softmax(logits, dim=1).T.reshape(len(CHILD), *resolution)
    return weights.to(dtype).contiguous(), box_min.to(dtype), box_max.to(dtype)


def _axis_angle_to_matrix(rotvec: torch.Tensor) -> torch.Tensor:
    angle = rotvec.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    axis = rotvec / angle
    x, y, z = axis.unbind(-1)
    zero = torch.zeros_like(x)
    skew = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*rotvec.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=rotvec.dtype).expand_as(skew)
    s, c = torch.sin(angle)[..., None], torch.cos(angle)[..., None]
    return eye + s * skew + (1 - c) * skew @ skew


def _bone_transforms(seed: int, max_angle: float = 0.6, dtype=torch.float32) -> torch.Tensor:
    """Random pose by forward kinematics: B_j = G_j(pose) @ inverse(G_j(canonical))."""
    generator = torch.Generator().manual_seed(seed)
    num_joints = len(PARENTS)
    directions = torch.randn(num_joints, 3, generator=generator, dtype=torch.float64)
    directions = torch.nn.functional.normalize(directions, dim=-1)
    angles = torch.rand(num_joints, 1, generator=generator, dtype=torch.float64) * max_angle
    rotations = _axis_angle_to_matrix(directions * angles)
    joints = JOINTS.double()
    world = []
    for j, parent in enumerate(PARENTS):
        local = torch.eye(4, dtype=torch.float64)
        local[:3, :3] = rotations[j]
        if parent < 0:
            local[:3, 3] = joints[j] + torch.tensor([0.1, -0.2, 0.05], dtype=torch.float64)
            world.append(local)
        else:
            local[:3, 3] = joints[j] - joints[parent]
            world.append(world[parent] @ local)
    world = torch.stack(world)
    rest_inverse = torch.eye(4, dtype=torch.float64).repeat(num_joints, 1, 1)
    rest_inverse[:, :3, 3] = -joints
    return (world @ rest_inverse).to(dtype)


def _canonical_points(count: int, seed: int, dtype=torch.float32) -> torch.Tensor:
    """Points in capsules around the bones, joints included (t spans the whole segment)."""
    generator = torch.Generator().manual_seed(seed)
    starts, ends = _bone_segments()
    bone = torch.randint(0, len(CHILD), (count,), generator=generator)
    t = torch.rand(count, 1, generator=generator)
    offset = torch.nn.functional.normalize(torch.randn(count, 3, generator=generator), dim=-1)
    offset = offset * RADIUS * torch.rand(count, 1, generator=generator) ** (1 / 3)
    return (starts[bone] + t * (ends[bone] - starts[bone]) + offset).to(dtype)


def _recovery(candidates, valid, x_true, tolerance=1e-4):
    error = (candidates - x_true[:, None, :]).norm(dim=-1)
    error = torch.where(valid, error, torch.full_like(error, float("inf")))
    return error.min(dim=1).values < tolerance


@pytest.fixture(scope="module")
def stick_figure():
    weights, box_min, box_max = _stick_figure_grid()
    config = DeformerConfig(init_bones=INIT_BONES)
    return FastSnarfDeformer(weights, box_min, box_max, config)


def test_identity_pose_returns_each_point_once(stick_figure):
    frame = stick_figure.prepare(torch.eye(4).repeat(len(PARENTS), 1, 1))
    x_canonical = _canonical_points(500, seed=0)
    candidates, valid = stick_figure.canonicalize(x_canonical, frame)
    assert candidates.shape == (500, len(INIT_BONES), 3) and valid.shape == (500, len(INIT_BONES))
    # All 13 starts coincide with the point, which already solves LBS: duplicates leave one.
    assert valid.sum(dim=1).tolist() == [1] * 500
    chosen, any_valid = select_candidates(candidates, valid, torch.zeros(valid.shape))
    assert bool(any_valid.all())
    torch.testing.assert_close(chosen, x_canonical, atol=1e-6, rtol=0)
    x_posed = stick_figure.forward_skinning(x_canonical, frame)
    torch.testing.assert_close(x_posed, x_canonical, atol=1e-6, rtol=0)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_canonicalize_recovers_posed_points(stick_figure, seed):
    frame = stick_figure.prepare(_bone_transforms(seed))
    x_canonical = _canonical_points(3000, seed=seed)
    x_posed = stick_figure.forward_skinning(x_canonical, frame)
    candidates, valid = stick_figure.canonicalize(x_posed, frame)
    recovered = _recovery(candidates, valid, x_canonical)
    rate = float(recovered.float().mean())
    print(f"seed {seed}: recovered {rate:.4%} of 3000 points")
    assert rate > 0.99
    # Every valid candidate is a true root inside the box, and no two valid roots coincide.
    x_reposed = stick_figure.forward_skinning(candidates.reshape(-1, 3), frame).reshape(candidates.shape)
    residual = (x_reposed - x_posed[:, None, :]).norm(dim=-1)
    assert bool((residual[valid] < 1e-5).all())
    pair_distance = (candidates[:, :, None, :] - candidates[:, None, :, :]).norm(dim=-1)
    both_valid = valid[:, :, None] & valid[:, None, :] & ~torch.eye(len(INIT_BONES), dtype=torch.bool)
    assert bool((pair_distance[both_valid] >= 1e-4).all())


def test_top_k_starts_keep_recovery(stick_figure):
    weights, box_min, box_max = _stick_figure_grid()
    config = DeformerConfig(init_bones=INIT_BONES, init_top_k=3)
    deformer = FastSnarfDeformer(weights, box_min, box_max, config)
    frame = deformer.prepare(_bone_transforms(4))
    x_canonical = _canonical_points(2000, seed=4)
    candidates, valid = deformer.canonicalize(deformer.forward_skinning(x_canonical, frame), frame)
    assert candidates.shape == (2000, 3, 3)
    assert float(_recovery(candidates, valid, x_canonical).float().mean()) > 0.97



#: Start bones without the elbows and knees: the forearms and shins are skinned to bones that start
#: no search, as a body model's knee belongs to a twist bone and its ankle to the foot's children.
SPARSE_INIT_BONES = (0, 1, 2, 3, 4, 5, 8, 11, 14)


def test_init_parts_follow_the_chain_to_the_nearest_start_bone():
    parts = init_parts(PARENTS, SPARSE_INIT_BONES)
    assert len(parts) == len(PARENTS)
    named = {bone: SPARSE_INIT_BONES[part] for bone, part in enumerate(parts)}
    assert named[12] == named[13] == 11 and named[15] == named[16] == 14  # shin and foot: their hip
    assert named[6] == named[7] == 5 and named[10] == 8  # forearm and hand: their shoulder
    assert all(named[b] == b for b in SPARSE_INIT_BONES)
    assert init_parts([-1, 0, 1], (1,)) == (0, 0, 0)  # above every start bone: the first part
    with pytest.raises(InputError, match="init_parts"):
        DeformerConfig(init_bones=(0, 1), init_parts=(0, 2, 1))


def _bent_pose_recovery(configs: dict[str, DeformerConfig]) -> dict[str, float]:
    """Share of 3000 stick-figure points root-found back after a strongly bent pose, per config;
    every valid candidate must reproduce its posed point."""
    weights, box_min, box_max = _stick_figure_grid()
    bones = _bone_transforms(4, max_angle=1.0)
    x_canonical = _canonical_points(3000, seed=6)
    recovered = {}
    for name, config in configs.items():
        deformer = FastSnarfDeformer(weights, box_min, box_max, config)
        frame = deformer.prepare(bones)
        x_posed = deformer.forward_skinning(x_canonical, frame)
        candidates, valid = deformer.canonicalize(x_posed, frame)
        assert candidates.shape == (len(x_canonical), deformer.candidates_per_point(frame), 3)
        reposed = deformer.forward_skinning(candidates[valid], frame)
        assert (reposed - x_posed.unsqueeze(1).expand_as(candidates)[valid]).norm(dim=-1).max() < 1e-4
        recovered[name] = float(_recovery(candidates, valid, x_canonical).float().mean())
    return recovered


def test_top_k_ranked_by_parts_find_roots_where_starts_own_no_weight(stick_figure):
    """With the knees and elbows not among the starts, ranking a start by its bone's own weight
    keeps the wrong one for some shin and forearm points in a strongly bent pose (measured 94.5 %
    recovered); ranking by its part's weight keeps the one that converges (100 %), as trying every
    start does."""
    recovered = _bent_pose_recovery({
        "own": DeformerConfig(init_bones=SPARSE_INIT_BONES, init_top_k=1, fallback_starts=False),
        "parts": DeformerConfig(init_bones=SPARSE_INIT_BONES, init_top_k=1, fallback_starts=False,
                                init_parts=init_parts(PARENTS, SPARSE_INIT_BONES)),
        "all": DeformerConfig(init_bones=SPARSE_INIT_BONES),
    })
    assert recovered["parts"] > recovered["own"] + 0.02, recovered
    assert recovered["parts"] > recovered["all"] - 0.01, recovered


def test_fallback_starts_find_the_roots_a_wrong_ranking_loses(stick_figure):
    """Where none of a point's kept starts converges (here the own-weight ranking of the test
    above, which keeps a wrong start for some bent shins and forearms), the fallback tries the
    other starts: as many roots come back as with every start (measured 94.5 % -> 100 %, every
    start 100 %)."""
    recovered = _bent_pose_recovery({
        "kept only": DeformerConfig(init_bones=SPARSE_INIT_BONES, init_top_k=1, fallback_starts=False),
        "fallback": DeformerConfig(init_bones=SPARSE_INIT_BONES, init_top_k=1),
        "all": DeformerConfig(init_bones=SPARSE_INIT_BONES),
    })
    assert recovered["fallback"] > recovered["kept only"] + 0.02, recovered
    assert recovered["fallback"] > recovered["all"] - 0.005, recovered


def test_remove_duplicates_is_sequential():
    candidates = torch.tensor([[[0.0, 0, 0], [0.6e-4, 0, 0], [1.2e-4, 0, 0], [5.0, 0, 0]]])
    valid = torch.tensor([[True, True, True, False]])
    # The third is a duplicate of the second only, which was itself dropped: it stays valid.
    assert _remove_duplicates(candidates, valid, 1e-4).tolist() == [[True, False, True, False]]


def test_select_candidates_picks_highest_valid_score():
    candidates = torch.arange(12, dtype=torch.float32).reshape(2, 2, 3)
    candidates = torch.cat([candidates, candidates + 100], dim=1)  # (2, 4, 3)
    valid = torch.tensor([[True, False, True, True], [False, False, False, False]])
    score = torch.tensor([[0.5, 9.0, 2.0, 1.0], [1.0, 2.0, 3.0, 4.0]])
    chosen, any_valid = select_candidates(candidates, valid, score)
    torch.testing.assert_close(chosen[0], candidates[0, 2])
    assert any_valid.tolist() == [True, False]


def _solve(deformer, x_posed, frame, near):
    """The valid root of each posed point closest to `near` (for finite differences)."""
    candidates, valid = deformer.canonicalize(x_posed, frame)
    distance = (candidates - near[:, None]).norm(dim=-1)
    distance = torch.where(valid, distance, torch.full_like(distance, float("inf")))
    best = distance.argmin(dim=1)
    assert bool(torch.isfinite(distance.min(dim=1).values).all())
    return candidates[torch.arange(len(best)), best]


def test_implicit_gradient_matches_finite_differences():
    weights, box_min, box_max = _stick_figure_grid(dtype=torch.float64)
    config = DeformerConfig(init_bones=INIT_BONES, max_iterations=60, converge_threshold=1e-12)
    deformer = FastSnarfDeformer(weights, box_min, box_max, config)
    bones = _bone_transforms(5, dtype=torch.float64).requires_grad_(True)
    frame = deformer.prepare(bones)
    x_true = _canonical_points(6, seed=5, dtype=torch.float64)
    x_posed = deformer.forward_skinning(x_true, frame).detach().requires_grad_(True)
    root = _solve(deformer, x_posed, frame, x_true)
    torch.testing.assert_close(root, x_true, atol=1e-9, rtol=0)
    x_canonical = deformer.attach_implicit_gradient(root, x_posed, frame)
    torch.testing.assert_close(x_canonical, root, atol=0, rtol=0)

    # d x_c / d x_d against central differences of re-solved roots.
    rows = [torch.autograd.grad(x_canonical[:, r].sum(), x_posed, retain_graph=True)[0] for r in range(3)]
    jacobian = torch.stack(rows, dim=1)  # (P, 3 out, 3 in)
    eps = 1e-5
    frame_fixed = deformer.prepare(bones.detach())
    for c in range(3):
        step = torch.zeros(3, dtype=torch.float64)
        step[c] = eps
        plus = _solve(deformer, x_posed.detach() + step, frame_fixed, root)
        minus = _solve(deformer, x_posed.detach() - step, frame_fixed, root)
        torch.testing.assert_close(jacobian[:, :, c], (plus - minus) / (2 * eps), atol=1e-6, rtol=1e-5)
    # It is the inverse of the full LBS Jacobian (including d w / d x), not of sum_j w_j R_j.
    lbs_jacobian = deformer.lbs_jacobian(root, frame_fixed)
    identity = torch.eye(3, dtype=torch.float64).expand(6, 3, 3)
    torch.testing.assert_close(jacobian @ lbs_jacobian, identity, atol=1e-9, rtol=0)

    # d x_c / d (translation of the left elbow bone) through the prepared frame.
    bone = 6
    probe = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
    grad_bones = torch.autograd.grad((x_canonical @ probe).sum(), bones)[0]
    for c in range(3):
        bumped = [bones.detach().clone(), bones.detach().clone()]
        bumped[0][bone, c, 3] += eps
        bumped[1][bone, c, 3] -= eps
        plus = _solve(deformer, x_posed.detach(), deformer.prepare(bumped[0]), root)
        minus = _solve(deformer, x_posed.detach(), deformer.prepare(bumped[1]), root)
        numeric = (((plus - minus) / (2 * eps)) @ probe).sum()
        torch.testing.assert_close(grad_bones[bone, c, 3], numeric, atol=1e-6, rtol=1e-5)


def test_float64_grid_gives_float64_roots_and_rejects_bad_shapes(stick_figure):
    with pytest.raises(InputError, match="bone_transforms"):
        stick_figure.prepare(torch.eye(4).repeat(3, 1, 1))
    frame = stick_figure.prepare(torch.eye(4).repeat(len(PARENTS), 1, 1))
    with pytest.raises(InputError, match="x_posed"):
        stick_figure.canonicalize(torch.zeros(5, 2), frame)
    with pytest.raises(InputError, match="init_bones"):
        weights, box_min, box_max = _stick_figure_grid()
        FastSnarfDeformer(weights, box_min, box_max, DeformerConfig(init_bones=(0, 40)))
    candidates, valid = stick_figure.canonicalize(torch.zeros(0, 3), frame)
    assert candidates.shape == (0, len(INIT_BONES), 3) and valid.shape == (0, len(INIT_BONES))


def test_canonicalize_throughput(stick_figure):
    """Points/s of canonicalize for 2^14 posed points and 13 starts on CPU (reported, -s)."""
    frame = stick_figure.prepare(_bone_transforms(6))
    x_posed = stick_figure.forward_skinning(_canonical_points(2**14, seed=6), frame)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # one thread: the figure is less sensitive to other processes
    try:
        stick_figure.canonicalize(x_posed[:256], frame)  # warm-up
        start = time.perf_counter()
        candidates, valid = stick_figure.canonicalize(x_posed, frame)
        seconds = time.perf_counter() - start
    finally:
        torch.set_num_threads(threads)
    print(f"canonicalize: {2**14 / seconds:,.0f} points/s ({seconds:.3f} s for 2^14 points, "
          "13 starts, 1 thread)")
    assert bool(valid.any(dim=1).float().mean() > 0.99)


def test_chunked_canonicalize_equals_unchunked():
    weights, box_min, box_max = _stick_figure_grid()
    whole = FastSnarfDeformer(weights, box_min, box_max, DeformerConfig(init_bones=INIT_BONES))
    chunk_config = DeformerConfig(init_bones=INIT_BONES, chunk_size=97)
    chunked = FastSnarfDeformer(weights, box_min, box_max, chunk_config)
    bones = _bone_transforms(7)
    x_posed = whole.forward_skinning(_canonical_points(500, seed=7), whole.prepare(bones))
    candidates, valid = whole.canonicalize(x_posed, whole.prepare(bones))
    candidates_chunked, valid_chunked = chunked.canonicalize(x_posed, chunked.prepare(bones))
    assert torch.equal(valid, valid_chunked)
    torch.testing.assert_close(candidates, candidates_chunked, atol=1e-6, rtol=0)
