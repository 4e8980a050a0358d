"""Where each stage reads and writes by default: one run directory holding every artifact.

    layout = RunLayout(Path("igavatar-run"))
    layout.capture, layout.dataset, layout.model    # igavatar-run/capture, .../dataset, .../model

Only `stages/` knows this layout; the library takes explicit paths.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

DEFAULT_RUN_DIR = Path(os.environ.get("IGAVATAR_RUN_DIR", "igavatar-run"))


@dataclass(frozen=True)
class RunLayout:
    """Default artifact paths inside a run directory, in the order the stages make them."""

    root: Path = DEFAULT_RUN_DIR

    @property
    def capture(self) -> Path:
        return self.root / "capture"

    @property
    def dataset(self) -> Path:
        return self.root / "dataset"

    @property
    def model(self) -> Path:
        return self.root / "model"

    @property
    def mesh(self) -> Path:
        return self.root / "mesh"

    @property
    def animation(self) -> Path:
        return self.root / "animation"

    @property
    def report(self) -> Path:
        return self.root / "report"
