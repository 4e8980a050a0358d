"""What every stage does the same way: time its steps, skip work whose artifact is up to date.

    clock = StageClock()
    with clock("load_s"):
        model = load_model(path)
    if not options.force and unchanged(out, "mesh", config, inputs):
        return skipped("mesh", out)
    ... build_manifest(..., timings=clock.finish())
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from igavatar.artifacts.manifest import MANIFEST_NAME, InputRecord, read_artifact, sha256_json
from igavatar.errors import ArtifactError

#: Why a stage did nothing (its summary's "skipped" value).
UNCHANGED = "inputs and options unchanged (use --force to redo)"


class StageClock:
    """Wall-clock seconds of a stage's steps, for its manifest's `timings`."""

    def __init__(self) -> None:
        self.started = time.perf_counter()
        self.timings: dict[str, float] = {}

    @contextmanager
    def __call__(self, key: str) -> Iterator[None]:
        """Time the block and add its seconds to timings[key] (a step may run in several parts)."""
        tick = time.perf_counter()
        try:
            yield
        finally:
            self.timings[key] = self.timings.get(key, 0.0) + time.perf_counter() - tick

    def add(self, key: str, seconds: float) -> None:
        self.timings[key] = self.timings.get(key, 0.0) + seconds

    def elapsed(self) -> float:
        return time.perf_counter() - self.started

    def finish(self) -> dict[str, float]:
        """The timings with total_s, the seconds since the clock started."""
        self.timings["total_s"] = self.elapsed()
        return self.timings


def unchanged(out: Path, kind: str, config: dict, inputs: list[InputRecord] | list[dict]) -> bool:
    """Whether `out` already holds an intact `kind` artifact made with this config from these inputs.

    Read-only, so a stage calls it before its output-target check. `inputs` are InputRecords or
    their JSON (hashes compared, not paths: the same file content at another path is the same input).
    """
    if not (Path(out) / MANIFEST_NAME).is_file():
        return False
    try:
        manifest = read_artifact(Path(out), expected=kind)
    except ArtifactError:
        return False
    records = [r.to_json() if isinstance(r, InputRecord) else r for r in inputs]
    return (sha256_json(manifest["config"]) == sha256_json(config)
            and [i.get("sha256") for i in manifest["inputs"]] == [i.get("sha256") for i in records])


def skipped(key: str, out: Path) -> dict:
    """The summary of a stage that found its artifact up to date."""
    return {key: str(out), "skipped": UNCHANGED}
