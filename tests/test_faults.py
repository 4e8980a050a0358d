"""Fault injection through the CLI: outputs that are not ours, full and read-only disks, oversize
options, corrupt artifacts, killed runs, SIGTERM, and the log a run writes without a TTY.

Every case checks what the user sees (one line, a non-zero exit code, no traceback) and what is
left on disk (their files byte-identical, earlier artifacts still valid, no temporary leftovers).
Disk faults are simulated by making the write raise the OSError the kernel would, so the tests
run everywhere, as any user.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import signal
from pathlib import Path

import numpy as np
import pytest

from igavatar.artifacts.manifest import read_artifact, sealed
from igavatar_cli.main import app
from tests.conftest import write_tiny_capture


def _one_error_line(result, code: int, *needles: str) -> str:
    """The run failed with `code`, said so in one `error:` line containing every needle, no traceback."""
    text = " ".join(result.output.split())
    assert result.exit_code == code, result.output
    assert "Traceback" not in result.output
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)
    assert result.output.count("error:") == 1, result.output
    for needle in needles:
        assert needle in text, (needle, result.output)
    return text


def _tree_digest(root: Path) -> dict[str, str]:
    """Relative path -> sha256 of every file under root (a file root: its own digest)."""
    if root.is_file():
        return {".": hashlib.sha256(root.read_bytes()).hexdigest()}
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def _leftovers(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir() if ".tmp-" in p.name or ".old-" in p.name)


def _export_args(model: Path, out: Path, *extra: str) -> list[str]:
    return ["export", "--model", str(model), "--out", str(out), "--resolution", "16", "--formats", "ply",
            "--device", "cpu", "-q", *extra]


@pytest.fixture
def user_folder(tmp_path: Path) -> Path:
    docs = tmp_path / "docs"
    docs.mkdir()
    (docs / "thesis.txt").write_text("four years of work\n")
    return docs


@pytest.fixture
def own_model(tiny_model, tmp_path) -> Path:
    """A private copy of the shared tiny model (tests below damage or retrain theirs)."""
    copy = tmp_path / "model"
    shutil.copytree(tiny_model, copy)
    return copy


# ------------------------------------------------------------------------------------------------
# --out that is not ours


def test_preprocess_into_a_user_folder_is_refused_and_the_folder_is_untouched(cli_runner, tiny_skeleton_capture, user_folder):
    before = _tree_digest(user_folder)
    result = cli_runner.invoke(app, ["preprocess", "--capture", str(tiny_skeleton_capture), "--out", str(user_folder)])
    _one_error_line(result, 2, f"--out {user_folder}", "not an igavatar artifact", "another --out")
    assert _tree_digest(user_folder) == before
    assert _leftovers(user_folder.parent) == []


def test_preprocess_onto_its_own_capture_is_refused(cli_runner, tiny_skeleton_capture):
    before = _tree_digest(tiny_skeleton_capture)
    result = cli_runner.invoke(app, ["preprocess", "--capture", str(tiny_skeleton_capture), "--out", str(tiny_skeleton_capture)])
    _one_error_line(result, 2, "is the input", "another --out")
    assert _tree_digest(tiny_skeleton_capture) == before


def test_export_into_a_folder_with_notes_is_refused(cli_runner, tiny_model, tmp_path):
    notes = tmp_path / "notes"
    notes.mkdir()
    (notes / "notes.txt").write_text("do not delete\n")
    before = _tree_digest(notes)
    _one_error_line(cli_runner.invoke(app, _export_args(tiny_model, notes)), 2, "not an igavatar artifact")
    assert _tree_digest(notes) == before


@pytest.mark.parametrize("command", ["preprocess", "export"])
def test_an_existing_file_as_out_is_refused_and_kept(cli_runner, tiny_skeleton_capture, tiny_model, tmp_path, command):
    target = tmp_path / "result.bin"
    target.write_bytes(b"\x00user data\xff")
    args = (["preprocess", "--capture", str(tiny_skeleton_capture), "--out", str(target)] if command == "preprocess"
            else _export_args(tiny_model, target))
    _one_error_line(cli_runner.invoke(app, args), 2, "is an existing file", f"delete {target} yourself")
    assert target.read_bytes() == b"\x00user data\xff"
    assert _leftovers(tmp_path) == []


def test_a_link_to_an_artifact_as_out_is_refused_and_both_kept(cli_runner, tiny_model, tmp_path):
    mesh = tmp_path / "mesh-real"
    mesh.mkdir()
    (mesh / "keep.txt").write_text("the link's target\n")
    link = tmp_path / "mesh"
    link.symlink_to(mesh, target_is_directory=True)
    _one_error_line(cli_runner.invoke(app, _export_args(tiny_model, link)), 2, "is a symbolic link", "another --out")
    assert link.is_symlink() and (mesh / "keep.txt").read_text() == "the link's target\n"


def test_out_inside_an_input_or_containing_it_is_refused(cli_runner, tiny_model, tmp_path):
    model = tmp_path / "run" / "model"
    shutil.copytree(tiny_model, model)
    before = _tree_digest(tmp_path / "run")
    _one_error_line(cli_runner.invoke(app, _export_args(model, model / "mesh")), 2, "lies inside the input")
    _one_error_line(cli_runner.invoke(app, _export_args(model, tmp_path / "run")), 2, "contains the input")
    assert _tree_digest(tmp_path / "run") == before


# ------------------------------------------------------------------------------------------------
# Disk faults: no space, read-only


def _raise(code: int):
    def fail(*args, **kwargs):
        path = next((a for a in args if isinstance(a, (str, Path))), None)
        raise OSError(code, os.strerror(code), str(path) if path is not None else None)
    return fail


def test_no_space_during_export_keeps_the_previous_mesh(cli_runner, tiny_model, tmp_path, monkeypatch):
    out = tmp_path / "mesh"
    assert cli_runner.invoke(app, _export_args(tiny_model, out)).exit_code == 0
    before = _tree_digest(out)
    import stages.export

    monkeypatch.setattr(stages.export, "_write_mesh", _raise(errno.ENOSPC))
    result = cli_runner.invoke(app, _export_args(tiny_model, out, "--force"))
    _one_error_line(result, 5, "no space left on the device", "free some space")
    assert _tree_digest(out) == before
    read_artifact(out, expected="mesh")
    assert _leftovers(tmp_path) == []


def test_no_space_during_preprocess_keeps_the_previous_dataset(cli_runner, tiny_skeleton_capture, tmp_path, monkeypatch):
    out = tmp_path / "dataset"
    args = ["preprocess", "--capture", str(tiny_skeleton_capture), "--out", str(out), "-q"]
    assert cli_runner.invoke(app, args).exit_code == 0
    before = _tree_digest(out)
    monkeypatch.setattr(np, "savez_compressed", _raise(errno.ENOSPC))
    _one_error_line(cli_runner.invoke(app, [*args, "--force"]), 5, "no space left")
    assert _tree_digest(out) == before
    read_artifact(out, expected="dataset")
    assert _leftovers(tmp_path) == []


def test_read_only_output_location_is_one_line(cli_runner, tiny_skeleton_capture, tmp_path, monkeypatch):
    import tempfile

    monkeypatch.setattr(tempfile, "mkdtemp", _raise(errno.EROFS))
    result = cli_runner.invoke(app, ["preprocess", "--capture", str(tiny_skeleton_capture), "--out", str(tmp_path / "ds")])
    _one_error_line(result, 5, "read-only", "writable location")
    assert not (tmp_path / "ds").exists()


def test_train_on_a_full_disk_leaves_no_work_dir_and_keeps_the_model(cli_runner, small_run, own_model, monkeypatch):
    before = _tree_digest(own_model)
    import stages.train

    monkeypatch.setattr(stages.train, "save_state", _raise(errno.ENOSPC))
    result = cli_runner.invoke(app, ["train", "--dataset", str(small_run / "dataset"), "--out", str(own_model),
                                     "--preset", "tiny", "--device", "cpu", "-q", "--force"])
    _one_error_line(result, 5, "no space left")
    assert not own_model.with_name("model.work").exists()
    assert _tree_digest(own_model) == before
    read_artifact(own_model, expected="model")


def test_read_only_work_dir_in_train_is_one_line(cli_runner, small_run, tmp_path, monkeypatch):
    real_mkdir = Path.mkdir

    def mkdir(self, *args, **kwargs):
        if self.name.endswith(".work"):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(self))
        return real_mkdir(self, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", mkdir)
    result = cli_runner.invoke(app, ["train", "--dataset", str(small_run / "dataset"), "--out", str(tmp_path / "m"),
                                     "--preset", "tiny", "--device", "cpu", "-q"])
    _one_error_line(result, 5, "m.work", "read-only")


# ------------------------------------------------------------------------------------------------
# Leftovers of killed runs, oversize options, corrupt files


def _dead_pid() -> int:
    pid = 4_000_000
    while True:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return pid
        except PermissionError:
            pass
        pid -= 1


def test_a_killed_exports_temporary_dir_is_removed_by_the_next_export(cli_runner, tiny_model, tmp_path):
    killed = tmp_path / f".mesh.tmp-{_dead_pid()}-k1ll3d"
    legacy = tmp_path / ".mesh.tmp-a1b2c3d4"  # the pid-less name of earlier versions
    running = tmp_path / f".mesh.tmp-{os.getpid()}-alive"  # a live process's: not ours to remove
    unrelated = tmp_path / ".notes.tmp-1-keep"
    for path in (killed, legacy, running, unrelated):
        path.mkdir()
        (path / "canonical.ply").write_bytes(b"half")
    assert cli_runner.invoke(app, _export_args(tiny_model, tmp_path / "mesh")).exit_code == 0
    assert not killed.exists() and not legacy.exists()
    assert running.exists() and unrelated.exists()


def test_an_oversize_resolution_is_refused_before_any_allocation(cli_runner, tiny_model, tmp_path, monkeypatch):
    import stages.export

    def never(*args, **kwargs):
        raise AssertionError("allocated before the size check")

    monkeypatch.setattr(stages.export, "load_model", never)
    monkeypatch.setattr(stages.export, "canonical_surface", never)
    result = cli_runner.invoke(app, ["export", "--model", str(tiny_model), "--out", str(tmp_path / "mesh"),
                                     "--resolution", "20000", "--device", "cpu"])
    _one_error_line(result, 2, "--resolution 20000", "GiB", "of available memory", "choose a smaller value")
    assert not (tmp_path / "mesh").exists()


def test_oversize_rays_and_samples_are_refused_before_training(cli_runner, small_run, tmp_path):
    result = cli_runner.invoke(app, ["train", "--dataset", str(small_run / "dataset"), "--out", str(tmp_path / "m"),
                                     "--preset", "tiny", "--rays", "10000000", "--samples", "100000", "--device", "cpu"])
    _one_error_line(result, 2, "--rays 10000000 x --samples 100000", "GiB")
    assert not (tmp_path / "m").exists() and not (tmp_path / "m.work").exists()


def test_a_truncated_npz_with_a_rewritten_hash_is_a_corrupt_artifact(cli_runner, own_model, tmp_path):
    weights = own_model / "weights.npz"
    weights.write_bytes(weights.read_bytes()[: weights.stat().st_size // 2])
    manifest = json.loads((own_model / "manifest.json").read_text())
    for output in manifest["outputs"]:
        if output["path"] == "weights.npz":
            output["sha256"] = hashlib.sha256(weights.read_bytes()).hexdigest()
            output["bytes"] = weights.stat().st_size
    (own_model / "manifest.json").write_text(json.dumps(sealed(manifest)))
    _one_error_line(cli_runner.invoke(app, ["validate", str(own_model)]), 3, "weights.npz", "corrupt model artifact", "igavatar train")
    _one_error_line(cli_runner.invoke(app, _export_args(own_model, tmp_path / "mesh")), 3, "corrupt model artifact")


# ------------------------------------------------------------------------------------------------
# Training: SIGTERM, --resume


def _train_args(small_run: Path, out: Path, *extra: str) -> list[str]:
    return ["train", "--dataset", str(small_run / "dataset"), "--out", str(out), "--preset", "tiny", "--device", "cpu",
            "-q", *extra]


def test_sigterm_during_training_leaves_a_resumable_checkpoint(cli_runner, small_run, tmp_path, monkeypatch):
    from igavatar.training.trainer import Trainer

    real_step = Trainer.train_step

    def step_then_sigterm(self):
        result = real_step(self)
        if self.step == 2:
            os.kill(os.getpid(), signal.SIGTERM)  # the handler raises here, between two steps
        return result

    monkeypatch.setattr(Trainer, "train_step", step_then_sigterm)
    out = tmp_path / "model"
    handler_before = signal.getsignal(signal.SIGTERM)
    text = _one_error_line(cli_runner.invoke(app, _train_args(small_run, out)), 143,
                           "terminated (SIGTERM) at step 2", "--resume")
    assert "model.work/checkpoint.npz" in text
    assert signal.getsignal(signal.SIGTERM) == handler_before and not out.exists()
    monkeypatch.setattr(Trainer, "train_step", real_step)

    # Another option: refused, saying which one differs.
    _one_error_line(cli_runner.invoke(app, _train_args(small_run, out, "--resume", "--steps", "9")), 2,
                    "steps: 6 -> 9", "repeat the interrupted run's options")
    resumed = cli_runner.invoke(app, _train_args(small_run, out, "--resume", "--json"))
    assert resumed.exit_code == 0, resumed.output
    assert json.loads(resumed.output)["steps"] == 6
    read_artifact(out, expected="model")
    assert not (tmp_path / "model.work").exists()


def test_resume_without_checkpoint_leaves_nothing_behind(cli_runner, small_run, tmp_path):
    _one_error_line(cli_runner.invoke(app, _train_args(small_run, tmp_path / "model", "--resume")), 2, "no checkpoint")
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------------------------
# Messages that say what to do


def test_a_capture_where_a_dataset_is_expected_suggests_preprocess(cli_runner, tiny_skeleton_capture, tmp_path):
    result = cli_runner.invoke(app, ["train", "--dataset", str(tiny_skeleton_capture), "--out", str(tmp_path / "m"),
                                     "--preset", "tiny", "--device", "cpu"])
    _one_error_line(result, 3, "needs a dataset artifact", f"igavatar preprocess --capture {tiny_skeleton_capture}")


@pytest.mark.parametrize("fault", ["scaled-w2c", "nan-pose", "empty-mask"])
def test_bad_frames_are_named(cli_runner, tmp_path, fault):
    capture = write_tiny_capture(tmp_path / "cap", n_frames=3)
    if fault == "scaled-w2c":
        w2c = np.repeat(np.eye(4)[None], 3, axis=0)
        w2c[1, :3, :3] *= 2.0
        cams = dict(np.load(capture / "cameras.npz"))
        np.savez(capture / "cameras.npz", **(cams | {"w2c": w2c}))
        needles = ("not orthonormal", "frame f001", "rigid")
    elif fault == "nan-pose":
        poses = dict(np.load(capture / "poses.npz"))
        poses["rotvecs"][2, 1, 0] = np.nan
        np.savez(capture / "poses.npz", **poses)
        needles = ("'rotvecs' holds NaN", "frame f002")
    else:
        import cv2

        cv2.imwrite(str(capture / "masks" / "f001.png"), np.zeros((16, 16), np.uint8))
        needles = ("f001.png", "empty", "remove masks/")
    result = cli_runner.invoke(app, ["preprocess", "--capture", str(capture), "--out", str(tmp_path / "ds")])
    _one_error_line(result, 2, *needles)
    assert not (tmp_path / "ds").exists()


# ------------------------------------------------------------------------------------------------
# The first run without a TTY


def test_demo_without_a_tty_logs_each_stage_and_training_lines(cli_runner, tmp_path, monkeypatch):
    import stages.demo

    def fake_stage(name: str, steps: int = 0):
        def run(options, progress):
            if steps:
                with progress.task("training", total=steps) as advance:
                    for _ in range(steps):
                        advance(1, loss="0.1234", psnr="20.00", it_s="5.00")
            return {"ok": name}
        return run

    for name in ("synth", "preprocess", "export", "animate", "eval"):
        monkeypatch.setattr(stages.demo, f"run_{name}", fake_stage(name))
    monkeypatch.setattr(stages.demo, "run_train", fake_stage("train", steps=40))
    result = cli_runner.invoke(app, ["demo", "--run-dir", str(tmp_path / "run"), "--device", "cpu"])
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    for number, name in enumerate(stages.demo.DEMO_STAGES, start=1):
        assert f"demo stage {number}/6 {name}: started" in lines
        assert any(line.startswith(f"demo stage {number}/6 {name}: done in ") for line in lines)
    assert "training: started (40 steps)" in lines
    steps = [line for line in lines if line.startswith("training: ") and "loss" in line]
    assert len(steps) == 20  # every 2 steps of 40
    assert "training: 40/40  loss 0.1234  psnr 20.00  it_s 5.00" in steps[-1] and "eta" in steps[-1]
    assert any(line.startswith("training: done in ") for line in lines)
