"""The ``visnerf`` command line: one sub-command per job.

Each area registers its own sub-commands (``register(subparsers)``), so this module only wires them.
A handler takes the parsed arguments and returns the process exit code.
"""

import argparse
import importlib
import importlib.metadata
import importlib.util
import sys

# The model's modules that contribute sub-commands, in the order they appear in ``visnerf --help``.
_COMMAND_MODULES = (
    "visnerf.commands",  # train, render, info
    "visnerf.scenes.commands",  # make-scene, scenes
    "visnerf.evaluation.commands",  # eval
    "visnerf.animation.commands",  # animate
)
COMMAND_GROUP = "visnerf.commands"
"""Entry-point group through which other packages of the distribution add sub-commands (the server's
``serve`` and ``submit``, pyproject.toml): the model names no package above it."""


def command_modules() -> list[str]:
    """The model's command modules, then those the installed distributions register under
    ``COMMAND_GROUP`` (by entry-point name)."""
    plugins = sorted(importlib.metadata.entry_points(group=COMMAND_GROUP), key=lambda e: e.name)
    return [*_COMMAND_MODULES, *(e.value for e in plugins)]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="visnerf",
        description="Learn ViSNeRF models from images of scientific visualizations and explore them.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in command_modules():
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name is not None and name.startswith(exc.name):
                continue  # that part of the distribution is not present
            raise
        module.register(sub)
    return parser


def missing_modules(args: argparse.Namespace) -> list[str]:
    """The modules a sub-command needs (``set_defaults(requires=(...))``) that this install lacks:
    training and evaluation packages live in the ``train`` extra, which a server install leaves out."""
    return [name for name in getattr(args, "requires", ()) if importlib.util.find_spec(name) is None]


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        parser.print_help()
        return 2
    if missing := missing_modules(args):
        print(
            f"error: visnerf {args.command} needs {', '.join(missing)}, from the train extra: "
            "pip install 'visnerf[train]' (in a checkout: pip install -e '.[train]')",
            file=sys.stderr,
        )
        return 2
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
