"""The calibration press plan: even cover of the pad and the force range for few presses,
inside the safety envelope, deterministic, and used by ``beadsight collect --plan calibration``."""

from __future__ import annotations

import numpy as np
import pytest

from beadsight.cli import main
from beadsight.data.recording import read_events, read_session
from beadsight.rig.plan import PressPlan, envelope_for, low_discrepancy

CENTRE = np.array(PressPlan().centre_xy_mm)


def _layout(plan: PressPlan) -> tuple[np.ndarray, np.ndarray]:
    """(n, 2) offsets from the centre (mm) and (n,) depths of the data presses."""
    targets = [t for t in plan.targets() if t.kind == "press"]
    xy = np.array([(t.x_mm, t.y_mm) for t in targets]) - CENTRE
    return xy, np.array([t.z_mm for t in targets])


@pytest.mark.parametrize("seed", range(16))
def test_every_quadrant_and_depth_band_for_8_presses_or_more(seed):
    for n in range(8, 301):
        xy, z = _layout(PressPlan(presses=n, pattern="calibration", seed=seed))
        quadrants = set(((xy > 0) @ (2, 1)).tolist())  # 0..3: (x > 0, y > 0) as two bits
        bands = set(np.minimum(((z - 127.0) * 4).astype(int), 3).tolist())
        assert quadrants == {0, 1, 2, 3} and bands == {0, 1, 2, 3}, (seed, n)


def test_covers_the_pad_more_evenly_than_random_presses():
    """The largest empty square of a 4x4 grid of pad cells: for 16 presses the calibration
    layout leaves no cell empty; uniform random presses leave several."""

    def empty_cells(xy: np.ndarray, r: float) -> int:
        cells = np.minimum(((xy + r) / (2 * r) * 4).astype(int), 3)
        return 16 - len({tuple(c) for c in cells.tolist()})

    plan = PressPlan(presses=16, pattern="calibration")
    assert empty_cells(_layout(plan)[0], plan.range_mm) <= 1
    random = [empty_cells(_layout(PressPlan(presses=16, seed=s))[0], 13.75) for s in range(20)]
    assert np.mean(random) >= 3


def test_plan_is_deterministic_inside_the_envelope_and_timed():
    plan = PressPlan(presses=30, pattern="calibration", seed=5)
    assert plan.targets() == PressPlan(presses=30, pattern="calibration", seed=5).targets()
    assert plan.targets() != PressPlan(presses=30, pattern="calibration", seed=6).targets()
    envelope = envelope_for(plan)
    for t in plan.targets():
        for z in (plan.z_clear_mm, t.z_mm):
            envelope.check_point((t.x_mm, t.y_mm, z), device="printer")  # raises if outside
    xy, z = _layout(plan)
    assert np.abs(xy).max() <= plan.range_mm and 127.0 <= z.min() and z.max() <= 128.0
    # F200 descent and F700 rise over ~10 mm, 1 s dwell, 0.5 s settle, F700 travel: ~6.5 s
    per_press = plan.duration_s() / plan.total
    assert 5.5 < per_press < 8.0
    u = low_discrepancy(1000, 0)
    assert u.min() >= 0 and u.max() <= 1 and abs(u.mean() - 0.5) < 0.01


def test_collect_cli_runs_the_calibration_plan(tmp_path, capsys):
    out = tmp_path / "raw"
    args = ["collect", "--virtual", "--plan", "calibration", "--presses", "2"]
    args += ["--calibration-presses", "0", "--time-scale", "8", "--virtual-camera", "sensor"]
    args += ["--image-size", "32", "--out", str(out), "--no-progress"]
    assert main(args) == 0
    assert "plan: 2 presses (calibration" in capsys.readouterr().out
    assert read_session(out)["status"] == "complete"
    starts = [e for e in read_events(out) if e.get("event") == "press_start"]
    plan_xy = _layout(PressPlan(presses=2, pattern="calibration", calibration_presses=0))[0]
    got = np.array([e["offset_mm"] for e in starts])
    assert np.allclose(got, plan_xy[: len(got)], atol=1e-6) and len(got) == 2
