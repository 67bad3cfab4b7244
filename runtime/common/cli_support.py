"""What the `dct` command groups of runtime share: one-line errors, output checks, a progress bar.

Rules (as in `dct calibrate`): an input error is ONE line on stderr and exit status 2, nothing
is written; an output path is checked before the work, an existing file is refused unless
--force, and outputs are written atomically after the work succeeded.
"""
from __future__ import annotations

import sys
from importlib.metadata import entry_points
from pathlib import Path

import click

from calibration.cli_support import OneLineError


class InputError(OneLineError):
    """Bad input (file, option): one line on stderr, exit status 2."""

    exit_code = 2


def checked_output(path: Path | None, what: str, inputs, force: bool) -> None:
    """Refuse (InputError) an output path that exists (unless force), is an input, or cannot be written."""
    from calibration.outputs import OutputPathError, check_output_path

    if path is None:
        return
    try:
        check_output_path(path, what=what, inputs=[p for p in inputs if p is not None], overwrite=force)
    except OutputPathError as exc:
        raise InputError(str(exc)) from None


class ProgressBar:
    """A click progress bar on stderr, created on the first report (its length is known then).

    Called as progress(done, total): frames (integers) or simulated seconds (floats, shown in
    thousandths of the total)."""

    def __init__(self, label: str):
        self.label = label
        self.bar = None
        self.scale = 1.0
        self.shown = 0

    def __call__(self, done: float, total: float) -> None:
        if self.bar is None:
            self.scale = 1.0 if float(total).is_integer() else 1000.0 / max(float(total), 1e-9)
            length = max(1, round(float(total) * self.scale))
            self.bar = click.progressbar(length=length, label=self.label, file=sys.stderr)
            self.bar.__enter__()
        target = min(round(float(done) * self.scale), self.bar.length)
        if target > self.shown:
            self.bar.update(target - self.shown)
            self.shown = target

    def close(self) -> None:
        if self.bar is not None:
            self.bar.__exit__(None, None, None)


def scenario_evaluator(group: str, name: str, command: str):
    """The simulator's evaluation function behind `command --scenario` (runtime must not import
    hil_sim: it is found through the entry point `name` of `group` and loaded only when asked for);
    a one-line error when it is not installed or does not load."""
    eps = [ep for ep in entry_points(group=group) if ep.name == name]
    if not eps:
        raise OneLineError(f"{command} --scenario: no scenario evaluation is installed (entry point "
                           f"'{name}' in group '{group}'; the simulator package hil_sim provides it)")
    try:
        return eps[0].load()
    except (ImportError, AttributeError) as exc:
        raise OneLineError(f"{command} --scenario: the scenario evaluation ({eps[0].value}) cannot be "
                           f"loaded: {exc}") from None


__all__ = ["InputError", "ProgressBar", "checked_output", "scenario_evaluator"]
