"""The JSON codec every config class shares: `to_dict` / `from_dict`, `to_json` /
`from_json` and `with_edits`, strict about keys and types.

A config serialises to plain JSON (tuples become lists). `from_dict` refuses unknown
keys and values of the wrong type with a `ValueError` that names the field and the type
it wants (`_describe`, `_example`); missing keys take their defaults. The field types
come from the dataclasses' own annotations (`typing.get_type_hints`), so this module
knows no config class by name.
"""

from __future__ import annotations

import dataclasses
import json
import math
import numbers
import types
import typing
from typing import Any


class _ConfigMixin:
    """`to_dict` / `from_dict` / JSON and nested edits, shared by every config class."""

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict of JSON types (tuples become lists)."""
        out = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            out[f.name] = value.to_dict() if isinstance(value, _ConfigMixin) else _to_json(value)
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]):
        """Inverse of `to_dict`; strict about keys and types.

        Missing keys take their defaults; unknown keys raise `ValueError`.
        """
        if not isinstance(data, dict):
            raise ValueError(f"{cls.__name__}: expected a dict, got {type(data).__name__}")
        hints = typing.get_type_hints(cls)
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(
                f"{cls.__name__}: unknown key(s) {unknown}; known keys are {sorted(names)}"
            )
        kwargs = {}
        for name, value in data.items():
            kwargs[name] = _from_json(value, hints[name], f"{cls.__name__}.{name}")
        return cls(**kwargs)

    def to_json(self, **kwargs) -> str:
        return json.dumps(self.to_dict(), **kwargs)

    @classmethod
    def from_json(cls, text: str):
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{cls.__name__}: invalid JSON ({exc})") from exc
        return cls.from_dict(data)

    def with_edits(self, edits: dict[str, Any], *, path: str = ""):
        """`dataclasses.replace` with nested dicts for nested configs; strict keys and types.

        Every value goes through the same conversion and type check as `from_dict`
        (lists and tuples become tuples, integers are accepted for floats, NumPy scalars
        become Python numbers), so a wrong-typed edit (e.g. the string `"(0.1,0.2)"` for
        a tuple of floats, which is what `--set noise.edge_levels=(0.1,0.2)` gives) fails
        here with a `ValueError` naming the field and the type it wants, not later inside
        some validation or trace.

        Example: `cfg.with_edits({"model": {"variant": "fgt3"}, "train": {"steps": 10}})`.

        Args:
          edits: `{field: value}`, a nested dict for a nested config.
          path: dotted prefix naming this config in error messages (set by the nesting).
        """
        names = {f.name for f in dataclasses.fields(self)}
        unknown = sorted(set(edits) - names)
        if unknown:
            raise ValueError(f"{type(self).__name__}: unknown field(s) {unknown} in edits")
        hints = typing.get_type_hints(type(self))
        updates = {}
        for name, value in edits.items():
            where = f"{path}.{name}" if path else f"{type(self).__name__}.{name}"
            current = getattr(self, name)
            if isinstance(current, _ConfigMixin) and isinstance(value, dict):
                updates[name] = current.with_edits(value, path=f"{path}.{name}" if path else name)
            elif isinstance(current, _ConfigMixin) and isinstance(value, type(current)):
                updates[name] = value
            else:
                updates[name] = _from_json(_to_json(_plain(value)), hints[name], where)
        return dataclasses.replace(self, **updates)


def _plain(value: Any) -> Any:
    """NumPy scalars (anywhere in nested lists/tuples) as Python numbers; else unchanged."""
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    if isinstance(value, bool | str) or value is None:
        return value
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        return float(value)
    return value


def _describe(hint: Any) -> str:
    """What a field of type `hint` takes, in words (for error messages)."""
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        options = [_describe(a) for a in args if a is not type(None)]
        text = " or ".join(options)
        return f"{text} or null" if type(None) in args else text
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            item = _describe(args[0])
            if item.startswith("a list"):
                return f"a list of lists{item[len('a list') :]}"
            return f"a list of {_PLURAL.get(item, item)}"
        return f"a list of {len(args)} items ({', '.join(_describe(a) for a in args)})"
    return _SINGULAR.get(hint, str(hint))


def _example(hint: Any) -> str:
    """A JSON value of type `hint` (for error messages: what `--set` wants)."""
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        return _example(next(a for a in args if a is not type(None)))
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            pair = {int: "[1, 2]", float: "[0.1, 0.2]", str: '["a", "b"]'}
            return pair.get(args[0], f"[{_example(args[0])}]")
        return f"[{', '.join(_example(a) for a in args)}]"
    return {bool: "true", int: "2", float: "0.1", str: '"a"'}.get(hint, "...")


_SINGULAR = {bool: "true/false", int: "an integer", float: "a number", str: "a string"}
_PLURAL = {"an integer": "integers", "a number": "numbers", "a string": "strings"}


def _to_json(value: Any) -> Any:
    if isinstance(value, tuple | list):
        return [_to_json(v) for v in value]
    return value


def _from_json(value: Any, hint: Any, where: str) -> Any:
    """Converts a JSON value to the annotated type (lists → tuples), checking the type."""
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if isinstance(hint, type) and issubclass(hint, _ConfigMixin):
        return hint.from_dict(value)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        options = [arg for arg in args if arg is not type(None)]
        if len(options) == 1:
            return _from_json(value, options[0], where)
        for arg in options:
            try:
                return _from_json(value, arg, where)
            except ValueError:
                continue
        raise ValueError(f"{where}: expected {_describe(hint)}, got {value!r}")
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise ValueError(
                f"{where}: expected {_describe(hint)}, e.g. {_example(hint)}, got {value!r}"
            )
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_from_json(v, args[0], where) for v in value)
        if len(args) != len(value):
            raise ValueError(f"{where}: expected {len(args)} items, got {len(value)}")
        return tuple(_from_json(v, a, where) for v, a in zip(value, args, strict=True))
    if hint is bool:
        if not isinstance(value, bool):
            raise ValueError(f"{where}: expected true/false, got {value!r}")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{where}: expected an integer, got {value!r}")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f"{where}: expected a number, got {value!r}")
        try:
            number = float(value)
        except OverflowError:  # an integer of hundreds of digits
            number = math.inf
        # No config field means anything by inf or NaN (JSON has neither, Python's json
        # module reads both): refusing them here covers every float of every section.
        if not math.isfinite(number):
            raise ValueError(f"{where}: expected a finite number, got {value!r}")
        return number
    if hint is str:
        if not isinstance(value, str):
            raise ValueError(f"{where}: expected a string, got {value!r}")
        return value
    raise ValueError(f"{where}: unsupported type {hint}")
