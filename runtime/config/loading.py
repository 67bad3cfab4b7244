"""Reading the controller configuration: the shipped defaults, a user's overlay, where each value
came from.

`load_controller_config(path)` reads the shipped `runtime/config/default.yaml` and lays the
user's file over it: a user's file sets only what it changes (a file with `planner: {mode:
all-fixed}` is a whole config). Mappings merge key by key; any other value replaces the default;
a mapping whose kind changes (`kind:` of a VLM backend, `interface:` of a CAN bus, `type:` of a
topic) replaces the default's mapping whole, so no field of the other kind is left over. The
merged document is then validated once (runtime.config.schema): a problem is one line naming the
file, the field and the reason.

`config_sources(path)` says for every value where it came from: the user's file, the shipped
file, a preset, a rule that derived it from another field, or the schema's built-in default.
`dct config show` prints it.
"""
from __future__ import annotations

import json
from importlib import resources
from pathlib import Path

from pydantic import ValidationError

from calibration.errors import ConfigFileError, format_validation_error, load_yaml_data
from runtime.config.schema import DERIVED, ControllerConfig

#: Keys that say which kind of thing a mapping describes: a change of kind replaces the mapping.
KIND_KEYS = ("kind", "interface", "type")

SHIPPED = "shipped default"
BUILT_IN = "built-in default"
PRESET = "preset"


def shipped_config_path() -> Path:
    return Path(str(resources.files("runtime") / "config" / "default.yaml"))


def overlay(base: dict, over: dict) -> dict:
    """`over` laid on `base` (module docstring); neither is modified."""
    out = dict(base)
    for key, value in over.items():
        old = out.get(key)
        if isinstance(old, dict) and isinstance(value, dict) and not _kind_changes(old, value):
            out[key] = overlay(old, value)
        else:
            out[key] = value
    return out


def _kind_changes(old: dict, new: dict) -> bool:
    return any(k in old and k in new and old[k] != new[k] for k in KIND_KEYS)


def _validate(raw: dict, where: str) -> ControllerConfig:
    try:
        return ControllerConfig.model_validate_json(json.dumps(raw, allow_nan=False), strict=True)
    except ValidationError as exc:
        raise ConfigFileError(f"controller config {where}: {format_validation_error(exc)}") from None


def _documents(path: str | Path | None) -> tuple[dict, dict | None, str]:
    shipped = load_yaml_data(shipped_config_path(), "controller config")
    if path is None or Path(str(path)).resolve() == shipped_config_path().resolve():
        return shipped, None, str(shipped_config_path())
    user = load_yaml_data(Path(str(path)), "controller config")
    return shipped, user, f"{path} (over the shipped defaults)"


def load_controller_config(path: str | Path | None = None) -> ControllerConfig:
    """The shipped defaults with the user's file at `path` laid over them (None: the defaults
    alone), validated; ConfigFileError (one line) on any problem."""
    shipped, user, where = _documents(path)
    return _validate(shipped if user is None else overlay(shipped, user), where)


def _leaves(doc, prefix: str = ""):
    """(dotted path, value) of every leaf of a JSON-like document; a mapping's leaves, a list is one leaf."""
    if isinstance(doc, dict) and doc:
        for key, value in doc.items():
            yield from _leaves(value, f"{prefix}.{key}" if prefix else str(key))
    else:
        yield prefix, doc


def _has(doc: dict | None, dotted: str) -> bool:
    node = doc
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            return False
        node = node[part]
    return True


def config_sources(path: str | Path | None = None,
                   overrides: dict[str, str] | None = None) -> tuple[ControllerConfig, list[tuple[str, object, str]]]:
    """The merged config and, for every value, (dotted field, value, where it came from).

    overrides: dotted field -> what set it after loading (a command-line option), for fields
    the caller changed on the returned config itself."""
    shipped, user, _ = _documents(path)
    config = load_controller_config(path)
    merged = shipped if user is None else overlay(shipped, user)
    preset_fields = {"planner.algorithm", "partition", "planner.mode"}
    rows = []
    for field, value in _leaves(config.model_dump(mode="json")):
        if overrides and field in overrides:
            source = overrides[field]
        elif user is not None and _has(user, field):
            source = str(path)
        elif _has(merged, field):  # (not the shipped one when the user's mapping replaced it)
            source = SHIPPED
        elif field in preset_fields and not _has(merged, field):
            source = f"{PRESET} {config.preset}" if field != "planner.mode" else "the pair's preset name"
        elif field in DERIVED and not _has(merged, field):
            source = f"derived from {DERIVED[field]}"
        else:
            source = BUILT_IN
        rows.append((field, value, source))
    return config, rows


def format_sources(rows: list[tuple[str, object, str]]) -> str:
    """One line per value: `field = value  # source`, aligned."""
    shown = [(field, json.dumps(value), source) for field, value, source in rows]
    width = min(max((len(f) + len(v) + 3 for f, v, _ in shown), default=0), 72)
    return "\n".join(f"{f + ' = ' + v:<{width}}  # {s}" for f, v, s in shown)
