"""Process resources: peak host RAM and GPU memory for the manifests, and the host allocator.

    peak_memory = {"ram_bytes": peak_ram_bytes(), "cuda_bytes": peak_cuda_bytes()}
    tune_host_allocator()      # once per process, before the heavy work (the CLI does it)
"""

from __future__ import annotations

import ctypes
import os
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


#: What `tune_host_allocator` sets, with glibc's mallopt parameter numbers (malloc.h): tensors up
#: to 32 MiB (glibc's largest allowed threshold) come from the heap, and freed heap memory is kept
#: (up to 1 GiB) and grown in 64 MiB steps.
_MALLOPT = {"mmap_threshold": (-3, 32 << 20), "trim_threshold": (-1, 1 << 30), "top_pad": (-2, 64 << 20)}
ALLOCATOR_SETTINGS = {name: value for name, (_, value) in _MALLOPT.items()}
_ALLOCATOR_ENV = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_", "GLIBC_TUNABLES")


def tune_host_allocator() -> dict[str, int] | None:
    """Keep freed tensor memory in the process instead of handing it back to the kernel (glibc).

    A CPU training step allocates and frees tens of MB of (P, 128) activations and gradients.
    glibc serves blocks this size with fresh mmap()s, or trims them off the heap when freed, so
    every step pays a page fault per 4 KiB of them (thousands per step, about a fifth of a CPU
    step on a 2-core machine, measured). These settings keep that memory for the next step;
    the process's peak RSS is unchanged. Returns the settings applied, or None where they do not
    apply: not glibc, ``IGAVATAR_MALLOC_TUNING=0``, or the user set glibc's own malloc variables.
    """
    if os.environ.get("IGAVATAR_MALLOC_TUNING", "1").strip().lower() in ("0", "false", "no", "off"):
        return None
    if any(name in os.environ for name in _ALLOCATOR_ENV):
        return None  # the user's own settings win
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl and friends: no mallopt
        return None
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    # mallopt returns 1 when it accepts a setting.
    applied = {name: value for name, (parameter, value) in _MALLOPT.items() if mallopt(parameter, value) == 1}
    return applied or None
