"""Giving the C heap's free pages back between ticks (runtime.loop.heap): freed memory stuck in
the middle of glibc's heap leaves the resident size after a trim; the loop trims between ticks
at its rate, never inside a tick, and not at all when asked not to."""
from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from runtime.loop.fixed_rate import FixedRateLoop
from runtime.loop.heap import HeapTrimmer
from runtime.loop.telemetry import STAGES
from tests.runtime.loop.test_fixed_rate import FakeClock, FakeControlled

glibc = pytest.mark.skipif(not HeapTrimmer().available, reason="malloc_trim is glibc's")


@glibc
def test_freed_memory_in_the_middle_of_the_heap_leaves_the_resident_size_after_a_trim():
    # In a process of its own: 64 MB of 64-kB blocks (below malloc's mmap threshold: in the heap),
    # each followed by a small block that stays, so that the freed ones are holes malloc cannot
    # give back by shrinking the heap's top.
    code = textwrap.dedent("""
        import json
        from runtime.loop.heap import HeapTrimmer
        def rss_mb():
            return int(open("/proc/self/status").read().split("VmRSS:")[1].split()[0]) / 1024
        blocks, pins = [], []
        for _ in range(1024):
            blocks.append(bytearray(65536))
            pins.append(bytearray(600))
        del blocks
        before = rss_mb()
        trimmer = HeapTrimmer(every_ticks=1)
        trimmer.between_ticks(1)
        print(json.dumps({"before": before, "after": rss_mb(), "trims": trimmer.trims, "pins": len(pins)}))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    got = __import__("json").loads(out.stdout)
    assert got["trims"] == 1
    assert got["before"] - got["after"] >= 40.0, got  # most of the 64 MB back to the system


def test_the_loop_trims_between_ticks_at_its_rate_and_never_when_told_not_to():
    for every, expected in ((4, 3), (0, 0)):  # 12 ticks: after ticks 2, 6 and 10 (half-way between collections)
        clock = FakeClock()
        loop = FixedRateLoop(clock, period_s=0.05, stage_budgets_s={s: 0.05 for s in STAGES},
                             command_deadline_s=0.04, keepalive_period_s=None, trim_every_ticks=every)
        loop.run(FakeControlled(clock, lambda k: 0.001), lambda: False, max_ticks=12)
        assert loop.heap.trims == (expected if loop.heap.available else 0)
        assert loop.heap.summary()["trims"] == loop.heap.trims


_ARENAS = """
import ctypes, sys, threading
from runtime.loop.heap import limit_arenas
if sys.argv[1] != "none":
    assert limit_arenas(int(sys.argv[1]))
def work():
    for _ in range(20000):
        b = [bytearray(600) for _ in range(20)]
        del b
ts = [threading.Thread(target=work) for _ in range(8)]
[t.start() for t in ts]; [t.join() for t in ts]
ctypes.CDLL("libc.so.6").malloc_stats()
"""


@glibc
def test_the_arena_limit_holds_while_threads_allocate_at_once():
    """Eight threads allocating at once: glibc gives them arenas of their own unless limited."""

    def arenas(limit: str) -> int:
        r = subprocess.run([sys.executable, "-c", _ARENAS, limit], capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        return sum(line.startswith("Arena ") for line in r.stderr.splitlines())

    assert arenas("none") > 2  # the test can tell: unlimited, the threads spread over arenas
    assert arenas("2") <= 2
    assert arenas("1") == 1
