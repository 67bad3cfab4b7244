"""Preflight's checks of this computer: `clock_sync`, `cpus`, `cpu_governor`, `sched_fifo`,
`cpu_affinity` and `disk`."""
from __future__ import annotations

import glob
import os
import shutil
import subprocess
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from runtime.app.preflight.check import Check, one_line, read_text

#: Free disk below this FAILs (the recorder drops records on a full disk, but a drive without
#: its log cannot be analysed); below WARN_DISK_FACTOR x this WARNs.
DEFAULT_MIN_FREE_GB = 1.0
WARN_DISK_FACTOR = 4.0


def _run_text(argv: Sequence[str]) -> str | None:
    if shutil.which(argv[0]) is None:
        return None
    try:
        done = subprocess.run(list(argv), capture_output=True, text=True, timeout=5)
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout if done.returncode == 0 else None


def check_clock_sync(run_text: Callable[[Sequence[str]], str | None] = _run_text) -> Check:
    """NTP sync from timedatectl or chrony; WARN when it is off or cannot be told."""
    fix = "enable time sync: sudo timedatectl set-ntp true (or install chrony)"
    out = run_text(["timedatectl", "show", "-p", "NTPSynchronized", "--value"])
    if out is not None and out.strip() in ("yes", "no"):
        if out.strip() == "yes":
            return Check("clock_sync", "PASS", "timedatectl: NTP synchronized")
        chrony = run_text(["chronyc", "tracking"])
        if chrony is None:
            return Check("clock_sync", "WARN", "timedatectl: clock not synchronized (recorded times may drift "
                         "from other computers' logs)", fix)
    chrony = run_text(["chronyc", "tracking"])
    if chrony is not None:
        leap = next((ln.split(":", 1)[1].strip() for ln in chrony.splitlines() if ln.startswith("Leap status")), None)
        if leap == "Normal":
            return Check("clock_sync", "PASS", "chrony: synchronized (leap status Normal)")
        return Check("clock_sync", "WARN", f"chrony: not synchronized (leap status {leap})", fix)
    return Check("clock_sync", "WARN", "clock sync unknown: neither timedatectl nor chronyc answered", fix)


def check_cpus(realtime: Any, *, getaffinity: Callable[[int], set[int]] | None = None,
               sys_root: str | Path = "/") -> list[Check]:
    """`cpus` (at least 2 usable, realtime.cpus among them) and `cpu_governor`."""
    getaffinity = getaffinity or os.sched_getaffinity
    usable = sorted(getaffinity(0))
    wanted = list(realtime.cpus) if realtime is not None and realtime.cpus else []
    checks = []
    missing = sorted(set(wanted) - set(usable))
    if len(usable) < 2:
        checks.append(Check("cpus", "FAIL", f"{len(usable)} usable CPU ({usable}); the loop is sized for 2 cores",
                            "run on a computer (or cgroup/cpuset) with at least 2 CPUs"))
    elif missing:
        checks.append(Check("cpus", "FAIL", f"realtime.cpus {wanted} names CPUs {missing} this process cannot use "
                            f"(usable: {usable})", "list only usable CPUs in realtime.cpus (config)"))
    else:
        checks.append(Check("cpus", "PASS", f"{len(usable)} usable CPUs {usable}"
                            + (f"; the loop will be pinned to {wanted}" if wanted else "")))
    root = Path(sys_root) / "sys" / "devices" / "system" / "cpu"
    governors = {}
    for path in sorted(glob.glob(str(root / "cpu[0-9]*" / "cpufreq" / "scaling_governor"))):
        cpu = Path(path).parent.parent.name
        governors[cpu] = read_text(Path(path)) or "?"
    fix = "sudo cpupower frequency-set -g performance (or the BIOS power profile)"
    if not governors:
        checks.append(Check("cpu_governor", "WARN", "no cpufreq governor (a VM, or frequency scaling off): "
                            "cannot tell whether the CPU clocks down", "check the BIOS power profile"))
    else:
        slow = {c: g for c, g in governors.items() if g != "performance"}
        if slow:
            shown = ", ".join(f"{c}={g}" for c, g in list(slow.items())[:4]) + (" ..." if len(slow) > 4 else "")
            checks.append(Check("cpu_governor", "WARN", f"governor not 'performance' on {len(slow)} of "
                                f"{len(governors)} CPUs ({shown}): ticks may run slower after idle", fix))
        else:
            checks.append(Check("cpu_governor", "PASS", f"'performance' on all {len(governors)} CPUs"))
    return checks


def check_realtime(realtime: Any, *, request: Callable[..., Any] | None = None) -> list[Check]:
    """`sched_fifo` and `cpu_affinity`: ask for them on a throwaway thread, as the loop will."""
    from runtime.loop.realtime_setup import RealtimeConfig, request_realtime, rtprio_limit

    realtime = realtime or RealtimeConfig()
    request = request or request_realtime
    result = []
    cpus = realtime.cpus or tuple(sorted(os.sched_getaffinity(0)))

    def run() -> None:
        result.append(request(realtime.fifo_priority, cpus, fifo=True))

    t = threading.Thread(target=run, name="preflight-realtime")
    t.start()
    t.join()
    grant = result[0]
    checks = []
    if grant.fifo_granted:
        note = "" if realtime.fifo else " (but realtime.fifo is off in the config: the loop stays SCHED_OTHER)"
        checks.append(Check("sched_fifo", "PASS", f"SCHED_FIFO priority {realtime.fifo_priority} allowed{note}"))
    else:
        limit = rtprio_limit()
        checks.append(Check("sched_fifo", "WARN", f"SCHED_FIFO priority {realtime.fifo_priority} refused "
                            f"({(grant.fifo_reason or '').split('; fix:')[0]}): the loop will run SCHED_OTHER "
                            "(normal priority; lateness and deadline misses are counted as always)",
                            f"LimitRTPRIO={realtime.fifo_priority} in the unit (RLIMIT_RTPRIO now "
                            f"{'unlimited' if limit is None else limit}) or run as root"))
    if grant.affinity_granted:
        what = f"the loop will be pinned to CPUs {list(realtime.cpus)}" if realtime.cpus else \
            "allowed; not requested (realtime.cpus is null: the loop is not pinned)"
        checks.append(Check("cpu_affinity", "PASS", what))
    else:
        checks.append(Check("cpu_affinity", "WARN", f"pinning to CPUs {list(cpus)} refused "
                            f"({(grant.affinity_reason or '').split('; fix:')[0]}): the loop will not be pinned",
                            "list usable CPUs in realtime.cpus; check the cpuset of the service"))
    return checks


def check_disk(log_dir: str | Path, min_free_gb: float = DEFAULT_MIN_FREE_GB,
               disk_usage: Callable[[str], Any] = shutil.disk_usage) -> Check:
    d = Path(log_dir)
    probe = d
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    try:
        free = disk_usage(str(probe)).free
    except OSError as exc:
        return Check("disk", "FAIL", f"cannot read free space of {d}: {one_line(exc)}", "pass an existing --log-dir")
    gb = free / 1e9
    msg = f"{gb:.1f} GB free for logs in {d}"
    if gb < min_free_gb:
        return Check("disk", "FAIL", msg + f" (need {min_free_gb:g} GB)", f"free space in {d} or pass --log-dir")
    if gb < WARN_DISK_FACTOR * min_free_gb:
        return Check("disk", "WARN", msg + f" (less than {WARN_DISK_FACTOR * min_free_gb:g} GB: a long MCAP "
                     "recording may fill it; the recorder then drops records)", f"free space in {d}")
    return Check("disk", "PASS", msg)
