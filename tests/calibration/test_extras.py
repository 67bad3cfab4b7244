"""calibration.extras: the optional-module table against pyproject.toml, the cause chain, require()."""
from __future__ import annotations

import sys
import tomllib
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

from calibration.extras import (NOT_IMPORTED, OPTIONAL_MODULES, MissingExtraError, missing_extra,
                                missing_extra_message, require)

PYPROJECT = Path(__file__).resolve().parents[2] / "pyproject.toml"


def _extras() -> dict[str, set[str]]:
    extras = tomllib.loads(PYPROJECT.read_text())["project"]["optional-dependencies"]
    return {name: {canonicalize_name(Requirement(r).name) for r in reqs} for name, reqs in extras.items()}


def test_every_module_comes_from_the_extra_the_table_names():
    extras = _extras()
    for module, (dist, extra) in OPTIONAL_MODULES.items():
        assert canonicalize_name(dist) in extras[extra], (module, dist, extra)


def test_every_distribution_of_the_command_extras_is_covered():
    covered = {canonicalize_name(d) for d, _ in OPTIONAL_MODULES.values()} | set(NOT_IMPORTED)
    used = {extra for _, extra in OPTIONAL_MODULES.values()}
    assert used == set(_extras()) - {"test"}  # every extra but the test suite's
    for extra in used:
        missing = _extras()[extra] - covered
        assert not missing, f"extra {extra}: add {sorted(missing)} to OPTIONAL_MODULES or NOT_IMPORTED"


def _raised_from(inner: BaseException, outer: BaseException) -> BaseException:
    try:
        try:
            raise inner
        except BaseException as exc:
            raise outer from exc
    except BaseException as exc:
        return exc


def test_missing_extra_follows_the_cause_chain():
    assert missing_extra(ModuleNotFoundError("No module named 'cvxpy'", name="cvxpy")) == "cvxpy"
    assert missing_extra(ModuleNotFoundError("x", name="evo.core.metrics")) == "evo"
    wrapped = _raised_from(ModuleNotFoundError("x", name="rosbags.highlevel"), RuntimeError("reading failed"))
    assert missing_extra(wrapped) == "rosbags"
    # Not an optional module, not a missing module, nothing at all.
    assert missing_extra(ModuleNotFoundError("x", name="numpy")) is None
    assert missing_extra(ImportError("cannot import name 'x' from 'cvxpy'", name="cvxpy")) is None
    assert missing_extra(RuntimeError("cvxpy")) is None
    assert missing_extra(None) is None


def test_the_message_names_the_extra_and_the_pip_command():
    line = missing_extra_message("cvxpy", "dct bench planner")
    assert line.startswith("dct bench planner needs cvxpy, from the optional 'bench' extra")
    assert "pip install -e '.[bench]'" in line and "\n" not in line
    assert "'ros' extra" in missing_extra_message("rclpy")


def test_require_finds_a_missing_module_without_importing_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "ecos", None)  # as if not installed
    with pytest.raises(MissingExtraError, match=r"x needs ecos, from the optional 'bench' extra") as info:
        require("cvxpy", "ecos", what="x")
    assert info.value.exit_code == 2
    require("cvxpy", what="x")  # installed here (the bench extra is in the test environment)
    with pytest.raises(ValueError, match="not an optional module"):
        require("numpy", what="x")
