"""Options dataclasses to and from JSON: the service stores a job's options with the job.

Every stage's options are a frozen dataclass whose fields are numbers, strings, booleans, tuples
of those, other options dataclasses, or `None` where the type says `X | None`. `options_to_dict`
gives the plain JSON form (tuples become lists), `options_from_dict` rebuilds the dataclass from
it by the field types, so that `options_from_dict(type(o), options_to_dict(o)) == o`.

>>> from dataclasses import dataclass
>>> @dataclass(frozen=True)
... class Inner:
...     sigma_m: float = 0.3
>>> @dataclass(frozen=True)
... class Outer:
...     inner: Inner | None = Inner()
...     steps: tuple[int, ...] = (1, 2)
>>> options_to_dict(Outer())
{'inner': {'sigma_m': 0.3}, 'steps': [1, 2]}
>>> options_from_dict(Outer, {"inner": None, "steps": [4]})
Outer(inner=None, steps=(4,))
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Mapping
from typing import Any, TypeVar

T = TypeVar("T")


class OptionsError(ValueError):
    """Options that do not match their dataclass (names the field)."""


def options_to_dict(options: Any) -> dict[str, Any]:
    """The JSON form of an options dataclass (nested dataclasses as objects, tuples as lists)."""
    if not dataclasses.is_dataclass(options) or isinstance(options, type):
        raise OptionsError(f"not an options dataclass: {options!r}")
    return {f.name: _to_json(getattr(options, f.name)) for f in dataclasses.fields(options)}


def _to_json(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return options_to_dict(value)
    if isinstance(value, tuple | list):
        return [_to_json(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)  # "inf", "nan": JSON has no literal for them
    return value


def options_from_dict(cls: type[T], data: Mapping[str, Any] | None, *, strict: bool = True) -> T:
    """Rebuild `cls` from its JSON form; missing fields take their defaults.

    Args:
        cls: an options dataclass.
        data: its `options_to_dict` form (None: the defaults).
        strict: refuse unknown keys (False: ignore them, for files written by other versions).

    Raises:
        OptionsError: an unknown key (when strict) or a value of the wrong type, naming the field.
    """
    if data is None:
        return cls()
    if not isinstance(data, Mapping):
        raise OptionsError(f"{cls.__name__}: expected an object, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}  # type: ignore[arg-type]
    unknown = sorted(set(data) - names)
    if unknown and strict:
        raise OptionsError(f"{cls.__name__}: unknown option(s) {', '.join(unknown)}")
    kwargs = {}
    for name in names & set(data):
        try:
            kwargs[name] = _from_json(hints[name], data[name])
        except OptionsError as exc:
            raise OptionsError(f"{cls.__name__}.{name}: {exc}") from None
    return cls(**kwargs)


def _from_json(tp: Any, value: Any) -> Any:
    """`value` (JSON) as an instance of the type annotation `tp`."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None:
            if type(None) in args:
                return None
            raise OptionsError("null is not allowed")
        last: OptionsError | None = None
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _from_json(arg, value)
            except OptionsError as exc:
                last = exc
        raise last or OptionsError(f"no type matches {value!r}")
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise OptionsError(f"expected a list, got {value!r}")
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_from_json(args[0], v) for v in value)
        if len(args) != len(value):
            raise OptionsError(f"expected {len(args)} values, got {len(value)}")
        return tuple(_from_json(a, v) for a, v in zip(args, value, strict=True))
    if origin is typing.Literal:
        if value not in typing.get_args(tp):
            raise OptionsError(f"{value!r} is not one of {typing.get_args(tp)}")
        return value
    if dataclasses.is_dataclass(tp):
        return options_from_dict(tp, value)
    if tp is float:
        if isinstance(value, str) and value in ("inf", "-inf", "nan"):
            return float(value)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise OptionsError(f"expected a number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise OptionsError(f"expected an integer, got {value!r}")
        return value
    if tp is bool or tp is str:
        if not isinstance(value, tp):
            raise OptionsError(f"expected {tp.__name__}, got {value!r}")
        return value
    raise OptionsError(f"type {tp!r} cannot be read from JSON")
