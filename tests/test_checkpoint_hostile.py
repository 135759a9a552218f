"""Checkpoints we did not write and that lie: forged numpy arrays, NaN models, bad metadata.

Loaders of forged arrays run in a subprocess, so that a crash (the failure these
files were built to cause) fails the tests instead of killing pytest. One child runs
the three isolated checks in turn (the ``isolated`` fixture; each test reads its own
part of the output): it imports torch once rather than three times.
"""

from __future__ import annotations

import json
import re
import textwrap
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from helpers.forged_checkpoints import (
    Forged,
    ForgedDtype,
    dtype_state,
    f8_with_object_field,
    object_array_with_cleared_flags,
    save_forged,
)
from helpers.isolated import run_isolated
from helpers.live import tiny_model as make_tiny_model
from helpers.synthetic_presses import write_synthetic_dataset
from test_checkpoint import reference_training_dict

from beadsight import load_checkpoint
from beadsight.checkpoint import (
    CheckpointError,
    checkpoint_summary,
    read_checkpoint_file,
)
from beadsight.cli import main
from beadsight.config import ModelConfig
from beadsight.model import UNet


def reference(width: int = 8, **changes) -> dict:
    ref = reference_training_dict(UNet(ModelConfig(width=width)), 64)
    ref.update(changes)
    return ref


FORGED = {
    "object_flags_cleared": object_array_with_cleared_flags,
    "f8_with_object_field": f8_with_object_field,
    "f8_with_int_field": lambda: Forged(
        (3,),
        ForgedDtype(
            "f8", dtype_state("<", ("x",), {"x": (ForgedDtype("i8", dtype_state("<")), 0)})
        ),
        b"\x00" * 24,
    ),
    "unicode": lambda: Forged((3,), ForgedDtype("U1", dtype_state("<")), b"\x00" * 12),
    "bytes_short_of_shape": lambda: Forged((1000,), ForgedDtype("f8", dtype_state("<")), b"\0" * 8),
    "altered_flags": lambda: Forged(
        (3,), ForgedDtype("f8", dtype_state("<", flags=63)), b"\0" * 24
    ),
}


@pytest.fixture(scope="module")
def forged(tmp_path_factory) -> dict[str, Path]:
    """Reference checkpoints whose pixel_mean is each forged array (only read by the tests)."""
    folder = tmp_path_factory.mktemp("forged")
    return {
        name: save_forged(reference(pixel_mean=make()), folder / f"{name}.pt")
        for name, make in FORGED.items()
    }


def loaders_check(forged: dict[str, Path]) -> str:
    """Child code: every loader on every forged file."""
    return f"""
        from beadsight.checkpoint import (UnsafeCheckpointError, checkpoint_summary,
                                          load_checkpoint, read_checkpoint_file)
        for path in {[str(p) for p in forged.values()]!r}:
            for load in (read_checkpoint_file, load_checkpoint, checkpoint_summary):
                try:
                    load(path)
                    print("LOADED", load.__name__, path)
                except UnsafeCheckpointError as e:
                    print("REFUSED", e)
        """


def test_forged_numpy_arrays_are_refused_by_the_loaders(isolated):
    part = isolated["loaders"]
    assert part.finished and part.returncode == 0, part.stderr
    lines = part.stdout.splitlines()
    assert not [ln for ln in lines if ln.startswith("LOADED")], part.stdout
    for name in FORGED:
        refused = [ln for ln in lines if f"{name}.pt: refused to load" in ln]
        assert len(refused) == 3, (name, part.stdout)
    assert "numpy dtype 'O8' is not a plain numeric" in part.stdout
    assert "f8_with_int_field.pt: refused to load: numpy dtype <f8 with fields" in part.stdout
    assert "needs 8000 bytes but holds 8" in part.stdout


@pytest.fixture(scope="module")
def forged_commands(tmp_path_factory, forged) -> list[list[str]]:
    """info, evaluate, predict, live, train --init and train --resume of a forged array."""
    tmp_path = tmp_path_factory.mktemp("commands")
    data = write_synthetic_dataset(tmp_path / "tiny.h5", presses=2, frames_per_press=20)
    ckpt = str(forged["object_flags_cleared"])
    run = tmp_path / "run"
    run.mkdir()
    (run / "last.pt").write_bytes(Path(ckpt).read_bytes())
    return [
        ["info", ckpt],
        ["evaluate", "--checkpoint", ckpt, "--data", str(data), "--out", str(tmp_path / "ev")],
        ["predict", "--checkpoint", ckpt, "--input", str(data), "--out", str(tmp_path / "p.h5")],
        ["live", "--checkpoint", ckpt, "--frames", "2", "--no-viewer"],
        [
            "train",
            "--data",
            str(data),
            "--out",
            str(tmp_path / "t"),
            "--init",
            ckpt,
            "--steps",
            "1",
        ],
        ["train", "--data", str(data), "--out", str(run), "--resume", "--steps", "1"],
    ]


def commands_check(commands: list[list[str]]) -> str:
    """Child code: each command through the CLI, its exit code printed."""
    return f"""
        from beadsight.cli import main
        for argv in {commands!r}:
            print("RC", argv[0], main(argv), flush=True)
        """


def test_every_command_refuses_a_forged_array(isolated, forged_commands):
    """info, evaluate, predict, live, train --init and train --resume, through the CLI."""
    part = isolated["commands"]
    assert part.finished and part.returncode == 0, part.stderr
    codes = [ln.split()[1:] for ln in part.stdout.splitlines() if ln.startswith("RC ")]
    assert codes == [[argv[0], "1"] for argv in forged_commands], part.stdout
    refused = part.stderr.count(".pt: refused to load: numpy dtype 'O8' is not a plain numeric")
    assert refused == len(forged_commands), part.stderr
    assert "Traceback" not in part.stderr


def test_plain_numpy_arrays_of_every_allowed_kind_still_load(tmp_path):
    arrays = {
        "big_endian": np.arange(6, dtype=">i4").reshape(2, 3),
        "fortran": np.asfortranarray(np.arange(6.0).reshape(2, 3)),
        "bool": np.array([True, False]),
        "empty": np.zeros((0, 3), np.float32),
        "scalar_array": np.array(2.5),
        "complex": np.array([1 + 2j], np.complex64),
        "half": np.array([0.5, 1.5], np.float16),
        "uint8": np.arange(256, dtype=np.uint8),
    }
    scalars = {"f8": np.float64(1.25), "i8": np.int64(-3), "b1": np.bool_(True)}
    ref = reference(extra_arrays=arrays, extra_scalars=scalars, nested=[(np.ones(2),)])
    torch.save(ref, tmp_path / "ref.pt")
    torch.save(ref, tmp_path / "legacy.pt", _use_new_zipfile_serialization=False)
    for name in ("ref.pt", "legacy.pt"):
        loaded = read_checkpoint_file(tmp_path / name)
        for key, want in arrays.items():
            got = loaded["extra_arrays"][key]
            assert type(got) is np.ndarray and got.dtype == want.dtype and got.flags.writeable
            np.testing.assert_array_equal(got, want)
        for key, want in scalars.items():
            got = loaded["extra_scalars"][key]
            assert isinstance(got, np.generic) and got.dtype == want.dtype and got == want
        np.testing.assert_array_equal(loaded["nested"][0][0], np.ones(2))
        assert load_checkpoint(tmp_path / name).meta.output_scale_kpa == pytest.approx(1.8734)


# --- item 13: models that can only output NaN, and malformed metadata ------------------
def _own(tiny_model, path: Path, meta_change=None, weights_change=None) -> Path:
    tiny_model.save(path)
    obj = torch.load(path, weights_only=True)
    if meta_change is not None:
        meta = json.loads(obj["beadsight"])
        obj["beadsight"] = meta_change(meta) if callable(meta_change) else meta_change
        if isinstance(obj["beadsight"], dict):
            obj["beadsight"] = json.dumps(obj["beadsight"])
    if weights_change is not None:
        weights_change(obj["state_dict"])
    torch.save(obj, path)
    return path


def _nan_weight(state: dict) -> None:
    state["C1.layer.0.weight"][0, 0, 0, 0] = float("nan")


def _set(key, value):
    def change(meta: dict) -> dict:
        meta[key] = value
        return meta

    return change


def _set_model(key, value):
    def change(meta: dict) -> dict:
        meta["model"][key] = value
        return meta

    return change


BAD_OWN = {
    "nan_weight": ({"weights_change": _nan_weight}, "weight 'C1.layer.0.weight' has 1 NaN/inf"),
    "inf_weight": (
        {"weights_change": lambda s: s["pred.bias"].fill_(float("inf"))},
        "weight 'pred.bias' has 1 NaN/inf",
    ),
    "zero_std": ({"meta_change": _set("pixel_std", [40.0, 0.0, 40.0])}, "pixel_std is .*> 0"),
    "nan_scale": (
        {"meta_change": _set("output_scale_kpa", float("nan"))},
        "output_scale_kpa is nan",
    ),
    "zero_scale": ({"meta_change": _set("output_scale_kpa", 0.0)}, "output_scale_kpa is 0.0"),
    "one_mean": ({"meta_change": _set("pixel_mean", [120.0])}, "pixel_mean has 1 value"),
    "json_list": ({"meta_change": "[]"}, "metadata is a JSON list; expected an object"),
    "width_1e6": ({"meta_change": _set_model("width", 10**6)}, "width is 1000000 in the metadata"),
    "span_1e6": ({"meta_change": _set_model("frame_stride", 10**6)}, "window spans 14000001"),
    "image_1e6": (
        {"meta_change": lambda m: {**m, "geometry": {**m["geometry"], "image_size_px": 10**6}}},
        "image_size_px is 1000000",
    ),
    "mean_text": ({"meta_change": _set("pixel_mean", "abc")}, "pixel_mean is 'abc'"),
    "provenance_list": ({"meta_change": _set("provenance", [])}, "provenance is not a JSON"),
}
BAD_REFERENCE = {
    "ref_nan_weight": ({"weights_change": _nan_weight}, "weight 'C1.layer.0.weight' has 1"),
    "ref_zero_std": ({"pixel_std": np.array([31.0, 0.0, 33.0])}, "pixel_std is .*> 0"),
    "ref_nan_pressure": ({"avg_pressure": np.float64("nan")}, "avg_pressure is nan"),
    "ref_one_mean": ({"pixel_mean": np.array([101.5])}, "pixel_mean has 1 value"),
    "ref_pressure_shape": ({"avg_pressure": np.array([1873.4])}, r"avg_pressure has shape \(1,\)"),
    "ref_info_list": ({"data_loader_info": ["image_size"]}, "data_loader_info is a list"),
    "ref_dropout_text": ({"dropout_prob": "high"}, "dropout_prob is 'high'; expected a number"),
}


@pytest.fixture(scope="module")
def bad_checkpoints(tmp_path_factory) -> dict[str, tuple[Path, str]]:
    """Only read by the tests: built once for the module."""
    tmp_path, model = tmp_path_factory.mktemp("bad"), make_tiny_model()
    out = {}
    for name, (change, message) in BAD_OWN.items():
        out[name] = (_own(model, tmp_path / f"{name}.pt", **change), message)
    for name, (change, message) in BAD_REFERENCE.items():
        ref = reference()
        if "weights_change" in change:
            change["weights_change"](ref["model_state_dict"])
        else:
            ref.update(change)
        torch.save(ref, tmp_path / f"{name}.pt")
        out[name] = (tmp_path / f"{name}.pt", message)
    return out


def bad_check(bad_checkpoints: dict[str, tuple[Path, str]]) -> str:
    """Child code: load_checkpoint and `info` on each bad checkpoint (width 10^6 among them)."""
    cases = {name: str(path) for name, (path, _message) in bad_checkpoints.items()}
    return f"""
        from beadsight.checkpoint import CheckpointError, load_checkpoint
        from beadsight.cli import main
        for name, path in {cases!r}.items():
            try:
                load_checkpoint(path)
                print(name, "LOADED")
            except CheckpointError as e:
                print(name, "REFUSED", e)
            print(name, "INFO", main(["info", path]))
        """


@pytest.fixture(scope="module")
def isolated(forged, forged_commands, bad_checkpoints) -> dict[str, SimpleNamespace]:
    """Run each check above in one child process, in turn; per check: its stdout, its
    stderr (an exception's traceback included), whether it finished, the exit code."""
    checks = {
        "loaders": loaders_check(forged),
        "commands": commands_check(forged_commands),
        "bad": bad_check(bad_checkpoints),
    }
    checks = {name: textwrap.dedent(code) for name, code in checks.items()}
    proc = run_isolated(
        f"""
        import sys, traceback
        for name, code in {checks!r}.items():
            for stream in (sys.stdout, sys.stderr):
                print("@@ check", name, file=stream, flush=True)
            try:
                exec(code, {{"__name__": "__main__"}})
            except BaseException:
                traceback.print_exc()
            else:
                print("@@ finished", name, flush=True)
            sys.stdout.flush()
            sys.stderr.flush()
        """
    )
    parts = {name: SimpleNamespace(stdout="", stderr="") for name in checks}
    for stream in ("stdout", "stderr"):
        pieces = re.split(r"^@@ check (\w+)\n", getattr(proc, stream), flags=re.M)
        for name, text in zip(pieces[1::2], pieces[2::2], strict=True):
            setattr(parts[name], stream, text)
    for name, part in parts.items():
        part.finished = f"@@ finished {name}" in part.stdout.splitlines()
        part.returncode = proc.returncode
    return parts


def test_bad_models_and_metadata_are_refused_at_load_and_by_info(isolated, bad_checkpoints):
    """Same named error from load_checkpoint and from `info`; run isolated (width 10^6)."""
    part = isolated["bad"]
    assert part.finished and part.returncode == 0, part.stderr[-3000:]
    assert "Traceback" not in part.stderr, part.stderr[-3000:]
    lines = part.stdout.splitlines()
    errors = [ln.split(": error: ", 1)[1] for ln in part.stderr.splitlines() if ": error: " in ln]
    for name, (path, message) in bad_checkpoints.items():
        refused = [ln for ln in lines if ln.startswith(f"{name} REFUSED")]
        assert len(refused) == 1, (name, part.stdout)
        text = refused[0].split(" REFUSED ", 1)[1]
        assert text.startswith(f"{path}: ") and re.search(message, text), (name, text)
        assert f"{name} INFO 1" in lines and text in errors, (name, errors)


def test_predict_and_live_refuse_a_nan_model(bad_checkpoints, make_dataset, tmp_path, capsys):
    data = make_dataset(presses=2, frames_per_press=20)
    for name in ("nan_weight", "zero_std", "nan_scale", "one_mean", "ref_nan_pressure"):
        path = str(bad_checkpoints[name][0])
        out = tmp_path / f"{name}.h5"
        assert main(["predict", "--checkpoint", path, "--input", str(data), "--out", str(out)]) == 1
        assert f"{path}: " in capsys.readouterr().err and not out.exists()
        argv = ["live", "--checkpoint", path, "--frames", "2", "--no-viewer"]
        assert main(argv) == 1
        assert f"{path}: " in capsys.readouterr().err


def test_info_reads_every_checkpoint_load_checkpoint_reads(tmp_path, capsys):
    torch.save(reference(), tmp_path / "legacy.pt", _use_new_zipfile_serialization=False)
    assert load_checkpoint(tmp_path / "legacy.pt").meta.channel_order == "BGR"
    assert main(["info", str(tmp_path / "legacy.pt"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert (
        summary == checkpoint_summary(tmp_path / "legacy.pt") and summary["format"] == "reference"
    )
    (tmp_path / "dir.pt").mkdir()
    with pytest.raises(CheckpointError, match=r"dir\.pt: is a directory; expected a checkpoint"):
        load_checkpoint(tmp_path / "dir.pt")
