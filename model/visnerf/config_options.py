"""Command-line options generated from the typed configuration (``visnerf.config``).

Every field of ``TrainConfig``, ``FieldConfig`` and ``RenderConfig`` is an option of ``visnerf
train``, and every field of ``FramesConfig`` one of ``visnerf render`` and ``visnerf animate``:
``--field-name``, typed by the field's annotation, its help the field's docstring, so that a new
setting needs no command-line code. The exceptions are named: ``--time-budget`` (minutes) is
declared by the command itself (``HAND_WRITTEN``), a few options answer to a shorter name too
(``ALIASES``), and the fields the data or the end of training decide are no options
(``NOT_OPTIONS``, with the reason). An option that is not given leaves the configuration's value
(the recipe's); the configuration's own checks judge a given one, and the command refuses it with
their message, naming the field.
"""

import argparse
import dataclasses
import math
import types
import typing
from typing import Any

from visnerf.config import FieldConfig, FramesConfig, RenderConfig, TrainConfig
from visnerf.field_docs import field_docs
from visnerf.training.recipe import CHOSEN_FIELDS

CONFIG_CLASSES: tuple[type, ...] = (TrainConfig, FieldConfig, RenderConfig)

HAND_WRITTEN: dict[tuple[str, str], str] = {
    ("TrainConfig", "time_budget_s"): "--time-budget",
}
"""Fields ``visnerf train`` declares itself (``commands.register``), and the option of each:
the budget is given in minutes."""

ALIASES: dict[tuple[str, str], str] = {
    ("TrainConfig", "resolution_final"): "--resolution",
    ("TrainConfig", "tv_weight_appearance"): "--tv-appearance",
    ("TrainConfig", "validate_every_s"): "--validate-every",
}
"""Shorter names some generated options answer to as well."""

NOT_OPTIONS: dict[tuple[str, str], str] = {
    ("FieldConfig", "resolution"): "follows from the content box and --resolution",
    ("FieldConfig", "param_lengths"): "the number of training values of each parameter, from the data",
    ("RenderConfig", "full_step_ratio"): "chosen at the end of training from held-out frames, else training frames "
                                           "(visnerf calibrate)",
}
"""Fields that are not options, and why."""


def option_of(cls: type, name: str) -> str | None:
    """The option that sets field ``name`` of ``cls`` (None: not an option, see ``NOT_OPTIONS``)."""
    key = (cls.__name__, name)
    if key in NOT_OPTIONS:
        return None
    return HAND_WRITTEN.get(key) or ALIASES.get(key) or "--" + name.replace("_", "-")


def _dest(cls: type, name: str) -> str:
    return f"config__{cls.__name__}__{name}"


def _finite(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def _whole(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None


def _parser_for(annotation: Any) -> tuple[Any, str]:
    """(argparse ``type``, metavar) for a field annotation."""
    if annotation is int:
        return _whole, "N"
    if annotation is float:
        return _finite, "X"
    if annotation is str:
        return str, "TEXT"
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is typing.Literal:
        def choose(text: str) -> Any:
            if text not in args:
                raise argparse.ArgumentTypeError(f"expected one of {', '.join(map(str, args))}, got {text!r}")
            return text

        return choose, "{" + ",".join(map(str, args)) + "}"
    if origin in (types.UnionType, typing.Union) and type(None) in args:
        inner, metavar = _parser_for(next(a for a in args if a is not type(None)))
        return (lambda text: None if text.lower() == "none" else inner(text)), f"{metavar}|none"
    if origin is tuple:
        item = _finite if float in args else _whole
        fixed = None if (len(args) == 2 and args[1] is Ellipsis) else len(args)

        def parse(text: str) -> tuple:
            values = tuple(item(part) for part in text.split(",") if part.strip())
            if fixed is not None and len(values) != fixed:
                raise argparse.ArgumentTypeError(f"expected {fixed} comma-separated values, got {text!r}")
            return values

        return parse, "A,B,.."
    raise TypeError(f"no command-line form for a field of type {annotation!r}")


TITLES = {"TrainConfig": ("training (TrainConfig)", "the recipe's values unless given"),
          "FieldConfig": ("field (FieldConfig)", "the recipe's values unless given"),
          "RenderConfig": ("renderer (RenderConfig)", "the recipe's values unless given"),
          "FramesConfig": ("frames on this machine (FramesConfig)", "the defaults unless given"),
          "BakeConfig": ("bake (BakeConfig)", "the defaults unless given")}
"""Each configuration's option group: its title and where a value not given comes from."""


def add_config_options(parser: argparse.ArgumentParser, classes: tuple[type, ...] = CONFIG_CLASSES) -> None:
    """One option for every field of ``classes`` that is neither hand-written nor left out, in a
    group per configuration, each defaulting to "not given"."""
    for cls in classes:
        docs, hints = field_docs(cls), typing.get_type_hints(cls)
        title, source = TITLES[cls.__name__]
        group = parser.add_argument_group(title, f"{source}; see model/visnerf/config/")
        for f in dataclasses.fields(cls):
            key = (cls.__name__, f.name)
            if key in HAND_WRITTEN or key in NOT_OPTIONS:
                continue
            default = f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]
            help_text = docs.get(f.name, "").split(". ")[0].rstrip(".")
            shown = "chosen from the data, see visnerf info" if key in CHOSEN_FIELDS else repr(default)
            help_text = (help_text + f" (default: {shown})").strip().replace("%", "%%")
            names = [option_of(cls, f.name)]
            if key in ALIASES:
                names.append("--" + f.name.replace("_", "-"))
            if hints[f.name] is bool:
                group.add_argument(*names, dest=_dest(cls, f.name), default=None,
                                   action=argparse.BooleanOptionalAction, help=help_text)
            else:
                kind, metavar = _parser_for(hints[f.name])
                group.add_argument(*names, dest=_dest(cls, f.name), default=None, type=kind, metavar=metavar,
                                   help=help_text)


def given_options(args: argparse.Namespace, cls: type) -> dict[str, Any]:
    """The generated options of ``cls`` given on the command line, by field name."""
    return {f.name: getattr(args, _dest(cls, f.name)) for f in dataclasses.fields(cls)
            if getattr(args, _dest(cls, f.name), None) is not None}


def config_from_args(cls: type, args: argparse.Namespace) -> Any:
    """``cls`` built from its generated options (``add_config_options(parser, (cls,))``) and its
    defaults; ValueError names a field whose value its checks refuse."""
    return cls(**given_options(args, cls))


def frames_config(args: argparse.Namespace) -> FramesConfig:
    """The ``FramesConfig`` the options of ``add_config_options(parser, (FramesConfig,))`` give;
    ValueError names a field whose value its checks refuse."""
    return FramesConfig(**given_options(args, FramesConfig))
