"""The rest file (.npz): written and read back, refused by name when it is not one, and
checked for size before any array is read (issue 26, item 3: a small file must not make
the reader allocate what its headers claim)."""

from __future__ import annotations

import io
import struct
import tracemalloc
import zipfile

import numpy as np
import pytest
from helpers.isolated import run_isolated

from beadsight.data.rest import (
    REST_FILE_MAX_PX,
    RestFileError,
    RestReference,
    average_rest,
    load_rest_file,
)

IMAGE = np.random.default_rng(0).integers(0, 256, (64, 64, 3), dtype=np.uint8)
MOST = REST_FILE_MAX_PX * REST_FILE_MAX_PX * 3  # bytes a rest image may hold


def npy_header(shape: tuple[int, ...], descr: str = "|u1") -> bytes:
    """A .npy version 1.0 header claiming ``shape`` of ``descr``."""
    text = f"{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape!r}, }}"
    text += " " * (-(10 + len(text) + 1) % 64) + "\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text.encode("latin1")


def npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


def write_npz(path, members: dict[str, bytes], compress: bool = False) -> None:
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with zipfile.ZipFile(path, "w", method) as z:
        for name, data in members.items():
            z.writestr(f"{name}.npy", data)


def good_members(**changes: bytes) -> dict[str, bytes]:
    members = {
        "version": npy(np.int64(2)),
        "image": npy(IMAGE),
        "frames": npy(np.int64(8)),
        "taken_at_s": npy(np.float64(12.5)),
    }
    return {**members, **changes}


def test_a_rest_reference_round_trips(tmp_path):
    rest = RestReference(average_rest(np.stack([IMAGE, 255 - IMAGE])), 2, 3.25, "start-up")
    path = rest.save(tmp_path / "rest.npz")
    back = load_rest_file(path, image_size=64)
    np.testing.assert_array_equal(back.image, rest.image)
    assert (back.frames, back.taken_at_s, back.origin) == (2, 3.25, "file")
    with pytest.raises(RestFileError, match=r"the image is 64x64 px but the model expects 128x128"):
        load_rest_file(path, image_size=128)


@pytest.mark.parametrize(
    "members, message",
    [
        (good_members(image=npy(IMAGE.astype(np.float32))), "field 'image' has dtype float32"),
        (good_members(image=npy(IMAGE[..., :2])), r"field 'image' has shape \(64, 64, 2\)"),
        (good_members(image=npy(IMAGE[:, :32])), "the image is 32x64 px; expected a square"),
        (good_members(version=npy(np.int64(1))), "version 1, expected 2"),
        (good_members(frames=npy(np.int64(0))), "frames must be >= 1"),
        ({k: v for k, v in good_members().items() if k != "image"}, "field 'image' is missing"),
        (good_members(image=npy_header((64, 64, 3)) + b"\0" * 100), "100 bytes of data, 12288"),
        (good_members(image=npy(np.array([IMAGE], dtype=object))), "'image' has dtype object"),
        (good_members(image=b"not numpy at all"), "field 'image': not a readable .npy array"),
    ],
)
def test_a_bad_rest_file_is_refused_by_name(tmp_path, members, message):
    path = tmp_path / "bad.npz"
    write_npz(path, members)
    with pytest.raises(RestFileError, match=message) as e:
        load_rest_file(path)
    assert str(path) in str(e.value)


def test_files_that_are_not_rest_files(tmp_path):
    text = tmp_path / "text.npz"
    text.write_text("not a rest file")
    with pytest.raises(RestFileError, match=r"text.npz: not an .npz file"):
        load_rest_file(text)
    with pytest.raises(RestFileError, match="is a folder"):
        load_rest_file(tmp_path)
    with pytest.raises(FileNotFoundError):
        load_rest_file(tmp_path / "missing.npz")


def _peak_while(load) -> tuple[Exception, int]:
    tracemalloc.start()
    try:
        try:
            load()
        except RestFileError as e:
            error = e
        else:
            raise AssertionError("the file was accepted")
        return error, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_a_header_claiming_7_tib_is_refused_before_any_allocation(tmp_path):
    path = tmp_path / "claims.npz"
    side = 1 << 20  # (1 Mi, 2.33 Mi, 3) uint8: 7 TiB
    write_npz(path, good_members(image=npy_header((side, side, 7), "|u1")))
    error, _ = _peak_while(lambda: load_rest_file(path))
    assert "field 'image' has shape (1048576, 1048576, 7)" in str(error)
    write_npz(path, good_members(image=npy_header((side, side * 7 // 3, 3), "|u1")))
    error, peak = _peak_while(lambda: load_rest_file(path))
    assert "declares shape (1048576, 2446677, 3) uint8 (7696580345856 bytes)" in str(error)
    assert f"at most {MOST} bytes are expected" in str(error)
    assert peak < 1 << 20, peak  # nothing was allocated for the claim


def test_a_small_compressed_file_cannot_inflate(tmp_path):
    """A 0.3 MB .npz whose image member inflates to 1000 times that, far more than its
    header declares (a zip bomb), is refused from the zip directory's size before any of
    it is read."""
    path = tmp_path / "bomb.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=6) as z:
        for name, data in good_members().items():
            if name != "image":
                z.writestr(f"{name}.npy", data)
        with z.open("image.npy", "w", force_zip64=True) as f:
            f.write(npy_header((64, 64, 3)))
            chunk = bytes(64 << 20)
            for _ in range(4):  # 256 MiB of zeros after the header
                f.write(chunk)
    assert path.stat().st_size < 1 << 20
    error, peak = _peak_while(lambda: load_rest_file(path))
    assert "field 'image' claims 268435584 bytes; at most 3145728 bytes of data" in str(error)
    assert peak < 1 << 20, peak


def test_live_and_health_refuse_a_forged_rest_file_with_a_named_error(tmp_path):
    path = tmp_path / "claims.npz"
    write_npz(path, good_members(image=npy_header((1 << 20, 1 << 21, 3))))
    proc = run_isolated(
        f"""
        import resource
        from beadsight.cli import main
        rc = main(["health", "--rest", {str(path)!r}, "--backend", "torch", "--seconds", "1"])
        print("RC", rc, "PEAK_RSS_MB", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss >> 10)
        """
    )
    assert "RC 1 " in proc.stdout, proc.stdout + proc.stderr[-2000:]
    assert f"rest file {path}: field 'image' declares shape (1048576, 2097152, 3)" in proc.stderr
    assert int(proc.stdout.split("PEAK_RSS_MB")[1]) < 1024, proc.stdout
