"""Command-line options made from the config dataclasses' fields, so that every default
the CLI shows and uses is the dataclass's own (one place to change it).

A table row ``(field, help)`` or ``(field, help, {argparse keywords})`` becomes
``--field-name`` with the field's default: ``type`` follows the default (give it for
fields whose default is None), a False bool becomes a ``store_true`` switch and a True
one a ``--no-field`` switch.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Iterable
from typing import Any

Row = tuple  # (field, help) or (field, help, kwargs)
MAX_FLAG_VALUE = 2**32  # no count, size, seed, rate or duration flag means more (a typo)
MAX_BUDGET_MIN = 7 * 24 * 60.0  # a wall-clock budget beyond a week, minutes (a typo)


class Number:
    """An argparse ``type`` for numbers: ``kind`` (int or float), finite, from ``low`` to
    ``high`` (``positive``: above ``low``). :func:`check_numbers` gives every int or float
    flag the default one (0 .. :data:`MAX_FLAG_VALUE`); a flag with other bounds names its
    own, e.g. ``type=Number(float, positive=True, high=MAX_BUDGET_MIN)``."""

    def __init__(
        self,
        kind: type = float,
        low: float = 0,
        high: float = MAX_FLAG_VALUE,
        *,
        positive: bool = False,
    ):
        self.kind, self.low, self.high, self.positive = kind, low, high, positive
        self.__name__ = kind.__name__  # argparse names the type in its "invalid ..." errors

    def __call__(self, text: str) -> int | float:
        value = self.kind(text)
        if not (math.isfinite(value) and self.low <= value <= self.high) or (
            self.positive and value == self.low
        ):
            relation = f"> {show(self.low)}" if self.positive else f">= {show(self.low)}"
            raise argparse.ArgumentTypeError(
                f"expected a finite number {relation} and <= {show(self.high)}, got {text!r}"
            )
        return value


MINUTES = Number(float, positive=True, high=MAX_BUDGET_MIN)  # budgets and intervals, minutes


def check_numbers(parser: argparse.ArgumentParser) -> None:
    """Give every int or float option of ``parser`` and its subcommands the default
    :class:`Number` check (finite, 0 .. :data:`MAX_FLAG_VALUE`)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                check_numbers(sub)
        elif action.type in (int, float):
            action.type = Number(action.type)


def field_default(cls: type, name: str) -> Any:
    """The default of dataclass field ``cls.name``."""
    for f in dataclasses.fields(cls):
        if f.name == name:
            if f.default is not dataclasses.MISSING:
                return f.default
            if f.default_factory is not dataclasses.MISSING:
                return f.default_factory()
            raise TypeError(f"{cls.__name__}.{name} has no default")
    raise TypeError(f"{cls.__name__} has no field {name!r}")


def show(value: Any) -> str:
    """A default as the help text shows it."""
    if isinstance(value, (tuple, list)):
        return " ".join(show(v) for v in value)
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def with_default(help: str, default: Any) -> str:
    return (
        help
        if default is None or isinstance(default, bool)
        else f"{help} (default: {show(default)})"
    )


def add_option(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    flag: str,
    default: Any,
    help: str,
    **kwargs: Any,
) -> None:
    """``flag`` with a default taken from the library (a module constant), shown in the
    help; ``type`` follows the default unless given."""
    if default is not None and "type" not in kwargs and "action" not in kwargs:
        kwargs["type"] = type(default[0]) if isinstance(default, tuple) else type(default)
    parser.add_argument(flag, default=default, help=with_default(help, default), **kwargs)


def add_field(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    cls: type,
    name: str,
    help: str,
    *,
    flag: str | None = None,
    override: bool = False,
    **kwargs: Any,
) -> None:
    """``--name`` (or ``flag``) for field ``cls.name``, storing to ``args.<name>``.

    ``override``: the option's own default is None ("not given"), so that only flags
    the user gives override a settings file; the help still shows the field's default.
    """
    default = field_default(cls, name)
    option = flag or "--" + name.replace("_", "-")
    kwargs.setdefault("dest", name)
    if isinstance(default, bool) and "action" not in kwargs:
        if default:
            option = flag or "--no-" + name.replace("_", "-")
        kwargs["action"] = "store_false" if default else "store_true"
    elif "action" not in kwargs:
        if "type" not in kwargs and default is not None:
            kwargs["type"] = type(default[0]) if isinstance(default, tuple) else type(default)
        if flag and "choices" not in kwargs:
            kwargs.setdefault("metavar", flag.lstrip("-").replace("-", "_").upper())
    parser.add_argument(
        option,
        default=None if override else default,
        help=with_default(help, default),
        **kwargs,
    )


def add_fields(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    cls: type,
    rows: Iterable[Row],
    **common: Any,
) -> None:
    """One :func:`add_field` per table row; ``common`` keywords go to every row."""
    for row in rows:
        name, help, extra = (*row, {})[:3]
        add_field(parser, cls, name, help, **{**common, **extra})


def given(**values: Any) -> dict[str, Any]:
    """The keyword arguments whose value is not None: options the user gave, leaving the
    called function's own defaults for the others."""
    return {k: v for k, v in values.items() if v is not None}


def field_values(args: argparse.Namespace, cls: type, *, given_only: bool = False) -> dict:
    """The parsed values of ``cls``'s fields that ``args`` holds (``given_only``: not None)."""
    names = {f.name for f in dataclasses.fields(cls)}
    return {k: v for k, v in vars(args).items() if k in names and not (given_only and v is None)}
