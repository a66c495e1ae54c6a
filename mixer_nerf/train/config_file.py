"""Training settings read from a file for ``train --config``: a run's own ``config.json`` or a
JSON/TOML table of TrainConfig fields, each value checked against the field's type."""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from pathlib import Path
from typing import Any

from .config import TrainConfig


class ConfigFileError(ValueError):
    """A config file is missing, unparsable or holds settings TrainConfig does not have."""


def read_config_file(path: str | Path) -> dict[str, Any]:
    """TrainConfig settings from ``path`` (``.json`` or ``.toml``).

    A run folder's ``config.json`` (``{"train": {...}, "model": {...}}``) gives its ``train``
    table; any other file is the table itself. Values are converted to the field types (a JSON
    list to a tuple, an int to a float); the result may name only some fields.

    Raises:
        ConfigFileError: naming ``path``, before anything is trained.
    """
    path = Path(path)
    table = _parse(path)
    if isinstance(table.get("train"), dict) and "model" in table:
        table = table["train"]
    hints = typing.get_type_hints(TrainConfig)
    names = [f.name for f in dataclasses.fields(TrainConfig)]
    unknown = sorted(set(table) - set(names))
    if unknown:
        raise ConfigFileError(f"{path}: unknown training settings {unknown}")
    return {name: _convert(path, name, table[name], hints[name]) for name in names if name in table}


def value_type(hint: Any) -> Any:
    """The type of a field's values: ``int`` for ``int | None``, the hint itself otherwise."""
    if isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union:
        (kind,) = (arg for arg in typing.get_args(hint) if arg is not type(None))
        return kind
    return hint


def _parse(path: Path) -> dict[str, Any]:
    if path.suffix not in (".json", ".toml"):
        raise ConfigFileError(f"{path}: a config file must be .json or .toml")
    try:
        text = path.read_text()
    except OSError as e:
        raise ConfigFileError(f"{path}: cannot read the config file: {e.strerror}") from e
    try:
        if path.suffix == ".json":
            table = json.loads(text)
        else:
            import tomllib  # Python 3.11+

            table = tomllib.loads(text)
    except ImportError as e:
        raise ConfigFileError(f"{path}: TOML config files need Python 3.11 or newer (tomllib)") from e
    except ValueError as e:  # JSONDecodeError and TOMLDecodeError are ValueErrors
        raise ConfigFileError(f"{path}: not valid {path.suffix[1:].upper()}: {e}") from e
    if not isinstance(table, dict):
        raise ConfigFileError(f"{path}: expected a table of settings, got {type(table).__name__}")
    return table


def _convert(path: Path, name: str, value: Any, hint: Any) -> Any:
    kind = value_type(hint)
    optional = kind is not hint
    origin = typing.get_origin(kind) or kind
    if value is None and optional:
        return None
    if origin is tuple and isinstance(value, (list, tuple)):
        (item,) = {a for a in typing.get_args(kind) if a is not Ellipsis}
        return tuple(_convert(path, name, v, item) for v in value)
    is_bool = isinstance(value, bool)
    if (origin is float and isinstance(value, (int, float)) and not is_bool) or (
        origin is int and isinstance(value, int) and not is_bool
    ):
        return origin(value)
    if origin in (str, bool, dict) and isinstance(value, origin):
        return value
    expected = getattr(kind, "__name__", str(kind))
    raise ConfigFileError(f"{path}: {name} must be {expected}, got {value!r}")
