"""Host allocator settings: applied on glibc, never over the user's own, off on request."""

from __future__ import annotations

import sys

import pytest

from stages.resources import ALLOCATOR_SETTINGS, tune_host_allocator

glibc = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="mallopt is glibc's (Linux)")


@glibc
def test_allocator_settings_are_applied_on_glibc(monkeypatch):
    for name in ("IGAVATAR_MALLOC_TUNING", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_", "GLIBC_TUNABLES"):
        monkeypatch.delenv(name, raising=False)
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        pytest.skip("this Linux libc has no mallopt (not glibc)")
    assert tune_host_allocator() == ALLOCATOR_SETTINGS


def test_allocator_tuning_respects_opt_out_and_user_settings(monkeypatch):
    monkeypatch.setenv("IGAVATAR_MALLOC_TUNING", "0")
    assert tune_host_allocator() is None
    monkeypatch.delenv("IGAVATAR_MALLOC_TUNING")
    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "131072")
    assert tune_host_allocator() is None
