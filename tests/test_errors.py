"""The error family: what users can cause derives from BeadSightError (printed as one
line by the CLI); errors that were ValueErrors stay ValueErrors for callers catching that."""

from __future__ import annotations

import pytest

from beadsight.checkpoint import CheckpointError, UnsafeCheckpointError
from beadsight.config import ConfigError as ConfigErrorFromConfig
from beadsight.data.dataset import DatasetError
from beadsight.data.recording import RecordingError
from beadsight.devices.base import DeviceError
from beadsight.errors import USER_ERRORS, BeadSightError, ConfigError
from beadsight.files import WriteError
from beadsight.lens import LensError
from beadsight.live.recording.readings import ReadingsFileError
from beadsight.preprocess import FrameSizeError
from beadsight.sim.dataset import SimulationError

FORMERLY_VALUE_ERRORS = (
    ConfigError,
    CheckpointError,
    UnsafeCheckpointError,
    DatasetError,
    FrameSizeError,
    LensError,
    ReadingsFileError,
    SimulationError,
)


@pytest.mark.parametrize("error", [*FORMERLY_VALUE_ERRORS, WriteError, RecordingError, DeviceError])
def test_user_errors_are_beadsight_errors(error):
    assert issubclass(error, BeadSightError)
    assert issubclass(error, USER_ERRORS)


@pytest.mark.parametrize("error", FORMERLY_VALUE_ERRORS)
def test_former_value_errors_are_still_value_errors(error):
    assert issubclass(error, ValueError)


def test_plain_value_errors_are_not_user_errors():
    assert not issubclass(ValueError, USER_ERRORS)
    assert not issubclass(KeyError, USER_ERRORS) and not issubclass(TypeError, USER_ERRORS)


def test_config_error_has_one_home():
    assert ConfigErrorFromConfig is ConfigError


def test_cli_user_error_class_is_gone():
    import beadsight.cli

    assert not hasattr(beadsight.cli, "UserError")
