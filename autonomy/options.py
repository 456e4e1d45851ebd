"""Typed, validated option objects shared by the algorithms and the config loader.

An options class is a frozen dataclass whose fields are made with :func:`option`, which keeps
the default, a one-line description and the allowed range in one place. The class calls
:func:`validate` from ``__post_init__``, so a bad value fails where it is made, whether it
came from a TOML file, a ``--set`` override or a notebook.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import operator
import typing
from typing import Any


class OptionError(ValueError):
    """A value that does not fit its option; ``key`` names the field."""

    def __init__(self, key: str, message: str):
        super().__init__(f"{key}: {message}")
        self.key = key
        self.message = message


def option(
    default: Any,
    *,
    doc: str,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    choices: tuple[str, ...] | None = None,
) -> Any:
    """A dataclass field carrying its description and its allowed values."""
    metadata = {"doc": doc, "ge": ge, "gt": gt, "le": le, "lt": lt, "choices": choices}
    if isinstance(default, list):
        return dataclasses.field(default_factory=lambda: list(default), metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


@functools.lru_cache(maxsize=None)
def field_types(cls: type) -> dict[str, Any]:
    """The resolved annotation of every field of an options class (resolved once per class)."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def _tuple_item(kind: Any) -> Any:
    """``str`` or ``float`` for ``tuple[str, ...]`` or ``tuple[float, ...]``, the container
    types an option may have; None for any other type."""
    if typing.get_origin(kind) is tuple:
        args = typing.get_args(kind)
        if len(args) == 2 and args[1] is Ellipsis and args[0] in (str, float):
            return args[0]
    return None


def _type_name(kind: Any) -> str:
    item = _tuple_item(kind)
    if item is not None:
        return f"a list of {'strings' if item is str else 'numbers'}"
    return {bool: "a boolean", int: "an integer", float: "a number", str: "a string"}.get(
        kind, str(kind)
    )


def _check_type(name: str, value: Any, kind: Any) -> None:
    # bool is a subclass of int in Python; a config value `true` is never a number.
    if kind is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    elif kind is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif _tuple_item(kind) is str:
        ok = isinstance(value, tuple) and all(isinstance(item, str) for item in value)
    elif _tuple_item(kind) is float:
        ok = isinstance(value, tuple) and all(
            isinstance(item, (int, float)) and not isinstance(item, bool) for item in value)
    else:
        ok = isinstance(value, kind)
    if not ok:
        raise OptionError(name, f"must be {_type_name(kind)}, got {value!r}")


_BOUNDS = (("ge", ">=", operator.ge), ("gt", ">", operator.gt),
           ("le", "<=", operator.le), ("lt", "<", operator.lt))


def _check_range(name: str, value: Any, f: dataclasses.Field) -> None:
    meta = f.metadata
    # For a tuple option the bounds and choices apply to each element.
    items = value if isinstance(value, tuple) else (value,)
    if any(isinstance(item, float) and not math.isfinite(item) for item in items):
        what = "finite numbers" if isinstance(value, tuple) else "a finite number"
        raise OptionError(name, f"must be {what}, got {value!r}")
    for key, symbol, holds in _BOUNDS:
        limit = meta.get(key)
        if limit is not None and not all(holds(item, limit) for item in items):
            raise OptionError(name, f"must be {symbol} {limit:g}, got {value!r}")
    choices = meta.get("choices")
    if choices is not None:
        for item in items:
            if item not in choices:
                raise OptionError(name, f"must be one of {', '.join(choices)}; got {item!r}")


def validate(obj: Any) -> None:
    """Check every field of an options dataclass against its type and range.

    Raises :class:`OptionError` naming the first bad field. Nested options classes are
    validated by their own ``__post_init__``.
    """
    types = field_types(type(obj))
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        kind = types[f.name]
        if dataclasses.is_dataclass(kind):
            if not isinstance(value, kind):
                raise OptionError(f.name, f"must be a {kind.__name__}, got {value!r}")
            continue
        _check_type(f.name, value, kind)
        _check_range(f.name, value, f)


def describe(cls: type) -> dict[str, str]:
    """Field name -> its one-line description, for help texts and docs."""
    return {f.name: f.metadata.get("doc", "") for f in dataclasses.fields(cls)}
