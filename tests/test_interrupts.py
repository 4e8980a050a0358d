"""Ctrl-C and SIGTERM at every point of a run: held where a step must finish whole, never swallowed,
never a crash; the command ends with rc 130 (143 for SIGTERM) and one line, and earlier artifacts
stay byte-identical (issue 37).

Signals are real: the process sends them to itself with os.kill at the chosen point. The two cases
that need a fresh process (an interrupt during imports, and one inside scipy's multi-threaded
k-d tree query, which used to crash the interpreter) run the CLI in a subprocess.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from igavatar.errors import Terminated
from igavatar.interrupts import deferred_interrupts, raise_if_interrupted, signals_as_interrupts
from igavatar_cli.main import app

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def _python_ctrl_c_handler():
    """Python installs its Ctrl-C handler only when SIGINT is not ignored at start-up, and a shell
    starts a background job (`cmd &`) with SIGINT ignored: igavatar then rightly leaves Ctrl-C
    ignored, and these tests, which send it, would see nothing. Each test runs as under a terminal."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def _digest(root: Path) -> dict[str, str]:
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def _interrupted(result, code: int = 130, needle: str = "interrupted") -> None:
    assert result.exit_code == code, result.output
    assert "Traceback" not in result.output
    assert needle in result.output, result.output


# ------------------------------------------------------------------------------------------------
# The mechanism


def test_a_held_interrupt_is_raised_when_the_block_ends():
    ran_to_end = False
    with pytest.raises(KeyboardInterrupt):
        with deferred_interrupts():
            os.kill(os.getpid(), signal.SIGINT)
            ran_to_end = True
    assert ran_to_end
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_sigterm_held_inside_nested_blocks_arrives_once_as_terminated():
    with signals_as_interrupts():
        with pytest.raises(Terminated):
            with deferred_interrupts():
                with deferred_interrupts():
                    os.kill(os.getpid(), signal.SIGTERM)
                reached_outer_end = True
        assert reached_outer_end


def test_a_swallowed_interrupt_resurfaces_at_the_next_check():
    with signals_as_interrupts():
        try:  # what trimesh does around its optional imports
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(100):  # the handler runs between bytecodes
                pass
        except BaseException:
            pass
        with pytest.raises(KeyboardInterrupt):
            raise_if_interrupted()
    raise_if_interrupted()  # a new command starts with a clean slate


def test_an_ignored_signal_stays_ignored():
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with deferred_interrupts():
            os.kill(os.getpid(), signal.SIGINT)
    finally:
        signal.signal(signal.SIGINT, previous)


# ------------------------------------------------------------------------------------------------
# In-process: training steps, the checkpoint write, an export's mesh write


@pytest.fixture
def earlier_model(tiny_model, tmp_path) -> Path:
    model = tmp_path / "model"
    shutil.copytree(tiny_model, model)
    return model


def _train(small_run: Path, out: Path, *extra: str) -> list[str]:
    return ["train", "--dataset", str(small_run / "dataset"), "--out", str(out), "--preset", "tiny", "--device", "cpu",
            "-q", *extra]


@pytest.mark.parametrize("point", ["shape-init-step", "training-step", "checkpoint-write"])
def test_ctrl_c_during_training_keeps_the_earlier_model(cli_runner, small_run, earlier_model, monkeypatch, point):
    import stages.train
    from igavatar.training.trainer import Trainer

    before = _digest(earlier_model)
    if point == "shape-init-step":
        import igavatar.training.run_state as run_state

        real_fit = run_state.fit_sdf_to_template

        def fit(field, targets, steps, batch, seed, on_step):
            def step(i, loss):
                if i == 2:
                    os.kill(os.getpid(), signal.SIGINT)
                on_step(i, loss)
            return real_fit(field, targets, steps, batch, seed=seed, on_step=step)

        monkeypatch.setattr(run_state, "fit_sdf_to_template", fit)
        needle = "interrupted"
    elif point == "training-step":
        real_step = Trainer.train_step

        def step(self):
            if self.step == 1:  # mid-step: held until the step is whole
                os.kill(os.getpid(), signal.SIGINT)
            return real_step(self)

        monkeypatch.setattr(Trainer, "train_step", step)
        needle = "training interrupted at step 2"
    else:
        real_save = stages.train.save_state
        sent = []

        def save(path, state):
            if path.name == "checkpoint.npz" and not sent:  # the first one, at step 3
                sent.append(True)
                os.kill(os.getpid(), signal.SIGINT)
            real_save(path, state)

        monkeypatch.setattr(stages.train, "save_state", save)
        needle = "training interrupted at step 3"
    # --seed 1: not the cached shape fit of the earlier model, so shape initialization runs.
    _interrupted(cli_runner.invoke(app, _train(small_run, earlier_model, "--seed", "1")), 130, needle)
    assert _digest(earlier_model) == before
    leftovers = [p.name for p in earlier_model.parent.iterdir() if ".tmp-" in p.name or ".old-" in p.name]
    assert leftovers == []


def test_ctrl_c_while_an_export_writes_its_mesh(cli_runner, tiny_model, tmp_path, monkeypatch):
    import stages.export

    args = ["export", "--model", str(tiny_model), "--out", str(tmp_path / "mesh"), "--resolution", "16",
            "--formats", "ply", "--device", "cpu", "-q"]
    assert cli_runner.invoke(app, args).exit_code == 0
    before = _digest(tmp_path / "mesh")
    real_write = stages.export._write_mesh

    def write(path, *rest):
        real_write(path, *rest)
        os.kill(os.getpid(), signal.SIGINT)  # after the file is half the artifact

    monkeypatch.setattr(stages.export, "_write_mesh", write)
    _interrupted(cli_runner.invoke(app, [*args, "--force"]))
    assert _digest(tmp_path / "mesh") == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mesh"]


# ------------------------------------------------------------------------------------------------
# Fresh processes: during the imports, inside the k-d tree query


_DRIVER = textwrap.dedent("""
    import os, signal, sys, threading
    from igavatar_cli.main import app
    point = sys.argv[1]
    if point == "import":
        class SignalOnImport:  # Ctrl-C lands inside trimesh's `try: import scipy.spatial except BaseException`
            def find_spec(self, name, path=None, target=None):
                if name == "scipy.spatial" and "trimesh" in sys.modules:
                    sys.meta_path.remove(self)
                    os.kill(os.getpid(), signal.SIGINT)
                return None
        sys.meta_path.insert(0, SignalOnImport())
    else:
        import igavatar.geometry.mesh_ops as mesh_ops
        class SignalDuringQuery(mesh_ops.cKDTree):
            def query(self, *args, **kwargs):
                threading.Timer(0.05, os.kill, (os.getpid(), signal.SIGINT)).start()
                return super().query(*args, **kwargs)
        mesh_ops.cKDTree = SignalDuringQuery
    app(sys.argv[2:])
""")


@pytest.mark.parametrize("point", ["import", "kd-tree-query"])
def test_ctrl_c_in_a_fresh_process_ends_with_130_and_no_crash(small_run, earlier_model, point):
    before = _digest(earlier_model)
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONFAULTHANDLER": "1"}
    result = subprocess.run([sys.executable, "-c", _DRIVER, point, *_train(small_run, earlier_model, "--seed", "2")],
                            capture_output=True, text=True, env=env, cwd=REPO, timeout=600)
    output = result.stdout + result.stderr
    assert result.returncode == 130, output  # not 0 (swallowed, the model replaced) nor -11 (segfault)
    assert "interrupted" in output and "Traceback" not in output and "Fatal Python error" not in output, output
    assert _digest(earlier_model) == before


def test_ctrl_c_during_the_k_d_tree_query_arrives_once_the_query_has_finished(monkeypatch):
    import igavatar.geometry.mesh_ops as mesh_ops

    finished = {}

    class SignalDuringQuery(mesh_ops.cKDTree):
        def query(self, *args, **kwargs):
            os.kill(os.getpid(), signal.SIGINT)  # while the workers start
            finished["distance"] = super().query(*args, **kwargs)[0]
            return finished["distance"], None

    monkeypatch.setattr(mesh_ops, "cKDTree", SignalDuringQuery)
    rng = np.random.default_rng(0)
    samples, points = rng.normal(size=(20_000, 3)), rng.uniform(-2, 2, (100_000, 3))
    with pytest.raises(KeyboardInterrupt):
        mesh_ops.nearest_sample_distance(samples, points)
    np.testing.assert_array_equal(finished["distance"], SignalDuringQuery.__mro__[1](samples).query(points)[0])


# ------------------------------------------------------------------------------------------------
# --resume after a real Ctrl-C is exact


@pytest.mark.parametrize("point, at", [("mid-step", 1), ("mid-step", 4), ("checkpoint-write", 3), ("step-start", 5)])
def test_resume_after_ctrl_c_gives_the_uninterrupted_weights_bit_for_bit(cli_runner, small_run, tiny_model, tmp_path,
                                                                         monkeypatch, point, at):
    import igavatar.training.trainer as trainer_module
    import stages.train

    calls = {"loss": 0}
    if point == "mid-step":  # after the forward pass, before backward and the optimizer
        real_total_loss = trainer_module.total_loss

        def total_loss(*args, **kwargs):
            calls["loss"] += 1
            if calls["loss"] == at + 1:
                os.kill(os.getpid(), signal.SIGINT)
            return real_total_loss(*args, **kwargs)

        monkeypatch.setattr(trainer_module, "total_loss", total_loss)
    elif point == "checkpoint-write":
        real_save = stages.train.save_state

        def save(path, state):
            if path.name == "checkpoint.npz" and not calls["loss"]:
                calls["loss"] = 1
                os.kill(os.getpid(), signal.SIGINT)
            real_save(path, state)

        monkeypatch.setattr(stages.train, "save_state", save)
    else:
        real_step = trainer_module.Trainer.train_step

        def step(self):
            if self.step == at:
                os.kill(os.getpid(), signal.SIGINT)
            return real_step(self)

        monkeypatch.setattr(trainer_module.Trainer, "train_step", step)
    out = tmp_path / "model"
    _interrupted(cli_runner.invoke(app, _train(small_run, out)), 130, "training interrupted at step")
    monkeypatch.undo()
    resumed = cli_runner.invoke(app, _train(small_run, out, "--resume"))
    assert resumed.exit_code == 0, resumed.output
    with np.load(out / "weights.npz") as got, np.load(tiny_model / "weights.npz") as want:
        assert sorted(got.files) == sorted(want.files)
        for key in want.files:
            np.testing.assert_array_equal(got[key], want[key], err_msg=key)
    log_got = (out / "training_log.csv").read_text().splitlines()
    log_want = (tiny_model / "training_log.csv").read_text().splitlines()
    drop_time = lambda rows: [",".join(v for k, v in zip(rows[0].split(","), r.split(",")) if "seconds" not in k) for r in rows]
    assert drop_time(log_got) == drop_time(log_want)
