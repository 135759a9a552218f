"""The ``beadsight`` command line: argument parsing only; every command calls the library.

Each area registers its subcommands in its own module (``cli/train.py``,
``cli/sim.py``, ...) through ``register(commands)``: a name, a help line and two
functions, one adding the command's arguments and one running it (taking the parsed
``argparse.Namespace``, returning an exit code). Only the command being run gets its
arguments, and area modules import the library inside those functions, so
``beadsight --help`` and ``beadsight CMD --help`` start without torch.

Errors: a :class:`~beadsight.errors.BeadSightError` (or a missing file) is the user's to
fix and prints one line, exit 1. Anything else is a bug in beadsight: it prints
"internal error" (with the traceback under ``-v``), exit 70.
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import logging
import signal
import sys
import threading
import traceback
from collections.abc import Callable, Iterable, Sequence

from beadsight import __version__
from beadsight.cli.options import check_numbers

AREAS = (
    "data",
    "train",
    "calibrate",
    "evaluate",
    "sim",
    "rig",
    "export",
    "live",
    "health",
)  # modules, in help order
EXIT_USER_ERROR = 1
EXIT_INTERNAL_ERROR = 70  # EX_SOFTWARE (sysexits.h)
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 128 + signal.SIGTERM  # 143, as a shell reports a process SIGTERM ended

Handler = Callable[[argparse.Namespace], "int | None"]


class Commands:
    """The subcommands of ``beadsight``: registered by name and help line; the arguments
    of each are added only when it is the command being run (or all, for ``build_all``)."""

    def __init__(self, subparsers: argparse._SubParsersAction):
        self._subparsers = subparsers
        self._pending: dict[str, tuple[argparse.ArgumentParser, Callable]] = {}

    def add(
        self,
        name: str,
        run: Handler | None = None,
        arguments: Callable[[argparse.ArgumentParser], None] | None = None,
        *,
        help: str | None = None,
        description: str | None = None,
    ) -> None:
        """Register ``beadsight NAME``: ``arguments(parser)`` adds its options when needed,
        ``run(args)`` runs it (None: ``arguments`` sets ``func`` itself, e.g. for nested
        subcommands). The help line is the first line of ``run``'s docstring and the
        description its whole text, unless given."""
        first, description_text = _doc_parts(run)
        help = help or first
        parser = self._subparsers.add_parser(
            name, help=help, description=description or description_text or help
        )
        if run is not None:
            parser.set_defaults(func=run)
        self._pending[name] = (parser, arguments or (lambda parser: None))

    @property
    def names(self) -> list[str]:
        return list(self._subparsers.choices)

    def build(self, name: str) -> None:
        """Add the arguments of command ``name`` (once)."""
        entry = self._pending.pop(name, None)
        if entry is not None:
            parser, arguments = entry
            arguments(parser)


def _doc_parts(run: Handler | None) -> tuple[str, str]:
    """(help line, description) from a command function's docstring: the first line as
    argparse help lines are written (lower case, no full stop), and the whole text."""
    doc = inspect.cleandoc(getattr(run, "__doc__", None) or "")
    if not doc:
        return "", ""
    first = doc.split("\n\n")[0].replace("\n", " ").rstrip(".")
    return first[:1].lower() + first[1:], doc


def build_parser(commands: Iterable[str] | None = None) -> argparse.ArgumentParser:
    """The ``beadsight`` parser, with the arguments of ``commands`` (None: of every command).

    ``main`` asks only for the command it runs; tests and docs take them all.
    """
    parser = argparse.ArgumentParser(
        prog="beadsight",
        description="BeadSight visuo-tactile sensor toolkit: simulate, collect, train, "
        "evaluate, run live.",
    )
    parser.add_argument("--version", action="version", version=f"beadsight {__version__}")
    parser.add_argument(
        "-v", "--verbose", action="store_true", help="debug logging and full tracebacks"
    )
    registry = Commands(parser.add_subparsers(dest="command", metavar="COMMAND"))
    for area in AREAS:
        importlib.import_module(f"beadsight.cli.{area}").register(registry)
    for name in registry.names if commands is None else commands:
        registry.build(name)
    check_numbers(parser)
    return parser


def command_name(argv: Sequence[str]) -> str | None:
    """The subcommand in ``argv``: its first word that is not an option (the top-level
    options take no values)."""
    return next((a for a in argv if not a.startswith("-")), None)


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    name = command_name(argv)
    parser = build_parser([name] if name else [])
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    return run_command(args)


class Terminated(KeyboardInterrupt):
    """SIGTERM (``docker stop``, systemd, ``kill``) raised as Ctrl-C is, so that every
    command stops the same way: summary printed, recordings finished, run state saved."""


def _terminate_like_ctrl_c(signum: int, frame: object) -> None:
    raise Terminated()


def run_command(args: argparse.Namespace) -> int:
    """Run the parsed command; errors become one line (the user's) or an internal error.
    SIGTERM is handled as Ctrl-C (:class:`Terminated`), exit 143."""
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminate_like_ctrl_c) if main_thread else None
    try:
        return _run(args)
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)


def _run(args: argparse.Namespace) -> int:
    from beadsight.errors import USER_ERRORS

    try:
        return int(args.func(args) or 0)
    except Terminated:
        print("terminated (SIGTERM)", file=sys.stderr)
        return EXIT_TERMINATED
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except USER_ERRORS as e:
        print(f"beadsight {args.command}: error: {e}", file=sys.stderr)
        return EXIT_USER_ERROR
    except Exception as e:  # noqa: BLE001 - a bug: say so, never as a user error
        print(f"beadsight {args.command}: internal error: {type(e).__name__}: {e}", file=sys.stderr)
        if args.verbose:
            traceback.print_exc()
        else:
            print(
                "This is a bug in beadsight. Rerun with -v for the traceback, and please "
                "report it with that output.",
                file=sys.stderr,
            )
        return EXIT_INTERNAL_ERROR


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
