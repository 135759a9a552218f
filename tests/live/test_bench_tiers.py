"""`beadsight bench live --tiers`: eager torch, the best fp32 runtime and int8 on one CPU."""

from __future__ import annotations

import json

from beadsight.assets import shipped_model_path
from beadsight.checkpoint import load_checkpoint
from beadsight.inference.int8 import ACCURATE
from beadsight.live.tiers import bench_tiers, tiers_summary


def test_tiers_report_rate_latency_speedup_and_metric_deltas(shared_cache):
    model = load_checkpoint(shipped_model_path())
    # 20 frames: over a dozen readings per tier, enough for a rate and p50/p99
    result = bench_tiers({"shipped": model}, frames=20, cache_dir=shared_cache, threads=None)
    json.dumps(result, allow_nan=False)  # strict JSON: --json prints it
    assert result["cpu"].startswith("CPU: ") and isinstance(result["flags"], list)
    rows = result["shipped"]["tiers"]
    assert [r["tier"] for r in rows] == ["eager torch fp32", "best fp32", "int8"]
    assert rows[0]["backend"] == "torch/fp32" and rows[0]["speedup_vs_eager"] == 1.0
    assert rows[1]["backend"].endswith("/fp32") and rows[2]["backend"] == "int8/int8"
    for row in rows:
        assert row["readings_per_s"] > 0 and 0 < row["p50_ms"] <= row["p99_ms"]
        cam = row["camera"]  # 20 frames offered at 30 Hz on the wall clock
        # paced by the camera, not back to back (every tier runs at over 100/s here); a
        # late first reading and an early last one can lift a dozen readings' mean rate
        # a little above 30 Hz
        assert cam["offered_hz"] == 30 and 0 < cam["readings_per_s"] <= 40
        assert cam["age_p99_ms"] > 0 and cam["skipped_frames"] >= 0
        assert cam["held"] == (cam["skipped_frames"] == 0 and cam["age_p99_ms"] <= 1e3 / 30)
        assert set(row["metric_deltas_pct"]) >= {"mae_kpa", "force_error_pct", "iou"}
    assert (
        rows[0]["metric_parity_ok"] and max(map(abs, rows[0]["metric_deltas_pct"].values())) < 1e-3
    )
    assert rows[1]["metric_parity_ok"]
    # the gate's verdict is its 2 % bound; the default int8 recipe sits about that edge on
    # this model (CoP +1.7 to +4.9 % by CPU and threads: test_int8.py), so either verdict
    # can be right here
    worst = max(map(abs, rows[2]["metric_deltas_pct"].values()))
    assert rows[2]["metric_parity_ok"] == (worst <= 2) and worst < 10
    # int8 runs the first recipe its gate passes (the last one, refused, when none does)
    assert [r["int8_recipe"] for r in rows[:2]] == [None, None]
    assert rows[2]["int8_recipe"] == ACCURATE.key or rows[2]["metric_parity_ok"]
    assert worst > 0  # it is not fp32
    text = tiers_summary(result)
    assert "int8/int8" in text and "metric gate passes" in text and result["cpu"] in text
    assert f"(recipe {rows[2]['int8_recipe']})" in text
    assert "camera 30 Hz" in text and "age p99" in text
