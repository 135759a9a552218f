"""Issue 26: SIGTERM (docker stop, systemd) is handled like Ctrl-C by the long-running
commands -- summary printed, recordings finished, no ``.partial`` left -- checked with real
child processes and ``os.kill``."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time

import pytest
from helpers.live import live_argv, press_frames, tiny_model, write_video
from helpers.synthetic_presses import write_synthetic_dataset

from beadsight.data.recording import open_recording, read_events, read_session
from beadsight.live.recording.readings import open_readings

ENV = {**os.environ, "PYTHONUNBUFFERED": "1"}


def _start(args: list[str]) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "beadsight", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=ENV,
    )


def _wait_for(predicate, proc: subprocess.Popen, timeout_s: float = 120) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "the child never got going"
        time.sleep(0.05)


def _terminate(proc: subprocess.Popen) -> tuple[str, str]:
    os.kill(proc.pid, signal.SIGTERM)
    try:
        return proc.communicate(timeout=60)
    finally:
        proc.kill()


def test_live_on_sigterm_prints_its_summary_and_finishes_the_recording(tmp_path):
    frames, _ = press_frames(presses=2, per_press=30)
    video = write_video(tmp_path / "v.avi", frames, fps=30)
    checkpoint = tiny_model().save(tmp_path / "tiny.pt")
    out = tmp_path / "rec.h5"
    more = ["--no-viewer", "--loop", "--output", str(out), "--report-every", "0.2"]
    proc = _start(live_argv(checkpoint, video, *more))
    lines: list[str] = []

    def reported() -> bool:  # a periodic report with readings: they are being recorded
        lines.append(proc.stdout.readline())
        found = re.search(r" (\d+) readings,", lines[-1])
        return found is not None and int(found.group(1)) > 0

    _wait_for(reported, proc)
    stdout, stderr = _terminate(proc)
    stdout = "".join(lines) + stdout
    assert proc.returncode == 0, stderr[-2000:]
    assert "interrupted: stopping" in stdout and "final: " in stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec.h5", "tiny.pt", "v.avi"]
    with open_readings(out) as rf:
        assert len(rf) > 0, stdout


def test_collect_on_sigterm_lifts_the_finger_and_keeps_the_recording(tmp_path):
    out = tmp_path / "raw"
    proc = _start(
        [
            "collect",
            "--virtual",
            "--virtual-camera",
            "sensor",
            "--image-size",
            "64",
            "--time-scale",
            "8",
            "--calibration-presses",
            "0",
            "--no-progress",
            "--presses",
            "20",
            "--out",
            str(out),
        ]
    )

    def pressing() -> bool:
        events = read_events(out) if (out / "events.jsonl").exists() else []
        return any(e["event"] == "press_start" for e in events)

    _wait_for(pressing, proc)
    stdout, stderr = _terminate(proc)
    assert proc.returncode == 130, stderr[-2000:]  # collect's exit code of status "interrupted"
    assert "interrupted" in stdout and "internal error" not in stderr
    assert read_session(out)["status"] == "interrupted"
    rec = open_recording(out)
    assert len(rec.frames) > 0 and not any("truncated" in w for w in rec.warnings)
    assert rec.moves.xyz_mm[-1, 2] == pytest.approx(137.5)  # the last command lifted the finger
    assert not list(out.glob("*.partial"))


def test_train_on_sigterm_saves_last_pt_and_exits_143(tmp_path):
    data = write_synthetic_dataset(tmp_path / "d.h5", 6, 40, 64, 0, 30.0)
    run = tmp_path / "run"
    proc = _start(
        [
            "train",
            "--data",
            str(data),
            "--out",
            str(run),
            "--width",
            "8",
            "--batch-size",  # cheap steps: the test only needs two of them before SIGTERM
            "8",
            "--steps",
            "100000",
            "--log-every-steps",
            "1",
            "--no-progress",
        ]
    )
    metrics = run / "metrics.jsonl"
    _wait_for(lambda: metrics.exists() and metrics.read_text().count("\n") >= 2, proc)
    stdout, stderr = _terminate(proc)
    assert proc.returncode == 143, stderr[-2000:]
    assert "terminated (SIGTERM)" in stderr and "internal error" not in stderr
    assert "interrupted at step" in stderr
    assert (run / "last.pt").is_file()
    assert not list(run.glob(".*.tmp"))
