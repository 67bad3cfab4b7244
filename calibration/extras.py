"""Optional dependencies: which extra of the package installs a module, and the one-line error a
command gives when it needs one that is not installed.

A command that needs an optional extra (pyproject.toml `[project.optional-dependencies]`) says so
in one line naming the extra and the pip command, exit status 2, never a traceback or an
"internal error". Two ways there:

* `require(...)` before the work, where a command knows what it will need (find_spec: nothing is
  imported);
* `missing_extra(exc)` in the `dct` error handler (runtime.app.cli) and the lazy command groups
  (calibration.cli_support.LazyGroup): a ModuleNotFoundError of an optional module, raised
  anywhere in a command (or the cause of what was raised), becomes the same line.

It lives in calibration, the lowest package, beside cli_support, so that every package's command
line can use it. tests/calibration/test_extras.py checks OPTIONAL_MODULES against pyproject.toml.
"""
from __future__ import annotations

import importlib.util

from calibration.cli_support import OneLineError

#: Top-level module -> (the distribution in the extra that provides it, the extra). Only the extras
#: that commands use (the `test` extra is for the test suite).
OPTIONAL_MODULES: dict[str, tuple[str, str]] = {
    "cvxpy": ("cvxpy", "bench"),
    "clarabel": ("clarabel", "bench"),
    "ecos": ("ecos", "bench"),
    "rclpy": ("ros-jazzy-rclpy", "ros"),
    "std_msgs": ("ros-jazzy-std-msgs", "ros"),
    "sensor_msgs": ("ros-jazzy-sensor-msgs", "ros"),
    "nav_msgs": ("ros-jazzy-nav-msgs", "ros"),
    "geometry_msgs": ("ros-jazzy-geometry-msgs", "ros"),
    "diagnostic_msgs": ("ros-jazzy-diagnostic-msgs", "ros"),
    "visualization_msgs": ("ros-jazzy-visualization-msgs", "ros"),
    "evo": ("evo", "eval"),
    "rosbags": ("rosbags", "eval"),
    "ray": ("ray", "ray"),
}
#: Distributions of those extras that no command imports, and why.
NOT_IMPORTED: dict[str, str] = {
    "py-spy": "a profiler run as a program (docs/commands.md), never imported",
    "ros-jazzy-rmw-fastrtps-cpp": "the DDS layer rclpy loads as a shared library",
}


class MissingExtraError(OneLineError):
    """A command needs an optional dependency that is not installed: one line, exit status 2."""

    exit_code = 2


def install_hint(extra: str) -> str:
    return f"pip install -e '.[{extra}]' (in the checkout; or pip install 'dct-controller[{extra}]')"


def missing_extra_message(module: str, what: str | None = None) -> str:
    """The one line for a missing optional `module` (KeyError when it is not an optional one)."""
    _, extra = OPTIONAL_MODULES[module]
    if what:
        return f"{what} needs {module}, from the optional '{extra}' extra, which is not installed: {install_hint(extra)}"
    return f"{module} (from the optional '{extra}' extra) is not installed: {install_hint(extra)}"


def missing_extra(exc: BaseException | None) -> str | None:
    """The top-level optional module whose absence raised `exc` (a ModuleNotFoundError, or an error
    raised from one: its __cause__ / __context__ chain); None when it is anything else."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, ModuleNotFoundError) and exc.name:
            top = exc.name.partition(".")[0]
            if top in OPTIONAL_MODULES:
                return top
        exc = exc.__cause__ or exc.__context__
    return None


def is_installed(module: str) -> bool:
    """Whether `module` can be imported (found on the path; not imported here)."""
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):  # a parent package that does not import, or a broken entry
        return False


def require(*modules: str, what: str) -> None:
    """MissingExtraError (one line naming the extra) for the first of `modules` that is not installed."""
    for module in modules:
        if module not in OPTIONAL_MODULES:
            raise ValueError(f"require: {module!r} is not an optional module (OPTIONAL_MODULES)")
        if not is_installed(module):
            raise MissingExtraError(missing_extra_message(module, what))


__all__ = ["NOT_IMPORTED", "OPTIONAL_MODULES", "MissingExtraError", "install_hint", "is_installed", "missing_extra",
           "missing_extra_message", "require"]
