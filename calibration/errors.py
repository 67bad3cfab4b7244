"""Loading YAML files into pydantic models with errors that name the file, field and reason.

`load_yaml_model` reads every configuration file of the project (robot description, controller
config, scenarios, calibration files). It is strict, and every failure is a `ConfigFileError`
whose message is ONE line::

    <what> <file>: <field.path>: <reason> (got <value>); <next field>: <reason> (got <value>)

Rules, in the order they are checked:

* the file must be readable UTF-8 text: a binary file (a NUL byte) or an invalid UTF-8 sequence
  is named with its byte offset; an empty file (or one with only comments) is an error;
* it must be valid YAML, with no key repeated in a mapping (PyYAML would silently keep the last
  one; here the key and both lines are named) and a mapping at the top level;
* every value must be one JSON can carry (mapping with text keys, list, text, number, bool,
  null) and every number must be finite: `.nan` / `.inf` are refused wherever they appear
  (``mass_kg: must be a finite number (got nan)``); `!!binary`, `!!set` and similar tags are
  refused naming the field;
* the data is validated in pydantic's *strict* JSON mode: `true` is not a number, `"1.0"` is
  not a number, `1` is not `true`; integers are accepted for floats and lists for tuples.

YAML dialect: PyYAML's safe schema with two changes that make it match what people write:
timestamps are left as text (a `datetime` field parses the ISO text itself, a text field keeps
it as written), and `1e-3` is a number (YAML 1.1 needs a dot: `1.0e-3`; YAML 1.2 does not).
"""
from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any, Iterator, TypeVar

import yaml
from pydantic import BaseModel, ValidationError

M = TypeVar("M", bound=BaseModel)

#: A value shown in an error is cut to this many characters.
MAX_SHOWN_VALUE_CHARS = 80


class ConfigFileError(ValueError):
    """A configuration, description or calibration file is missing, unreadable or invalid."""


class DuplicateKeyError(yaml.constructor.ConstructorError):
    """A key appears twice in one YAML mapping."""


# ---------------------------------------------------------------------------- the YAML loader
_FLOAT_TAG = "tag:yaml.org,2002:float"
_TIMESTAMP_TAG = "tag:yaml.org,2002:timestamp"
_MERGE_TAG = "tag:yaml.org,2002:merge"
# PyYAML's YAML 1.1 float pattern plus exponent-only numbers (1e-3, 2E5) as YAML 1.2 reads them.
_FLOAT_PATTERN = re.compile(
    r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
    |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
    |\.[0-9][0-9_]*(?:[eE][-+]?[0-9]+)?
    |[-+]?[0-9][0-9_]*(?::[0-5]?[0-9])+\.[0-9_]*
    |[-+]?\.(?:inf|Inf|INF)
    |\.(?:nan|NaN|NAN))$""",
    re.X,
)


def _strict_resolvers() -> dict:
    """SafeLoader's implicit resolvers without timestamps and with the YAML 1.2 float pattern."""
    out: dict = {}
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items():
        kept = [(tag, _FLOAT_PATTERN if tag == _FLOAT_TAG else rx) for tag, rx in resolvers if tag != _TIMESTAMP_TAG]
        if kept:
            out[first] = kept
    return out


class StrictSafeLoader(yaml.SafeLoader):
    """yaml.SafeLoader that refuses duplicate keys and keeps timestamps as text (see module doc)."""

    yaml_implicit_resolvers = _strict_resolvers()

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        first_seen: dict[Any, str] = {}
        for key_node, _ in node.value:
            if key_node.tag == _MERGE_TAG:  # `<<: *anchor`: explicit keys may override merged ones
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                seen = first_seen.get(key)
            except TypeError:  # unhashable key: SafeLoader reports it below
                continue
            mark = key_node.start_mark
            where = f"line {mark.line + 1}, column {mark.column + 1}"
            if seen is not None:
                raise DuplicateKeyError(None, None, f"duplicate key {key!r} at {where} (first at {seen})", mark)
            first_seen[key] = where
        return super().construct_mapping(node, deep=deep)


def parse_yaml_text(text: str) -> Any:
    """Parse YAML text with `StrictSafeLoader` (yaml.YAMLError on bad syntax or duplicate keys)."""
    return yaml.load(text, Loader=StrictSafeLoader)  # noqa: S506 - a SafeLoader subclass


# ---------------------------------------------------------------------------- one-line messages
def show_value(value: Any) -> str:
    """A value as it would read in the file (JSON-like), cut to MAX_SHOWN_VALUE_CHARS."""
    if isinstance(value, float) and not math.isfinite(value):
        text = "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    else:
        try:
            text = json.dumps(value, default=repr, ensure_ascii=False)
        except (TypeError, ValueError):
            text = repr(value)
    text = " ".join(text.split())  # one line
    if len(text) > MAX_SHOWN_VALUE_CHARS:
        text = text[: MAX_SHOWN_VALUE_CHARS - 3] + "..."
    return text


def _field_path(loc: tuple) -> str:
    return ".".join(str(p) for p in loc) or "(top level)"


def _reason(msg: str) -> str:
    for prefix in ("Value error, ", "Assertion failed, "):
        if msg.startswith(prefix):
            msg = msg[len(prefix):]
    return " ".join(msg.split())


def format_validation_error(err: ValidationError) -> str:
    """Every field error on one line: "field.path: reason (got value); ..."."""
    parts = []
    for e in err.errors():
        part = f"{_field_path(tuple(e['loc']))}: {_reason(e['msg'])}"
        value = e.get("input")
        # A missing field has no value; a whole-section (model) check names its numbers itself.
        if e.get("type") != "missing" and not isinstance(value, dict):
            part += f" (got {show_value(value)})"
        parts.append(part)
    return "; ".join(parts)


def _yaml_error_text(exc: yaml.YAMLError) -> str:
    """A PyYAML error as one line: the problem and its line/column."""
    problem = getattr(exc, "problem", None)
    mark = getattr(exc, "problem_mark", None)
    if problem is None:
        return " ".join(str(exc).split())
    text = problem
    context = getattr(exc, "context", None)
    if context and not isinstance(exc, DuplicateKeyError):
        text = f"{context}, {text}"
    if mark is not None and not isinstance(exc, DuplicateKeyError):
        text += f" at line {mark.line + 1}, column {mark.column + 1}"
    return " ".join(text.split())


# ---------------------------------------------------------------------------- JSON-representable
_JSON_SCALARS = (str, bool, int, type(None))


def json_problems(value: Any, loc: tuple = ()) -> Iterator[str]:
    """Yield "field.path: reason (got value)" for every value JSON cannot carry or that is not finite."""
    if isinstance(value, dict):
        for k, v in value.items():
            if not isinstance(k, str):
                yield f"{_field_path(loc)}: key {show_value(k)} must be text (quote it)"
                continue
            yield from json_problems(v, loc + (k,))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            yield from json_problems(v, loc + (i,))
    elif isinstance(value, float):
        if not math.isfinite(value):
            yield f"{_field_path(loc)}: must be a finite number (got {show_value(value)})"
    elif not isinstance(value, _JSON_SCALARS):
        yield (f"{_field_path(loc)}: a YAML {type(value).__name__} value is not supported here; "
               f"use text, a number, true/false, a list or a mapping (got {show_value(value)})")


# ---------------------------------------------------------------------------- the loader
def _read_text(path: Path, what: str) -> str:
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ConfigFileError(f"{what} {path}: cannot read file: {exc.strerror or exc}") from exc
    nul = data.find(b"\x00")
    if nul >= 0:
        raise ConfigFileError(f"{what} {path}: is a binary file, not YAML text (NUL byte at byte offset {nul})")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ConfigFileError(
            f"{what} {path}: is not UTF-8 text (byte 0x{data[exc.start]:02x} at byte offset {exc.start}: {exc.reason})"
        ) from None
    return text


def load_yaml_data(path: Path, what: str) -> dict:
    """Read `path` as strict YAML (see module doc) into a mapping of JSON-representable values."""
    path = Path(path)
    text = _read_text(path, what)
    try:
        raw = parse_yaml_text(text)
    except DuplicateKeyError as exc:
        raise ConfigFileError(f"{what} {path}: {_yaml_error_text(exc)}") from None
    except yaml.YAMLError as exc:
        raise ConfigFileError(f"{what} {path}: not valid YAML: {_yaml_error_text(exc)}") from None
    except RecursionError:
        raise ConfigFileError(f"{what} {path}: not valid YAML: nested too deeply") from None
    if raw is None:
        raise ConfigFileError(f"{what} {path}: the file is empty (expected a mapping of {what} fields)")
    if not isinstance(raw, dict):
        raise ConfigFileError(f"{what} {path}: expected a mapping at the top level, got {type(raw).__name__}")
    problems = list(json_problems(raw))
    if problems:
        raise ConfigFileError(f"{what} {path}: " + "; ".join(problems))
    return raw


def load_yaml_model(path: Path, model: type[M], what: str) -> M:
    """Read `path` as YAML and validate it as `model` in strict mode; every failure is a ConfigFileError.

    The message is one line naming the file, each bad field, the reason and the value given.
    """
    raw = load_yaml_data(path, what)
    try:
        return model.model_validate_json(json.dumps(raw, allow_nan=False), strict=True)
    except ValidationError as exc:
        raise ConfigFileError(f"{what} {path}: {format_validation_error(exc)}") from None


__all__ = ["ConfigFileError", "DuplicateKeyError", "StrictSafeLoader", "format_validation_error",
           "json_problems", "load_yaml_data", "load_yaml_model", "parse_yaml_text", "show_value"]
