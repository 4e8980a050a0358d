"""The device a stage runs on, and its CPU kernels built before the work starts (first time only).

    device = resolve_device("auto")   # cuda when available, else cpu
    build_kernels(device, progress)   # no-op on CUDA, with IGAVATAR_KERNELS=0 or when cached

Without this the first training step would silently stall for the minute a build takes.
"""

from __future__ import annotations

import torch

from igavatar.errors import InputError
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


def resolve_device(name: str) -> torch.device:
    """'auto' -> cuda when available, else cpu; 'cuda' without a GPU is a clear error."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: no CUDA device is available to torch here; use --device cpu or auto")
    if name not in ("cpu", "cuda"):
        raise InputError(f"--device {name!r}: expected auto, cpu or cuda")
    return torch.device(name)
