"""Giving a dropped slide's memory back to the system."""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import gc


def release_memory() -> None:
    """Give freed memory back to the system: collect cycles, then trim glibc's heap.

    Without the trim, a dropped slide's arrays below glibc's (self-raising) mmap
    threshold stay in the process's heap, and its resident memory never shrinks.
    """
    gc.collect()
    libc = _glibc()
    if libc is not None:
        libc.malloc_trim(0)


@functools.cache  # looked up when first needed: `find_library` runs ldconfig
def _glibc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
    except OSError:
        return None
    return libc if libc is not None and hasattr(libc, "malloc_trim") else None
