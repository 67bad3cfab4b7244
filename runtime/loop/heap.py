"""Giving the C heap's free memory back to the system, between ticks.

glibc's malloc keeps memory a program freed in its heaps (one per thread that allocates, up to
eight per core) for the next allocation, and raises its mmap threshold up to 32 MB each time a
large block is freed, so that lidar frames and images (hundreds of kB each, allocated and freed
every tick) end up in those heaps too. Their free space becomes fragmented, and the resident
size of a long-running process grows though what it holds does not: measured in the real-time
controller after two minutes, 426 MB of heap of which 174 MB in use. `malloc_trim(0)` returns
every whole free page of every heap to the system (madvise); the loop calls it between ticks,
where a collection already runs, about every ten seconds, taking a few milliseconds.

`limit_arenas` caps the number of those heaps for the controller process before its threads start
(`realtime.malloc_arena_max`): the trim returns whole free pages only, and the free space the
threads' own heaps held was what the resident size of the real-time controller moved with.

Only where the C library is glibc; elsewhere `HeapTrimmer.available` is False and it does nothing.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import time

#: Ticks between two trims (10 s at 20 Hz), after the loop's full collection.
TRIM_EVERY_TICKS = 200


#: glibc's mallopt parameter number for the most arenas (malloc.h: M_ARENA_MAX).
M_ARENA_MAX = -8


def _glibc(name: str, argtypes: list, restype):
    """A function of glibc's malloc (ctypes), or None where the C library has none of that name."""
    lib = ctypes.util.find_library("c")
    if lib is None:
        return None
    try:
        fn = getattr(ctypes.CDLL(lib), name)
    except (OSError, AttributeError):
        return None
    fn.argtypes, fn.restype = argtypes, restype
    return fn


def limit_arenas(most: int) -> bool:
    """At most `most` malloc arenas for the process from now on (glibc's default: eight per core,
    one more each time threads contend). Each arena keeps its own free space: in the real-time
    controller (the DDS receiver, the recorder, the VPP's helpers and the loop allocating frames
    and images in their own arenas) the free space held, not the memory in use, made the resident
    size (census: 193 MB in use throughout, 20-316 MB free in the arenas). Call it before the
    threads start. False where the C library is not glibc or refuses."""
    global arena_limit
    mallopt = _glibc("mallopt", [ctypes.c_int, ctypes.c_int], ctypes.c_int)
    if mallopt is None or mallopt(M_ARENA_MAX, int(most)) != 1:
        return False
    arena_limit = int(most)
    return True


#: The arena limit set for this process (limit_arenas), None while glibc's default holds.
arena_limit: int | None = None


def _malloc_trim():
    """glibc's malloc_trim, or None."""
    return _glibc("malloc_trim", [ctypes.c_size_t], ctypes.c_int)


class HeapTrimmer:
    """Calls malloc_trim(0) every `every_ticks` ticks (0: only when `trim()` is called); counts the
    calls and times them on the wall clock (a report: it decides nothing)."""

    def __init__(self, every_ticks: int = TRIM_EVERY_TICKS) -> None:
        self.every_ticks = int(every_ticks)
        self._trim = _malloc_trim()
        self.available = self._trim is not None
        self.trims = 0
        self.max_ms = 0.0
        self.total_ms = 0.0

    def between_ticks(self, ticks_run: int) -> None:
        """After tick number `ticks_run` (from 1): a trim on the schedule, half-way between the
        loop's full collections."""
        if self.every_ticks > 0 and (ticks_run + self.every_ticks // 2) % self.every_ticks == 0:
            self.trim()

    def trim(self) -> None:
        """One malloc_trim(0) now (nothing without glibc)."""
        if self._trim is None:
            return
        t0 = time.perf_counter()
        self._trim(0)
        ms = (time.perf_counter() - t0) * 1e3
        self.trims += 1
        self.total_ms += ms
        self.max_ms = max(self.max_ms, ms)

    def summary(self) -> dict:
        return {"available": self.available, "every_ticks": self.every_ticks, "trims": self.trims,
                "max_ms": round(self.max_ms, 3), "mean_ms": round(self.total_ms / self.trims, 3) if self.trims else None}
