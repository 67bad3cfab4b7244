"""The result of one preflight check (`Check`: PASS / WARN / FAIL, the message, the fix) and the
small helpers every check uses."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

Status = Literal["PASS", "WARN", "FAIL"]


@dataclass(frozen=True)
class Check:
    """One preflight result. `fix` says how to make it PASS (shown unless it passed)."""

    name: str
    status: Status
    message: str
    fix: str | None = None

    @property
    def ok(self) -> bool:
        return self.status != "FAIL"

    def text(self) -> str:
        """The message and, unless it passed, the fix."""
        return self.message if self.status == "PASS" or not self.fix else f"{self.message}; fix: {self.fix}"

    def line(self) -> str:
        return f"{self.status:<4}  {self.name:<16} {self.text()}"

    def as_json(self) -> dict[str, Any]:
        return {"name": self.name, "ok": self.ok, "status": self.status, "message": self.text()}


def one_line(exc: BaseException) -> str:
    """An exception's message on one line (its type name when it has none)."""
    return " ".join(str(exc).split()) or type(exc).__name__


def read_text(path: Path) -> str | None:
    """The stripped text of a small file (/sys, /proc), None when it cannot be read."""
    try:
        return path.read_text().strip()
    except OSError:
        return None
