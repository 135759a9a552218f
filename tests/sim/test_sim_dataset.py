"""``simulate_dataset`` and ``beadsight simulate``: the recorded ground truth is the rig's."""

from __future__ import annotations

import numpy as np
import pytest

from beadsight.cli import main
from beadsight.config import REFERENCE_G_TO_N
from beadsight.data.dataset import open_dataset
from beadsight.data.labels import label_maps
from beadsight.geometry import total_force_n
from beadsight.sim import SimConfig, SimulatedSession, SimulationError, simulate_dataset

PRESSES = 3
SEED = 1


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "sim.h5"
    return simulate_dataset(out, PRESSES, seed=SEED, image_size=64, progress=False)


def rerun_session(image_size=64):
    """The same session again, physics and scale only (rendering never changes them)."""
    cfg = SimConfig.preset(100, image_size_px=image_size)
    return list(SimulatedSession(cfg, SEED, PRESSES, render=False))


def test_dataset_is_readable_with_the_right_presses(dataset):
    with open_dataset(dataset) as ds:
        assert ds.num_presses == PRESSES
        assert ds.image_size == 64 and ds.channel_order == "RGB" and ds.fps == 30.0
        assert ds.frames.dtype == np.uint8
        assert ds.timestamp_s.dtype == np.float64 and np.all(np.diff(ds.timestamp_s) > 0)
        sim = ds.provenance["simulator"]
        assert sim["seed"] == SEED and sim["presses"] == PRESSES
        assert SimConfig.from_dict(sim["config"]) == SimConfig.preset(100, image_size_px=64)
        assert ds.provenance["source"] == "sim"
        assert ds.valid.mean() > 0.98 and not ds.valid[0]  # before the scale's first reading
        frames_per_press = len(ds) / PRESSES
        assert 150 < frames_per_press < 260


def test_force_is_the_scales_and_position_is_commanded(dataset):
    frames = rerun_session()
    readings = np.array([r for f in frames for r in f.scale_readings])
    t = np.array([f.timestamp_s for f in frames])
    true_force = np.array([f.true_force_n for f in frames])
    with open_dataset(dataset) as ds:
        assert len(ds) == len(frames)
        assert np.array_equal(ds.timestamp_s, t)
        expected = np.interp(t, readings[:, 0], readings[:, 1]) * REFERENCE_G_TO_N
        assert np.allclose(ds.force_n[ds.valid], expected[ds.valid])
        assert np.array_equal(ds.position_mm, np.stack([f.commanded_xy_mm for f in frames]))
        # Close to the true force, but not it: sampled at 10 Hz, averaged, noisy, drifting.
        err = np.abs(ds.force_n - true_force)[ds.valid]
        assert np.median(err) < 0.1 and err.max() > 0.01


def test_label_maps_integrate_to_the_scale_force(dataset):
    with open_dataset(dataset) as ds:
        idx = np.flatnonzero(ds.contact)
        assert len(idx) > 60
        maps = label_maps(ds.force_n[idx], ds.position_mm[idx], ds.contact[idx], ds.geometry)
        integral = total_force_n(maps, ds.geometry)
        assert np.allclose(integral, ds.force_n[idx], rtol=0.01)
        peaks = [ds.force_n[a:b].max() for a, b in ds.presses]
        assert all(3 < p < 30 for p in peaks)


def test_same_seed_same_dataset(tmp_path, dataset):
    again = simulate_dataset(
        tmp_path / "again.h5", PRESSES, seed=SEED, image_size=64, progress=False
    )
    other = simulate_dataset(tmp_path / "other.h5", 1, seed=SEED + 1, image_size=64, progress=False)
    with open_dataset(dataset) as a, open_dataset(again) as b, open_dataset(other) as c:
        assert np.array_equal(a.frames[:50], b.frames[:50])
        assert np.array_equal(a.force_n, b.force_n)
        assert not np.array_equal(a.frames[:50], c.frames[:50])


def test_bad_arguments(tmp_path, dataset):
    with pytest.raises(SimulationError, match="presses"):
        simulate_dataset(tmp_path / "x.h5", 0)
    with pytest.raises(SimulationError, match="pouches"):
        simulate_dataset(tmp_path / "x.h5", 3, pouches=4)
    with pytest.raises(SimulationError, match="already exists"):
        simulate_dataset(dataset, 1)
    assert not (tmp_path / "x.h5").exists()


def test_simulate_cli(tmp_path, capsys):
    out = tmp_path / "cli.h5"
    argv = [
        "simulate",
        "--out",
        str(out),
        "--presses",
        "2",
        "--seed",
        "3",
        "--beads",
        "75",
        "--image-size",
        "32",
        "--fps",
        "10",  # a third of the frames of 30 fps
        "--pouches",
        "2",
        "--no-progress",
    ]
    assert main(argv) == 0
    assert str(out) in capsys.readouterr().out
    with open_dataset(out) as ds:
        assert ds.num_presses == 2 and ds.image_size == 32 and ds.fps == 10.0
        assert ds.provenance["simulator"]["config"]["n_beads"] == 75
        assert ds.provenance["simulator"]["pouches"] == 2
    assert main(argv) == 1  # refuses to overwrite
    err = capsys.readouterr().err
    assert "already exists" in err and str(out) in err
    assert main([*argv, "--overwrite"]) == 0


def test_sharded_simulation_joins_every_shard_in_order(tmp_path):
    """--workers: each shard is the session of its own seed; the joined file holds every
    shard's frames and labels unchanged, on one increasing clock, and the same seed and
    workers give the same file."""
    # 10 fps: a third of the frames, as good as 30 for joining them.
    kwargs = dict(seed=SEED, image_size=32, fps=10.0, pouches=3, variety="train", progress=False)
    joined = simulate_dataset(tmp_path / "joined.h5", 3, workers=2, **kwargs)
    again = simulate_dataset(tmp_path / "again.h5", 3, workers=2, **kwargs)
    with open_dataset(joined) as d, open_dataset(again) as e:
        shards = d.provenance["simulator"]["shards"]
        assert [(s["presses"], s["pouches"]) for s in shards] == [(2, 2), (1, 1)]
        assert d.num_presses == 3
        assert np.all(np.diff(d.timestamp_s) > 0)
        assert np.array_equal(d.frames[:], e.frames[:])
        first = simulate_dataset(
            tmp_path / "shard0.h5",
            2,
            seed=shards[0]["seed"],
            image_size=32,
            fps=10.0,
            pouches=2,
            variety="train",
            progress=False,
        )
        with open_dataset(first) as s0:
            n = len(s0)
            assert np.array_equal(d.frames[:n], s0.frames[:])
            assert np.array_equal(d.force_n[:n], s0.force_n)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again.h5", "joined.h5", "shard0.h5"]
    with pytest.raises(SimulationError, match="workers"):
        simulate_dataset(tmp_path / "x.h5", 2, workers=0)
