"""beadsight predict: datasets and real video files (MJPG .avi written with OpenCV)."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

from beadsight.checkpoint import load_checkpoint
from beadsight.cli import main
from beadsight.data.dataset import open_dataset
from beadsight.data.rest import (
    REST_FRAMES,
    REST_MAX_FORCE_N,
    RestFileError,
    RestReference,
    average_rest,
    rest_ends,
    with_rest,
)
from beadsight.data.windows import WindowBuffer, WindowReader
from beadsight.evaluation.predict import PredictionError, predict_recording
from beadsight.geometry import total_force_n

FPS = 30.0
pytestmark = pytest.mark.usefixtures("one_torch_thread")  # a shared 2-core machine


def write_video(path: Path, frames_bgr: np.ndarray, fps: float = FPS) -> Path:
    h, w = frames_bgr.shape[1:3]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    assert writer.isOpened()
    for frame in frames_bgr:
        writer.write(np.ascontiguousarray(frame))
    writer.release()
    return path


def read_video_rgb(path: Path) -> np.ndarray:
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
    cap.release()
    return np.stack(frames)


def textured_frames(n: int, h: int, w: int, seed: int = 0) -> np.ndarray:
    """Smooth moving pattern (survives MJPG): (n, h, w, 3) uint8."""
    rows, cols = np.mgrid[0:h, 0:w]
    t = np.arange(n)[:, None, None]
    base = 128 + 60 * np.sin(rows[None] / 5.0 + t / 4.0) * np.cos(cols[None] / 7.0)
    rgb = np.stack([base, base[:, ::-1] * 0.8 + 20, 255 - base], axis=-1)
    return np.clip(rgb + seed, 0, 255).astype(np.uint8)


def check_layout(f: h5py.File, n: int, size: int = 64, window: int = 15) -> None:
    assert f["pressure_kpa"].shape == (n, size, size)
    assert f["pressure_kpa"].dtype == np.float32 and f["pressure_kpa"].compression == "gzip"
    for name in ("force_n", "has_pressure", "timestamp_s", "frame_index", "valid"):
        assert f[name].shape == (n,), name
    assert f["cop_mm"].shape == (n, 2)
    np.testing.assert_array_equal(f["frame_index"][()], np.arange(n))
    np.testing.assert_array_equal(f["valid"][()], np.arange(n) >= window - 1)
    has = f["has_pressure"][()]
    cop = f["cop_mm"][()]
    np.testing.assert_array_equal(np.isnan(cop).any(axis=1), ~has)  # NaN only where empty
    assert not f["pressure_kpa"][: window - 1].any()


def test_predict_dataset(make_dataset, tiny_model, tmp_path):
    data = make_dataset(presses=2, frames_per_press=20)
    out = predict_recording(
        tiny_model, data, tmp_path / "pred.h5", device="cpu", batch_size=8, progress=False
    )
    assert out == tmp_path / "pred.h5"
    with open_dataset(data) as ds, h5py.File(out, "r") as f:
        check_layout(f, len(ds))
        np.testing.assert_array_equal(f["timestamp_s"][()], ds.timestamp_s)
        maps = f["pressure_kpa"][()]
        for end in (14, 15, 27, len(ds) - 1):
            expected = tiny_model.predict(ds.read_frames(end - 14, end + 1))
            np.testing.assert_allclose(maps[end], expected, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(
            f["force_n"][()], total_force_n(maps.astype(np.float64), tiny_model.geometry)
        )
        assert f.attrs["input_kind"] == "dataset" and f.attrs["span"] == f.attrs["frames"] == 15
    assert not list(tmp_path.glob("*.partial"))


def test_cli_predict_video(tiny_model, tmp_path, capsys):
    model_file = tiny_model.save(tmp_path / "model.pt")
    n = 24
    video = write_video(tmp_path / "clip.avi", textured_frames(n, 64, 64)[..., ::-1])
    out = tmp_path / "clip_pred.h5"
    code = main(
        [
            "predict",
            "--checkpoint",
            str(model_file),
            "--input",
            str(video),
            "--out",
            str(out),
            "--device",
            "cpu",
            "--batch-size",
            "4",
            "--no-progress",
        ]
    )
    assert code == 0
    captured = capsys.readouterr()
    assert f"{n} frames ({n - 14} with a full window)" in captured.out
    assert "frame/s" not in captured.err
    decoded = read_video_rgb(video)
    assert len(decoded) == n
    with h5py.File(out, "r") as f:
        check_layout(f, n)
        np.testing.assert_allclose(f["timestamp_s"][()], np.arange(n) / FPS)
        assert f.attrs["input_kind"] == "video" and f.attrs["preprocess"] == "none"
        for end in (14, n - 1):
            expected = tiny_model.predict(decoded[end - 14 : end + 1])
            # the CLI ran batches of 4, this one window: group norm sums in another order
            # (1e-5 kPa apart); a window off by one frame differs by far more
            np.testing.assert_allclose(f["pressure_kpa"][end], expected, rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("preprocess", ["none", "auto"])
def test_video_needs_preprocessing(tiny_model, tmp_path, preprocess):
    """Frames neither at the model's size nor from the reference camera (100x80, width x
    height) are refused unless a preprocessing is named: the rule live sensing follows."""
    video = write_video(tmp_path / "raw.avi", textured_frames(16, 80, 100))
    with pytest.raises(PredictionError, match="raw.avi delivers 100x80 frames.*64x64"):
        predict_recording(
            tiny_model,
            video,
            tmp_path / "o.h5",
            preprocess=preprocess,
            device="cpu",
            progress=False,
        )
    assert not (tmp_path / "o.h5").exists() and not list(tmp_path.glob("*.partial"))


def test_video_reference_preprocessing(tiny_model, tmp_path):
    from beadsight.preprocess import Preprocessor

    n = 16
    video = write_video(tmp_path / "raw.avi", textured_frames(n, 80, 100))
    out = predict_recording(
        tiny_model, video, tmp_path / "o.h5", preprocess="reference", device="cpu", progress=False
    )
    pre = Preprocessor.reference(input_hw=(80, 100), output_size=64)
    cap = cv2.VideoCapture(str(video))
    frames = np.stack([pre(cap.read()[1]) for _ in range(n)])
    cap.release()
    with h5py.File(out, "r") as f:
        check_layout(f, n)
        assert f.attrs["preprocess"] == "reference"
        expected = tiny_model.predict(frames[n - 15 :])
        np.testing.assert_allclose(f["pressure_kpa"][n - 1], expected, rtol=1e-5, atol=1e-5)


def test_bad_inputs(tiny_model, make_dataset, tmp_path):
    with pytest.raises(PredictionError, match="missing.avi: input file not found"):
        predict_recording(tiny_model, tmp_path / "missing.avi", tmp_path / "o.h5", progress=False)
    junk = tmp_path / "junk.avi"
    junk.write_bytes(b"this is not a video" * 100)
    with pytest.raises(PredictionError, match="junk.avi"):
        predict_recording(tiny_model, junk, tmp_path / "o.h5", progress=False)
    small = make_dataset(presses=2, frames_per_press=20, image_size=32, name="small.h5")
    with pytest.raises(PredictionError, match="32x32 px.*image_size=64x64"):
        predict_recording(tiny_model, small, tmp_path / "o.h5", progress=False)
    data = make_dataset(presses=2, frames_per_press=20)
    with pytest.raises(PredictionError, match="--preprocess reference"):
        predict_recording(
            tiny_model, data, tmp_path / "o.h5", preprocess="reference", progress=False
        )
    with pytest.raises(PredictionError, match="overwrite the input"):
        predict_recording(tiny_model, data, data, progress=False)
    with pytest.raises(PredictionError, match="--batch-size"):
        predict_recording(tiny_model, data, tmp_path / "o.h5", batch_size=0, progress=False)


def test_failed_run_keeps_existing_output(tiny_model, tmp_path):
    out = tmp_path / "o.h5"
    out.write_bytes(b"previous results")
    junk = tmp_path / "junk.avi"
    junk.write_bytes(b"\x00" * 4096)
    with pytest.raises(PredictionError):
        predict_recording(tiny_model, junk, out, progress=False, overwrite=True)
    assert out.read_bytes() == b"previous results"


def test_short_video_has_no_valid_frames(tiny_model, tmp_path):
    video = write_video(tmp_path / "short.avi", textured_frames(5, 64, 64))
    out = predict_recording(tiny_model, video, tmp_path / "o.h5", device="cpu", progress=False)
    with h5py.File(out, "r") as f:
        assert f["valid"].shape == (5,) and not f["valid"][()].any()
        assert not f["has_pressure"][()].any()


@pytest.mark.parametrize("window", [1, 4])
def test_window_buffer_matches_slicing(window):
    rng = np.random.default_rng(0)
    stream = rng.integers(0, 255, (23, 2, 2, 3), dtype=np.uint8)
    ring = WindowBuffer(window)
    got, pos = [], 0
    for size in (2, 1, 5, 7, 8):
        windows, first = ring.push(stream[pos : pos + size])
        assert len(windows) == size - first
        for k in range(first, size):
            end = pos + k
            assert end >= window - 1
            got.append(end)
            np.testing.assert_array_equal(windows[k - first], stream[end - window + 1 : end + 1])
        pos += size
    assert got == list(range(window - 1, 23))


# --- rest-referenced models -------------------------------------------------------------
def _rest_video(data: Path, tmp_path: Path) -> tuple[Path, np.ndarray]:
    """An MJPG video of frames 32..91 of ``data`` (it starts with the 8 unloaded frames that
    end press 0); returns it and its decoded RGB frames."""
    with open_dataset(data) as ds:
        frames = ds.read_frames(32, 92)
        assert (ds.force_n[32:40] <= REST_MAX_FORCE_N).all()
    video = write_video(tmp_path / "pouch.avi", frames[..., ::-1])
    return video, read_video_rgb(video)


def test_rest_model_on_a_video_rests_on_its_first_frames(rest_run, tmp_path, caplog):
    data, checkpoint = rest_run
    model = load_checkpoint(checkpoint)
    video, decoded = _rest_video(data, tmp_path)
    n, first = len(decoded), REST_FRAMES - 1  # frame 7 ends the rest image (span 3 < 8)
    with caplog.at_level(logging.INFO, logger="beadsight.evaluation.rest_images"):
        out = predict_recording(
            checkpoint, video, tmp_path / "o.h5", device="cpu", batch_size=4, progress=False
        )
    assert f"average of the input's first {REST_FRAMES} frames" in caplog.text
    rest = average_rest(decoded[:REST_FRAMES])
    with h5py.File(out, "r") as f:
        assert f.attrs["rest_source"] == "stream_start" and "rest_file" not in f.attrs
        assert f"first {REST_FRAMES} frames" in f.attrs["rest_note"]
        np.testing.assert_array_equal(f["valid"][()], np.arange(n) >= first)
        maps = f["pressure_kpa"][()]
        assert not maps[:first].any()
        inputs = np.stack([with_rest(rest, decoded[e - 2 : e + 1]) for e in range(first, n)])
        np.testing.assert_allclose(maps[first:], model.predict(inputs), rtol=1e-5, atol=1e-5)


def test_rest_model_on_a_video_with_a_rest_file(rest_run, tmp_path, capsys):
    data, checkpoint = rest_run
    model = load_checkpoint(checkpoint)
    video, decoded = _rest_video(data, tmp_path)
    rest = textured_frames(1, 32, 32, seed=9)[0]  # RGB, the model's size
    png = RestReference(rest, frames=8).save(tmp_path / "rest.npz")
    out = tmp_path / "o.h5"
    argv = ["predict", "--checkpoint", checkpoint, "--input", video, "--out", out, "--rest", png]
    assert main([*map(str, argv), "--device", "cpu", "--no-progress"]) == 0
    assert "and a rest image: file" in capsys.readouterr().out
    n = len(decoded)
    with h5py.File(out, "r") as f:
        assert f.attrs["rest_source"] == "file" and f.attrs["rest_file"] == str(png)
        np.testing.assert_array_equal(f["valid"][()], np.arange(n) >= 2)  # span 3
        inputs = np.stack([with_rest(rest, decoded[e - 2 : e + 1]) for e in range(2, n)])
        expected = model.predict(inputs)
        np.testing.assert_allclose(f["pressure_kpa"][2:], expected, rtol=1e-5, atol=1e-5)
        # not the stream's first frames: the file's image made the difference
        stream = [with_rest(average_rest(decoded[:8]), decoded[e - 2 : e + 1]) for e in (9, 30)]
        assert np.abs(model.predict(np.stack(stream)) - expected[[7, 28]]).max() > 1e-3


def test_rest_model_on_a_dataset_uses_the_dataset_rule(rest_run, tmp_path):
    data, checkpoint = rest_run
    model = load_checkpoint(checkpoint)
    out = predict_recording(checkpoint, data, tmp_path / "o.h5", device="cpu", progress=False)
    with open_dataset(data) as ds, h5py.File(out, "r") as f:
        rests = rest_ends(ds.force_n, ds.valid)
        valid = (np.arange(len(ds)) >= 2) & (rests >= 0)
        assert f.attrs["rest_source"] == "dataset"
        np.testing.assert_array_equal(f["valid"][()], valid)
        ends = np.flatnonzero(valid)
        assert ends.size and not (ds.press_id[ends] == 0).any()
        inputs = WindowReader(ds, 3, rest=True)(ends)
        for k, e in enumerate(ends[[0, ends.size // 2, -1]].tolist()):
            r = int(rests[e])
            rest = average_rest(ds.read_frames(r - REST_FRAMES + 1, r + 1))
            np.testing.assert_array_equal(inputs[[0, ends.size // 2, -1][k], 0], rest)
        maps = f["pressure_kpa"][()]
        np.testing.assert_allclose(maps[ends], model.predict(inputs), rtol=1e-5, atol=1e-5)
        assert not maps[~valid].any()


def test_bad_rest_files_are_named(rest_run, tiny_model, tmp_path, capsys):
    checkpoint = rest_run[1]
    video = write_video(tmp_path / "v.avi", textured_frames(12, 32, 32)[..., ::-1])
    small = RestReference(textured_frames(1, 16, 16)[0]).save(tmp_path / "small.npz")
    wide = RestReference(textured_frames(1, 32, 48)[0]).save(tmp_path / "wide.npz")
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a rest file")
    for path, match in (
        (small, r"rest file .*small\.npz: the image is 16x16 px but the model expects 32x32"),
        (wide, r"rest file .*wide\.npz: the image is 48x32 px; expected a square"),
        (junk, r"rest file .*junk\.npz: "),
        (tmp_path / "missing.npz", r"rest file .*missing\.npz: not found"),
    ):
        with pytest.raises(RestFileError, match=match):
            predict_recording(checkpoint, video, tmp_path / "o.h5", rest=path, progress=False)
    assert not (tmp_path / "o.h5").exists() and not list(tmp_path.glob("*.partial"))
    # a model without rest input refuses --rest; the command line says it in one line
    plain = tiny_model.save(tmp_path / "plain.pt")
    video64 = write_video(tmp_path / "v64.avi", textured_frames(16, 64, 64)[..., ::-1])
    argv = ["predict", "--checkpoint", plain, "--input", video64, "--out", tmp_path / "o.h5"]
    assert main([*map(str, argv), "--rest", str(small), "--no-progress"]) == 1
    assert "not rest-referenced" in capsys.readouterr().err
    argv = ["predict", "--checkpoint", checkpoint, "--input", video, "--out", tmp_path / "o.h5"]
    assert main([*map(str, argv), "--rest", str(small), "--no-progress"]) == 1
    assert "small.npz: the image is 16x16 px" in capsys.readouterr().err
