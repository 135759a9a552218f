"""benchmarks/foreign_look.py (and the calibration curve it runs) end to end at a tiny size:
real simulated pouches of a held-out look family, the shipped base model, real
``calibrate`` and ``train`` runs of a few seconds. Every family x pouch x count point
lands in the JSON and the tables; a rerun skips the finished points and measures only the
missing ones; a rerun with other settings, or with counts that would reach the test presses, is refused."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "foreign_look.py"
FAMILIES = ("grey_ring",)  # one family: the families are one loop, pouches another
SEEDS = (100, 101)
COUNTS = (0, 3)
TINY = [
    "--families", "grey_ring", "--pouches", "2", "--counts", "0", "3", "--test-presses", "1", "--test-frames", "4",
    "--budget-min", "0.01", "--device", "cpu",
]  # fmt: skip


def bench(out: Path, capsys) -> str:
    """Run the benchmark in this process (as its ``__main__`` does); its stdout."""
    import foreign_look

    capsys.readouterr()
    foreign_look.main([*TINY, "--out", str(out)])
    return capsys.readouterr().out


def model_times(out: Path) -> dict[str, int]:
    """mtime (ns) of every point's model file, by its folder relative to ``out``."""
    files = [*out.glob("*/pouch*/calibrate*/model.pt"), *out.glob("*/pouch*/scratch*/best.pt")]
    return {str(f.parent.relative_to(out)): f.stat().st_mtime_ns for f in files}


@pytest.mark.slow
def test_foreign_look_measures_every_point_and_resumes(tmp_path, monkeypatch, capsys):
    monkeypatch.syspath_prepend(str(SCRIPT.parent))
    out = tmp_path / "fl"
    first = bench(out, capsys)
    summary = json.loads(first.strip().splitlines()[-1])  # the JSON object last
    record = json.loads((out / "foreign_look.json").read_text())
    assert Path(summary["json"]) == out / "foreign_look.json"
    assert (out / "foreign_look.png").stat().st_size > 10_000
    assert record["settings"]["budget_min"] == 0.01 and record["cpu"]
    got = {(p["family"], p["seed"]) for p in record["pouches"]}
    assert got == {(f, s) for f in FAMILIES for s in SEEDS}
    for p in record["pouches"]:
        assert p["presses"] == max(COUNTS) + 1
        assert 0 < p["zero-shot"]["frames"] <= 4 and p["zero-shot"]["mae_kpa"] > 0
        assert set(p["calibrate"]) == {str(n) for n in COUNTS}
        assert set(p["scratch"]) == {"3"}  # from scratch needs presses
        assert p["calibrate"]["0"]["chosen"] == "zero-press"  # rest frames only
        assert p["calibrate"]["0"]["steps"] == 0 and not p["calibrate"]["0"]["fine_tuned"]
        assert p["calibrate"]["3"]["chosen"] in ("zero-shot", "zero-press", "decoder", "all")
        for point in (*p["calibrate"].values(), *p["scratch"].values()):
            assert point["frames"] == p["zero-shot"]["frames"]  # the same fixed test frames
            assert point["seconds"] > 0
    # the tables: one per family, a row per run with both pouches in it, and the kept models
    for family in FAMILIES:
        assert f"\n{family} (seeds 100-101):" in first
    rows = [line for line in first.splitlines() if line.startswith("| ")]
    runs = [r for r in rows if r.split("|")[2].strip() in ("zero-shot", "calibrate", "scratch")]
    runs += [r for r in rows if "calibrate --presses 0" in r]
    assert len(runs) == len(FAMILIES) * 4  # zero-shot, presses 0, calibrate 3, scratch 3
    assert all(r.split("|")[3].strip() == "2" for r in runs)  # both pouches in every mean
    zero = [r for r in runs if "calibrate --presses 0" in r]
    assert len(zero) == len(FAMILIES) and all("| zero-press, zero-press |" in r for r in zero)
    # the targets: 0 presses judged on what was measured, 60 presses not measured
    targets = summary["targets"]
    assert {t["family"] for t in targets} == set(FAMILIES)
    assert all(t["met"] is not None for t in targets if t["target"].startswith("0 presses"))
    assert all(t["met"] is None for t in targets if t["target"].startswith("60 presses"))
    assert summary["all_met"] is None and "not measured" in first

    # resume: drop two points; the rerun measures those two and nothing else
    before = model_times(out)
    for p in record["pouches"]:
        if (p["family"], p["seed"]) == ("grey_ring", 101):
            del p["calibrate"]["3"]
        if (p["family"], p["seed"]) == ("grey_ring", 100):
            del p["calibrate"]["0"]
    (out / "foreign_look.json").write_text(json.dumps(record))
    bench(out, capsys)
    after = model_times(out)
    changed = {k for k in before if after[k] != before[k]}
    assert changed == {"grey_ring/pouch101/calibrate3", "grey_ring/pouch100/calibrate0"}
    again = json.loads((out / "foreign_look.json").read_text())
    for old, new in zip(record["pouches"], again["pouches"], strict=True):
        assert new["zero-shot"] == old["zero-shot"]
        for method in ("calibrate", "scratch"):
            assert {k: new[method][k] for k in old[method]} == old[method]
    assert all(set(p["calibrate"]) == {"0", "3"} for p in again["pouches"])

    # other settings, or counts that would reach the test presses: refused, nothing measured
    import foreign_look

    from beadsight.errors import ConfigError

    args = [*TINY, "--out", str(out)]
    with pytest.raises(ConfigError, match="measured with budget_min 0.01, this run asks 0.1"):
        foreign_look.main([*args, "--budget-min", "0.1"])
    with pytest.raises(ConfigError, match="use another --out for larger counts"):
        foreign_look.main([*args, "--counts", "5"])
    with pytest.raises(SystemExit):  # calibrate needs 3 presses or none
        foreign_look.main([*args, "--counts", "2"])
    assert "--counts must be 0 or >= 3" in capsys.readouterr().err
    assert model_times(out) == after
