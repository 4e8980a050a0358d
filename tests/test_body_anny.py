"""The Anny adapter: igavatar FK + LBS reproduce Anny's own forward pass (acceptance: < 1e-4 m)."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

pytest.importorskip("anny")

from igavatar.body.anny_body import (  # noqa: E402
    ANNY_BONE_COUNT,
    ANNY_PHENOTYPE_DEFAULTS,
    ANNY_PHENOTYPE_LABELS,
    AnnyBody,
    load_anny,
    resolve_phenotype,
)
from igavatar.body.rotations import axis_angle_to_matrix, rigid_matrix  # noqa: E402
from igavatar.errors import BodyModelError, InputError  # noqa: E402

ACCEPTANCE_M = 1e-4
OTHER_PHENOTYPE = {"gender": 0.9, "age": 0.25, "muscle": 0.7, "weight": 0.8, "height": 0.15, "proportions": 0.3}


@pytest.fixture(scope="module")
def body() -> AnnyBody:
    return AnnyBody.load()


@pytest.fixture(scope="module")
def anny_default_model():
    """Anny exactly as a user gets it: anny.Anny() with its default (Warp) skinning."""
    import anny

    load_anny()  # points anny at the same cache directory
    return anny.Anny()


def random_pose_parameters(seed: int, n_frames: int = 3, max_angle: float = 0.5) -> torch.Tensor:
    """Anny "local-ref" deltas: every bone rotated up to max_angle, a random global pose at entry 0."""
    generator = torch.Generator().manual_seed(seed)
    axis = torch.randn(n_frames, ANNY_BONE_COUNT, 3, generator=generator, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angle = torch.rand(n_frames, ANNY_BONE_COUNT, 1, generator=generator, dtype=torch.float64) * max_angle
    angle[:, 0] = torch.rand(n_frames, 1, generator=generator, dtype=torch.float64) * np.pi
    rotations = axis_angle_to_matrix(axis * angle)
    translation = torch.zeros(n_frames, ANNY_BONE_COUNT, 3, dtype=torch.float64)
    translation[:, 0] = torch.randn(n_frames, 3, generator=generator, dtype=torch.float64)
    return rigid_matrix(rotations, translation)


def test_anny_body_shapes_and_skeleton(body: AnnyBody):
    vertex_count = body.rest_vertices.shape[0]
    assert body.rest_vertices.shape == (vertex_count, 3) and vertex_count == 13718
    assert body.rest_vertices.dtype == torch.float32
    assert body.faces.shape[1] == 3 and body.faces.dtype == torch.int64
    assert int(body.faces.min()) == 0 and int(body.faces.max()) == vertex_count - 1
    assert body.skinning_weights.shape == (vertex_count, ANNY_BONE_COUNT)
    torch.testing.assert_close(body.skinning_weights.sum(-1), torch.ones(vertex_count))
    assert body.skeleton.num_joints == ANNY_BONE_COUNT
    assert body.skeleton.joint_names[0] == "root" and "lowerleg01.L" in body.skeleton.joint_names
    # Anny's frame: +Z up, the face towards -Y, the subject's left at +X; height ~1.6 m.
    height = float(body.rest_vertices[:, 2].max() - body.rest_vertices[:, 2].min())
    assert 1.4 < height < 1.9
    heads = body.skeleton.rest_joints
    assert heads[body.skeleton.index("head"), 2] > heads[body.skeleton.index("foot.L"), 2]
    assert heads[body.skeleton.index("eye.L"), 1] < heads[body.skeleton.index("head"), 1]
    assert heads[body.skeleton.index("upperleg01.L"), 0] > 0
    assert body.phenotype == dict(ANNY_PHENOTYPE_DEFAULTS)
    assert body.phenotype_labels == ANNY_PHENOTYPE_LABELS
    assert body.phenotype_values.shape == (len(ANNY_PHENOTYPE_LABELS),)


@pytest.mark.parametrize("seed", [0, 1])
def test_fk_lbs_reproduce_anny_default_forward(body: AnnyBody, anny_default_model, seed: int):
    """The acceptance test: random poses through Anny's own default model vs igavatar's FK + LBS."""
    pose_parameters = random_pose_parameters(seed)
    with torch.no_grad():
        expected = anny_default_model(pose_parameters=pose_parameters)["vertices"]
    local_rotations, root_translation = body.local_rotations_from_pose_parameters(pose_parameters)
    ours = body.posed_vertices(local_rotations, root_translation)
    assert ours.dtype == torch.float64
    assert float((ours - expected).abs().max()) < ACCEPTANCE_M
    # float32, the library's working precision, is well within the tolerance too.
    ours32 = body.posed_vertices(local_rotations.float(), root_translation.float())
    assert float((ours32.double() - expected).abs().max()) < ACCEPTANCE_M
    # The posed mesh really moved (a zero pose would also "agree" with itself).
    assert float((expected - body.rest_vertices.double()).abs().max()) > 0.3


def test_fk_lbs_reproduce_anny_for_another_phenotype(body: AnnyBody):
    other = body.with_phenotype(OTHER_PHENOTYPE)
    assert other.model is body.model
    assert float((other.rest_vertices - body.rest_vertices).abs().max()) > 0.01
    pose_parameters = random_pose_parameters(seed=2, n_frames=2)
    rotations, translation = other.local_rotations_from_pose_parameters(pose_parameters)
    difference = other.posed_vertices(rotations, translation) - other.anny_posed_vertices(pose_parameters)
    assert float(difference.abs().max()) < ACCEPTANCE_M


def test_pose_parameter_conversion_round_trips(body: AnnyBody):
    pose_parameters = random_pose_parameters(seed=3, n_frames=2)
    rotations, translation = body.local_rotations_from_pose_parameters(pose_parameters)
    back = body.pose_parameters_from_local_rotations(rotations, translation)
    torch.testing.assert_close(back, pose_parameters, atol=1e-12, rtol=0)
    generator = torch.Generator().manual_seed(4)
    rotations = axis_angle_to_matrix(0.4 * torch.randn(2, ANNY_BONE_COUNT, 3, generator=generator, dtype=torch.float64))
    translation = torch.randn(2, 3, generator=generator, dtype=torch.float64)
    again = body.local_rotations_from_pose_parameters(body.pose_parameters_from_local_rotations(rotations, translation))
    torch.testing.assert_close(again[0], rotations, atol=1e-12, rtol=0)
    torch.testing.assert_close(again[1], translation, atol=1e-12, rtol=0)
    # numpy float32 input (as read from poses.npz) gives float32 tensors.
    rotations32, translation32 = body.local_rotations_from_pose_parameters(pose_parameters.float().numpy())
    assert rotations32.dtype == torch.float32 and translation32.shape == (2, 3)


def test_identity_rotations_are_the_rest_mesh_and_anny_identity_is_its_reference_pose(body: AnnyBody):
    identity = torch.eye(3, dtype=torch.float64).expand(1, ANNY_BONE_COUNT, 3, 3)
    rest = body.posed_vertices(identity)[0]
    torch.testing.assert_close(rest.float(), body.rest_vertices)
    # Anny's identity deltas put the root head at the origin and each bone at its reference
    # orientation: not the rest mesh, but still reproduced exactly by the conversion.
    anny_identity = torch.eye(4, dtype=torch.float64).expand(1, ANNY_BONE_COUNT, 4, 4)
    rotations, translation = body.local_rotations_from_pose_parameters(anny_identity)
    torch.testing.assert_close(translation[0], -body.skeleton.rest_joints_tensor(torch.float64)[0])
    expected = body.anny_posed_vertices(anny_identity)
    assert float((body.posed_vertices(rotations, translation) - expected).abs().max()) < 1e-9


def test_canonical_star_pose_separates_the_limbs(body: AnnyBody):
    star = body.canonical_star_pose()
    assert star.shape == (ANNY_BONE_COUNT, 3, 3) and star.dtype == torch.float32
    vertices = body.posed_vertices(star.double()[None])[0].numpy()
    skeleton = body.skeleton
    dominant = body.skinning_weights.argmax(-1).numpy()

    def part(bone: str) -> np.ndarray:
        inside = np.zeros(skeleton.num_joints, dtype=bool)
        inside[skeleton.descendants(skeleton.index(bone))] = True
        return inside[dominant]

    def gap(a: np.ndarray, b: np.ndarray) -> float:
        return float(cKDTree(vertices[b]).query(vertices[a])[0].min())

    left_leg, right_leg = part("upperleg01.L"), part("upperleg01.R")
    assert gap(left_leg, right_leg) > 0.05  # thighs apart, even at the crotch
    assert gap(part("lowerleg01.L"), part("lowerleg01.R")) > 0.3
    rest_vertices = body.rest_vertices.numpy()
    for side in ("L", "R"):
        arm = part(f"clavicle.{side}")
        shoulder = skeleton.rest_joints[skeleton.index(f"upperarm01.{side}")]
        # Beyond the armpit, the arm is clear of the torso and the legs.
        free_arm = part(f"upperarm01.{side}") & (np.linalg.norm(rest_vertices - shoulder, axis=1) > 0.1)
        assert gap(free_arm, ~arm) > 0.03
    # The legs spread sideways (feet apart, rising a little), the body stays upright.
    assert float(np.ptp(vertices[:, 0])) > float(np.ptp(rest_vertices[:, 0])) - 1e-6
    assert vertices[:, 2].min() > rest_vertices[:, 2].min() + 0.03


def test_phenotype_and_pose_inputs_are_validated(body: AnnyBody):
    assert resolve_phenotype({"height": 1.0})["height"] == 1.0
    with pytest.raises(InputError, match="unknown Anny phenotype label 'shoe_size'"):
        resolve_phenotype({"shoe_size": 0.5})
    with pytest.raises(InputError, match=r"'age' = 1.5, expected a value in \[0, 1\]"):
        resolve_phenotype({"age": 1.5})
    with pytest.raises(InputError, match=r"expected \(N, 104, 4, 4\)"):
        body.local_rotations_from_pose_parameters(torch.eye(4).expand(2, 24, 4, 4))
    translated = torch.eye(4, dtype=torch.float64).repeat(1, ANNY_BONE_COUNT, 1, 1)
    translated[0, 5, 0, 3] = 0.1
    with pytest.raises(InputError, match="non-root bone 'lowerleg02.L'"):
        body.local_rotations_from_pose_parameters(translated)
    sheared = torch.eye(4, dtype=torch.float64).repeat(1, ANNY_BONE_COUNT, 1, 1)
    sheared[0, 3, 0, 1] = 0.5
    with pytest.raises(InputError, match="not rotations"):
        body.local_rotations_from_pose_parameters(sheared)


def test_missing_anny_package_is_a_body_model_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "anny", None)  # makes `import anny` raise ImportError
    with pytest.raises(BodyModelError, match="needs the Python package 'anny'"):
        load_anny()


def test_status_message_only_when_the_cache_must_be_built(tmp_path, monkeypatch):
    messages: list[str] = []
    load_anny(on_status=messages.append)  # the warm default cache: no message
    assert messages == []
    # An empty cache directory would trigger the slow build: check the message, skip the build.
    import anny

    def refuse(*args, **kwargs):
        raise RuntimeError("build refused in test")

    monkeypatch.setattr(anny, "Anny", refuse)
    try:
        with pytest.raises(BodyModelError, match="could not build or load the Anny body model"):
            load_anny(cache_dir=tmp_path / "anny-cache", on_status=messages.append)
    finally:
        monkeypatch.undo()
        load_anny()  # point anny back at the default cache for the other tests
    assert messages == [f"building Anny body-model cache in {tmp_path / 'anny-cache'} (first run, ~1 min)"]
