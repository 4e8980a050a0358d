"""`igavatar eval`: a schema-valid report with every metric, scan matching, bad inputs, report helpers."""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from igavatar.artifacts.manifest import read_artifact, sealed, validate_against
from igavatar.errors import InputError
from igavatar.metrics.geometry import evenly_spaced_vertices, volumetric_iou
from igavatar.metrics.report import (
    METRIC_KEYS,
    error_colors,
    error_mesh_panel,
    markdown_report,
    mean_over_frames,
    metric_curves_image,
)
from igavatar_cli.main import app
from schemas import load_schema
from igavatar.capture.scans import match_scans
from igavatar.metrics.frame_geometry import frame_geometry, signed_volume, volume_check
from igavatar.metrics.lpips_scorer import lpips_scorer
from stages.eval import EvalOptions, run_eval
from stages.eval_options import IMAGE_DEFAULTS, ImageSettings, image_frame_indices, resolve_image_settings

FAST = dict(mesh_resolution=32, surface_samples=300, iou_points=20_000, image_scale=0.25, samples_per_ray=16, image_frames=0,
            device="cpu")


@pytest.fixture(scope="module")
def report(tiny_model, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("eval") / "report"
    run_eval(EvalOptions(model=tiny_model, out=out, iou_open_meshes=True, **FAST))
    return out


def _test_frames(small_run: Path) -> list[str]:
    return json.loads((small_run / "dataset" / "manifest.json").read_text())["data"]["splits"]["test"]


# ----------------------------------------------------------------------------- end to end


def test_report_is_schema_valid_with_every_metric_per_frame_and_mean(report, small_run):
    manifest = read_artifact(report, expected="report")  # schema of data + every file's sha256
    document = json.loads((report / "metrics.json").read_text())
    validate_against("report", document, "metrics.json")
    assert {k: v for k, v in document.items() if k != "frames"} == manifest["data"]
    tests = _test_frames(small_run)
    assert document["frame_names"] == tests == [r["frame"] for r in document["frames"]]
    assert load_schema("report")["properties"]["metrics"]["required"] == list(METRIC_KEYS)

    for key in METRIC_KEYS:
        entry = document["metrics"][key]
        assert entry["protocol"] and entry["units"] and entry["frame"] and entry["better"] in ("lower", "higher")
        values = [r["values"][key] for r in document["frames"]]
        if key == "lpips_full":  # no weights here: never a made-up number
            assert values == [None] * len(tests) and entry["mean"] is None
            assert entry["status"].startswith("not computed")
            continue
        assert all(np.isfinite(v) for v in values), key
        assert entry["n_frames"] == len(tests)
        assert entry["mean"] == pytest.approx(np.mean(values), rel=1e-12)
        if key in ("psnr_full_db", "ssim_full", "psnr_mask_bbox_db", "ssim_mask_bbox"):
            assert entry["background"] == "white" and entry["frame"].startswith("image")
        else:
            assert entry["background"] is None and entry["frame"].startswith("world")
    settings = document["settings"]
    assert settings["background"] == "white" and settings["test_time_pose_refinement"] is False
    assert settings["image_size"] == [16, 16] and settings["dataset_image_size"] == [64, 64]
    for record in document["frames"]:
        iou = record["geometry"]["volumetric_iou"]
        assert iou["status"] in ("computed", "approximate")
        # A mesh that is not watertight (a tiny model's blob reaches its box) is flagged and noted.
        if not iou["pred_watertight"]:
            assert iou["status"] == "approximate" and any("not watertight" in n for n in record["notes"])

    panel = cv2.imread(str(report / document["frames"][0]["files"]["side_by_side"]))
    assert panel.shape == (16, 48, 3)
    assert (report / "plots" / "metric_curves.png").is_file()
    for record in document["frames"]:
        assert (report / record["files"]["error_render"]).is_file()
    table = (report / "report.md").read_text()
    assert all(f"`{name}`" in table for name in tests) and "**mean**" in table
    assert "LPIPS" in table and "not computed" in table
    # Every markdown table keeps its column count (a bare '|' inside "|cos|" would break it).
    for block in re.findall(r"(?:^\|.*\n)+", table, flags=re.M):
        counts = {len(re.findall(r"(?<!\\)\|", line)) for line in block.splitlines()}
        assert len(counts) == 1, block


def test_reported_chamfer_is_that_of_the_world_space_mesh_written(report):
    """The worst frame's PLY is the evaluated posed mesh: its Chamfer to the scan is the reported one."""
    document = json.loads((report / "metrics.json").read_text())
    (ply,) = (report / "geometry").glob("worst_*.ply")
    name = ply.stem[len("worst_"):]
    record = next(r for r in document["frames"] if r["frame"] == name)
    pred = trimesh.load(ply, process=False)
    scan = trimesh.load(record["scan"], process=False)
    # The paper protocol's vertices: both meshes' edges split to at most PAPER_MAX_EDGE_M.
    pred_v = evenly_spaced_vertices(pred.vertices, pred.faces)[0]
    scan_v = evenly_spaced_vertices(scan.vertices, scan.faces)[0]
    p2g = cKDTree(scan_v).query(pred_v)[0] * 100.0
    g2p = cKDTree(pred_v).query(scan_v)[0] * 100.0
    expected = 0.5 * (np.mean(p2g**2) + np.mean(g2p**2))
    assert record["values"]["chamfer_l2_cm2"] == pytest.approx(expected, rel=1e-5)
    assert len(pred.visual.vertex_colors) == len(pred.vertices)
    assert record["values"]["chamfer_l1_surface_mm"] == max(
        r["values"]["chamfer_l1_surface_mm"] for r in document["frames"])


def test_missing_and_extra_scans_are_reported(tiny_model, small_run, tmp_path, cli_runner):
    tests = _test_frames(small_run)
    gt = tmp_path / "scans"
    shutil.copytree(small_run / "capture" / "scans", gt)
    (gt / f"{tests[0]}.ply").unlink()
    shutil.copyfile(gt / f"{tests[1]}.ply", gt / "stranger.ply")
    (gt / "readme.txt").write_text("not a scan")
    out = tmp_path / "report"
    result = cli_runner.invoke(app, [
        "eval", "--model", str(tiny_model), "--gt", str(gt), "--out", str(out), "--no-images", "--iou-points", "0",
        "--mesh-resolution", "32", "--surface-samples", "200", "--device", "cpu", "--json",
    ])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["scans_missing"] == [tests[0]] and summary["scans_extra"] == ["stranger"]
    assert summary["scans_matched"] == len(tests) - 1
    document = json.loads((out / "metrics.json").read_text())
    matching = document["gt_matching"]
    assert matching["ignored_files"] == ["readme.txt"]
    assert len(matching["other_split"]) == 4  # the training frames' scans: listed, not evaluated
    missing = document["frames"][0]
    assert missing["frame"] == tests[0] and missing["geometry"] is None and missing["scan"] is None
    assert missing["values"]["chamfer_l2_cm2"] is None and "no scan" in missing["notes"][0]
    assert document["metrics"]["chamfer_l2_cm2"]["n_frames"] == len(tests) - 1
    assert document["metrics"]["volumetric_iou"]["mean"] is None
    assert document["metrics"]["psnr_full_db"]["status"] == "not computed: --no-images"
    table = (out / "report.md").read_text()
    assert "`stranger`" in table and f"`{tests[0]}`" in table.split("**missing**")[1].splitlines()[0]


def test_bad_inputs_fail_with_one_line_and_write_nothing(tiny_model, small_run, tmp_path, cli_runner):
    out = tmp_path / "report"

    def fails(args: list[str], code: int, *fragments: str) -> None:
        result = cli_runner.invoke(app, ["eval", "--out", str(out), "--device", "cpu", *args])
        assert result.exit_code == code, result.output
        message = " ".join(result.output.split())
        assert message.startswith("error:") and all(f in message for f in fragments), message
        assert "Traceback" not in result.output and not out.exists()

    fails(["--model", str(tiny_model), "--gt", str(tmp_path / "nope")], 2, "--gt", "nope", "no such directory")
    fails(["--model", str(small_run / "dataset")], 3, "is a dataset artifact", "igavatar train")
    (tmp_path / "empty").mkdir()
    fails(["--model", str(tiny_model), "--gt", str(tmp_path / "empty")], 2, "no scan is named after a test frame")
    fails(["--model", str(tiny_model), "--no-geometry", "--no-images"], 2, "nothing to evaluate")
    moved = tmp_path / "elsewhere" / "model"
    shutil.copytree(tiny_model, moved)
    manifest = json.loads((moved / "manifest.json").read_text())
    manifest["data"]["dataset"] = str(tmp_path / "gone" / "data")
    (moved / "manifest.json").write_text(json.dumps(sealed(manifest)))
    fails(["--model", str(moved)], 2, "data.dataset", "--dataset")


# ----------------------------------------------------------------------------- pieces


def test_match_scans_classifies_every_file(tmp_path):
    for name in ("t0.ply", "t1.OBJ", "a0.ply", "zz.obj", "x.pkl"):
        (tmp_path / name).write_text("")
    matching = match_scans(tmp_path, ["t0", "t1", "t2"], ["a0", "a1", "t0", "t1", "t2"])
    assert sorted(matching.matched) == ["t0", "t1"] and matching.missing == ["t2"]
    assert matching.extra == ["zz"] and matching.other_split == ["a0"] and matching.ignored_files == ["x.pkl"]
    (tmp_path / "t0.obj").write_text("")
    with pytest.raises(InputError, match="two scans for frame 't0'"):
        match_scans(tmp_path, ["t0"], ["t0"])


def test_signed_volume_and_volume_check_expose_self_intersection():
    cube = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    assert signed_volume(cube.vertices, cube.faces) == pytest.approx(1.0, abs=1e-12)
    # Two overlapping cubes: watertight, but the overlap (0.5 x 0.7 x 0.8) has winding number 2, so
    # the signed volume (2) exceeds what ray parity sees inside (2 - 2 x 0.28 = 1.44).
    shifted = cube.copy()
    shifted.apply_translation((0.5, 0.3, 0.2))
    overlapping = trimesh.util.concatenate([cube, shifted])
    result = volumetric_iou((overlapping.vertices, overlapping.faces), (cube.vertices, cube.faces), 40_000, 0)
    box_volume = float(np.prod(np.subtract(result["box_max"], result["box_min"])))
    pred = volume_check(overlapping.vertices, overlapping.faces, result["n_inside_pred"], result["n_points"], box_volume)
    gt = volume_check(cube.vertices, cube.faces, result["n_inside_gt"], result["n_points"], box_volume)
    assert pred["signed_volume_m3"] == pytest.approx(2.0) and pred["parity_volume_m3"] == pytest.approx(1.44, rel=0.05)
    assert not pred["consistent"] and gt["consistent"]


def test_frame_geometry_of_a_perfect_and_of_an_open_prediction():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    options = EvalOptions(model=Path("m"), out=Path("r"), surface_samples=500, iou_points=20_000)
    values, details, notes, error_mm = frame_geometry(v, f, v, f, options)
    assert values["chamfer_l2_cm2"] == 0.0 and values["normal_consistency_vertices"] == pytest.approx(1.0)
    assert values["chamfer_l1_surface_mm"] < 1e-9 and values["normal_consistency_surface"] == pytest.approx(1.0)
    assert values["volumetric_iou"] == 1.0 and details["volumetric_iou"]["status"] == "computed"
    assert notes == [] and np.all(error_mm < 1e-6)
    offset = v + 0.003 * v / np.linalg.norm(v, axis=1, keepdims=True)  # 3 mm outwards
    _, _, _, error_mm = frame_geometry(offset, f, v, f, options)
    assert np.all((error_mm > 2.9) & (error_mm <= 3.0 + 1e-6))  # chords of the flat faces: a bit under 3 mm
    values, details, notes, _ = frame_geometry(v, f[1:], v, f, options)  # one face missing: a hole
    # The same vertices but for the missing face's split points (PAPER_MAX_EDGE_M): near 0, not 0.
    assert values["volumetric_iou"] is None and values["chamfer_l2_cm2"] < 1e-3
    assert details["volumetric_iou"]["status"].startswith("not computed: the prediction is not watertight")
    open_options = EvalOptions(model=Path("m"), out=Path("r"), surface_samples=500, iou_points=20_000, iou_open_meshes=True)
    values, details, notes, _ = frame_geometry(v, f[1:], v, f, open_options)
    assert values["volumetric_iou"] > 0.95 and details["volumetric_iou"]["status"] == "approximate"


def test_lpips_is_not_computed_without_local_weights(tmp_path, monkeypatch):
    import torch

    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    scorer, status = lpips_scorer(torch.device("cpu"))
    assert scorer is None and status.startswith("not computed")


def test_image_defaults_follow_the_device_and_the_model_and_frames_are_evenly_spaced():
    import torch

    options = EvalOptions(model=Path("m"), out=Path("r"))
    # Size and frames follow the device; samples per ray follow the model (its validation renders').
    assert resolve_image_settings(options, torch.device("cpu"), model_samples=96) == ImageSettings(0.25, 96, 10)
    assert resolve_image_settings(options, torch.device("cuda"), model_samples=128) == ImageSettings(1.0, 128, 0)
    assert IMAGE_DEFAULTS["cpu"] == (0.25, 10) and IMAGE_DEFAULTS["cuda"] == (1.0, 0)
    chosen = EvalOptions(model=Path("m"), out=Path("r"), image_scale=0.5, samples_per_ray=8, image_frames=3)
    assert resolve_image_settings(chosen, torch.device("cuda"), model_samples=96) == ImageSettings(0.5, 8, 3)
    assert image_frame_indices(30, 10) == {0, 3, 6, 10, 13, 16, 19, 23, 26, 29}
    assert image_frame_indices(5, 0) == image_frame_indices(5, 9) == set(range(5))


def test_mean_over_frames_skips_missing_values():
    assert mean_over_frames([1.0, None, 3.0, float("nan")]) == (2.0, 2)
    assert mean_over_frames([None, None]) == (None, 0)


def test_metric_curves_draw_values_and_gaps():
    image = metric_curves_image(["a", "b", "c"], {"chamfer_l2_cm2": [0.5, None, 0.7], "volumetric_iou": [None] * 3},
                                {"chamfer_l2_cm2": 0.6}, columns=2, panel_size=(120, 200))
    assert image.shape == (120, 400, 3) and image.dtype == np.uint8
    line = np.all(image == (31, 119, 180), axis=-1)
    assert line[:, :200].sum() > 10 and line[:, 200:].sum() == 0  # the all-missing panel draws no curve
    with pytest.raises(InputError, match="unknown metric"):
        metric_curves_image(["a"], {"psnr": [1.0]})


def test_error_colors_and_mesh_panel_follow_the_distance():
    np.testing.assert_allclose(error_colors(np.array([0.0]), 20.0)[0], [0, 0, 128 / 255], atol=1e-9)
    assert np.argmax(error_colors(np.array([25.0]), 20.0)[0]) == 0  # red past vmax
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    K = np.array([[80.0, 0, 32], [0, 80.0, 32], [0, 0, 1]])
    w2c = np.eye(4)
    w2c[2, 3] = 3.0
    for error_mm, channel in ((0.0, 2), (30.0, 0)):  # blue for a perfect fit, red beyond vmax
        panel = error_mesh_panel(sphere.vertices, sphere.faces, sphere.vertices, sphere.faces,
                                 np.full(len(sphere.vertices), error_mm), K, w2c, 64, 64, vmax_mm=20.0)
        assert panel.shape == (18 + 64, 2 * 64 + 70, 3)
        pred = panel[18:, 64:128].reshape(-1, 3).astype(int)
        hit = np.any(pred != 255, axis=1)
        assert hit.sum() > 500
        assert np.all(np.argmax(pred[hit], axis=1) == channel)


def test_markdown_report_has_means_matching_and_a_row_per_frame():
    metrics = {k: {"mean": None, "n_frames": 0, "status": "not computed: test"} for k in METRIC_KEYS}
    metrics["chamfer_l2_cm2"] = {"mean": 0.5, "n_frames": 1, "status": "mean over 1 of 2 test frames"}
    values = {k: None for k in METRIC_KEYS}
    document = {
        "inputs": {"model": "m", "dataset": "d", "gt": "g"},
        "settings": {"geometry": True, "images": False, "mesh_resolution": 64, "image_size": [8, 8],
                     "image_scale": 0.5, "dataset_image_size": [16, 16], "samples_per_ray": 4, "background": "white",
                     "test_time_pose_refinement": False, "surface_samples": 10, "iou_points": 0, "seed": 0},
        "metrics": metrics,
        "frames": [{"frame": "f0", "values": {**values, "chamfer_l2_cm2": 0.5}, "notes": []},
                   {"frame": "f1", "values": values, "notes": ["no scan"]}],
        "gt_matching": {"matched": ["f0"], "missing": ["f1"], "extra": ["x"], "other_split": [], "ignored_files": []},
        "notes": ["LPIPS not computed"], "files": {"metrics": "metrics.json"},
    }
    text = markdown_report(document)
    assert "| `f0` | 0.500 |" in text and "| `f1` | — |" in text and "| **mean** | 0.500 |" in text
    assert "**missing** (test frames without a scan, no geometry metrics): `f1`" in text
    assert "`f1`: no scan" in text and "| 25 | 0.579 |" in text


def test_report_checks_the_canonical_shape_against_the_synthetic_truth(report):
    document = json.loads((report / "metrics.json").read_text())
    canonical = document["canonical"]
    assert canonical["truth"].startswith("ground_truth/clothed_rest.npz")
    limbs = canonical["limb_check"]
    # An Anny template has every part; each part's coverage is a share and the verdict follows it.
    assert {"left_hand", "right_forearm", "head", "left_foot"} <= set(limbs["parts"])
    for part, entry in limbs["parts"].items():
        assert 0.0 <= entry["covered"] <= 1.0 and entry["passed"] == (entry["covered"] >= limbs["min_covered"])
    assert limbs["passed"] == (not limbs["failed_parts"])
    assert canonical["leg_gap"]["points"] > 0 and 0.0 <= canonical["leg_gap"]["webbed"] <= 1.0
    truth = canonical["against_truth"]
    assert truth["chamfer_l1_mm"] > 0 and 0.0 <= truth["volumetric_iou"] <= 1.0
    picture = cv2.imread(str(report / document["files"]["canonical mesh, front and side, beside the truth and the template"]))
    assert picture.shape[0] == 3 * picture.shape[1] // 2  # three rows (prediction, truth, template) of two views


def test_an_up_to_date_report_is_skipped_and_force_redoes_it(tiny_model, tmp_path):
    options = EvalOptions(model=tiny_model, out=tmp_path / "report", geometry=False, image_scale=0.25, samples_per_ray=8,
                          image_frames=1, device="cpu")
    first = run_eval(options)
    manifest = (tmp_path / "report" / "manifest.json").read_bytes()
    again = run_eval(options)
    assert "skipped" not in first and again["skipped"].startswith("inputs and options unchanged")
    assert (tmp_path / "report" / "manifest.json").read_bytes() == manifest
    assert "skipped" not in run_eval(dataclasses.replace(options, image_frames=2))  # other options: redone
    assert "skipped" not in run_eval(dataclasses.replace(options, image_frames=2, force=True))
