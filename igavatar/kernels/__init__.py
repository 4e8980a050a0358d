"""Optional C++/OpenMP CPU kernels, compiled lazily on first use, each behind its PyTorch reference.

    from igavatar.kernels import load_kernel
    module = load_kernel("skinning")        # None: use the plain PyTorch path
    if module is not None and kernel_applies(x): y = module.broyden(...)

Sources live in ``csrc/<name>.cpp`` next to this file, shared headers in ``csrc/*.h`` (part of
every kernel's cache key). Nothing compiles at import time: the first call of :func:`load_kernel`
builds the extension with ``torch.utils.cpp_extension.load`` (ninja and a C++ compiler; about
30-60 s per kernel on 2 cores) into a per-torch-version cache directory, and later processes load
the cached library in milliseconds. When the build fails (no compiler, no
ninja) the caller gets None, falls back to the reference path, and one line on stderr says why.

``IGAVATAR_KERNELS=0`` turns every fast path off, the kernels and the PyTorch-level shortcuts
that consult :func:`kernels_enabled` (the non-rigid MLP's shared-pose first layer): the reference
path everywhere, e.g. to compare;
``IGAVATAR_KERNEL_CACHE`` moves the build directory (default ``~/.cache/igavatar/kernels``).
"""

from __future__ import annotations

import hashlib
import logging
import os
import threading
from pathlib import Path
from types import ModuleType

import torch

__all__ = ["KERNEL_NAMES", "kernel_built", "kernel_status", "kernels_enabled", "load_kernel", "set_kernels_enabled"]

_SOURCE_DIR = Path(__file__).resolve().parent / "csrc"
_LOG = logging.getLogger(__name__)
KERNEL_NAMES: tuple[str, ...] = tuple(sorted(path.stem for path in _SOURCE_DIR.glob("*.cpp")))
"""Every kernel with a source in csrc/."""
_LOCK = threading.Lock()
_LOADED: dict[str, ModuleType | None] = {}
_FAILURES: dict[str, str] = {}
_OVERRIDE: bool | None = None


def kernels_enabled() -> bool:
    """Whether the fast kernels may be used: ``set_kernels_enabled`` if called, else the env var."""
    if _OVERRIDE is not None:
        return _OVERRIDE
    return os.environ.get("IGAVATAR_KERNELS", "1").strip().lower() not in ("0", "false", "no", "off")


def set_kernels_enabled(enabled: bool | None) -> None:
    """Force the kernels on/off in this process (None: back to ``IGAVATAR_KERNELS``); for benchmarks and tests."""
    global _OVERRIDE
    _OVERRIDE = enabled


def _cache_dir(name: str) -> Path:
    root = Path(os.environ.get("IGAVATAR_KERNEL_CACHE", Path.home() / ".cache" / "igavatar" / "kernels"))
    # One directory per torch build and source text, the shared headers included (csrc/*.h): a
    # stale library is never loaded. The source folder is part of the key too: torch's build
    # records absolute source paths, so two checkouts sharing one directory would rebuild it in
    # turn (and wait on each other's build lock).
    digest = hashlib.sha1((_SOURCE_DIR / f"{name}.cpp").read_bytes())
    digest.update(str(_SOURCE_DIR.resolve()).encode())
    for header in sorted(_SOURCE_DIR.glob("*.h")):
        digest.update(header.name.encode() + header.read_bytes())
    digest.update(torch.__version__.encode())
    return root / f"{name}-{digest.hexdigest()[:12]}"


def kernel_built(name: str) -> bool:
    """Whether loading `name` is quick: already loaded here, or a compiled library is cached."""
    if name in _LOADED:
        return True
    return any(_cache_dir(name).glob("*.so"))


def load_kernel(name: str) -> ModuleType | None:
    """The compiled extension ``csrc/<name>.cpp``, building it on first use; None when disabled or unbuildable."""
    if not kernels_enabled():
        return None
    if name in _LOADED:  # the hot path (every chunk, every root-finding call): no lock
        return _LOADED[name]
    with _LOCK:
        if name in _LOADED:
            return _LOADED[name]
        module = None
        try:
            module = _build(name)
        except Exception as error:  # noqa: BLE001 - any build failure means "use the reference"
            reason = " ".join(str(error).split())[:300]
            _FAILURES[name] = reason
            # One line through logging (the library never prints); with no logging set up,
            # Python's last-resort handler writes it to stderr.
            _LOG.warning("igavatar: fast CPU kernel %r unavailable (%s); using the PyTorch path", name, reason)
        _LOADED[name] = module
        return module


def _build(name: str) -> ModuleType:
    from torch.utils import cpp_extension

    source_path = _SOURCE_DIR / f"{name}.cpp"
    build_dir = _cache_dir(name)
    build_dir.mkdir(parents=True, exist_ok=True)
    return cpp_extension.load(
        name=f"igavatar_{name}",
        sources=[str(source_path)],
        build_directory=str(build_dir),
        # No -march=native: the cached library must not depend on the CPU it was built on.
        extra_cflags=["-O3", "-fopenmp"],
        extra_ldflags=["-fopenmp"],
        verbose=False,
    )


def kernel_status() -> dict[str, str]:
    """name -> "loaded" / "failed: why" / "disabled" for every kernel source (benchmarks print it)."""
    status = {}
    for name in KERNEL_NAMES:
        if not kernels_enabled():
            status[name] = "disabled"
        elif name in _FAILURES:
            status[name] = f"failed: {_FAILURES[name]}"
        else:
            status[name] = "loaded" if _LOADED.get(name) is not None else "not built yet"
    return status
