"""The figures of benchmarks/live_response.py and benchmarks/steady_press.py, on made-up
readings whose answers are known; benchmarks/live_offline.py end to end on a tiny
simulated dataset; benchmarks/live_rest.py on the simulator's first press;
benchmarks/input_stage.py on a small rest-referenced model."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from beadsight.live.recording.readings import open_readings

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
FPS = 30.0


def benchmark(name: str):
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def presses(n: int = 3) -> np.ndarray:
    """The true force of ``n`` presses: 1 s rest, 0.5 s up to 6 N, 1 s held, 0.5 s down."""
    one = np.concatenate(
        [np.zeros(30), np.linspace(0, 6, 15), np.full(30, 6.0), np.linspace(6, 0, 15)]
    )
    return np.concatenate([np.tile(one, n), np.zeros(30)])


def test_live_response_measures_a_known_lag_error_and_latch():
    live = benchmark("live_response")
    true = presses()
    t = np.arange(len(true)) / FPS
    noise = np.random.default_rng(0).normal(0, 1e-3, len(t))  # no two readings alike
    late = np.concatenate([np.zeros(2), true[:-2]]) + noise  # 2 frames late
    got = live.response(t, late, true, np.full(len(t), 0.004))
    assert got["presses"] == 3 and got["missed"] == 0
    assert got["onset_lag_ms_median"] == pytest.approx(66.7, abs=0.1)
    assert got["release_lag_ms_max"] == pytest.approx(66.7, abs=0.1)
    assert got["repeated_pct"] == 0 and got["latency_ms_median"] == 4.0
    low = live.response(t, 0.9 * true, true, np.zeros(len(t)))  # 10 % low, on time
    assert low["force_error_pct"] == pytest.approx(10.0) and low["onset_lag_ms_max"] == 0
    latched = late.copy()
    latched[(true > 2) & (np.arange(len(true)) % 10 != 0)] = 5.0  # the same value again
    assert live.response(t, latched, true, np.zeros(len(t)))["repeated_pct"] > 70
    blip = late.copy()
    blip[np.searchsorted(t, 3.36) : np.searchsorted(t, 3.46)] = 1.5  # at rest, before press 2
    got = live.response(t, blip, true, np.zeros(len(t)))
    assert got["release_lag_ms_max"] == pytest.approx(66.7, abs=0.1)  # not the blip
    assert got["unloaded_over_1n_pct"] == pytest.approx(100 * 3 / (true == 0).sum(), abs=0.01)
    nothing = live.response(t, np.zeros(len(t)), true, np.zeros(len(t)))
    assert nothing["missed"] == 3 and nothing["onset_lag_ms_median"] is None


def test_steady_press_judges_the_held_frames_and_counts_rests_under_load():
    steady = benchmark("steady_press")
    t = np.arange(0, 20, 1 / FPS)
    captured = 1000 + t / 4  # frames read 4 times faster than the camera rate
    true = np.where((t > 5) & (t < 15), 6.0, 0.0)
    published = np.where(true > 0, 5.7, 0.0)  # 5 % low throughout
    rows = list(zip(t, captured, published, true, ["ok"] * len(t), strict=True))
    result = steady.judge(rows, [1000.25, 1000.5, 1004.0])
    assert result.max_deviation_pct == pytest.approx(5.0) and result.rests_while_loaded == 0
    assert result.seconds == pytest.approx(10 - 1.5, abs=0.1)
    assert steady.judge(rows, [1001.3, 1003.8]).rests_while_loaded == 2  # t = 5.2 s, 15.2 s
    assert steady.judge(rows, [1003.8 + 8 / FPS / 4]).rests_while_loaded == 0  # t = 15.47 s


def test_live_offline_scores_both_rows_on_a_simulated_dataset(tmp_path, capsys):
    """End to end through the real CLI: simulate, evaluate, live replay, compare."""
    from helpers.cli import beadsight_ok
    from helpers.live import tiny_model

    data = tmp_path / "sim.h5"
    simulate = ["simulate", "--presses", "1", "--image-size", "64", "--out", str(data)]
    # 15 fps: the press lasts as long (the replay is real time) in half the frames to score
    beadsight_ok(*simulate, "--fps", "15", "--no-progress")
    checkpoint = tiny_model().save(tmp_path / "tiny.pt")
    argv = [str(data), "--checkpoint", str(checkpoint), "--work", str(tmp_path / "work")]
    argv += ["--backend", "torch"]  # live's auto would time every runtime first
    capsys.readouterr()
    benchmark("live_offline").main(argv)
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[1].startswith("offline ") and lines[2].startswith("live ")  # both rows
    figures = json.loads(lines[-1])
    rows, why = figures["rows"], figures["why"]
    assert rows["offline"]["frames"] > 0 and rows["live"]["frames"] > 0
    with open_readings(tmp_path / "work" / "live.h5") as rf:
        assert why["readings"] == len(rf)
    valid = why["valid_frames"]
    assert rows["live"]["coverage"] == pytest.approx(rows["live"]["frames"] / valid, abs=1e-4)
    assert rows["live"]["frames"] + why["valid_frames_without_reading"] == valid
    compared = rows["live_on_offline_frames"]["frames"]
    assert compared == rows["offline_on_live_frames"]["frames"] == why["compared_with_offline"]
    assert compared + why["readings_offline_does_not_score"] == rows["live"]["frames"]
    assert why["differ_from_offline"] == (
        why["differ_after_a_late_frame"] + why["differ_without_a_late_frame"]
    )
    offline = json.loads((tmp_path / "work" / "offline" / "metrics.json").read_text())
    assert rows["offline"]["mae_kpa"] == offline["mae_kpa"]
    assert rows["offline"]["frames"] == offline["frames"]
    assert figures["offline_backend"] == figures["live_backend"] == "torch/fp32"


def test_train_speed_compares_variants_of_the_real_step(monkeypatch):
    speed = benchmark("train_speed")
    monkeypatch.setattr(speed, "STORE_FRAMES", 40)
    monkeypatch.setattr(
        sys,
        "argv",
        [
            "train_speed.py",
            "--size",
            "16",
            "--widths",
            "4",
            "--batch",
            "2",
            "--rounds",
            "2",
            "--steps",
            "1",
            "--warmup",
            "1",
            "--variants",
            "main",
            "t1+now",
            "now",
        ],
    )
    args = speed.parse_args()
    rows = speed.run_variants(args, speed.torch.device("cpu"))
    assert [r["variant"] for r in rows] == ["main", "t1+now", "now"]
    assert rows[0]["speedup"] == 1.0 and rows[1]["threads"] == [1]
    assert set(rows[2]["threads"]) <= {1, speed.torch.get_num_threads()}  # the tuner's choice
    for r in rows:
        assert r["width"] == 4 and r["samples_per_s"] > 0 and len(r["samples_per_s_rounds"]) == 2
        assert r["cpu_ms_per_sample"] > 0
    with pytest.raises(SystemExit, match="unknown lever"):
        speed.Variant.parse("now+nope")


def test_live_rest_reads_one_session_live_and_with_the_offline_rest(rest_model, tmp_path, capsys):
    live_rest = benchmark("live_rest")
    checkpoint = rest_model.save(tmp_path / "rest.pt")
    argv = ["--checkpoint", str(checkpoint), "--seeds", "0", "--readings", "180"]
    live_rest.main([*argv, "--backend", "torch", "--json"])  # the session's first press
    figures = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    rows = figures["seeds"]["0"]
    assert set(rows) == {"live", "offline_rest"}
    assert rows["live"]["presses"] == rows["offline_rest"]["presses"] == 1  # the same frames
    assert figures["mean"]["live"]["presses"] == 1


def test_live_rest_refuses_a_model_without_a_rest_input(tmp_path, capsys):
    from helpers.live import tiny_model

    from beadsight.errors import ConfigError

    checkpoint = tiny_model().save(tmp_path / "plain.pt")
    live_rest = benchmark("live_rest")
    with pytest.raises(ConfigError, match="plain.pt: not a rest-referenced model"):
        live_rest.compare(checkpoint, seeds=(0,), readings=10, backend="torch")
    with pytest.raises(SystemExit):  # the command line: a usage error, not a traceback
        live_rest.main(["--checkpoint", str(tmp_path / "missing.pt")])
    assert "missing.pt: checkpoint file not found" in capsys.readouterr().err


def test_steady_press_refuses_a_ramp_feed_that_is_not_a_feed(capsys):
    with pytest.raises(SystemExit):  # a usage error naming the option, not a traceback
        benchmark("steady_press").main(["--ramp-feed", "0", "--hold-s", "1"])
    assert "--ramp-feed must be a feed > 0 mm/min, got 0.0" in capsys.readouterr().err


def test_input_stage_streams_both_graphs_alike(rest_model, tmp_path, capsys):
    """The module graph and the plane ring, streamed on the same frames, give the same
    maps (fp32), and the figures come out as one JSON line."""
    checkpoint = rest_model.save(tmp_path / "rest.pt")
    argv = ["--checkpoint", str(checkpoint), "--frames", "30", "--tiers", "openvino fp32"]
    benchmark("input_stage").main([*argv, "--json"])
    figures = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    row = figures["openvino fp32"]
    assert row["max_abs_diff_kpa"] < 1e-3 and row["speedup_p50"] > 0
    assert set(figures["per_frame_ms"]) == {"ring (numpy)", "module steps (torch)"}
    with pytest.raises(SystemExit):  # the command line: a usage error, not a traceback
        benchmark("input_stage").main(["--checkpoint", str(tmp_path / "missing.pt")])
    assert "missing.pt: checkpoint file not found" in capsys.readouterr().err
