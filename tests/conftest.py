"""Shared fixtures: small hand-made captures and a CLI runner.

    def test_x(tiny_skeleton_capture): ...   # a valid capture v1 directory (body model 'skeleton')
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner


def write_tiny_capture(root: Path, n_frames: int = 3, size: int = 16, body_model: str = "skeleton") -> Path:
    """Write a minimal, valid capture v1 (skeleton body model) with solid-color images and masks."""
    root.mkdir(parents=True, exist_ok=True)
    frames = [f"f{i:03d}" for i in range(n_frames)]
    (root / "images").mkdir()
    (root / "masks").mkdir()
    for i, name in enumerate(frames):
        image = np.full((size, size, 3), 40 * i, np.uint8)
        mask = np.zeros((size, size), np.uint8)
        mask[size // 4 : 3 * size // 4, size // 4 : 3 * size // 4] = 255
        cv2.imwrite(str(root / "images" / f"{name}.png"), image)
        cv2.imwrite(str(root / "masks" / f"{name}.png"), mask)
    K = np.array([[size, 0, size / 2], [0, size, size / 2], [0, 0, 1]], np.float64)
    w2c = np.eye(4)
    w2c[2, 3] = 3.0
    np.savez(root / "cameras.npz", K=K, w2c=w2c, height=size, width=size)
    parents = np.array([-1, 0, 1], np.int64)
    rest = np.array([[0, 0, 0], [0, 0.3, 0], [0, 0.6, 0]], np.float64)
    np.savez(
        root / "poses.npz", parents=parents, rest_joints=rest,
        rotvecs=np.zeros((n_frames, 3, 3)), transl=np.zeros((n_frames, 3)),
    )
    meta = {
        "format": "igavatar-capture", "version": 1, "body_model": body_model, "frames": frames,
        "splits": {"train": frames[:-1], "test": frames[-1:]},
    }
    (root / "capture.json").write_text(json.dumps(meta))
    return root


@pytest.fixture
def tiny_skeleton_capture(tmp_path: Path) -> Path:
    return write_tiny_capture(tmp_path / "capture")


@pytest.fixture
def cli_runner() -> CliRunner:
    return CliRunner()


@pytest.fixture(scope="session")
def small_run(tmp_path_factory) -> Path:
    """A tiny synthetic capture (96 px, 4 train + 3 test frames) and its dataset, shared by tests."""
    from stages.preprocess import PreprocessOptions, run_preprocess
    from stages.synth import SynthOptions, run_synth

    run = tmp_path_factory.mktemp("run")
    run_synth(SynthOptions(out=run / "capture", resolution=96, train_frames=4, test_frames=3, seed=3))
    run_preprocess(PreprocessOptions(capture=run / "capture", out=run / "dataset", max_size=64))
    return run


@pytest.fixture(scope="session")
def tiny_model(small_run, tmp_path_factory) -> Path:
    """A model artifact trained on `small_run` with the `tiny` preset, shared (read-only) by tests."""
    from stages.train import TrainOptions, run_train

    out = tmp_path_factory.mktemp("model") / "model"
    run_train(TrainOptions(dataset=small_run / "dataset", out=out, preset="tiny", device="cpu"))
    return out


def built_kernel(name: str):
    """The compiled kernel `name`, built with the kernels forced on.

    A machine without a C++ compiler cannot build it: the kernel tests are skipped there, saying
    so. Anywhere else a failed build is a test failure (with the loader's reason), never a skip.
    """
    from igavatar import kernels

    kernels.set_kernels_enabled(True)
    try:
        module = kernels.load_kernel(name)
    finally:
        kernels.set_kernels_enabled(None)
    if module is not None:
        return module
    if not any(shutil.which(compiler) for compiler in ("c++", "g++", "clang++")):
        pytest.skip(f"no C++ compiler on PATH: the {name!r} kernel cannot be built here")
    pytest.fail(f"{name!r} kernel failed to build: {kernels.kernel_status().get(name)}")


@pytest.fixture
def kernels_on():
    """Kernels forced on for one test (whatever IGAVATAR_KERNELS says), switch restored after."""
    from igavatar import kernels

    kernels.set_kernels_enabled(True)
    yield
    kernels.set_kernels_enabled(None)
