"""The ``--holdout-*`` options of ``visnerf train`` and ``calibrate``: ``HoldoutConfig``'s fields
as command-line options, their parsers, and the config built back from them."""

import argparse
import math
from typing import TYPE_CHECKING

from visnerf.arg_types import number as parse_number
from visnerf.config import HoldoutConfig
from visnerf.field_docs import field_docs

if TYPE_CHECKING:
    from visnerf.data.scene import SceneData


def parse_settings(text: str) -> tuple[tuple[float, ...], ...]:
    """``"0.12,0.0225,0.7;0.155,0.0215,0.55"`` -> settings."""
    if not text:
        return ()
    try:
        return tuple(tuple(float(v) for v in part.split(",")) for part in text.split(";") if part.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"cannot read parameter settings {text!r}: use 'a,b,c;d,e,f'") from None


def parse_axis_value(text: str) -> tuple[str, float]:
    """``"OmM=0.1375"`` or ``"0=0.1375"`` -> (axis name or index, value), for ``--holdout-value``
    (the axis is resolved against the dataset once it is loaded: ``holdout_config``)."""
    axis, sep, value = text.partition("=")
    axis = axis.strip()
    if not sep or not axis:
        raise argparse.ArgumentTypeError(f"cannot read held-out axis value {text!r}: use AXIS=VALUE, the axis "
                                         "by its name or its index among the varying parameters (OmM=0.1375, 0=0.1375)")
    number = parse_number(value)
    if not math.isfinite(number):
        raise argparse.ArgumentTypeError(f"held-out axis value {text!r}: {value.strip()!r} is not a finite number")
    return axis, number


def holdout_config(scene: "SceneData", args: argparse.Namespace) -> HoldoutConfig:
    """The hold-out that ``--holdout-views``, ``--holdout-params`` and ``--holdout-value`` name, the
    axes of ``--holdout-value`` resolved against ``scene`` (ValueError naming an unknown axis)."""
    from visnerf.data.holdout import axis_index

    values = tuple((axis_index(scene, axis), value) for axis, value in getattr(args, "holdout_value", ()))
    return HoldoutConfig(views=args.holdout_views, settings=args.holdout_params, axis_values=values)


def parse_views(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"cannot read view indices {text!r}: use '0,7,21'") from None


HOLDOUT_OPTIONS = (("views", "--holdout-views", parse_views, "I,J,.."),
                   ("settings", "--holdout-params", parse_settings, "A,B;C,D"),
                   ("axis_values", "--holdout-value", parse_axis_value, "AXIS=VALUE"))
"""``HoldoutConfig``'s fields as options (``holdout_config`` builds it back): field, option, parser, metavar."""


def add_holdout_options(parser: argparse.ArgumentParser, purpose: str) -> None:
    """The ``--holdout-*`` options, their help from ``HoldoutConfig``'s field docs; ``purpose`` says
    what the frames are held out for."""
    docs = field_docs(HoldoutConfig)
    for name, option, parse, metavar in HOLDOUT_OPTIONS:
        many = name == "axis_values"  # one AXIS=VALUE at a time
        parser.add_argument(option, type=parse, default=[] if many else (), metavar=metavar,
                            action="append" if many else "store",
                            help=f"{docs[name]} Held out {purpose}"
                            + ("; AXIS: a name or an index; repeatable" if many else ""))
