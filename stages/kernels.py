"""Build the CPU kernels before a stage's work starts, under a progress bar, the first time only.

    build_kernels(device, progress)   # no-op on CUDA, with IGAVATAR_KERNELS=0 or when cached

Without this the first training step would silently stall for the minute a build takes.
"""

from __future__ import annotations

import torch

from igavatar.kernels import KERNEL_NAMES, kernel_built, kernels_enabled, load_kernel
from stages.progress import NULL_PROGRESS, ProgressSink


def build_kernels(device: torch.device, progress: ProgressSink = NULL_PROGRESS) -> None:
    """Compile the kernels that are not cached yet (a failed build falls back, see igavatar.kernels)."""
    if device.type != "cpu" or not kernels_enabled():
        return
    missing = [name for name in KERNEL_NAMES if not kernel_built(name)]
    if not missing:
        return
    with progress.task("building the CPU kernels (first run only, about a minute each)", total=len(missing)) as advance:
        for name in missing:
            load_kernel(name)
            advance()
