"""`igavatar batch` on a local Ray (2 CPUs, loopback): spec checks, failures kept to their job,
skipping on a re-run, a killed worker retried, and joining a head started with `ray start`."""

from __future__ import annotations

import csv
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from igavatar.errors import InputError
from igavatar_cli.batch_plans import known_options
from igavatar_cli.main import app
from stages.batch_job import parse_progress
from stages.batch_spec import read_spec

pytest.importorskip("ray", reason="the batch tests need Ray: pip install -e '.[test]' installs it")

TINY = {"preprocess": {"max_size": 32}, "train": {"preset": "tiny", "device": "cpu"},
        "export": {"resolution": 32, "coarse_resolution": 16, "formats": "ply", "glb_faces": 0, "device": "cpu"},
        "eval": {"mesh_resolution": 32, "surface_samples": 200, "iou_points": 2000, "image_scale": 0.25,
                 "samples": 8, "image_frames": 1, "iou_open_meshes": True, "device": "cpu"}}


def _group():
    import typer

    return typer.main.get_command(app)


def _write(path: Path, spec: dict) -> Path:
    path.write_text(json.dumps(spec))
    return path


def _batch(spec: Path, *args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "igavatar_cli.main", "batch", str(spec), "--cpus-per-job", "1",
                           "--local-cpus", "2", *args],
                          capture_output=True, text=True, timeout=timeout, env={**os.environ, "RAY_ADDRESS": ""})


def _summary(out: Path) -> dict[str, dict]:
    with open(out / "summary.csv") as f:
        return {row["job"]: row for row in csv.DictReader(f)}


@pytest.fixture(scope="module")
def broken_capture(tmp_path_factory) -> Path:
    capture = tmp_path_factory.mktemp("broken") / "capture"
    capture.mkdir()
    (capture / "capture.json").write_text('{"format": "igavatar-capture", "version": 1, "frames": []}')
    return capture


# ----------------------------------------------------------------------------- the spec


def test_spec_errors_name_the_key_and_nothing_runs(tmp_path, small_run):
    known = known_options(_group())
    capture = str(small_run / "capture")

    def fails(spec: dict, *fragments: str) -> None:
        with pytest.raises(InputError) as error:
            read_spec(_write(tmp_path / "spec.json", spec), known)
        assert all(f in str(error.value) for f in fragments), str(error.value)

    fails({"out": "r", "jobs": [{"name": "a", "capture": capture}], "extra": 1}, "unknown key 'extra'")
    fails({"out": "r", "jobs": [{"name": "a", "capture": capture, "trian": {}}]}, "jobs[0].trian", "unknown key")
    fails({"out": "r", "defaults": {"train": {"stepz": 3}}, "jobs": [{"name": "a", "capture": capture}]},
          "defaults.train.stepz", "no option --stepz")
    fails({"out": "r", "defaults": {"render": {}}, "jobs": [{"name": "a", "capture": capture}]}, "unknown stage 'render'")
    fails({"out": "r", "jobs": [{"name": "a", "capture": capture, "train": {"out": "x"}}]}, "set by batch")
    fails({"out": "r", "jobs": [{"name": "a"}]}, "exactly one of capture")
    fails({"out": "r", "jobs": [{"name": "a", "capture": capture}, {"name": "a", "capture": capture}]}, "two jobs")
    result = _batch(_write(tmp_path / "bad.json", {"out": "r", "jobs": [{"name": "a", "capture": capture,
                                                                          "train": {"steps": "many"}}]}))
    assert result.returncode == 2 and result.stderr.startswith("error: job a: train:") and "--steps" in result.stderr
    assert "Traceback" not in result.stderr and not (tmp_path / "r").exists()


def test_a_grid_expands_into_named_jobs_with_the_options_merged(tmp_path, small_run):
    spec = read_spec(_write(tmp_path / "spec.json", {
        "out": "runs", "defaults": {"train": {"preset": "tiny", "steps": 5}},
        "grid": {"train.seed": [0, 1], "train.regularizer": ["smooth", "none"]},
        "jobs": [{"name": "a", "capture": str(small_run / "capture"), "train": {"steps": 7}}]}), known_options(_group()))
    assert [job.name for job in spec.jobs] == ["a_seed0_regularizersmooth", "a_seed0_regularizernone",
                                               "a_seed1_regularizersmooth", "a_seed1_regularizernone"]
    assert spec.jobs[3].options["train"] == {"preset": "tiny", "steps": 7, "seed": 1, "regularizer": "none"}
    assert spec.jobs[0].run_dir == tmp_path / "runs" / "a_seed0_regularizersmooth"


def test_the_issues_minimal_spec_dry_runs_to_the_commands(tmp_path, small_run, cli_runner):
    (tmp_path / "captures").mkdir()
    for name in ("a", "b"):
        (tmp_path / "captures" / name).symlink_to(small_run / "capture")
    spec = _write(tmp_path / "spec.json", {"out": "runs/",
                                           "defaults": {"preprocess": {"max_size": 64}, "train": {"preset": "tiny"}},
                                           "jobs": [{"name": "a", "capture": "captures/a"},
                                                    {"name": "b", "capture": "captures/b"}]})
    result = cli_runner.invoke(app, ["batch", str(spec), "--dry-run", "--json"])
    assert result.exit_code == 0, result.output
    commands = json.loads(result.output)
    run_a = tmp_path / "runs" / "a"
    assert commands["a"] == [f"igavatar preprocess --run-dir {run_a} --capture {tmp_path / 'captures' / 'a'} --max-size 64",
                             f"igavatar train --run-dir {run_a} --preset tiny", f"igavatar export --run-dir {run_a}",
                             f"igavatar eval --run-dir {run_a}"]
    assert not (tmp_path / "runs").exists()  # a dry run writes nothing


def test_progress_lines_are_read_back():
    assert parse_progress("training: 120/800  loss 0.1  psnr 20.1  eta 1 min 05 s") == {
        "task": "training", "step": 120, "total": 800, "eta": "1 min 05 s"}
    assert parse_progress("training: started (800 steps)") is None


# ----------------------------------------------------------------------------- on Ray


def test_three_jobs_one_broken_then_a_rerun_skips_everything(tmp_path, small_run, broken_capture):
    out = tmp_path / "runs"
    spec = _write(tmp_path / "spec.json", {"out": str(out), "defaults": TINY, "jobs": [
        {"name": "a", "capture": str(small_run / "capture")},
        {"name": "b", "capture": str(small_run / "capture"), "train": {"seed": 1}},
        {"name": "broken", "capture": str(broken_capture)}]})
    first = _batch(spec)
    assert first.returncode == 1, first.stderr
    rows = _summary(out)
    assert set(rows) == {"a", "b", "broken"} and rows["a"]["status"] == rows["b"]["status"] == "ok"
    assert rows["broken"]["status"] == "failed" and rows["broken"]["error"].startswith("preprocess:")
    assert "capture.json" in rows["broken"]["error"] and "body_model" in rows["broken"]["error"]
    assert float(rows["a"]["psnr_full_db"]) > 5 and float(rows["b"]["chamfer_l1_surface_mm"]) > 0
    assert (out / "a" / "mesh" / "canonical.ply").is_file() and (out / "b" / "report" / "metrics.json").is_file()
    assert "| broken | failed |" in (out / "summary.md").read_text()
    manifests = {p: p.stat().st_mtime_ns for p in out.glob("[ab]/*/manifest.json")}
    second = _batch(spec)
    assert second.returncode == 1
    rows = _summary(out)
    assert rows["a"]["skipped"] == rows["b"]["skipped"] == "preprocess,train,export,eval"
    assert {p: p.stat().st_mtime_ns for p in out.glob("[ab]/*/manifest.json")} == manifests


def _processes() -> list[tuple[int, int, str]]:
    """(pid, parent pid, command line) of every process, from `ps` (Linux and macOS)."""
    listing = subprocess.run(["ps", "-ww", "-eo", "pid=,ppid=,args="], capture_output=True, text=True, check=True).stdout
    rows = []
    for line in listing.splitlines():
        pid, ppid, args = (line.split(None, 2) + [""])[:3]
        rows.append((int(pid), int(ppid), args))
    return rows


def _stage_process(run_dir: Path, stage: str) -> tuple[int, int] | None:
    """(pid, parent pid) of a running `igavatar_cli.main STAGE --run-dir run_dir`, the parent being
    the Ray worker that started it."""
    for pid, ppid, args in _processes():
        words = args.split()
        if "igavatar_cli.main" in words and stage in words and str(run_dir) in words:
            return pid, ppid
    return None


def test_a_killed_worker_is_retried_and_the_job_succeeds(tmp_path, small_run):
    out = tmp_path / "runs"
    tiny = {**TINY, "train": {**TINY["train"], "steps": 400}}
    spec = _write(tmp_path / "spec.json", {"out": str(out), "defaults": tiny,
                                           "jobs": [{"name": "k", "capture": str(small_run / "capture")}]})
    batch = subprocess.Popen([sys.executable, "-m", "igavatar_cli.main", "batch", str(spec), "--max-retries", "1",
                              "--local-cpus", "2"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             env={**os.environ, "RAY_ADDRESS": ""})
    deadline, stage = time.time() + 300, None
    while stage is None and time.time() < deadline and batch.poll() is None:
        stage = _stage_process(out / "k", "train")
        time.sleep(0.2)
    assert stage is not None, "the job's train stage never started"
    time.sleep(3)  # mid-training
    os.kill(stage[1], signal.SIGKILL)  # the Ray worker running the job
    stdout, stderr = batch.communicate(timeout=600)
    assert batch.returncode == 0, stderr
    row = _summary(out)["k"]
    assert row["status"] == "ok" and row["attempts"] == "2"
    assert float(row["psnr_full_db"]) > 5


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_joins_a_head_started_with_ray_start(tmp_path, small_run):
    ray_cli = str(Path(sys.executable).parent / "ray")
    port = _free_port()
    env = {**os.environ, "RAY_ADDRESS": ""}
    started = subprocess.run([ray_cli, "start", "--head", "--node-ip-address", "127.0.0.1", "--port", str(port),
                              "--num-cpus", "2", "--include-dashboard", "false", "--disable-usage-stats"],
                             capture_output=True, text=True, timeout=120, env=env)
    assert started.returncode == 0, started.stderr
    try:
        out = tmp_path / "runs"
        spec = _write(tmp_path / "spec.json", {"out": str(out), "defaults": TINY,
                                               "jobs": [{"name": "c", "capture": str(small_run / "capture")}]})
        result = _batch(spec, "--stages", "preprocess", "--address", f"127.0.0.1:{port}")
        assert result.returncode == 0, result.stderr
        assert _summary(out)["c"]["status"] == "ok" and (out / "c" / "dataset" / "manifest.json").is_file()
    finally:
        subprocess.run([ray_cli, "stop", "--force"], capture_output=True, timeout=120, env=env)
