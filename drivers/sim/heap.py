"""Give the memory a build freed back to the system.

glibc keeps freed blocks in its heap for reuse, and after a large free it raises its mmap threshold,
so the temporaries of building a world (noise fields, meshes, rock tables: hundreds of MiB) stay in
the process's resident memory long after they are gone. `malloc_trim(0)` returns the free pages; on
a C library without it this does nothing.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import functools


@functools.cache
def _trim():
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):
        return None


def give_back_free_heap() -> None:
    trim = _trim()
    if trim is not None:
        trim(0)
