"""Issue 26: `info` says nothing when all is well (no "warning: None"), and a trained
model's card names its dataset and start model relative to the run, never by the absolute
paths of the machine that trained it."""

from __future__ import annotations

from helpers.train import one_torch_thread  # noqa: F401  (an autouse fixture)

from beadsight.cli import main


def test_info_of_a_healthy_dataset_prints_no_warning(make_dataset, capsys):
    data = make_dataset(presses=2, frames_per_press=20)
    assert main(["info", str(data)]) == 0
    out, err = capsys.readouterr()
    assert "warning" not in out and err == ""
    assert "presses: 2" in out


def test_model_card_records_paths_relative_to_the_run(make_dataset, tmp_path, capsys):
    data = make_dataset(presses=6, frames_per_press=40)
    first, second = tmp_path / "runs" / "first", tmp_path / "runs" / "second"
    train = ["train", "--data", str(data), "--width", "8", "--steps", "1", "--no-progress"]
    train += ["--batch-size", "8"]  # one cheap step: the test is about the recorded paths
    assert main([*train, "--out", str(first)]) == 0
    assert main([*train, "--out", str(second), "--init", str(first / "last.pt")]) == 0
    capsys.readouterr()
    assert main(["info", str(second / "last.pt")]) == 0
    out = capsys.readouterr().out
    assert "dataset: ../../tiny.h5" in out
    assert "initialised_from: ../first/last.pt" in out
    card = [line for line in out.splitlines() if not line.strip().startswith("path:")]
    assert not [line for line in card if str(tmp_path) in line]  # (path: the file asked about)
