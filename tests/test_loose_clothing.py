"""The masks decide the shape prior: a dress gets the visual hull, tight clothes keep the template."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from igavatar.artifacts.manifest import read_artifact
from igavatar.capture.loose_clothing import LOOSE_OVER_SPILL, LOOSE_SHARE, outside_share, template_fit, template_silhouette
from igavatar_cli.main import app
from stages.preprocess import PreprocessOptions, run_preprocess
from stages.synth import SynthOptions, run_synth

K = np.array([[100.0, 0.0, 50.0], [0.0, 100.0, 50.0], [0.0, 0.0, 1.0]])
W2C = np.eye(4)
W2C[2, 3] = 2.0  # the camera 2 m in front of the origin, looking along +z: 50 px per meter


def _box(size: float) -> tuple[np.ndarray, np.ndarray]:
    box = trimesh.creation.box(extents=(size, size, size))
    return np.asarray(box.vertices), np.asarray(box.faces)


def test_silhouette_of_a_box_has_its_projected_size():
    vertices, faces = _box(0.4)  # front face at z = 1.8 m: 0.4 m * 100 / 1.8 = 22.2 px wide
    silhouette = template_silhouette(vertices, faces, K, W2C, (100, 100))
    rows, cols = np.nonzero(silhouette)
    assert 21 <= cols.max() - cols.min() + 1 <= 24 and 21 <= rows.max() - rows.min() + 1 <= 24
    assert abs(cols.mean() - 49.5) < 1 and abs(rows.mean() - 49.5) < 1


def test_share_counts_only_pixels_beyond_the_distance():
    silhouette = np.zeros((100, 100), bool)
    silhouette[30:70, 40:60] = True
    skirt = silhouette.copy()
    skirt[70:80, 30:70] = True  # 10 rows below the body: 5 px within reach, 5 beyond
    assert outside_share(silhouette, silhouette, 2.0) == 0.0
    # By brute force: each mask pixel's Euclidean distance to the nearest silhouette pixel.
    body = np.argwhere(silhouette)
    pixels = np.argwhere(skirt)
    nearest = np.sqrt(((pixels[:, None, :] - body[None, :, :]) ** 2).sum(-1)).min(1)
    assert outside_share(skirt, silhouette, 6.0) == pytest.approx((nearest > 6.0).mean(), abs=0.01)
    assert outside_share(np.zeros_like(skirt), silhouette, 1.0) == 0.0


def test_template_fit_converts_meters_at_the_roots_depth():
    vertices, faces = _box(0.4)
    silhouette = template_silhouette(vertices, faces, K, W2C, (100, 100))
    wide = np.zeros_like(silhouette)
    wide[20:80, 20:80] = True  # reaches ~19 px = 0.38 m (at 2 m, 50 px/m) outside the box
    body = [(vertices, faces, np.zeros(3))]
    tight = template_fit([silhouette], body, K[None], W2C[None], distance_m=0.04)
    loose = template_fit([wide], body, K[None], W2C[None], distance_m=0.04)
    far = template_fit([wide], body, K[None], W2C[None], distance_m=0.6)  # 30 px: beyond its corners (27 px)
    assert tight.loose == 0.0 and loose.loose > 0.5 and far.loose == 0.0
    # The template stays inside all three masks: no spill, and only the wide mask's looseness asks for the hull.
    assert tight.spill == loose.spill == far.spill == 0.0
    assert loose.hull_is_better and not tight.hull_is_better


def test_a_template_posed_off_the_mask_is_not_loose_clothing():
    """A limb posed where the person is not leaves mask pixels far from the template, as a skirt
    does, but the template then lies on background too: the poses are off, and the hull (which
    carves what any view's mask leaves out) would take the limb away."""
    vertices, faces = _box(0.4)
    silhouette = template_silhouette(vertices, faces, K, W2C, (100, 100))
    shifted = np.roll(silhouette, 8, axis=1)  # the person 8 px (0.16 m) to the side of the posed template
    body = [(vertices, faces, np.zeros(3))]
    fit = template_fit([shifted], body, K[None], W2C[None], distance_m=0.04)  # 2 px
    # By construction both sides leave a strip of 8 - 2 = 6 of the box's ~22 columns beyond the distance.
    assert fit.loose == pytest.approx(fit.spill, abs=0.02) and fit.spill > 0.2
    assert fit.loose >= LOOSE_SHARE and fit.loose < LOOSE_OVER_SPILL * fit.spill and not fit.hull_is_better


@pytest.mark.parametrize("garment, expected", [("dress", "visual_hull"), ("shirt-trousers", "template")])
def test_auto_shape_prior_follows_the_masks(tmp_path, garment, expected):
    run_synth(SynthOptions(out=tmp_path / "capture", resolution=96, train_frames=10, test_frames=0, seed=7,
                           garment=garment, phenotype=("gender=0.9", "weight=0.3")))
    run_preprocess(PreprocessOptions(capture=tmp_path / "capture", out=tmp_path / "dataset", max_size=96))
    data = read_artifact(tmp_path / "dataset", expected="dataset")["data"]
    assert data["shape_prior"] == expected
    share, spill = data["loose_clothing"]["share"], data["loose_clothing"]["spill"]
    assert (share >= LOOSE_SHARE and share >= LOOSE_OVER_SPILL * spill) == (expected == "visual_hull")
    assert (tmp_path / "dataset" / "body_template.ply").exists() == (expected == "visual_hull")
    if garment == "dress":
        # --shape-prior template keeps the naked template whatever the masks say.
        run_preprocess(PreprocessOptions(capture=tmp_path / "capture", out=tmp_path / "forced", max_size=96,
                                         shape_prior="template"))
        forced = read_artifact(tmp_path / "forced", expected="dataset")["data"]
        assert forced["shape_prior"] == "template" and "loose_clothing" not in forced


def test_template_prior_on_a_bare_skeleton_without_a_body_is_a_clear_error(cli_runner, tmp_path):
    run_synth(SynthOptions(out=tmp_path / "capture", resolution=64, train_frames=8, test_frames=0, skeleton="bare"))
    result = cli_runner.invoke(app, ["preprocess", "--capture", str(tmp_path / "capture"), "--out", str(tmp_path / "d"),
                                     "--shape-prior", "template", "--body-fit", "none"])
    assert result.exit_code == 2 and "bare skeleton" in result.output and "auto" in result.output
    assert not (tmp_path / "d").exists()
    # With Anny fitted to the joints (the default) there is a template to keep.
    result = cli_runner.invoke(app, ["preprocess", "--capture", str(tmp_path / "capture"), "--out", str(tmp_path / "d"),
                                     "--shape-prior", "template"])
    assert result.exit_code == 0, result.output
    assert read_artifact(tmp_path / "d", expected="dataset")["data"]["shape_prior"] == "template"
