"""Issue 13 items 5-6: the reference's processed HDF5 layout, written and read back.

The expected layout is the reference's raw_data_process.py (reference-facts section 6):
the names, dtypes, chunking, units (grams), BGR order and attributes its training
scripts read (``images``, ``forces``, ``position``, ``valid``, ``time``; attributes
``sensor_size``, ``contact_radius``, ``force_unit``, ``dist_unit``, ``pixel_mean``,
``pixel_std``, ``average_force``, ...).
"""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from helpers.synthetic_presses import make_press_arrays, synthetic_press_frames

from beadsight.cli import main
from beadsight.config import REFERENCE_G_TO_N, SensorGeometry
from beadsight.data.dataset import open_dataset
from beadsight.data.dataset_writer import DatasetWriter
from beadsight.data.labels import label_maps
from beadsight.data.recording import REFERENCE_CENTRE_XY_MM
from beadsight.data.reference_file import export_reference
from beadsight.files import OutputExistsError

N_INVALID = (0, 1, 2, 150)  # frames with unknown force and position


@pytest.fixture
def ours(tmp_path):
    """Our dataset (RGB, newtons, float64 time) with some invalid frames (NaN labels)."""
    geometry = SensorGeometry(image_size_px=32)
    rng = np.random.default_rng(4)
    force, position = make_press_arrays(4, 40, geometry, rng)
    frames = synthetic_press_frames(force, position, geometry, rng)
    n = len(force)
    valid = np.ones(n, bool)
    valid[list(N_INVALID)] = False
    force[list(N_INVALID)] = np.nan
    position[list(N_INVALID)] = np.nan
    path = tmp_path / "ours.h5"
    with DatasetWriter(path, geometry, fps=30.0, provenance={"source": "test"}) as w:
        w.append(frames, force, position, valid, 1.7e9 + np.arange(n) / 30)
    return path


def test_export_writes_the_reference_layout(ours, tmp_path):
    out = export_reference(ours, tmp_path / "ref.h5")
    with open_dataset(ours) as ds, h5py.File(out, "r") as f:
        n = len(ds)
        assert set(f.keys()) == {"images", "forces", "position", "valid", "time"}
        spec = {
            "images": ((n, 32, 32, 3), np.uint8, (1, 32, 32, 3)),
            "forces": ((n,), np.float32, (1,)),
            "position": ((n, 2), np.float32, (1, 2)),
            "valid": ((n,), np.bool_, (1,)),
            "time": ((n,), np.float32, (1,)),
        }
        for name, (shape, dtype, chunks) in spec.items():
            assert (f[name].shape, f[name].dtype, f[name].chunks) == (shape, dtype, chunks), name
        assert f["images"].compression is None
        rgb = ds.read_frames(0, n)
        np.testing.assert_array_equal(f["images"][()], rgb[..., ::-1])  # BGR
        grams = f["forces"][()]
        ok = ds.valid
        np.testing.assert_allclose(grams[ok], ds.force_n[ok] / REFERENCE_G_TO_N, rtol=1e-6)
        assert (grams[~ok] == 0).all()  # the reference's force outside its logs
        pos = f["position"][()]
        np.testing.assert_allclose(pos[ok], ds.position_mm[ok], rtol=1e-6, atol=1e-5)
        centre = np.float32(REFERENCE_CENTRE_XY_MM)
        np.testing.assert_allclose(pos[~ok], np.broadcast_to(-1 - centre, (len(N_INVALID), 2)))
        np.testing.assert_array_equal(f["valid"][()], ds.valid)
        np.testing.assert_array_equal(f["time"][()], ds.timestamp_s.astype(np.float32))
        attrs = dict(f.attrs)
        assert attrs["force_unit"] == "g" and attrs["dist_unit"] == "mm"
        np.testing.assert_array_equal(attrs["resolution"], [32, 32])
        np.testing.assert_array_equal(attrs["sensor_size"], [41, 41])
        assert attrs["contact_radius"] == 6.25 and attrs["radius"] == 13.75 and attrs["fps"] == 30
        np.testing.assert_allclose(attrs["center"], REFERENCE_CENTRE_XY_MM)
        assert (attrs["start_time"], attrs["end_time"], attrs["compression_level"]) == (0, -1, 0)
        bgr = f["images"][()].reshape(-1, 3).astype(np.float64)
        np.testing.assert_allclose(attrs["pixel_mean"], bgr.mean(0), rtol=1e-9)
        np.testing.assert_allclose(attrs["pixel_std"], bgr.std(0), rtol=1e-6)
        assert attrs["average_force"].dtype == np.float32
        assert attrs["average_force"] == np.mean(grams)


def test_round_trip_gives_identical_labels(ours, tmp_path):
    """ours -> reference layout -> our reader: the same frames, presses and label maps."""
    out = export_reference(ours, tmp_path / "ref.h5")
    with open_dataset(ours) as a, open_dataset(out) as b:
        assert b.is_reference and b.channel_order == "BGR" and len(a) == len(b)
        assert a.geometry == b.geometry and b.fps == a.fps
        np.testing.assert_array_equal(b.read_frames(0, len(b)), a.read_frames(0, len(a)))
        np.testing.assert_array_equal(b.valid, a.valid)
        np.testing.assert_array_equal(b.contact, a.contact)
        np.testing.assert_array_equal(b.press_id, a.press_id)
        np.testing.assert_array_equal(b.presses, a.presses)
        assert a.num_presses == 4
        ok = a.valid
        index = np.flatnonzero(ok)
        maps_a = label_maps(a.force_n[index], a.position_mm[index], a.contact[index], a.geometry)
        maps_b = label_maps(b.force_n[index], b.position_mm[index], b.contact[index], b.geometry)
        assert (maps_a > 0).sum() > 1000
        np.testing.assert_array_equal(maps_a > 0, maps_b > 0)  # the same disks, pixel for pixel
        # The layout stores grams and mm as float32 (6e-8 relative): interior pixels agree
        # to that, and the anti-aliased rim pixels move by at most 1e-4 kPa.
        np.testing.assert_allclose(maps_b, maps_a, rtol=1e-6, atol=1e-4)
        inside = maps_a > 0.999 * maps_a.max(axis=(1, 2), keepdims=True)
        np.testing.assert_allclose(maps_b[inside], maps_a[inside], rtol=1e-6)
        np.testing.assert_allclose(b.force_n[ok], a.force_n[ok], rtol=1e-6)
        np.testing.assert_allclose(b.position_mm[ok], a.position_mm[ok], atol=1e-5)
        np.testing.assert_allclose(b.rgb_pixel_stats()[0], a.rgb_pixel_stats()[0], rtol=1e-9)


def test_export_cli_refuses_to_overwrite_and_compresses(ours, tmp_path, capsys):
    out = tmp_path / "ref.h5"
    args = ["export-dataset", str(ours), "--format", "reference", "--out", str(out)]
    assert main(args) == 0
    assert "reference layout" in capsys.readouterr().out
    stamp = out.stat().st_mtime_ns
    assert main(args) == 1
    assert "already exists" in capsys.readouterr().err and out.stat().st_mtime_ns == stamp
    assert main([*args, "--overwrite", "--compression-level", "4"]) == 0
    with h5py.File(out, "r") as f:
        assert f["images"].compression == "gzip" and f["images"].compression_opts == 4
        assert f.attrs["compression_level"] == 4
    with pytest.raises(OutputExistsError, match="is a folder"):
        export_reference(ours, tmp_path)
    assert not list(tmp_path.glob("*.partial"))


def test_info_on_a_reference_file_derives_duration_from_frames(ours, tmp_path, capsys):
    """Item 5: float32 unix time has 128 s steps; duration = frames / fps, with a warning."""
    out = export_reference(ours, tmp_path / "ref.h5")
    assert main(["info", str(out), "--json"]) == 0
    captured = capsys.readouterr()
    summary = json.loads(captured.out.splitlines()[-1])
    assert summary["format"] == "reference" and summary["frames"] == 160
    assert summary["duration_s"] == pytest.approx(160 / 30)
    assert summary["duration_from"] == "frame count / fps"
    assert "float32" in captured.err and "spaced 128 s apart" in captured.err
    assert main(["info", str(ours), "--json"]) == 0  # our float64 times: from the timestamps
    captured = capsys.readouterr()
    summary = json.loads(captured.out.splitlines()[-1])
    assert summary["duration_s"] == pytest.approx(159 / 30)
    assert summary["duration_from"] == "timestamps" and "warning" not in captured.err
