"""Where a figure came from: the command, the commit, the machine, when.

Every benchmark's `--json` carries it (`provenance`), so that a figure in docs/results/ says which
code on which machine produced it (`dct report results` writes the page from the JSON).
"""
from __future__ import annotations

import datetime as _dt
import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path

_SOURCE = Path(__file__).resolve().parents[2]  # the checkout this code runs from, when it is one


def provenance(argv: list[str] | None = None) -> dict:
    args = sys.argv[1:] if argv is None else argv
    return {
        "command": "dct " + shlex.join(args),
        "commit": _git_commit(),
        "machine": machine(),
        "python": platform.python_version(),
        "utc": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
    }


def machine() -> dict:
    """The CPU model, the cores this process may use, the memory, the kernel."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        mem_gib = round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1)
    except (ValueError, OSError, AttributeError):
        mem_gib = None
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"cpu": cpu, "cores": cores, "memory_gib": mem_gib, "kernel": platform.release()}


def _git_commit() -> str | None:
    """The source checkout's commit (with `-dirty` when it has uncommitted changes); None outside one."""
    pyproject = _SOURCE / "pyproject.toml"
    try:
        if not pyproject.is_file() or 'name = "dct-controller"' not in pyproject.read_text(encoding="utf-8"):
            return None  # an installed copy, not a checkout: no commit to name
        rev = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=_SOURCE, capture_output=True,
                             text=True, timeout=5)
        if rev.returncode != 0:
            return None
        dirty = subprocess.run(["git", "status", "--porcelain"], cwd=_SOURCE,
                               capture_output=True, text=True, timeout=5).stdout.strip()
        return rev.stdout.strip() + ("-dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return None


def with_provenance(doc: dict) -> dict:
    """`doc` with its `provenance` added (a benchmark's --json)."""
    return {**doc, "provenance": provenance()}
