"""Give the C heap's free memory back to the system (glibc ``malloc_trim``).

A service frees as much as it allocates once its state is steady (retention, the dedup
window, the sums' compaction), but glibc keeps freed small blocks in its arenas, so the
resident size keeps the high-water mark of every batch's temporary arrays and SQLite
pages. Trimming every minute (on the worker thread, between transactions: it takes a
few milliseconds) lets RSS follow what the process holds. A no-op where the C library
has no ``malloc_trim`` (musl, macOS).
"""

from __future__ import annotations

import ctypes

TRIM_EVERY_S = 60.0


def _load_libc() -> ctypes.CDLL | None:
    """The symbols the process already has (the C library among them). Pitfall:
    ``ctypes.util.find_library`` runs ``ldconfig`` in a subprocess, a fork of the service
    that process supervisors see as a second instance of it."""
    try:
        lib = ctypes.CDLL(None)
    except OSError:
        return None
    return lib if hasattr(lib, "malloc_trim") else None


_LIBC = _load_libc()
"""The C library if it has ``malloc_trim`` (read once at import, never changed)."""


def trim_heap() -> bool:
    """``malloc_trim(0)``; whether memory was given back (False also where unsupported)."""
    return bool(_LIBC.malloc_trim(0)) if _LIBC is not None else False
