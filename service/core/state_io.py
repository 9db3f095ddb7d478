"""Plain values (frozen dataclasses of numbers, tuples, strings) to JSON and back, exactly.

Used to carry the pipeline's state (the filter, the estimator's prior) into a recording, so a
replay that starts in the middle of a dive starts where the daemon was. Floats survive the
round trip bit for bit (JSON numbers are written with Python's shortest exact repr); NaN and
infinities, which JSON lacks, are written as the strings "nan", "inf", "-inf".
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from typing import Any, TypeVar

T = TypeVar("T")
_SPECIAL = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf}


def to_plain(value: Any) -> Any:
    """A JSON-ready copy of `value` (dataclasses become objects, tuples lists)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, float):
        return value if math.isfinite(value) else str(value)
    if isinstance(value, list | tuple):
        return [to_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): to_plain(v) for k, v in value.items()}
    return value


def from_plain(tp: Any, value: Any) -> Any:
    """The inverse of `to_plain` for a value of type `tp` (a dataclass or a type hint)."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None:
            return None
        options = [a for a in typing.get_args(tp) if a is not type(None)]
        return from_plain(options[0], value) if len(options) == 1 else value
    if origin is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(from_plain(args[0], v) for v in value)
        return tuple(from_plain(a, v) for a, v in zip(args, value, strict=True))
    if origin is dict:
        _, value_type = typing.get_args(tp)
        return {k: from_plain(value_type, v) for k, v in value.items()}
    if tp is float:
        return _SPECIAL[value] if isinstance(value, str) else float(value)
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        hints = typing.get_type_hints(tp)
        fields = {f.name for f in dataclasses.fields(tp) if f.init}
        return tp(**{k: from_plain(hints[k], v) for k, v in value.items() if k in fields})
    return value
