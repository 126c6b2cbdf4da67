"""Typed configuration from TOML: every section a frozen dataclass, unknown keys and wrong types rejected
with the key's dotted path and what is allowed."""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

from genesis_rl.core.errors import UserInputError

T = TypeVar("T")


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp))


def _coerce(value: Any, tp: Any, key: str) -> Any:
    """Check ``value`` against the annotation ``tp`` (int, float, str, bool, tuple[str, ...], X | None)."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _coerce(value, inner[0], key)
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise UserInputError(f"{key} = {value!r} must be a list")
        (item,) = typing.get_args(tp)[:1]
        return tuple(_coerce(v, item, f"{key}[{i}]") for i, v in enumerate(value))
    if origin is dict or tp is dict:
        if not isinstance(value, Mapping):
            raise UserInputError(f"{key} = {value!r} must be a table")
        return dict(value)
    if tp is bool:
        if not isinstance(value, bool):
            raise UserInputError(f"{key} = {value!r} must be true or false")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise UserInputError(f"{key} = {value!r} must be an integer")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise UserInputError(f"{key} = {value!r} must be a number")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise UserInputError(f"{key} = {value!r} must be a string")
        return value
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):  # a class, never an instance, in an annotation
        return from_mapping(tp, value, key)
    return value


def from_mapping(cls: type[T], data: Mapping[str, Any] | None, section: str) -> T:
    """Build dataclass ``cls`` from a TOML table; errors name ``section.key``."""
    if data is not None and not isinstance(data, Mapping):
        raise UserInputError(f"[{section}] must be a table, got {data!r}")
    data = dict(data or {})
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(names))
    if unknown:
        raise UserInputError(f"unknown key(s) {', '.join(f'{section}.{k}' for k in unknown)}; "
                             f"allowed in [{section}]: {', '.join(names)}")
    kwargs = {k: _coerce(v, hints[k], f"{section}.{k}") for k, v in data.items()}
    try:
        return cls(**kwargs)
    except (ValueError, TypeError) as err:
        raise UserInputError(f"[{section}]: {err}") from None


def to_mapping(obj: Any) -> dict[str, Any]:
    """A dataclass as a TOML-ready dict (tuples as lists, None values dropped)."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            v = to_mapping(v)
        elif isinstance(v, tuple):
            v = list(v)
        if v is not None:
            out[f.name] = v
    return out


def read_toml(path: str | Path, what: str = "config", hint: str = "") -> dict[str, Any]:
    """A TOML file's tables; a folder, a missing file, bytes that are not UTF-8 and bad TOML are user errors
    that name ``what`` the file is (config, rulebook, ODD) and the file."""
    path = Path(path)
    if path.is_dir():
        raise UserInputError(f"{what} '{path}' is a folder; expected a TOML file")
    if not path.is_file():
        raise UserInputError(f"{what} file '{path}' does not exist{hint}")
    from genesis_rl.core.parsing import loads_toml, read_toml_text  # size and depth limits: a hostile file is one line

    return loads_toml(read_toml_text(path, what), f"{what} '{path}'")


def dump_toml(data: Mapping[str, Any]) -> str:
    """A minimal TOML writer for our configs (tables of scalars, lists and nested tables)."""

    def scalar(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, int | float):
            return repr(v)
        if isinstance(v, str):
            return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
        if isinstance(v, list | tuple):
            return "[" + ", ".join(scalar(x) for x in v) + "]"
        if isinstance(v, Mapping):
            return "{ " + ", ".join(f"{k} = {scalar(x)}" for k, x in v.items()) + " }"
        raise TypeError(f"cannot write {type(v)} to TOML")

    lines: list[str] = []

    def table(name: str, d: Mapping[str, Any]) -> None:
        lines.append(f"[{name}]")
        nested = []
        for k, v in d.items():
            flat_table = isinstance(v, Mapping) and v and all(not isinstance(x, Mapping) for x in v.values())
            if flat_table and k != "system_kwargs":
                nested.append((k, v))
            else:
                lines.append(f"{k} = {scalar(v)}")
        lines.append("")
        for k, v in nested:
            table(f"{name}.{k}", v)

    for name, d in data.items():
        table(name, d)
    return "\n".join(lines)
