"""Input-file schemas (pydantic v2) and their errors as one line naming the key, value and limit.

A file's tables are :class:`FileModel` subclasses: unknown keys are refused, numbers are numbers
(no ``"5"`` read as 5, no bool, nothing infinite or NaN), and :func:`parse` turns the first error
into the file's own :class:`~softphantom.errors.UserError` type:

>>> class Push(FileModel):
...     start_s: float = Field(ge=0)
...     force_N: Vec3
>>> parse(Push, {"start_s": -1, "force_N": [0, 1, 0]}, where="push[0]")
Traceback (most recent call last):
...
softphantom.errors.UserError: push[0].start_s = -1 must be >= 0 s
>>> parse(Push, {"start_s": 1, "force_N": [0, 1]}, where="push[0]")
Traceback (most recent call last):
...
softphantom.errors.UserError: push[0].force_N: expected 3 numbers [x, y, z], got [0, 1]
>>> parse(Push, {"start_s": 1, "force_N": [0, 1, 0], "speed": 3}, where="push[0]")
Traceback (most recent call last):
...
softphantom.errors.UserError: push[0]: unknown key 'speed' (known: force_N, start_s)
"""

from __future__ import annotations

import dataclasses
import functools
import types
import typing
from typing import Annotated, Any

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, Strict, ValidationError
from pydantic.dataclasses import dataclass as pydantic_dataclass
from pydantic_core import PydanticCustomError

from softphantom.errors import UserError

__all__ = ["Field", "FileModel", "Number", "Vec3", "between", "checked", "parse", "refuse"]

#: unit suffixes of key names (``radius_mm``, ``force_N``): a limit is printed with its unit
UNITS = {"mm3": "mm³", "mm": "mm", "kPa": "kPa", "N": "N", "s": "s", "m": "m", "deg": "deg", "mL": "mL"}


class FileModel(BaseModel):
    """A table of an input file: unknown keys refused, numbers strict and finite, frozen."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, frozen=True)


#: a number (int or float, not bool or ``"5"``; finite by the models' config)
Number = Annotated[float, Strict()]
#: three numbers [x, y, z] (a list or a tuple), kept as a tuple
Vec3 = Annotated[tuple[Number, ...], Field(min_length=3, max_length=3, strict=False)]


def refuse(message: str, **ctx: Any) -> PydanticCustomError:
    """An error raised inside a validator; :func:`parse` prints ``message`` after the key."""
    return PydanticCustomError("softphantom", message, ctx)


def between(lo: float, hi: float, unit: str = "", *, above: bool = False) -> AfterValidator:
    """``Annotated[float, between(6, 256)]``: a closed range (``above``: lo excluded), printed
    whole when it is left."""
    def check(v: float) -> float:
        if not (lo < v if above else lo <= v) or not v <= hi:
            raise refuse(f"must be in {'(' if above else '['}{lo:g}, {hi:g}]{' ' + unit if unit else ''}")
        return v
    return AfterValidator(check)


def _fmt(v: Any) -> str:
    return f"{v:.4g}" if isinstance(v, float) else repr(v)


def _path(where: str, loc: tuple) -> str:
    """``where`` (a table's path) and the keys of ``loc`` (a dotted key quoted as in TOML, an index in [])."""
    out = where
    for part in loc:
        key = f'"{part}"' if isinstance(part, str) and "." in part else str(part)
        out += f"[{part}]" if isinstance(part, int) else (f".{key}" if out else key)
    return out


def _strip(tp: Any) -> Any:
    while True:
        origin = typing.get_origin(tp)
        if origin is Annotated:
            tp = typing.get_args(tp)[0]
        elif origin in (typing.Union, types.UnionType):
            tp = next(a for a in typing.get_args(tp) if a is not type(None))
        else:
            return tp


def _fields(tp: Any) -> dict | None:
    """The pydantic fields of a model or a pydantic dataclass (None for anything else)."""
    return getattr(tp, "model_fields", None) if isinstance(tp, type) and issubclass(tp, BaseModel) \
        else getattr(tp, "__pydantic_fields__", None)


def _model_at(model: type, loc: tuple) -> type | None:
    """The model whose table sits at ``loc`` (for the list of its known keys)."""
    tp: Any = model
    for part in loc:
        tp = _strip(tp)
        if _fields(tp) is not None:
            tp = next((f.annotation for n, f in _fields(tp).items() if part in (n, f.alias)), None)
        elif typing.get_origin(tp) in (list, dict, tuple):
            tp = typing.get_args(tp)[-1 if typing.get_origin(tp) is not tuple else 0]
        else:
            return None
    tp = _strip(tp)
    return tp if _fields(tp) is not None else None


def _unit(loc: tuple) -> str:
    name = next((p for p in reversed(loc) if isinstance(p, str)), "")
    return " " + UNITS[name.rsplit("_", 1)[-1]] if "_" in name and name.rsplit("_", 1)[-1] in UNITS else ""


_EXPECTED = {"float_type": "a number", "int_type": "an integer", "bool_type": "true or false",
             "string_type": "a string", "list_type": "a list", "tuple_type": "a list", "dict_type": "a table",
             "model_type": "a table", "dataclass_type": "a table"}
_BOUND = {"greater_than": ">", "greater_than_equal": ">=", "less_than": "<", "less_than_equal": "<="}


def _is_point(model: type, loc: tuple) -> bool:
    """Whether the field at ``loc`` holds exactly 3 entries (a point or vector: say so when it is
    not a list at all)."""
    owner = _model_at(model, loc[:-1])
    f = next((f for n, f in (_fields(owner) or {}).items() if loc[-1] in (n, f.alias)), None) if owner else None
    if f is None:
        return False
    metas = list(f.metadata) + [m for a in typing.get_args(f.annotation) for m in getattr(a, "metadata", ())]
    return any(getattr(m, "max_length", None) == 3 for m in metas)


def message(model: type, err: dict, where: str = "", top: str = "top level") -> str:
    """One line for one pydantic error: ``where.key = value must be > 0 mm``."""
    loc, kind, value = tuple(err["loc"]), err["type"], err.get("input")
    path = _path(where, loc) or top
    ctx = err.get("ctx") or {}
    if kind in ("extra_forbidden", "unexpected_keyword_argument"):
        known = _model_at(model, loc[:-1])
        names = f" (known: {', '.join(sorted(f.alias or n for n, f in _fields(known).items()))})" if known else ""
        return f"{_path(where, loc[:-1]) or top}: unknown key {loc[-1]!r}{names}"
    if kind == "missing":
        return f"{path}: missing"
    if kind in ("list_type", "tuple_type") and _is_point(model, loc):
        return f"{path}: expected 3 numbers [x, y, z], got {value!r}"
    if kind in _EXPECTED:
        return f"{path}: expected {_EXPECTED[kind]}, got {value!r}"
    if kind in ("too_short", "too_long"):
        n = ctx.get("min_length") if kind == "too_short" else ctx.get("max_length")
        if n == 3:
            return f"{path}: expected 3 numbers [x, y, z], got {value!r}"
        if n == 1 and kind == "too_short":
            return f"{path}: expected a non-empty list, got {value!r}"
        return f"{path}: expected {'at least' if kind == 'too_short' else 'at most'} {n} entries, got {value!r}"
    if kind == "string_too_short":
        return f"{path}: expected a non-empty string, got {value!r}"
    if kind == "finite_number":
        return f"{path} = {value!r} must be finite"
    if kind == "literal_error":
        return f"{path}: {value!r} is not one of {ctx['expected'].replace(' or ', ', ').replace(chr(39), '')}"
    if kind in _BOUND:
        bound = next(iter(ctx.values()))
        return f"{path} = {_fmt(value)} must be {_BOUND[kind]} {_fmt(bound)}{_unit(loc)}"
    if kind == "softphantom":
        return f"{path} = {_fmt(value)} {err['msg']}" if not isinstance(value, dict) else f"{path}: {err['msg']}"
    return f"{path}: {err['msg']} (got {value!r})"


def checked(where: str = "", error: type[UserError] = UserError):
    """Class decorator: a frozen pydantic dataclass (unknown keys refused, numbers finite) whose
    construction, ``dataclasses.replace`` included, raises ``error`` with one line; ``where`` (the
    table's path) may hold ``{name}``, the instance's ``name``. Cross-field checks stay in
    ``__post_init__``, which runs after the fields are valid."""
    def wrap(cls):
        cls = pydantic_dataclass(frozen=True, config=ConfigDict(extra="forbid", allow_inf_nan=False))(cls)
        init, names = cls.__init__, [f.name for f in dataclasses.fields(cls)]

        @functools.wraps(init)
        def __init__(self, *args, **kwargs):
            try:
                init(self, *args, **kwargs)
            except ValidationError as exc:
                err = exc.errors()[0]
                if err["loc"] and isinstance(err["loc"][0], int):  # a positional argument: its field's name
                    err["loc"] = (names[err["loc"][0]], *err["loc"][1:])
                name = {**dict(zip(names, args)), **kwargs}.get("name")
                raise error(message(cls, err, where.format(name=name))) from None

        cls.__init__ = __init__
        return cls
    return wrap


def parse(model: type[BaseModel], data: Any, error: type[UserError] = UserError, where: str = "", source: str = "",
          top: str = "top level"):
    """``data`` validated as ``model``; the first problem raises ``error`` with one line, after
    ``source: `` (the file), with ``where`` (the table's own path) before each key and ``top``
    naming the file's top level."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        text = message(model, exc.errors()[0], where, top)
        raise error(f"{source}: {text}" if source else text) from None
