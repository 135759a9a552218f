import json

import h5py
import numpy as np
import pytest

from beadsight.config import SensorGeometry
from beadsight.data.dataset import DatasetError, open_dataset
from beadsight.data.dataset_writer import DatasetWriter
from beadsight.data.reference_file import import_reference


def write_reference_file(path, n=90, size=32, force_g=None, drop=()):
    """A file laid out like the reference processed HDF5 (BGR, grams, float32 time)."""
    rng = np.random.default_rng(0)
    if force_g is None:
        force_g = np.zeros(n)
        force_g[10:30] = 800.0
        force_g[50:70] = 1200.0
    with h5py.File(path, "w") as f:
        data = {
            "images": rng.integers(0, 256, (n, size, size, 3), dtype=np.uint8),
            "forces": np.asarray(force_g, np.float32),
            "position": np.tile(np.float32([[3.0, -2.0]]), (n, 1)),
            "valid": np.ones(n, bool),
            "time": (1.7e9 + np.arange(n) / 30).astype(np.float32),
        }
        for key, value in data.items():
            if key not in drop:
                f.create_dataset(key, data=value)
        f.attrs.update(
            {
                "fps": 30,
                "contact_radius": 6.25,
                "sensor_size": [41, 41],
                "force_unit": "g",
                "dist_unit": "mm",
                "radius": 13.75,
                "pixel_mean": [10.0, 20.0, 30.0],
                "pixel_std": [1.0, 2.0, 3.0],
            }
        )
    return data


def test_round_trip_of_own_format(make_dataset):
    path = make_dataset(presses=4, frames_per_press=40)
    with open_dataset(path) as ds:
        assert len(ds) == 160 and ds.num_presses == 4 and ds.image_size == 64
        assert ds.channel_order == "RGB" and not ds.is_reference
        assert ds.timestamp_s.dtype == np.float64 and np.diff(ds.timestamp_s).min() > 0.03
        assert set(np.unique(ds.press_id)) == {0, 1, 2, 3}
        assert ds.provenance["source"] == "test-fixture" and "beadsight_version" in ds.provenance
        frames = ds.read_frames(0, 5)
        assert frames.shape == (5, 64, 64, 3) and frames.dtype == np.uint8
        np.testing.assert_array_equal(ds.read_frames_at(np.array([4, 0])), frames[[4, 0]])
        mean, std = ds.rgb_pixel_stats()
        all_frames = ds.frames[()].reshape(-1, 3).astype(float)
        np.testing.assert_allclose(mean, all_frames.mean(0), rtol=1e-9)
        np.testing.assert_allclose(std, all_frames.std(0), rtol=1e-6)
    with h5py.File(path) as f:  # stored segmentation matches what the reader computes
        assert f["presses"].shape == (4, 2) and f["force"].attrs["unit"] == "N"
        assert json.loads(f.attrs["geometry"])["image_size_px"] == 64


def test_reference_file_is_read_natively_and_imported(tmp_path):
    data = write_reference_file(tmp_path / "ref.hdf5")
    with open_dataset(tmp_path / "ref.hdf5") as ds:
        assert ds.is_reference and ds.channel_order == "BGR" and ds.num_presses == 2
        np.testing.assert_allclose(ds.force_n[20], 800 * 9.81e-3)
        np.testing.assert_array_equal(ds.read_frames(0, 2), data["images"][:2, ..., ::-1])
        np.testing.assert_allclose(ds.rgb_pixel_stats()[0], [30, 20, 10])
        assert ds.geometry == SensorGeometry(image_size_px=32)
    out = import_reference(tmp_path / "ref.hdf5", tmp_path / "imported.h5")
    with open_dataset(out) as ds:
        assert not ds.is_reference and ds.channel_order == "RGB" and ds.num_presses == 2
        np.testing.assert_array_equal(ds.frames[:2], data["images"][:2, ..., ::-1])
        np.testing.assert_allclose(ds.force_n[20], 800 * 9.81e-3)


def test_crash_mid_write_leaves_readable_partial_file(tmp_path):
    g = SensorGeometry(image_size_px=16)
    w = DatasetWriter(tmp_path / "d.h5", g)
    w.append(
        np.zeros((5, 16, 16, 3), np.uint8),
        np.ones(5),
        np.zeros((5, 2)),
        np.ones(5, bool),
        np.arange(5.0),
    )
    w.abort()  # as if the process died here
    assert not (tmp_path / "d.h5").exists()
    with h5py.File(tmp_path / "d.h5.partial") as f:
        assert f["frames"].shape[0] == 5 and f["force"][4] == 1.0


def test_missing_file_corrupt_and_truncated(tmp_path, make_dataset):
    with pytest.raises(DatasetError, match="nope.h5: dataset file not found"):
        open_dataset(tmp_path / "nope.h5")
    (tmp_path / "text.h5").write_text("hello")
    with pytest.raises(DatasetError, match="text.h5: not a readable HDF5 file"):
        open_dataset(tmp_path / "text.h5")
    good = make_dataset()
    blob = good.read_bytes()
    (tmp_path / "cut.h5").write_bytes(blob[: len(blob) // 3])
    with pytest.raises(DatasetError, match="cut.h5: "):
        open_dataset(tmp_path / "cut.h5")


def test_foreign_and_incomplete_files(tmp_path):
    with h5py.File(tmp_path / "foreign.h5", "w") as f:
        f.create_dataset("spectra", data=np.zeros(3))
    with pytest.raises(DatasetError, match="foreign.h5: not a BeadSight dataset"):
        open_dataset(tmp_path / "foreign.h5")
    write_reference_file(tmp_path / "noforce.h5", drop=("forces",))
    with pytest.raises(DatasetError, match="noforce.h5: missing dataset 'forces'"):
        open_dataset(tmp_path / "noforce.h5")
    with h5py.File(tmp_path / "shape.h5", "w") as f:
        f.create_dataset("images", data=np.zeros((4, 8, 8), np.uint8))
    with pytest.raises(DatasetError, match=r"shape.h5: 'images' has shape \(4, 8, 8\)"):
        open_dataset(tmp_path / "shape.h5")


def test_nan_forces_and_no_presses(tmp_path):
    force = np.zeros(90)
    force[40] = np.nan
    write_reference_file(tmp_path / "nan.h5", force_g=force)
    with pytest.raises(DatasetError, match="nan.h5: field 'force' has 1 NaN/inf values.*frame 40"):
        open_dataset(tmp_path / "nan.h5")
    write_reference_file(tmp_path / "flat.h5", force_g=np.zeros(90))
    with (
        open_dataset(tmp_path / "flat.h5") as ds,
        pytest.raises(DatasetError, match="flat.h5: no presses"),
    ):
        ds.require_presses()


def test_writer_rejects_wrong_frames(tmp_path):
    with DatasetWriter(tmp_path / "w.h5", SensorGeometry(image_size_px=16)) as w:
        with pytest.raises(ValueError, match=r"frames must be \(n, 16, 16, 3\) uint8"):
            w.append(np.zeros((2, 16, 16, 3), np.float32), [0, 0], np.zeros((2, 2)), [1, 1], [0, 1])


def test_info_and_import_cli(tmp_path, capsys):
    from beadsight.cli import main

    write_reference_file(tmp_path / "ref.hdf5")
    assert (
        main(["import-reference", str(tmp_path / "ref.hdf5"), "--out", str(tmp_path / "o.h5")]) == 0
    )
    assert main(["info", str(tmp_path / "o.h5"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert summary["presses"] == 2 and summary["frames"] == 90 and summary["format"] == "beadsight"
    assert main(["info", str(tmp_path / "missing.h5")]) == 1
    assert "missing.h5: dataset file not found" in capsys.readouterr().err
    (tmp_path / "notes.txt").write_text("not data")
    assert main(["info", str(tmp_path / "notes.txt")]) == 1
    assert "notes.txt: neither a dataset (an HDF5 file) nor a checkpoint" in capsys.readouterr().err
