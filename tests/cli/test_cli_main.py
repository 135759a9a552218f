"""The command line itself: help without torch, defaults from the config dataclasses,
one-line user errors and internal errors that say so."""

from __future__ import annotations

import inspect
import json
import os
import subprocess
import sys

import pytest

from beadsight.cli import build_parser, command_name, main
from beadsight.cli.options import field_values

HEAVY = ("torch", "numpy", "cv2", "h5py", "scipy", "cyclonedds", "foxglove")
# `beadsight ARGS` in a fresh child process; prints the heavy modules it loaded.
HELP_PROBE = """
import json, sys
from beadsight.cli import main
try:
    main(json.loads(sys.argv[1]))
except SystemExit:
    pass
print(json.dumps([m for m in HEAVY if m in sys.modules]))
""".replace("HEAVY", repr(HEAVY))


def _subparsers(parser) -> dict:
    """The subcommands' parsers of the ``beadsight`` parser, by name."""
    return parser._subparsers._group_actions[0].choices


def _child_env() -> dict:
    src = os.path.join(os.path.dirname(__file__), "..", "..", "src")
    return {**os.environ, "PYTHONPATH": os.path.abspath(src)}


def _heavy_modules_of(argv: list[str]) -> list[str]:
    done = subprocess.run(
        [sys.executable, "-c", HELP_PROBE, json.dumps(argv)],
        capture_output=True,
        text=True,
        env=_child_env(),
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_help_of_beadsight_and_every_command_imports_no_torch():
    commands = list(_subparsers(build_parser([])))
    assert {"train", "collect", "process", "simulate", "demo", "live", "evaluate"} <= set(commands)
    assert _heavy_modules_of(["--help"]) == []  # `beadsight --help` loads no library at all
    for name in commands:
        heavy = _heavy_modules_of([name, "--help"])
        assert "torch" not in heavy, f"beadsight {name} --help imports torch"
        assert not {"cyclonedds", "foxglove"} & set(heavy), f"beadsight {name} --help: {heavy}"
        if name in (
            "train",
            "calibrate",
            "demo",
            "evaluate",
            "predict",
            "export",
            "info",
            "simulate",
        ):
            assert heavy == [], f"beadsight {name} --help imports {heavy}"


def test_python_m_beadsight_help_imports_no_torch():
    done = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "beadsight", "--help"],
        capture_output=True,
        text=True,
        env=_child_env(),
        timeout=60,
    )
    assert done.returncode == 0 and "train" in done.stdout
    imported = {line.split("|")[-1].strip() for line in done.stderr.splitlines() if "|" in line}
    assert "beadsight.cli" in imported
    assert not {m for m in imported if m.split(".")[0] in HEAVY}


def test_command_name_skips_top_level_options():
    assert command_name(["-v", "train", "--data", "x"]) == "train"
    assert command_name(["--help"]) is None


def _parse(*argv: str):
    return build_parser().parse_args(list(argv))


def test_cli_defaults_are_the_config_dataclasses_defaults():
    from beadsight.data.process.config import ProcessConfig
    from beadsight.demo.config import DemoConfig
    from beadsight.rig.collect import collect
    from beadsight.rig.config import DeviceSpec, VirtualRigSpec
    from beadsight.rig.plan import PressPlan
    from beadsight.sim.config import SimConfig
    from beadsight.train.config import TrainConfig, resolve_train_config

    args = _parse("process", "raw", "--out", "o.h5")
    assert ProcessConfig(**field_values(args, ProcessConfig)) == ProcessConfig()
    assert DemoConfig(**field_values(_parse("demo"), DemoConfig)) == DemoConfig()

    args = _parse("collect", "--out", "x", "--printer", "p", "--scale", "s", "--camera", "0")
    spec = DeviceSpec("p", "s", "0")
    for name in ("printer_baud", "scale_baud", "scale_protocol", "camera_fps"):
        assert getattr(args, name) == getattr(spec, name), name
    assert tuple(args.camera_size) == (spec.camera_width, spec.camera_height)
    rig = VirtualRigSpec()
    assert (args.time_scale, args.camera_mode, args.image_size_px, args.sim_seed) == (
        rig.time_scale,
        rig.camera_mode,
        rig.image_size_px,
        rig.seed,
    )
    signature = inspect.signature(collect).parameters
    assert args.force_limit == signature["force_limit_n"].default == 40.0
    assert args.on_force_limit == signature["on_force_limit"].default
    assert args.scale_timeout == signature["scale_timeout_s"].default
    assert all(
        getattr(args, name) is None for name in ("presses", "pattern", "calibration_presses")
    )
    help_text = _subparsers(build_parser(["collect"]))["collect"].format_help()
    assert f"(default: {PressPlan().presses})" in help_text

    args = _parse("simulate", "--out", "o.h5", "--presses", "2")
    sim = SimConfig()
    assert (args.n_beads, args.image_size_px, args.fps) == (sim.n_beads, sim.image_size_px, sim.fps)

    # train: flags stay None (so that a TOML file can set them); merged, they are the defaults
    args = _parse("train", "--data", "d.h5", "--out", "r")
    assert resolve_train_config(field_values(args, TrainConfig)) == TrainConfig("d.h5", "r")


def test_evaluate_predict_and_live_defaults_are_the_library_defaults():
    from beadsight.evaluation.config import EvaluateConfig
    from beadsight.evaluation.predict import predict_recording
    from beadsight.live.config import LiveRunConfig
    from beadsight.live.outputs.viewer.server import ViewerServer

    def assert_defaults(args, function, *names: str) -> None:
        defaults = inspect.signature(function).parameters
        assert {n: getattr(args, n) for n in names} == {n: defaults[n].default for n in names}

    args = _parse("evaluate", "--checkpoint", "c", "--data", "d", "--out", "o")
    assert_defaults(
        args, EvaluateConfig, "split", "batch_size", "device", "backend", "precision", "max_frames"
    )
    args = _parse("predict", "--checkpoint", "c", "--input", "i", "--out", "o")
    assert_defaults(
        args, predict_recording, "preprocess", "batch_size", "device", "backend", "precision"
    )
    args = _parse("live")
    assert_defaults(args, ViewerServer, "host", "port", "max_fps", "max_kpa")
    config = LiveRunConfig()
    assert (args.foxglove_port, args.max_age, args.ros_namespace) == (
        config.foxglove_port,
        config.max_age_s,
        config.ros_namespace,
    )
    assert config.foxglove_port == 8765  # Foxglove's usual port (issue 27)


def test_user_errors_are_one_line(tmp_path, capsys):
    notes = tmp_path / "notes.txt"
    notes.write_text("not data")
    for verbose in ([], ["-v"]):
        assert main([*verbose, "info", str(notes)]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("beadsight info: error: ")
        assert str(notes) in err[0]
    # a setting a config dataclass refuses
    code = main(["collect", "--virtual", "--out", str(tmp_path / "r"), "--time-scale", "0"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and err == ["beadsight collect: error: time_scale must be > 0, got 0.0"]


def _boom(*args, **kwargs):
    raise KeyError("a bug")


def test_internal_errors_say_so_with_the_traceback_only_under_v(monkeypatch, tmp_path, capsys):
    import beadsight.data.reference_file

    monkeypatch.setattr(beadsight.data.reference_file, "import_reference", _boom)
    argv = ["import-reference", str(tmp_path / "ref.hdf5"), "--out", str(tmp_path / "o.h5")]
    assert main(argv) == 70
    err = capsys.readouterr().err
    assert err.splitlines()[0] == "beadsight import-reference: internal error: KeyError: 'a bug'"
    assert "rerun with -v" in err.lower() and "Traceback" not in err
    assert main(["-v", *argv]) == 70
    err = capsys.readouterr().err
    assert "internal error: KeyError" in err
    assert "Traceback (most recent call last)" in err and "in _boom" in err


@pytest.mark.parametrize("argv", [["nope"], ["train", "--no-such-flag"]])
def test_usage_errors_exit_2(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
