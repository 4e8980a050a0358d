"""`train --view`: the training run on a page: loss and PSNR curves, the latest validation render,
and a coarse canonical mesh every N steps.

    panel = TrainingPanel(server, total_steps=1500, mesh_every=250)
    panel.on_step(step, {"loss": 0.1, "psnr": 21.0}, it_s=2.4)     # every step (cheap: buffered)
    panel.on_validation(step, image)                                  # (H, W, 3) uint8 panel
    if panel.wants_mesh(step): panel.show_mesh(vertices, faces, colors)

Every call runs on the training thread. Curves are sent at most once a second (a few hundred
numbers), so the page costs the step loop nothing measurable; the mesh costs a marching cubes,
which is why it comes every `mesh_every` steps at a low resolution (what N costs: README, "See it").
"""

from __future__ import annotations

import time

import numpy as np
import trimesh
import viser
import viser.uplot as uplot

#: Seconds between two updates of the curves and the status line.
CURVE_PERIOD_S = 1.0


class TrainingPanel:
    """The GUI of a training run on `server` (a page of its own, not the avatar viewer's)."""

    def __init__(self, server: viser.ViserServer, total_steps: int, mesh_every: int, up: np.ndarray | None = None):
        self.server, self.total_steps, self.mesh_every = server, int(total_steps), int(mesh_every)
        if up is not None:
            server.scene.set_up_direction(tuple(float(v) for v in up))
        self.steps: list[int] = []
        self.loss: list[float] = []
        self.psnr: list[float] = []
        self._sent = 0.0
        gui = server.gui
        self.status = gui.add_markdown("**training**: starting")
        self.loss_plot = gui.add_uplot(self._data("loss"), self._series("loss"), title="loss", aspect=2.0)
        self.psnr_plot = gui.add_uplot(self._data("psnr"), self._series("PSNR (dB)"), title="training PSNR (dB)",
                                       aspect=2.0)
        self.validation = gui.add_image(np.full((8, 24, 3), 255, np.uint8), label="validation: truth | render | normals")
        self.mesh_note = gui.add_markdown(f"canonical mesh every {self.mesh_every} steps" if self.mesh_every else
                                          "no canonical mesh (mesh every 0 steps)")
        self.mesh = None

    def _data(self, key: str) -> tuple[np.ndarray, np.ndarray]:
        values = self.loss if key == "loss" else self.psnr
        return np.asarray(self.steps, np.float64), np.asarray(values, np.float64)

    @staticmethod
    def _series(label: str) -> tuple[uplot.Series, ...]:
        return (uplot.Series(label="step"), uplot.Series(label=label, stroke="#3070d0", width=1.5))

    def on_step(self, step: int, metrics: dict[str, float], it_s: float) -> None:
        """Record one step; send the curves and the status line at most once per CURVE_PERIOD_S."""
        self.steps.append(int(step))
        self.loss.append(float(metrics.get("loss", np.nan)))
        self.psnr.append(float(metrics.get("psnr", np.nan)))
        now = time.monotonic()
        if now - self._sent < CURVE_PERIOD_S and step < self.total_steps:
            return
        self._sent = now
        eta = (self.total_steps - step) / max(it_s, 1e-9)
        self.status.content = (f"**training**: step {step} / {self.total_steps}, {it_s:.2f} it/s, "
                               f"about {eta / 60:.1f} min left; loss {self.loss[-1]:.4f}, PSNR {self.psnr[-1]:.2f} dB")
        with self.server.atomic():
            self.loss_plot.data = self._data("loss")
            self.psnr_plot.data = self._data("psnr")

    def on_validation(self, step: int, image: np.ndarray) -> None:
        self.validation.image = np.asarray(image, np.uint8)
        self.validation.label = f"validation at step {step}: truth | render | normals"

    def wants_mesh(self, step: int) -> bool:
        return bool(self.mesh_every) and (step % self.mesh_every == 0 or step == self.total_steps)

    def show_mesh(self, step: int, vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray, seconds: float) -> None:
        """The canonical mesh at `step` (vertices (V, 3), faces (F, 3), colors (V, 3) uint8)."""
        mesh = trimesh.Trimesh(vertices, faces, vertex_colors=colors, process=False)
        self.mesh = self.server.scene.add_mesh_trimesh("/canonical", mesh)
        self.mesh_note.content = (f"canonical mesh at step {step}: {len(faces)} faces, made in {seconds:.1f} s "
                                  f"(every {self.mesh_every} steps)")

    def finish(self, message: str) -> None:
        self.status.content = f"**training**: {message}"
