"""Writing output files so that nothing is lost or overwritten.

Rules every command follows (docs/commands.md):

* Check the output path *before* the long work starts (`check_output_path`): its folder must
  exist and be writable, it must not be a folder, and it must not be a shipped artifact (a file
  inside one of our installed packages: the LIMO description, the distance net, the default
  config, the scenario library) or one of the command's own inputs.
* Write *after* the command succeeded, atomically (`atomic_write_*`): a temporary file in the
  same folder, flushed and fsync'ed, then `os.replace` onto the name. A crash or a full disk
  leaves either the old file or the new one, never half of one.

Lives in `calibration` because it is the lowest package every other one may import (runtime,
models and hil_sim all load their YAML through `calibration.errors`).
"""
from __future__ import annotations

import contextlib
import importlib.util
import json
import os
import tempfile
from pathlib import Path
from typing import Any, BinaryIO, Iterable, Iterator

#: Our packages; a file inside one of them is a shipped artifact.
PACKAGES = ("firmware_bridge", "runtime", "models", "calibration", "hil_sim")


class OutputPathError(ValueError):
    """An output path that cannot or must not be written; the message names it and why."""


def shipped_roots() -> list[Path]:
    """The folders of our installed packages (found without importing them)."""
    roots = []
    for name in PACKAGES:
        spec = importlib.util.find_spec(name)
        if spec is not None and spec.submodule_search_locations:
            roots.extend(Path(p).resolve() for p in spec.submodule_search_locations)
    return roots


def is_shipped_artifact(path: str | Path) -> bool:
    """True when `path` lies inside one of our packages (a shipped file, or where one would go)."""
    p = Path(path).resolve()
    return any(p == r or r in p.parents for r in shipped_roots())


def check_output_path(
    path: str | Path,
    *,
    what: str = "output",
    inputs: Iterable[str | Path] = (),
    overwrite: bool = True,
    allow_shipped: bool = False,
) -> Path:
    """Validate an output path before the work that produces it; returns it as a Path.

    inputs: the command's input files; the output may not be one of them.
    overwrite: False refuses an existing file (the caller offers --force).
    allow_shipped: True only for commands whose job is to replace a shipped artifact, and
    only when the user asked for it explicitly.
    """
    p = Path(path)
    if str(path) == "" or p.name in ("", ".", ".."):
        raise OutputPathError(f"{what} path {str(path)!r} is not a file name")
    if p.is_dir():
        raise OutputPathError(f"{what} {p} is a folder; give a file name")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise OutputPathError(f"{what} {p}: folder {parent} does not exist (create it first)")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputPathError(f"{what} {p}: folder {parent} is not writable")
    if p.exists() and not os.access(p, os.W_OK) and not os.access(parent, os.W_OK):
        raise OutputPathError(f"{what} {p} exists and is not writable")
    resolved = p.resolve()
    for src in inputs:
        if src is not None and Path(src).resolve() == resolved:
            raise OutputPathError(f"{what} {p} is also an input of this command; write to another file")
    if not allow_shipped and is_shipped_artifact(resolved):
        raise OutputPathError(
            f"{what} {p} is inside the installed package (a shipped artifact); write somewhere else"
        )
    if not overwrite and p.exists():
        raise OutputPathError(f"{what} {p} already exists; choose another name or pass --force")
    return p


@contextlib.contextmanager
def atomic_file(path: str | Path) -> Iterator[BinaryIO]:
    """A binary file that becomes `path` only when the block ends without an error (temporary
    file in the same folder, fsync, rename); on an error the temporary file is removed and
    `path` is untouched. For outputs written as a stream (a tar archive)."""
    p = Path(path)
    parent = p.parent if str(p.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=parent)
    try:
        with os.fdopen(fd, "wb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        # mkstemp creates 0600; give the file the permissions a plain open() would.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, p)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write `data` to `path` atomically (atomic_file)."""
    with atomic_file(path) as f:
        f.write(data)
    return Path(path)


def atomic_write_text(path: str | Path, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | Path, obj: Any) -> Path:
    """JSON with 2-space indent and a final newline; NaN/inf are refused (not valid JSON)."""
    return atomic_write_text(path, json.dumps(obj, indent=2, allow_nan=False) + "\n")


__all__ = [
    "OutputPathError",
    "check_output_path",
    "atomic_write_bytes",
    "atomic_write_text",
    "atomic_write_json",
    "is_shipped_artifact",
    "shipped_roots",
]
