"""HDF5 files that lie, against every reader of HDF5 we did not write: datasets (ours and
the reference layout, and the reference import) and live readings files.

Files whose claims would make today's readers allocate tens of GB are opened in a
subprocess with limited address space (tests/helpers/isolated.py), so a reader that trusts the
claim fails its test instead of exhausting the machine.
"""

from __future__ import annotations

import json
from types import SimpleNamespace

import h5py
import numpy as np
import pytest
from data.test_dataset import write_reference_file
from helpers.isolated import run_isolated

from beadsight.cli import main
from beadsight.config import SensorGeometry
from beadsight.data.dataset import FORMAT, DatasetError, open_dataset
from beadsight.h5safe import MAX_FILTER_RATIO, check_dataset
from beadsight.live.recording.readings import ReadingsFileError, ReadingsWriter, open_readings

ROWS = 10**9  # what the forged files claim
SIZE = 32  # image side of the small files, px
COLUMNS = {"force": (), "position": (2,), "valid": (), "timestamp": ()}  # our dataset layout


def claim_rows(path, layout="ours", rows=ROWS):
    """A file of a few hundred KB whose datasets claim ``rows`` rows (~33 GB of columns).

    Four frames are written and the columns hold 4096 real rows (gzip): the
    rest of each claim is not in the file.
    """
    names = {"force": "forces", "timestamp": "time"} if layout == "reference" else {}
    with h5py.File(path, "w") as f:
        if layout == "ours":
            geometry = SensorGeometry(image_size_px=SIZE).to_json()
            f.attrs.update({"format": FORMAT, "format_version": 1, "geometry": geometry})
        frames = f.create_dataset(
            "images" if layout == "reference" else "frames",
            (rows, SIZE, SIZE, 3),
            np.uint8,
            chunks=(1, SIZE, SIZE, 3),
        )
        frames[:4] = 7
        for name, shape in COLUMNS.items():
            ds = f.create_dataset(
                names.get(name, name),
                (rows, *shape),
                bool if name == "valid" else np.float64,
                chunks=(4096, *shape),
                compression="gzip",
            )
            ds[:4096] = 1
    return path


def claim_readings(path, rows=ROWS):
    """A readings file whose columns and maps claim ``rows`` readings; none are written."""
    with h5py.File(path, "w") as f:
        geometry = SensorGeometry(image_size_px=8).to_json()
        f.attrs.update({"format": "beadsight-readings", "format_version": 1, "geometry": geometry})
        for name in ("timestamp_s", "frame_index", "force_n", "has_contact"):
            f.create_dataset(name, (rows,), np.float64, chunks=(1024,))
        for name in ("contact_area_mm2", "latency_s", "reference_force_n"):
            f.create_dataset(name, (rows,), np.float32, chunks=(1024,))
        f.create_dataset("cop_mm", (rows, 2), np.float32, chunks=(1024, 2))
        f.create_dataset("pressure_kpa", (rows, 8, 8), np.float32, chunks=(1, 8, 8))
    return path


def write_readings(path, n=5):
    reading = SimpleNamespace(
        pressure_kpa=np.ones((8, 8), np.float32),
        force_n=1.0,
        cop_mm=np.zeros(2),
        has_contact=True,
        contact_area_mm2=3.0,
        timestamp_s=1.7e9,
        latency_s=0.01,
        frame_index=0,
    )
    with ReadingsWriter(path, SensorGeometry(image_size_px=8)) as w:
        for _ in range(n):
            w.append(reading)
    return path


def test_absurd_row_claims_are_refused_before_any_allocation(tmp_path):
    ours = claim_rows(tmp_path / "ours.h5")
    ref = claim_rows(tmp_path / "ref.hdf5", layout="reference")
    readings = claim_readings(tmp_path / "readings.h5")
    sizes = [p.stat().st_size for p in (ours, ref, readings)]
    assert max(sizes) < 8 << 20  # the files are small; their claims are not
    proc = run_isolated(
        f"""
        import time
        from beadsight.cli import main
        for argv in (["info", {str(ours)!r}], ["info", {str(ref)!r}],
                     ["import-reference", {str(ref)!r}, "--out", {str(tmp_path / "o.h5")!r}],
                     ["to-mcap", {str(readings)!r}, "--out", {str(tmp_path / "r.mcap")!r}]):
            start = time.perf_counter()
            rc = main(argv)
            print("RC", argv[0], rc, f"{{time.perf_counter() - start:.3f}}", flush=True)
        # VmHWM: this process image's peak RSS (ru_maxrss would also count the pytest
        # process it was forked from: rusage survives execve, the address space does not)
        with open("/proc/self/status") as status:
            hwm_kb = next(int(ln.split()[1]) for ln in status if ln.startswith("VmHWM:"))
        print("PEAK_RSS_MB", hwm_kb // 1024)
        """
    )
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    codes = [ln.split()[1:3] for ln in proc.stdout.splitlines() if ln.startswith("RC ")]
    assert codes == [["info", "1"], ["info", "1"], ["import-reference", "1"], ["to-mcap", "1"]]
    errors = [ln for ln in proc.stderr.splitlines() if ": error: " in ln]
    assert len(errors) == 4, proc.stderr
    for line, name in zip(errors, ("frames", "images", "images", "timestamp_s"), strict=True):
        assert f"'{name}' claims shape (1000000000," in line and "the file stores only" in line
    assert f"{ours}: " in errors[0] and f"{ref}: " in errors[1] and f"{readings}: " in errors[3]
    assert not (tmp_path / "o.h5").exists() and not (tmp_path / "r.mcap").exists()
    peak_mb = int(proc.stdout.split("PEAK_RSS_MB")[1])
    assert peak_mb < 1024, proc.stdout  # the libraries, not the claimed rows


def test_the_column_claims_are_checked_too(tmp_path):
    """A column that claims more rows than it stores is refused even if read alone."""
    path = claim_rows(tmp_path / "ours.h5")
    with h5py.File(path) as f:
        with pytest.raises(DatasetError, match=r"'force' claims shape \(1000000000,\) \(7.5 GiB\)"):
            check_dataset(f["force"], "force", path, DatasetError)
        with pytest.raises(DatasetError, match=r"'valid' claims .* stores only"):
            check_dataset(f["valid"], "valid", path, DatasetError)


def test_honest_files_pass_the_checks(tmp_path, make_dataset):
    """Compressed, chunked, contiguous and empty datasets that hold what they claim."""
    path = tmp_path / "honest.h5"
    with h5py.File(path, "w") as f:
        zeros = np.zeros((64, 256, 256, 3), np.uint8)
        for name, chunks in (("zeros", (1, 256, 256, 3)), ("one_chunk", zeros.shape)):
            f.create_dataset(
                name, data=zeros, chunks=chunks, compression="gzip", compression_opts=9
            )
        f.create_dataset(
            "lzf", data=np.zeros((400, 64, 64), np.float32), chunks=(1, 64, 64), compression="lzf"
        )
        f.create_dataset("contiguous", data=np.arange(300_000.0))
        f.create_dataset("partial_chunk", data=np.arange(5000.0), chunks=(4096,))
        f.create_dataset("empty", (0, 64, 64, 3), np.uint8, maxshape=(None, 64, 64, 3))
        f.create_dataset("unwritten_small", (1000,), np.float64)
    with h5py.File(path) as f:
        ratio = f["one_chunk"].nbytes / f["one_chunk"].id.get_storage_size()
        assert 1000 < ratio < MAX_FILTER_RATIO  # deflate of 12 MiB of zeros: near its limit
        for name in f:
            check_dataset(f[name], name, path, DatasetError)
    write_reference_file(tmp_path / "ref.hdf5")
    with open_dataset(tmp_path / "ref.hdf5") as ds:
        assert len(ds) == 90
    with open_readings(write_readings(tmp_path / "r.h5")) as rf:
        assert len(rf) == 5 and rf.pressure_kpa[4].sum() == 64


def test_link_loops_and_links_out_of_the_file(tmp_path):
    write_reference_file(tmp_path / "loop.hdf5", drop=("images",))
    with h5py.File(tmp_path / "loop.hdf5", "a") as f:
        f["images"] = h5py.SoftLink("/more_images")
        f["more_images"] = h5py.SoftLink("/images")
    with pytest.raises(
        DatasetError, match=r"loop.hdf5: 'images' is a link that cannot be followed"
    ):
        open_dataset(tmp_path / "loop.hdf5")

    write_reference_file(tmp_path / "other.hdf5")
    write_reference_file(tmp_path / "external.hdf5", drop=("forces",))
    with h5py.File(tmp_path / "external.hdf5", "a") as f:
        f["forces"] = h5py.ExternalLink(str(tmp_path / "other.hdf5"), "/forces")
    with pytest.raises(
        DatasetError, match=r"external.hdf5: 'forces' is an external link to .*other"
    ):
        open_dataset(tmp_path / "external.hdf5")

    raw = tmp_path / "forces.bin"
    raw.write_bytes(np.full(90, 800.0, np.float32).tobytes())
    write_reference_file(tmp_path / "raw.hdf5", drop=("forces",))
    with h5py.File(tmp_path / "raw.hdf5", "a") as f:
        f.create_dataset("forces", (90,), np.float32, external=[(str(raw), 0, 360)])
    with pytest.raises(
        DatasetError, match=r"raw.hdf5: 'forces' keeps its data in an external file"
    ):
        open_dataset(tmp_path / "raw.hdf5")

    write_readings(tmp_path / "r.h5")
    with h5py.File(tmp_path / "r.h5", "a") as f:
        del f["force_n"]
        f["force_n"] = h5py.SoftLink("/force_n")
    with pytest.raises(ReadingsFileError, match=r"r.h5: 'force_n' is a link that cannot be"):
        open_readings(tmp_path / "r.h5")


def test_directories_and_devices_passed_as_files(tmp_path, capsys):
    folder = tmp_path / "folder.h5"
    folder.mkdir()
    with pytest.raises(DatasetError, match=r"folder.h5: is a directory; expected a dataset file"):
        open_dataset(folder)
    with pytest.raises(ReadingsFileError, match=r"folder.h5: is a directory; expected a readings"):
        open_readings(folder)
    with pytest.raises(DatasetError, match=r"/dev/null: not a regular file"):
        open_dataset("/dev/null")
    assert main(["info", str(folder)]) == 1
    assert "folder.h5: is a directory; expected a dataset file" in capsys.readouterr().err
    assert main(["import-reference", str(folder), "--out", str(tmp_path / "o.h5")]) == 1
    assert "folder.h5: is a directory" in capsys.readouterr().err


def test_oversized_attributes_and_object_datasets(tmp_path):
    write_reference_file(tmp_path / "attr.hdf5", drop=("position",))
    with h5py.File(tmp_path / "attr.hdf5", "a", libver="latest") as f:
        position = f.create_dataset("position", data=np.zeros((90, 2), np.float32))
        position.attrs["unit"] = np.zeros(10**6)  # 7.6 MiB of "metadata" (dense storage)
    with pytest.raises(
        DatasetError, match=r"attr.hdf5: attribute 'unit' of '/position' claims 7.6"
    ):
        open_dataset(tmp_path / "attr.hdf5")

    write_reference_file(tmp_path / "strings.hdf5", drop=("forces",))
    with h5py.File(tmp_path / "strings.hdf5", "a") as f:
        f.create_dataset("forces", data=np.array(["800"] * 90, dtype=h5py.string_dtype()))
    with pytest.raises(DatasetError, match=r"strings.hdf5: 'forces' has dtype object"):
        open_dataset(tmp_path / "strings.hdf5")


def test_readings_claims_are_checked_in_every_column(tmp_path):
    write_readings(tmp_path / "r.h5", n=5)
    with h5py.File(tmp_path / "r.h5", "a") as f:
        geometry = json.loads(f.attrs["geometry"])
        assert geometry["image_size_px"] == 8
        del f["latency_s"]
        f.create_dataset("latency_s", (5 * 10**6,), np.float32, chunks=(1024,))
    with pytest.raises(ReadingsFileError, match=r"r.h5: 'latency_s' claims shape \(5000000,\)"):
        open_readings(tmp_path / "r.h5")
