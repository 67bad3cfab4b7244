"""Loading YAML files into pydantic models with errors that name the file, field and reason."""
from __future__ import annotations

from pathlib import Path
from typing import TypeVar

import yaml
from pydantic import BaseModel, ValidationError

M = TypeVar("M", bound=BaseModel)


class ConfigFileError(ValueError):
    """A configuration, description or calibration file is missing, unreadable or invalid."""


def format_validation_error(err: ValidationError) -> str:
    lines = []
    for e in err.errors():
        where = ".".join(str(p) for p in e["loc"]) or "(top level)"
        lines.append(f"  {where}: {e['msg']}")
    return "\n".join(lines)


def load_yaml_model(path: Path, model: type[M], what: str) -> M:
    """Read `path` as YAML and validate it as `model`; every failure is a ConfigFileError."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigFileError(f"{what} {path}: cannot read file: {exc.strerror or exc}") from exc
    try:
        raw = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigFileError(f"{what} {path}: not valid YAML: {exc}") from exc
    if not isinstance(raw, dict):
        raise ConfigFileError(f"{what} {path}: expected a mapping at the top level, got {type(raw).__name__}")
    try:
        return model.model_validate(raw)
    except ValidationError as exc:
        raise ConfigFileError(f"{what} {path} is invalid:\n{format_validation_error(exc)}") from exc
