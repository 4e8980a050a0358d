"""`train --view`: a viser page that follows a training run (igavatar.viewer.training).

    monitor = TrainingMonitor.open(options, dataset, total_steps, progress)   # before shape init
    monitor.step(trainer, last, it_s)      # after every step: curves, and the mesh every N steps
    monitor.validation(step, panel)        # when training writes a validation panel
    monitor.close("done")

It only reads the trainer: no random numbers, no gradients, the model untouched, so a run with
--view writes the same artifacts as one without (tests/test_train_view.py).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from igavatar.avatar.dataset import DatasetArtifact
from igavatar.avatar.surfaces import canonical_surface, vertex_colors
from igavatar.viewer.server import open_server, server_url, stop_server
from igavatar.viewer.training import TrainingPanel
from stages.progress import ProgressSink

#: Coarse grid of the training mesh's marching cubes (its fine grid is --view-mesh-resolution).
_COARSE = 24


@dataclass(frozen=True)
class ViewSettings:
    """train --view's options: where to serve, and the canonical mesh's period and resolution."""

    host: str = "127.0.0.1"
    port: int = 8080
    mesh_every: int = 100
    mesh_resolution: int = 64


class TrainingMonitor:
    """The server and its panel for one training run."""

    def __init__(self, server, panel: TrainingPanel, settings: ViewSettings):
        self.server, self.panel, self.settings = server, panel, settings
        self.mesh_seconds = 0.0
        self.meshes = 0

    @classmethod
    def open(cls, settings: ViewSettings, dataset: DatasetArtifact, total_steps: int,
             progress: ProgressSink) -> TrainingMonitor:
        """Start the server (InputError for a busy port) and print its address."""
        server = open_server(settings.host, settings.port, label="igavatar train", flag="--view-port")
        panel = TrainingPanel(server, total_steps, settings.mesh_every, up=np.asarray(dataset.body_axes)[:, 1])
        progress.status(f"training viewer: {server_url(server)}")
        return cls(server, panel, settings)

    @torch.no_grad()
    def step(self, trainer, last: dict[str, float], it_s: float) -> None:
        self.panel.on_step(trainer.step, last, it_s)
        if self.panel.wants_mesh(trainer.step):
            started = time.perf_counter()
            vertices, faces = canonical_surface(trainer.avatar, resolution=self.settings.mesh_resolution,
                                                coarse_resolution=min(_COARSE, self.settings.mesh_resolution))
            if faces.shape[0]:
                colors = vertex_colors(trainer.avatar, vertices)
                seconds = time.perf_counter() - started
                self.panel.show_mesh(trainer.step, vertices, faces, colors, seconds)
            self.mesh_seconds += time.perf_counter() - started
            self.meshes += 1

    def validation(self, step: int, panel: np.ndarray) -> None:
        self.panel.on_validation(step, panel)

    def close(self, message: str) -> dict:
        """Stop the server; what the page cost (for the run's summary)."""
        self.panel.finish(message)
        stop_server(self.server)
        return {"meshes": self.meshes, "mesh_seconds": round(self.mesh_seconds, 2)}
