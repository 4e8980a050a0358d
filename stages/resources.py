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


#: Rough bytes per ray sample of one training step (encodings, MLP activations and their
#: gradients, the eikonal double backward): the `cpu` preset's ~98k samples peak near 2 GB of RAM
#: with the dataset loaded, so 16 KiB is a floor, never an over-estimate that refuses a good run.
TRAIN_BYTES_PER_SAMPLE = 16 << 10
#: Bytes per rendered pixel kept for a whole image (rgb, normal, depth, opacity and the uint8 copies).
IMAGE_BYTES_PER_PIXEL = 64


def available_memory_bytes(device: "torch.device | str | None" = None) -> int | None:  # noqa: F821
    """Memory a new allocation can use now: free GPU memory on CUDA, else MemAvailable (Linux) or RAM."""
    if device is not None and str(device).startswith("cuda"):
        import torch

        if torch.cuda.is_available():
            free, _total = torch.cuda.mem_get_info()
            return int(free)
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return int(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def _gib(nbytes: float) -> str:
    return f"{nbytes / 2**30:.1f} GiB"


def require_memory(nbytes: float, what: str, device: "torch.device | str | None" = None) -> None:  # noqa: F821
    """Refuse a size the user chose before allocating it, when it needs more memory than there is.

    Args:
        nbytes: an estimate (a floor) of the bytes the choice needs.
        what: the option and value, e.g. '--resolution 20000 (marching cubes)'.
        device: where it is allocated (CUDA: free GPU memory; else host RAM).
    Raises:
        ResourceLimitError naming the option, the estimate and the limit.
    """
    from igavatar.errors import ResourceLimitError

    limit = available_memory_bytes(device)
    if limit is None or nbytes <= limit:
        return
    where = "free GPU memory" if device is not None and str(device).startswith("cuda") else "available memory"
    raise ResourceLimitError(
        f"{what}: needs about {_gib(nbytes)}, more than the {_gib(limit)} of {where} on this machine; "
        "choose a smaller value"
    )


def require_marching_memory(canonical_box, resolution: int, what: str) -> None:
    """`require_memory` for marching cubes at `resolution` over a canonical box ((2, 3) nested lists or array).

    The grid lives in host memory whatever the device; the box is padded as export pads it (2 %).
    """
    import numpy as np

    from igavatar.geometry.extract import marching_cubes_bytes

    box = np.asarray(canonical_box, dtype=np.float64)
    pad = 0.02 * float((box[1] - box[0]).max())
    require_memory(marching_cubes_bytes(box[0] - pad, box[1] + pad, resolution), what)
