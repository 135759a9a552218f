"""Issue 26: every numeric flag is finite, in range and bounded (cli.options.Number), so that
`calibrate --budget-min inf` cannot fine-tune without end."""

from __future__ import annotations

import argparse

import pytest

from beadsight.calibrate.config import CalibrateConfig
from beadsight.cli import build_parser, main
from beadsight.cli.options import MAX_BUDGET_MIN, MAX_FLAG_VALUE, Number
from beadsight.config import ConfigError


def _argparse_error(argv, capsys) -> str:
    with pytest.raises(SystemExit) as exit:
        main(argv)
    assert exit.value.code == 2
    return capsys.readouterr().err


@pytest.mark.parametrize("value", ["inf", "nan", "-1", "0", "1e9"])
def test_calibrate_budget_must_be_finite_positive_and_bounded(value, capsys):
    err = _argparse_error(
        ["calibrate", "--data", "d.h5", "--out", "o", "--budget-min", value], capsys
    )
    assert (
        f"argument --budget-min: expected a finite number > 0 and <= {MAX_BUDGET_MIN:g}, "
        f"got '{value}'" in err
    )


@pytest.mark.parametrize(
    ("argv", "flag"),
    [
        (["train", "--data", "d.h5", "--lr", "nan"], "--lr"),
        (
            ["evaluate", "--checkpoint", "c", "--data", "d", "--out", "o", "--batch-size", "-3"],
            "--batch-size",
        ),
        (["simulate", "--out", "s.h5", "--fps", "-30"], "--fps"),
        (["live", "--duration", "inf"], "--duration"),
        (["health", "--seconds", "1e300"], "--seconds"),
    ],
)
def test_every_numeric_flag_is_checked(argv, flag, capsys):
    err = _argparse_error(argv, capsys)
    assert f"argument {flag}: expected a finite number >= 0 and <= {MAX_FLAG_VALUE}" in err


def test_every_int_or_float_option_of_every_command_has_the_check():
    def options(parser):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub in action.choices.values():
                    yield from options(sub)
            else:
                yield action

    typed = [a for a in options(build_parser()) if a.type in (int, float)]
    assert typed == []  # each became a Number
    assert sum(isinstance(a.type, Number) for a in options(build_parser())) > 60


def test_number_parses_ints_and_floats():
    assert Number(int)("12") == 12 and Number(float, positive=True)("0.5") == 0.5
    with pytest.raises(argparse.ArgumentTypeError, match="expected a finite number > 0"):
        Number(float, positive=True)("0")


def test_calibrate_config_refuses_an_infinite_budget():
    with pytest.raises(ConfigError, match="budget_min must be finite and > 0, got inf"):
        CalibrateConfig(data="d.h5", out="o", budget_min=float("inf"))
