"""The checks every configuration runs on its values, and reading one from a JSON document."""

import dataclasses
import math
import numbers
import types
import typing
from typing import Any


def require(ok: bool, message: str) -> None:
    if not ok:
        raise ValueError(message)


def check_positive(config: object, *names: str) -> None:
    for name in names:
        value = getattr(config, name)
        require(math.isfinite(value) and value > 0, f"{name} must be a finite number above 0, got {value!r}")


def check_non_negative(config: object, *names: str) -> None:
    for name in names:
        value = getattr(config, name)
        require(math.isfinite(value) and value >= 0, f"{name} must be a finite number of at least 0, got {value!r}")


def check_at_least(config: object, least: int, *names: str) -> None:
    for name in names:
        value = getattr(config, name)
        require(value >= least, f"{name} must be a whole number of at least {least}, got {value!r}")


def check_below_one(config: object, *names: str) -> None:
    for name in names:
        value = getattr(config, name)
        require(0.0 <= value < 1.0, f"{name} must be in [0, 1), got {value!r}")


def check_fractions(config: object, *names: str) -> None:
    """Increasing progress fractions in [0, 1]."""
    for name in names:
        values = getattr(config, name)
        require(all(0.0 <= v <= 1.0 for v in values), f"{name} must hold fractions in [0, 1], got {values!r}")
        require(all(b > a for a, b in zip(values, values[1:], strict=False)),
                 f"{name} must increase, got {values!r}")


def is_whole(value: object) -> bool:
    """An integer (numpy's too), not a bool and not a float that happens to be whole."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def has_type(value: object, annotation: object) -> bool:
    """Whether ``value`` is of a field's annotated type: int, float (an int too), bool, str, or a
    tuple of ints."""
    if typing.get_origin(annotation) is typing.Literal:
        return value in typing.get_args(annotation)
    if typing.get_origin(annotation) is tuple:
        args = typing.get_args(annotation)
        if not isinstance(value, tuple):
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            return all(has_type(v, args[0]) for v in value)
        return len(args) == len(value) and all(has_type(v, a) for v, a in zip(value, args, strict=True))
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return any(has_type(value, a) for a in typing.get_args(annotation))
    if annotation is type(None):
        return value is None
    if annotation is int:
        return is_whole(value)
    if annotation is float:
        return isinstance(value, numbers.Real) and not isinstance(value, bool)
    return isinstance(value, annotation) if isinstance(annotation, type) else True


TYPE_WORDS = {int: "a whole number", float: "a number", bool: "true or false", str: "a string"}


def check_types(cls: type, values: dict[str, Any]) -> None:
    """Each value has its field's annotated type. ``from_dict`` checks before it builds (a
    configuration read from JSON may hold anything), so that the refusal names the field."""
    for f in dataclasses.fields(cls):
        if f.name in values:
            if typing.get_origin(f.type) is typing.Literal:
                word = "one of " + ", ".join(repr(v) for v in typing.get_args(f.type))
            elif typing.get_origin(f.type) is tuple:
                first = typing.get_args(f.type)[0]
                word = {int: "whole numbers", float: "numbers"}.get(first, "a list")
            else:
                word = TYPE_WORDS.get(f.type, str(f.type))  # type: ignore[arg-type]
            require(has_type(values[f.name], f.type), f"{f.name} must be {word}, got {values[f.name]!r}")


def config_from_dict(cls: type, data: dict[str, Any], what: str) -> Any:
    """``cls`` from a JSON document (a checkpoint's, a run state's, the command line's): every key
    must name a field (``ValueError`` naming the others), JSON lists become tuples, each value is
    checked against its field's type before the configuration's own checks; a field the document
    does not name takes its default. Documents of older formats are migrated before they get here
    (``checkpoint.migrate``)."""
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise ValueError(f"unknown {what} keys {sorted(unknown)}")
    values = {k: tuple(tuple(x) if isinstance(x, list) else x for x in v) if isinstance(v, list) else v
              for k, v in data.items()}
    check_types(cls, values)
    return cls(**values)


def check_whole_in(config: object, least: int, most: int, *names: str) -> None:
    """Whole numbers in [least, most]; a tuple field is checked element by element."""
    for name in names:
        value = getattr(config, name)
        items = value if isinstance(value, tuple) else (value,)
        require(all(is_whole(v) and least <= v <= most for v in items),
                 f"{name} must be {'whole numbers' if isinstance(value, tuple) else 'a whole number'} "
                 f"in [{least}, {most}], got {value!r}")


def check_number_in(config: object, least: float, most: float, *names: str) -> None:
    for name in names:
        value = getattr(config, name)
        require(isinstance(value, numbers.Real) and math.isfinite(value) and least <= float(value) <= most,
                 f"{name} must be a finite number in [{least:g}, {most:g}], got {value!r}")
