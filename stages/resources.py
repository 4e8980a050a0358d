"""Resource figures recorded in manifests: peak host RAM (and GPU memory when there is a GPU).

    peak_memory = {"ram_bytes": peak_ram_bytes(), "cuda_bytes": peak_cuda_bytes()}
"""

from __future__ import annotations

import resource
import sys


def peak_ram_bytes() -> int:
    """Peak resident set size of this process so far (ru_maxrss is KiB on Linux, bytes on macOS)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(peak if sys.platform == "darwin" else peak * 1024)


def peak_cuda_bytes() -> int | None:
    """Peak CUDA memory allocated by torch in this process, or None without CUDA."""
    import torch

    if not torch.cuda.is_available():
        return None
    return int(torch.cuda.max_memory_allocated())
