"""Dataclass configuration plumbing: JSON -> dataclass, valid ranges, docstrings -> CLI flags.

A configuration dataclass documents each field with an attribute docstring (the string
literal under the field, as nerfstudio / tyro read them) and states its valid range in the
field's metadata:
    "min" / "max"  inclusive bounds        "gt"  exclusive lower bound
    "choices"      allowed values          "multiple_of"  e.g. 2 for an even count
`from_dict` builds a dataclass from a JSON object with one-line errors naming the key path;
`check_ranges` checks a built one; `add_flags` makes argparse flags whose help is the docstring.
Nothing here knows a particular configuration.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import functools
import inspect
import math
import textwrap
import types
import typing
from typing import Any, Literal

from .errors import InputError


def check(cond: bool, where: str, key: str, msg: str) -> None:
    """Raise `InputError("<where>: '<key>' <msg>")` unless cond."""
    if not cond:
        raise InputError(f"{where}: '{key}' {msg}")


@functools.cache
def field_docs(cls: type) -> dict[str, str]:
    """{field name: its attribute docstring, whitespace collapsed} of dataclass `cls`."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        except (OSError, TypeError, SyntaxError):
            continue
        body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
        for a, b in zip(body, body[1:], strict=False):
            if (
                isinstance(a, ast.AnnAssign)
                and isinstance(a.target, ast.Name)
                and isinstance(b, ast.Expr)
                and isinstance(b.value, ast.Constant)
                and isinstance(b.value.value, str)
            ):
                docs[a.target.id] = " ".join(inspect.cleandoc(b.value.value).split())
    return docs


def range_text(meta: typing.Mapping) -> str | None:
    """The valid range a field's metadata states, in words ("in [1, 1024]", "> 0"), or None."""
    if "choices" in meta:
        return f"one of {list(meta['choices'])}"
    lo, hi, gt = (_num(meta.get(k)) for k in ("min", "max", "gt"))
    if lo is None and hi is None and gt is None:
        return None
    if gt is not None:
        text = f"in ({gt}, {hi}]" if hi is not None else f"> {gt}"
    elif lo is not None and hi is not None:
        text = f"in [{lo}, {hi}]"
    elif lo is not None:
        text = f">= {lo}"
    else:
        text = f"<= {hi}"
    if meta.get("multiple_of"):
        text = f"a multiple of {meta['multiple_of']} {text}"
    return text


def _num(v: float | int | None) -> str | None:
    return None if v is None else str(v) if isinstance(v, int) else f"{v:g}"


def check_value(meta: typing.Mapping, v: Any, where: str, key: str) -> None:
    """One-line InputError unless v (a number; None passes) lies in the range of `meta`."""
    if v is None or isinstance(v, (bool, str, list, dict)):
        if "choices" in meta and v is not None and v not in meta["choices"]:
            raise InputError(f"{where}: '{key}' must be {range_text(meta)}, got {v!r}")
        return
    if not isinstance(v, (int, float)):
        return
    if not math.isfinite(v):
        raise InputError(f"{where}: '{key}' is not finite ({v})")
    ok = True
    if "choices" in meta:
        ok = v in meta["choices"]
    if "min" in meta:
        ok &= v >= meta["min"]
    if "max" in meta:
        ok &= v <= meta["max"]
    if "gt" in meta:
        ok &= v > meta["gt"]
    if meta.get("multiple_of"):
        ok &= v % meta["multiple_of"] == 0
    if not ok:
        raise InputError(f"{where}: '{key}' must be {range_text(meta)}, got {v!r}")


def check_ranges(obj: Any, where: str, prefix: str = "") -> None:
    """Check every field of dataclass instance `obj` (and nested ones) against its range."""
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            check_ranges(v, where, f"{prefix}{f.name}.")
        else:
            check_value(f.metadata, v, where, prefix + f.name)


def from_dict(cls: type, d: Any, where: str, prefix: str = "") -> Any:
    """Build dataclass `cls` from a JSON object, with one-line errors naming the key path.

    Types are checked and coerced, ranges in the fields' metadata checked, and a ValueError
    from the class's own checks (`__post_init__`) becomes a one-line InputError.
    """
    if not isinstance(d, dict):
        raise InputError(f"{where}: '{prefix.rstrip('.') or cls.__name__}' must be an object")
    hints = typing.get_type_hints(cls)
    kwargs = {}
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for key in d:
        if key not in fields:
            raise InputError(f"{where}: unknown key '{prefix}{key}'")
    for name, f in fields.items():
        key = prefix + name
        if name not in d:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise InputError(f"{where}: missing key '{key}'")
            continue
        kwargs[name] = _coerce(hints[name], d[name], where, key)
        check_value(f.metadata, kwargs[name], where, key)
    try:
        return cls(**kwargs)
    except ValueError as e:
        raise InputError(f"{where}: '{prefix.rstrip('.') or cls.__name__}' {e}") from None


def _coerce(tp: Any, v: Any, where: str, key: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if v is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _coerce(inner[0], v, where, key)
    if dataclasses.is_dataclass(tp):
        return from_dict(tp, v, where, key + ".")
    if origin is Literal:
        if v not in args:
            raise InputError(f"{where}: '{key}' must be one of {list(args)}, got {v!r}")
        return v
    if origin is list:
        if not isinstance(v, list):
            raise InputError(f"{where}: '{key}' must be a list")
        return [_coerce(args[0], x, where, f"{key}[{i}]") for i, x in enumerate(v)]
    if tp is bool:
        if not isinstance(v, bool):
            raise InputError(f"{where}: '{key}' must be true or false")
        return v
    if tp in (int, float):
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise InputError(f"{where}: '{key}' must be a number, got {v!r}")
        if not math.isfinite(v):  # before int(): int(inf) / int(nan) would raise
            raise InputError(f"{where}: '{key}' is not finite ({v})")
        if tp is int and float(v) != int(v):
            raise InputError(f"{where}: '{key}' must be an integer, got {v!r}")
        return tp(v)
    if tp is str:
        if not isinstance(v, str):
            raise InputError(f"{where}: '{key}' must be a string")
        return v
    return v


# -- command-line flags ------------------------------------------------------------------------


def flag_name(name: str) -> str:
    """The flag of a field: win_max -> --win-max."""
    return "--" + name.replace("_", "-")


def add_flags(
    parser: argparse.ArgumentParser | argparse._ActionsContainer,
    cls: type,
    names: typing.Iterable[str],
    *,
    aliases: typing.Mapping[str, list[str]] | None = None,
    notes: typing.Mapping[str, str] | None = None,
) -> None:
    """Add one flag per field of `cls` in `names`, its help the field's docstring.

    Every flag defaults to None (not given), so a caller can tell "left to the preset" from a
    value. notes: text appended to a field's help (e.g. what the default is).
    """
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for name in names:
        f = fields[name]
        kw = _flag_kwargs(hints[name])
        text = docs.get(name, "")
        rng = range_text(f.metadata)
        if rng and "choices" not in kw:
            text += f" Valid: {rng}."
        if notes and name in notes:
            text += f" {notes[name]}"
        flags = [flag_name(name), *((aliases or {}).get(name, []))]
        parser.add_argument(*flags, dest=name, default=None, help=text.replace("%", "%%"), **kw)


def _flag_kwargs(tp: Any) -> dict:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        return _flag_kwargs(next(a for a in args if a is not type(None)))
    if origin is Literal:
        return {"choices": list(args)}
    if tp is bool:
        return {"action": argparse.BooleanOptionalAction}
    if origin is list:
        return {"nargs": "+", "type": args[0], "metavar": args[0].__name__.upper()}
    if tp in (int, float):
        return {"type": tp, "metavar": "N" if tp is int else "X"}
    return {"type": str}
