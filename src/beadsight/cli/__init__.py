"""The ``beadsight`` command line: argument parsing only; every command calls the library.

Each area registers its subcommands in its own module (``cli/core.py``,
``cli/sim.py``, ...) through ``register(subparsers)``; each handler takes the
parsed ``argparse.Namespace`` and returns an exit code.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from beadsight import __version__

AREAS = ("data", "train", "evaluate", "sim", "rig", "export", "live")  # modules under beadsight.cli, in help order


class UserError(Exception):
    """An error caused by the user's input; printed without a traceback."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="beadsight",
        description="BeadSight visuo-tactile sensor toolkit: simulate, collect, train, evaluate, run live.",
    )
    parser.add_argument("--version", action="version", version=f"beadsight {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for area in AREAS:
        try:
            module = importlib.import_module(f"beadsight.cli.{area}")
        except ModuleNotFoundError as e:
            if e.name == f"beadsight.cli.{area}":
                continue
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    from beadsight.errors import USER_ERRORS

    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except USER_ERRORS as e:
        print(f"beadsight {args.command}: error: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
