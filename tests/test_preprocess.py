"""Preprocessing: the reference unwarp (constants, bit-exact sampling), resizing, a fitted fisheye lens."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from beadsight.lens import (
    FisheyeLens,
    LensError,
    board_points,
    fit_fisheye_lens,
    load_lens,
)
from beadsight.preprocess import (
    FrameSizeError,
    Preprocessor,
    reference_crop,
    reference_focal_lengths,
    reference_maps,
    reference_source_radius,
    reference_square,
)


def _reference_pixelwise(image: np.ndarray, row: int, col: int) -> np.ndarray:
    """One output pixel of the reference pipeline (before resize), straight from the
    description in reference-facts section 2, computed independently of the module."""
    h, w = image.shape[:2]
    side = min(h, w)
    square = image[h // 2 - side // 2 : h // 2 + side // 2, w // 2 - side // 2 : w // 2 + side // 2]
    c = (side - 1) // 2
    a, b = row + 142, col + 120
    dim = math.sqrt(2) * side
    ofoc = dim / (2 * math.tan(math.radians(60)))
    ifoc = dim * 180 / (180 * math.pi)
    rd = math.hypot(a - c, b - c)
    if rd == 0:
        return square[0, 0]
    rs = ifoc * math.atan(rd / ofoc)
    return square[int((a - c) * rs / rd + c), int((b - c) * rs / rd + c)]


def test_reference_constants():
    assert reference_square((1024, 1280)) == (0, 128, 1024)
    ofoc, ifoc = reference_focal_lengths(1024)
    assert ofoc == pytest.approx(418.05, abs=0.01)
    assert ifoc == pytest.approx(460.96, abs=0.01)
    assert reference_crop(1024) == (142, 120, 750)
    r_d = np.array([0.0, 100.0, 400.0])
    np.testing.assert_allclose(reference_source_radius(r_d), ifoc * np.arctan(r_d / ofoc))


def test_reference_map_radius_law_and_centre():
    rows, cols = reference_maps((1024, 1280), truncate=False)
    centre_sq = 511  # (1024 - 1) // 2, in the square; the square starts at column 128
    # output pixel at the square's centre maps to the centre
    r, c = 511 - 142, 511 - 120
    assert rows[r, c] == pytest.approx(centre_sq)
    assert cols[r, c] == pytest.approx(centre_sq + 128)
    # any pixel: source radius = ifoc * atan(r_d / ofoc), same direction
    ofoc, ifoc = reference_focal_lengths(1024)
    for rr, cc in [(0, 0), (100, 700), (749, 749), (300, 20)]:
        dy, dx = rr + 142 - centre_sq, cc + 120 - centre_sq
        r_d = math.hypot(dy, dx)
        sy, sx = rows[rr, cc] - centre_sq, cols[rr, cc] - 128 - centre_sq
        assert math.hypot(sy, sx) == pytest.approx(ifoc * math.atan(r_d / ofoc), rel=1e-9)
        assert sy * dx == pytest.approx(sx * dy, abs=1e-6)  # radial: same direction


def test_reference_interpolation_is_bit_exact():
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 256, (1024, 1280, 3), dtype=np.uint8)
    pre = Preprocessor.reference(output_size=750, channel_order="BGR")  # no resize
    out = pre(frame)
    assert out.shape == (750, 750, 3)
    for r, c in [(0, 0), (369, 391), (369, 392), (10, 740), (749, 0), (500, 123)]:
        np.testing.assert_array_equal(out[r, c], _reference_pixelwise(frame, r, c))
    # the reference's quirk: the exact centre samples the square's corner pixel
    np.testing.assert_array_equal(out[369, 391], frame[0, 128])


def test_output_is_rgb_and_sized():
    frame = np.zeros((1024, 1280, 3), np.uint8)
    frame[..., 0] = 255  # blue in BGR
    for kwargs in [
        {},
        {"interpolation": "linear"},
        {"resize": "linear"},
        {"interpolation": "linear", "resize": "supersample"},
    ]:
        out = Preprocessor.reference(output_size=64, **kwargs)(frame)
        assert out.shape == (64, 64, 3) and out.dtype == np.uint8
        assert (out[..., 2] == 255).all() and (out[..., :2] == 0).all()


def test_supersample_close_to_exact_area():
    rng = np.random.default_rng(1)
    frame = cv2.GaussianBlur(rng.integers(0, 256, (1024, 1280, 3), dtype=np.uint8), (0, 0), 3)
    exact = Preprocessor.reference(interpolation="linear", resize="area")(frame).astype(float)
    fast = Preprocessor.reference(interpolation="linear", resize="supersample")(frame)
    assert np.abs(exact - fast).mean() < 1.0


def test_reduced_input_matches_full_resolution():
    rng = np.random.default_rng(2)
    frame = cv2.GaussianBlur(rng.integers(0, 256, (1024, 1280, 3), dtype=np.uint8), (0, 0), 4)
    pre = Preprocessor.reference(output_size=128, interpolation="linear", resize="supersample")
    assert pre.max_reduction() == 4  # the 750 px crop still covers >= 128 px at 1/4 scale
    half = pre.for_reduced_input(2)
    assert half.input_hw == (512, 640)
    small = cv2.resize(frame, (640, 512), interpolation=cv2.INTER_AREA)
    diff = np.abs(pre(frame).astype(float) - half(small)).mean()
    assert diff < 2.0
    with pytest.raises(ValueError, match="interpolation='linear'"):
        Preprocessor.reference().for_reduced_input(2)


def test_wrong_frame_size_names_both_sizes():
    pre = Preprocessor.reference(output_size=64)
    with pytest.raises(FrameSizeError, match=r"640x480.*1280x1024"):
        pre(np.zeros((480, 640, 3), np.uint8))
    with pytest.raises(FrameSizeError, match="uint8"):
        pre(np.zeros((1024, 1280, 3), np.float32))
    with pytest.raises(FrameSizeError, match="expected a"):
        pre(np.zeros((1024, 1280), np.uint8))


def test_small_input_scales_crop_and_identity():
    pre = Preprocessor.reference(input_hw=(128, 160), output_size=32)
    assert pre.intermediate_hw == (94, 94)  # 750/1024 of the 128 px square
    assert pre(np.zeros((128, 160, 3), np.uint8)).shape == (32, 32, 3)
    ident = Preprocessor.identity(16, input_hw=(20, 30))
    frame = np.zeros((20, 30, 3), np.uint8)
    frame[:, 5:25] = (0, 0, 200)  # red (BGR) in the centre square
    out = ident(frame)
    assert out.shape == (16, 16, 3) and (out[..., 0] == 200).all()


def test_from_spec():
    assert Preprocessor.from_spec("reference", (1024, 1280), 64).description["kind"] == "reference"
    assert Preprocessor.from_spec("none", (64, 64), 64).description["kind"] == "none"
    with pytest.raises(ValueError, match="expected 'reference'"):
        Preprocessor.from_spec("fancy", (64, 64), 64)


# --- fisheye lens ------------------------------------------------------------------
TRUE_K = np.array([[115.0, 0, 162.5], [0, 116.0, 118.0], [0, 0, 1]])
TRUE_D = np.array([0.05, -0.02, 0.01, -0.003])
PATTERN = (9, 6)
SQUARE_MM = 20.0


def _render_views(count: int, hw=(240, 320), supersample=2, seed=1) -> list[np.ndarray]:
    """Checkerboards seen through the known fisheye model: every (supersampled) pixel is
    undistorted with the true K, D, its ray intersected with the board plane."""
    h, w = hw
    ys, xs = np.mgrid[0 : h * supersample, 0 : w * supersample].astype(np.float64)
    pix = np.stack([(xs + 0.5) / supersample - 0.5, (ys + 0.5) / supersample - 0.5], -1)
    und = cv2.fisheye.undistortPoints(pix.reshape(-1, 1, 2), TRUE_K, TRUE_D).reshape(-1, 2)
    rays = np.hstack([und, np.ones((len(und), 1))])
    rng = np.random.default_rng(seed)
    views = []
    for _ in range(count):
        rvec = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6), rng.uniform(-0.3, 0.3)])
        rot, _ = cv2.Rodrigues(rvec)
        middle = np.array([PATTERN[0] * SQUARE_MM / 2, PATTERN[1] * SQUARE_MM / 2, 0])
        tvec = np.array([rng.uniform(-40, 40), rng.uniform(-30, 30), rng.uniform(110, 150)])
        tvec = tvec - rot @ middle
        normal = rot[:, 2]
        dist = (normal @ tvec) / (rays @ normal)
        board = (rays * dist[:, None] - tvec) @ rot  # board coordinates (mm)
        u, v = np.floor(board[:, 0] / SQUARE_MM + 1), np.floor(board[:, 1] / SQUARE_MM + 1)
        inside = (u >= 0) & (u <= PATTERN[0]) & (v >= 0) & (v <= PATTERN[1]) & (dist > 0)
        value = np.where(inside, np.where((u + v) % 2 == 0, 20.0, 235.0), 128.0)
        img = value.reshape(h * supersample, w * supersample).astype(np.float32)
        views.append(cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA).astype(np.uint8))
    return views


@pytest.fixture(scope="module")
def lens() -> FisheyeLens:
    return fit_fisheye_lens(_render_views(8), PATTERN, SQUARE_MM)


def test_fitting_recovers_the_lens(lens):
    assert lens.views == 8
    assert lens.rms_px < 0.3
    np.testing.assert_allclose(np.diag(lens.K)[:2], np.diag(TRUE_K)[:2], rtol=0.02)
    np.testing.assert_allclose(lens.K[:2, 2], TRUE_K[:2, 2], atol=1.5)
    # the mapping (not the correlated coefficients) is what matters: project rays both ways
    angles = np.linspace(0, 1.0, 30)  # up to ~57 degrees off axis
    pts = np.stack([np.tan(angles), 0.5 * np.tan(angles), np.ones_like(angles)], 1)
    zero = np.zeros(3)
    true_px, _ = cv2.fisheye.projectPoints(pts.reshape(1, -1, 3), zero, zero, TRUE_K, TRUE_D)
    est_px, _ = cv2.fisheye.projectPoints(pts.reshape(1, -1, 3), zero, zero, lens.K, lens.D)
    assert np.abs(true_px - est_px).max() < 1.0


def test_lens_save_load_and_preprocessor(lens, tmp_path):
    path = lens.save(tmp_path / "cal.json")
    loaded = load_lens(path)
    np.testing.assert_allclose(loaded.K, lens.K)
    np.testing.assert_allclose(loaded.D, lens.D)
    assert loaded.image_hw == (240, 320)
    pre = Preprocessor.from_fisheye_lens(
        loaded, 32, pfov_deg=100, undistorted_px=200, crop=(40, 40, 120)
    )
    # the optical axis (undistorted centre) maps to the principal point
    centre = (200 - 1) / 2 - 40  # in crop pixels
    mid = (centre + 0.5) / 120 * pre.map_rows.shape[0] - 0.5
    i = int(round(mid))
    assert pre.map_cols[i, i] == pytest.approx(loaded.K[0, 2], abs=1.0)
    assert pre.map_rows[i, i] == pytest.approx(loaded.K[1, 2], abs=1.0)
    assert pre(np.zeros((240, 320, 3), np.uint8)).shape == (32, 32, 3)
    assert Preprocessor.from_spec(path, (240, 320), 32).description["kind"] == "fisheye-lens"
    with pytest.raises(FrameSizeError, match="320x240"):
        Preprocessor.from_fisheye_lens(loaded, 32, input_hw=(1024, 1280))


def test_lens_errors(tmp_path):
    with pytest.raises(LensError, match="at least 3"):
        fit_fisheye_lens([np.full((60, 80), 128, np.uint8)] * 3, PATTERN, SQUARE_MM)
    bad = tmp_path / "bad.json"
    bad.write_text(
        '{"format": "beadsight-fisheye-calibration", "K": [[1, 0], [0, 1]], '
        '"D": [0, 0, 0, 0], "image_hw": [10, 10]}'
    )
    with pytest.raises(LensError, match=r"bad\.json.*3x3"):
        load_lens(bad)
    bad.write_text("{not json")
    with pytest.raises(LensError, match=r"bad\.json: not valid JSON"):
        load_lens(bad)
    with pytest.raises(LensError, match="not found"):
        load_lens(tmp_path / "missing.json")


def test_board_points_layout():
    pts = board_points((3, 2), 10.0)
    assert pts.shape == (6, 3)
    np.testing.assert_allclose(pts[:4], [[0, 0, 0], [10, 0, 0], [20, 0, 0], [0, 10, 0]])
