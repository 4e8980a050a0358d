"""What a finished artifact protects (issue 37, items 3-6): files a user added to it, a camera that
cannot be one, an array of the wrong shape behind a matching hash, an edited manifest, a refused
--resume, and messages that name --out and say what to fix.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from igavatar.artifacts.manifest import sealed
from igavatar_cli.main import app
from tests.conftest import write_tiny_capture


def _fails(result, code: int, *needles: str) -> str:
    text = " ".join(result.output.split())
    assert result.exit_code == code, result.output
    assert "Traceback" not in result.output and result.output.count("error:") == 1, result.output
    for needle in needles:
        assert needle in text, (needle, text)
    return text


def _export(model: Path, out: Path, *extra: str) -> list[str]:
    return ["export", "--model", str(model), "--out", str(out), "--resolution", "16", "--formats", "ply",
            "--device", "cpu", "-q", *extra]


def _rehash(artifact: Path, name: str) -> None:
    """Rewrite the manifest's hash of `name` and its seal, as someone covering an edit would."""
    manifest = json.loads((artifact / "manifest.json").read_text())
    for output in manifest["outputs"]:
        if output["path"] == name:
            output["sha256"] = hashlib.sha256((artifact / name).read_bytes()).hexdigest()
            output["bytes"] = (artifact / name).stat().st_size
    (artifact / "manifest.json").write_text(json.dumps(sealed(manifest)))


# ------------------------------------------------------------------------------------------------
# 3. Files a user put inside an artifact folder


def test_an_artifact_folder_with_the_users_files_is_not_replaced(cli_runner, tiny_model, tmp_path):
    mesh = tmp_path / "mesh"
    assert cli_runner.invoke(app, _export(tiny_model, mesh)).exit_code == 0
    (mesh / "scene.blend").write_bytes(b"BLENDER-v300 hours of work")
    (mesh / "renders").mkdir()
    (mesh / "renders" / "r1.png").write_bytes(b"png")
    (mesh / ".DS_Store").write_bytes(b"finder")  # desktop litter does not count
    before = {p.relative_to(mesh).as_posix(): p.read_bytes() for p in mesh.rglob("*") if p.is_file()}

    _fails(cli_runner.invoke(app, _export(tiny_model, mesh, "--force")), 2,
           "also holds files it did not write", "renders/r1.png", "scene.blend", "move them out")
    assert {p.relative_to(mesh).as_posix(): p.read_bytes() for p in mesh.rglob("*") if p.is_file()} == before
    _fails(cli_runner.invoke(app, ["validate", str(mesh)]), 3, "2 file(s) its manifest does not list",
           "renders/r1.png", "scene.blend")

    shutil.rmtree(mesh / "renders")
    (mesh / "scene.blend").unlink()
    assert cli_runner.invoke(app, ["validate", str(mesh)]).exit_code == 0
    assert cli_runner.invoke(app, _export(tiny_model, mesh, "--force")).exit_code == 0


# ------------------------------------------------------------------------------------------------
# 4. Cameras that cannot be cameras


@pytest.mark.parametrize(
    "edit, needles",
    [
        (lambda K: K.__setitem__((0, 0), -K[0, 0]), ("not positive", "frame f000")),
        (lambda K: K.__setitem__((1, 1), 0.0), ("not positive",)),
        (lambda K: K.__setitem__((0, 2), 40 * K[0, 2]), ("principal point", "another image size")),
        (lambda K: K.__setitem__((2, 2), 0.0), ("last row of K",)),
    ],
    ids=["negative-fx", "zero-fy", "principal-point-far-off", "bad-last-row"],
)
def test_impossible_intrinsics_are_refused(cli_runner, tmp_path, edit, needles):
    capture = write_tiny_capture(tmp_path / "cap", n_frames=3)
    cameras = dict(np.load(capture / "cameras.npz"))
    K = np.repeat(cameras["K"][None], 3, axis=0)
    edit(K[0])
    np.savez(capture / "cameras.npz", **(cameras | {"K": K}))
    result = cli_runner.invoke(app, ["preprocess", "--capture", str(capture), "--out", str(tmp_path / "ds")])
    _fails(result, 2, "cameras.npz", "key 'K'", *needles)
    assert not (tmp_path / "ds").exists()


# ------------------------------------------------------------------------------------------------
# 5. A well-formed file of the wrong shape behind a matching hash


@pytest.mark.parametrize("file, key, cut", [("frames.npz", "K", lambda a: a[:, :2]),
                                            ("subject.npz", "canonical_box", lambda a: a[:1]),
                                            ("frames.npz", "bone_transforms", lambda a: a[:, :-1])])
def test_a_rehashed_array_of_the_wrong_shape_is_one_line(cli_runner, small_run, tmp_path, file, key, cut):
    dataset = tmp_path / "dataset"
    shutil.copytree(small_run / "dataset", dataset)
    arrays = dict(np.load(dataset / file))
    arrays[key] = cut(arrays[key])
    np.savez(dataset / file, **arrays)
    _rehash(dataset, file)
    found = f"has shape {tuple(arrays[key].shape)}"
    _fails(cli_runner.invoke(app, ["validate", str(dataset)]), 3, f"{file}: key '{key}'", found)
    _fails(cli_runner.invoke(app, ["train", "--dataset", str(dataset), "--out", str(tmp_path / "m"), "--preset", "tiny",
                                   "--device", "cpu", "-q"]), 3, f"key '{key}'", found, "re-run `igavatar preprocess`")
    assert not (tmp_path / "m").exists() and not (tmp_path / "m.work").exists()


def test_rehashed_weights_of_the_wrong_shape_are_one_line(cli_runner, tiny_model, tmp_path):
    model = tmp_path / "model"
    shutil.copytree(tiny_model, model)
    weights = dict(np.load(model / "weights.npz"))
    key = next(k for k in weights if weights[k].ndim == 2)
    weights[key] = weights[key][:1]
    np.savez(model / "weights.npz", **weights)
    _rehash(model, "weights.npz")
    _fails(cli_runner.invoke(app, ["validate", str(model)]), 3, "weights.npz", "do not fit the model", "igavatar train")
    _fails(cli_runner.invoke(app, _export(model, tmp_path / "mesh")), 3, "do not fit the model")


# ------------------------------------------------------------------------------------------------
# 6. Smaller items


def test_an_edited_manifest_field_is_noticed(cli_runner, small_run, tmp_path):
    dataset = tmp_path / "dataset"
    shutil.copytree(small_run / "dataset", dataset)
    manifest = json.loads((dataset / "manifest.json").read_text())
    manifest["config"]["max_size"] = 4096
    (dataset / "manifest.json").write_text(json.dumps(manifest, indent=2))
    _fails(cli_runner.invoke(app, ["validate", str(dataset)]), 3, "manifest.json: was edited after it was written",
           "igavatar preprocess")


def test_a_read_only_disk_names_the_output_not_the_temporary_folder(cli_runner, tiny_model, tmp_path, monkeypatch):
    import stages.export

    def read_only(path, *rest):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))

    monkeypatch.setattr(stages.export, "_write_mesh", read_only)
    text = _fails(cli_runner.invoke(app, _export(tiny_model, tmp_path / "mesh")), 5, "read-only")
    assert f"{tmp_path / 'mesh' / 'canonical.ply'}:" in text and ".tmp-" not in text
    assert list(tmp_path.iterdir()) == []


def test_a_refused_resume_leaves_the_work_folder_as_it_was(cli_runner, small_run, tmp_path, monkeypatch):
    from igavatar.training.trainer import Trainer

    real_step = Trainer.train_step

    def step_then_interrupt(self):
        result = real_step(self)
        if self.step == 2:
            raise KeyboardInterrupt
        return result

    monkeypatch.setattr(Trainer, "train_step", step_then_interrupt)
    args = ["train", "--dataset", str(small_run / "dataset"), "--out", str(tmp_path / "m"), "--preset", "tiny",
            "--device", "cpu", "-q"]
    assert cli_runner.invoke(app, args).exit_code == 130
    work = tmp_path / "m.work"
    before = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in work.iterdir() if p.is_file()}
    _fails(cli_runner.invoke(app, [*args, "--resume", "--seed", "5"]), 2, "seed: 0 -> 5")
    assert {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in work.iterdir() if p.is_file()} == before


def test_jpeg_images_without_image_ext_get_a_hint(cli_runner, tmp_path):
    capture = write_tiny_capture(tmp_path / "cap", n_frames=3)
    for png in (capture / "images").glob("*.png"):
        png.rename(png.with_suffix(".jpg"))
    _fails(cli_runner.invoke(app, ["preprocess", "--capture", str(capture), "--out", str(tmp_path / "ds")]), 2,
           "images missing", 'set "image_ext": ".jpg" in capture.json')


def test_a_partial_mean_says_how_many_frames_it_covers():
    from stages.eval_records import summary_of_metrics

    document = {"metrics": {"volumetric_iou": {"mean": 0.9, "n_frames": 3, "status": "mean over 3 of 4 test frames"},
                            "psnr": {"mean": 20.0, "n_frames": 4, "status": "mean over 4 of 4 test frames"}}}
    summary = summary_of_metrics(document, n_frames=4, keys=("volumetric_iou", "psnr"))
    assert summary == {"volumetric_iou": 0.9, "volumetric_iou_covers": "3 of 4 test frames (see the report's notes)",
                       "psnr": 20.0}
