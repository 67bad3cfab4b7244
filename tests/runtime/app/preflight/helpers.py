"""Helpers of the preflight tests: checks by name, the shipped files, YAML files."""
from __future__ import annotations

from importlib import resources
from pathlib import Path

import yaml

LIMO = Path(str(resources.files("calibration") / "robots" / "limo.yaml"))
SHIPPED_CONFIG = Path(str(resources.files("runtime") / "config" / "default.yaml"))


def by_name(checks):
    return {c.name: c for c in checks}


def write_yaml(path: Path, data) -> Path:
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path
