"""Sensor health under simulated drift, and the rest reference.

The drift tests run the simulator at rest (the finger above the pouch: the true force is
0 N, so the reading is the simulator's truth) through :class:`SensorWatch`.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from beadsight.errors import BeadSightError
from beadsight.health.checkup import drift_timeline
from beadsight.health.monitor import HealthMonitor, HealthSettings, judge
from beadsight.health.rest import REST_PX, RestAverage, load_rest
from beadsight.sim.config import SimConfig
from beadsight.sim.press import Press
from beadsight.sim.session import SimulatedSession

SIZE = 64
FPS = 30.0


def rest_frames(seconds: float):
    """(t_s, frame) of the simulated pouch at rest for ``seconds``."""
    base = SimConfig(image_size_px=SIZE)
    cfg = dataclasses.replace(base, dwell_s=seconds)
    for record in SimulatedSession(cfg, 0, [Press(0.0, 0.0, cfg.clear_z_mm)]):
        if record.frame_index / FPS > seconds:
            return
        yield record.frame_index / FPS, record.frame_rgb


def states_over(drift: str | None, seconds: float) -> dict[str, float]:
    """First frame time (s) of each health state under ``drift``, at rest."""
    return drift_timeline(drift, seconds, image_size=SIZE)


def test_no_drift_stays_ok():
    first = states_over(None, 8)
    assert set(first) == {"unknown", "ok"} and first["ok"] < 1.5


def test_settling_beads_drift_then_need_recalibration():
    first = states_over("settle,settle_tau_s=6", 16)  # 1.2 mm at the edge, fast
    assert first["ok"] < first["drifting"] < first["recalibrate"] < 16


def test_light_change_drifts_then_needs_recalibration():
    first = states_over("light,light_ramp_s=8", 14)
    assert first["ok"] < first["drifting"] < first["recalibrate"] < 12


@pytest.mark.parametrize("bump_mm, state", [(1.0, "drifting"), (2.0, "recalibrate")])
def test_camera_bump_small_drifts_large_recalibrates(bump_mm, state):
    first = states_over(f"bump,bump_at_s=3,bump_mm={bump_mm}", 6)
    assert first["ok"] < 3 <= first[state] < 5
    assert set(first) == {"unknown", "ok", state}


def test_zero_offset_against_a_saved_rest_reference(tmp_path):
    frames = [f for _, f in rest_frames(1.0)]
    average = RestAverage()
    for f in frames:
        average.add(f, 0.0)
    path = average.reference("auto").save(tmp_path / "rest.npz")
    reference = load_rest(path)
    assert reference.origin == "file" and reference.gray.shape == (REST_PX, REST_PX)
    monitor = HealthMonitor(41.0, HealthSettings(rest_frames=10), reference)
    for i, f in enumerate(frames[:10]):
        report = monitor.add(f, 0.2, i / FPS, rest=True)  # the model reads 0.2 N at rest
    assert report.state == "drifting" and report.figures["zero_offset_n"] == pytest.approx(0.2)
    assert "zero_offset_n" in report.message and report.reference == "file"


def test_bad_rest_file_names_the_field(tmp_path):
    bad = tmp_path / "bad.npz"
    np.savez(bad, version=1, gray=np.zeros((3, 3)), mean_rgb=np.zeros(3), zero_force_n=0.0)
    with pytest.raises(BeadSightError, match="field 'gray' must be finite numbers of shape"):
        load_rest(bad)
    (tmp_path / "text.npz").write_text("not a rest file")
    with pytest.raises(BeadSightError, match="not a rest reference"):
        load_rest(tmp_path / "text.npz")


def test_judge_takes_the_worst_figure_and_says_what_to_do():
    state, message = judge(
        {"bead_creep_mm": 0.1, "camera_shift_mm": 2.0}, HealthSettings().thresholds
    )
    assert state == "recalibrate" and "camera moved" in message
    assert judge({"bead_creep_mm": 0.35}, HealthSettings().thresholds)[0] == "drifting"
