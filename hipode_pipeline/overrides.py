"""Settings from the command line: `--set KEY=VALUE` (repeatable) and `--config FILE.toml`,
checked against a config dataclass's fields and types before any work.

VALUE is read as a TOML value (`3e-4`, `true`, `"bf16"`, `[256, 256]`); a bare word that is no
TOML value is taken as a string. `--set` wins over the file, which wins over the defaults.
"""

from __future__ import annotations

import dataclasses
import tomllib
import types
import typing
from pathlib import Path
from typing import Any

from hipode_pipeline.errors import SettingError

KEY_CHARS = frozenset("abcdefghijklmnopqrstuvwxyz0123456789_")


def parse_value(text: str) -> Any:
    """A TOML value, or the text itself when it is none (a bare word like bf16)."""
    try:
        return tomllib.loads(f"value = {text}")["value"]
    except tomllib.TOMLDecodeError:
        return text


def read_overrides(sets: list[str] | None, config_file: Path | None) -> dict[str, Any]:
    """--config FILE's table, then each --set KEY=VALUE on top."""
    values: dict[str, Any] = {}
    if config_file is not None:
        try:
            with open(config_file, "rb") as f:
                values = tomllib.load(f)
        except OSError as error:
            raise SettingError(f"--config {config_file}: cannot read it ({error})") from None
        except tomllib.TOMLDecodeError as error:
            raise SettingError(f"--config {config_file}: expected TOML, found {error}") from None
        nested = sorted(key for key, value in values.items() if isinstance(value, dict))
        if nested:
            raise SettingError(
                f"--config {config_file}: expected flat KEY = VALUE lines, found tables {nested}"
            )
    for item in sets or []:
        key, equals, text = item.partition("=")
        key = key.strip()
        if not equals or not key or not set(key) <= KEY_CHARS:
            raise SettingError(f"--set: expected KEY=VALUE (e.g. actor_lr=1e-4), found {item!r}")
        values[key] = parse_value(text.strip())
    return values


def _accepts(annotation: Any, value: Any) -> bool:
    """Whether `value` fits a dataclass field's type (int for float, no bool for numbers)."""
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        return any(_accepts(arm, value) for arm in typing.get_args(annotation))
    if annotation is type(None):
        return value is None
    if annotation is bool:
        return isinstance(value, bool)
    if annotation is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if annotation is float:
        return isinstance(value, int | float) and not isinstance(value, bool)
    if annotation is str:
        return isinstance(value, str)
    if origin in (tuple, list):
        (inner, *_) = typing.get_args(annotation) or (Any,)
        return isinstance(value, list | tuple) and all(
            inner is Any or inner is Ellipsis or _accepts(inner, v) for v in value
        )
    return True  # a type these settings do not use: left to the dataclass's own checks


def _type_name(annotation: Any) -> str:
    """float, bool | None, tuple[int, ...]: a type as a person writes it."""
    if isinstance(annotation, type) and not typing.get_args(annotation):
        return annotation.__name__
    return str(annotation).replace("typing.", "").replace("NoneType", "None")


def check_fields(cls: type, values: dict[str, Any], origin: str) -> dict[str, Any]:
    """`values` if every key is a field of `cls` and every value fits its type; else a
    SettingError naming the key, the expected type and what was found."""
    hints = typing.get_type_hints(cls)
    known = {field.name for field in dataclasses.fields(cls)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise SettingError(
            f"{origin}: unknown setting(s) {unknown}; expected some of {sorted(known)}"
        )
    for key, value in values.items():
        if not _accepts(hints[key], value):
            expected = _type_name(hints[key])
            raise SettingError(f"{origin}: {key}: expected {expected}, found {value!r}")
    return values
