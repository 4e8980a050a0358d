"""The kernel loader's fallbacks and the stages' first-run build step (no compilation here)."""

from __future__ import annotations

import contextlib
import logging

import torch

import igavatar.kernels as kernels
import stages.kernels as stage_kernels


class RecordingProgress:
    def __init__(self) -> None:
        self.tasks: list[tuple[str, int | None]] = []
        self.advanced = 0

    def status(self, message: str) -> None:
        pass

    @contextlib.contextmanager
    def task(self, description: str, total: int | None):
        self.tasks.append((description, total))

        def advance(*args, **kwargs) -> None:
            self.advanced += 1

        yield advance


def test_a_kernel_that_cannot_build_falls_back_with_one_logged_line(caplog, monkeypatch):
    monkeypatch.setattr(kernels, "_LOADED", {})
    monkeypatch.setattr(kernels, "_FAILURES", {})
    with caplog.at_level(logging.WARNING, logger="igavatar.kernels"):
        assert kernels.load_kernel("no_such_kernel") is None
        assert kernels.load_kernel("no_such_kernel") is None  # the failure is remembered: one line only
    lines = [r.getMessage() for r in caplog.records if r.name == "igavatar.kernels"]
    assert len(lines) == 1 and "no_such_kernel" in lines[0] and "PyTorch path" in lines[0]


def test_disabled_kernels_are_never_loaded(monkeypatch):
    monkeypatch.setenv("IGAVATAR_KERNELS", "0")
    assert not kernels.kernels_enabled()
    assert kernels.load_kernel("skinning") is None
    assert set(kernels.kernel_status().values()) == {"disabled"}
    kernels.set_kernels_enabled(True)
    try:
        assert kernels.kernels_enabled()  # the in-process switch wins over the variable
    finally:
        kernels.set_kernels_enabled(None)


def test_build_kernels_builds_only_missing_ones_under_a_progress_task(monkeypatch):
    built: list[str] = []
    monkeypatch.setattr(stage_kernels, "KERNEL_NAMES", ("hashgrid", "skinning"))
    monkeypatch.setattr(stage_kernels, "kernel_built", lambda name: name == "skinning")
    monkeypatch.setattr(stage_kernels, "load_kernel", lambda name: built.append(name))
    progress = RecordingProgress()
    stage_kernels.build_kernels(torch.device("cpu"), progress)
    assert built == ["hashgrid"] and progress.tasks[0][1] == 1 and progress.advanced == 1

    # Nothing to do on CUDA, when disabled, or when everything is cached.
    progress = RecordingProgress()
    stage_kernels.build_kernels(torch.device("cuda"), progress)
    monkeypatch.setattr(stage_kernels, "kernel_built", lambda name: True)
    stage_kernels.build_kernels(torch.device("cpu"), progress)
    monkeypatch.setattr(stage_kernels, "kernel_built", lambda name: False)
    monkeypatch.setattr(stage_kernels, "kernels_enabled", lambda: False)
    stage_kernels.build_kernels(torch.device("cpu"), progress)
    assert progress.tasks == [] and built == ["hashgrid"]


def test_cache_key_covers_the_kernel_source_and_the_shared_headers(tmp_path, monkeypatch):
    monkeypatch.setattr(kernels, "_SOURCE_DIR", tmp_path)
    monkeypatch.setenv("IGAVATAR_KERNEL_CACHE", str(tmp_path / "cache"))
    (tmp_path / "k.cpp").write_text('#include "shared.h"\n')
    (tmp_path / "shared.h").write_text("// v1\n")
    first = kernels._cache_dir("k")
    assert first.parent == tmp_path / "cache" and first.name.startswith("k-")
    (tmp_path / "shared.h").write_text("// v2\n")  # a header edit must not load the old library
    second = kernels._cache_dir("k")
    (tmp_path / "k.cpp").write_text('#include "shared.h"\n// edited\n')
    assert len({first, second, kernels._cache_dir("k")}) == 3
