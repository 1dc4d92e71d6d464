"""The ``--cinema-*`` options of the commands that read datasets, generated from ``CinemaCamera``.

Each field of ``CinemaCamera`` is an option ``--cinema-FIELD`` whose help is the field's
docstring; a given option takes precedence over the database's ``visnerf_camera.json``.
"""

import argparse
import dataclasses
import typing
from typing import Any

from visnerf.data.parsers.cinema_cameras import CAMERA_FILE, CinemaCamera
from visnerf.field_docs import field_docs

_PREFIX = "cinema__"


def _numbers(count: int) -> Any:
    def parse(text: str) -> tuple[float, ...]:
        try:
            values = tuple(float(v) for v in text.split(","))
        except ValueError:
            values = ()
        if len(values) != count:
            raise argparse.ArgumentTypeError(f"expected {count} comma-separated numbers, got {text!r}")
        return values

    return parse


def add_cinema_options(parser: argparse.ArgumentParser) -> None:
    """One ``--cinema-FIELD`` option for every field of ``CinemaCamera``, defaulting to "not given"."""
    docs, hints = field_docs(CinemaCamera), typing.get_type_hints(CinemaCamera)
    group = parser.add_argument_group(
        "Cinema databases (CinemaCamera)", f"what the database's angle columns lack; over its {CAMERA_FILE}")
    for f in dataclasses.fields(CinemaCamera):
        option = "--cinema-" + f.name.replace("_", "-")
        help_text = docs.get(f.name, "").split(". ")[0].rstrip(".").replace("%", "%%")
        hint = hints[f.name]
        literal = next((a for a in (hint, *typing.get_args(hint)) if typing.get_origin(a) is typing.Literal), None)
        if literal is not None:
            group.add_argument(option, dest=_PREFIX + f.name, choices=typing.get_args(literal), default=None,
                               help=help_text)
        elif f.name == "bounds":
            pairs = _numbers(6)
            group.add_argument(option, dest=_PREFIX + f.name, metavar="X0,Y0,Z0,X1,Y1,Z1", default=None,
                               type=lambda t, p=pairs: (p(t)[:3], p(t)[3:]), help=help_text)
        elif f.name in ("focal_point", "background"):
            group.add_argument(option, dest=_PREFIX + f.name, metavar="X,Y,Z", type=_numbers(3), default=None,
                               help=help_text)
        else:
            group.add_argument(option, dest=_PREFIX + f.name, metavar="X", type=float, default=None, help=help_text)


def cinema_camera(args: argparse.Namespace) -> CinemaCamera | None:
    """The ``CinemaCamera`` the options give (ValueError from its checks), None when none is given."""
    given = {f.name: getattr(args, _PREFIX + f.name) for f in dataclasses.fields(CinemaCamera)
             if getattr(args, _PREFIX + f.name, None) is not None}
    return CinemaCamera(**given) if given else None
