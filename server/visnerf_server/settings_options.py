"""``visnerf serve``'s options, one per server setting (``Settings``), generated from the settings.

Each field becomes ``--field-name``, typed by its annotation, its help the field's docstring; an
option not given leaves the setting to ``VISNERF_*`` and its default. A few keep the names users
know (``HAND_WRITTEN``), and the token is no option: a command line is visible to every user of the
machine (``VISNERF_TOKEN`` or ``VISNERF_TOKEN_FILE`` give it).
"""

import argparse
import types
import typing
from pathlib import Path
from typing import Any

from pydantic import SecretStr

from visnerf.field_docs import field_docs
from visnerf_server.settings import Settings

HAND_WRITTEN = {"checkpoints_dir": "--checkpoints", "client_dir": "--no-client"}
"""Settings whose option ``visnerf serve`` writes itself, under the name users know."""
NOT_OPTIONS = {"token": "a command line is visible to every user of the machine: VISNERF_TOKEN or VISNERF_TOKEN_FILE"}
"""Settings that are no option, and why."""


def option_name(name: str) -> str:
    return HAND_WRITTEN.get(name, "--" + name.replace("-", "_").replace("_", "-"))


def _words(text: str) -> tuple[str, ...]:
    return tuple(part.strip() for part in text.split(",") if part.strip())


def _type_of(annotation: Any) -> tuple[Any, str, dict[str, Any]]:
    """(argparse ``type``, metavar, extra ``add_argument`` keywords) for a setting's annotation."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is typing.Annotated:
        return _type_of(args[0])
    if origin in (types.UnionType, typing.Union):
        inner = [a for a in args if a is not type(None)]
        if len(inner) == 1:
            return _type_of(inner[0])
    if origin is typing.Literal:
        return str, "{" + ",".join(map(str, args)) + "}", {"choices": list(args)}
    if origin is tuple:
        return _words, "A,B,..", {}
    if annotation in (int, float, str):
        return annotation, {int: "N", float: "X", str: "TEXT"}[annotation], {}
    if annotation is Path:
        return Path, "PATH", {}
    raise TypeError(f"no command-line form for a setting of type {annotation!r}")


def add_settings_options(parser: argparse.ArgumentParser) -> None:
    """An option for every setting that is neither hand-written nor left out, in one group."""
    docs = field_docs(Settings)
    group = parser.add_argument_group("server settings", "each also VISNERF_<NAME>; see settings.py")
    for name, info in Settings.model_fields.items():
        if name in HAND_WRITTEN or name in NOT_OPTIONS:
            continue
        help_text = docs.get(name, "").split(". ")[0].rstrip(".").replace("%", "%%")
        annotation = info.annotation
        if annotation is bool:
            group.add_argument(option_name(name), dest=f"setting_{name}", default=None,
                               action=argparse.BooleanOptionalAction, help=help_text)
            continue
        if annotation is SecretStr:
            raise TypeError(f"setting {name} is a secret: list it in NOT_OPTIONS")
        kind, metavar, extra = _type_of(annotation)
        group.add_argument(option_name(name), dest=f"setting_{name}", default=None, type=kind, metavar=metavar,
                           help=help_text, **extra)


def given_settings(args: argparse.Namespace) -> dict[str, Any]:
    """The settings given as options (by field name)."""
    prefix = "setting_"
    return {k[len(prefix):]: v for k, v in vars(args).items() if k.startswith(prefix) and v is not None}
