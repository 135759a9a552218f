"""Simulated drift: the spec text, and what each kind does to frames (measured, not assumed)."""

from __future__ import annotations

import numpy as np
import pytest

from beadsight.errors import ConfigError
from beadsight.sim.config import SimConfig
from beadsight.sim.drift import DriftRenderer, DriftSpec, parse_drift
from beadsight.sim.simulator import PouchSimulator

SIZE = 64


@pytest.fixture(scope="module")
def frame():
    cfg = SimConfig(image_size_px=SIZE)
    return PouchSimulator(cfg, 0).render(), cfg.sensor_size_mm


def test_spec_text_kinds_fields_and_round_trip():
    assert parse_drift(None) == parse_drift("") == parse_drift("none") == DriftSpec()
    spec = parse_drift("settle, bump,bump_at_s=9")
    assert spec.settle and spec.bump and not spec.light and spec.bump_at_s == 9.0
    assert parse_drift("light_change=-0.5").light  # a field enables its kind
    assert parse_drift(spec.describe()) == spec


@pytest.mark.parametrize(
    "text, message",
    [
        ("wobble", "unknown kind 'wobble'"),
        ("bump,bump_at=3", "unknown field 'bump_at'"),
        ("bump_mm=far", "bump_mm must be a number, got 'far'"),
        ("settle=1", "'settle' is a kind; write it without a value"),
        ("settle_tau_s=0", "drift settle_tau_s must be > 0"),
        ("bump_mm=-1", "drift bump_mm must be >= 0"),
        ("light_tint=1.5", "drift light_tint must be in [0, 1)"),
    ],
)
def test_bad_spec_names_the_field(text, message):
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace(")", r"\)")):
        parse_drift(text)


def test_bump_shifts_the_image_by_the_given_mm_at_the_given_time(frame):
    image, size_mm = frame
    spec = parse_drift("bump,bump_at_s=5,bump_mm=2")
    drift = DriftRenderer(spec, SIZE, size_mm)
    assert drift.apply(image, 4.9) is image  # before the bump: untouched
    shifted = drift.apply(image, 5.0).astype(np.float32)
    px = round(2 * SIZE / size_mm)  # 3 px
    inner = slice(8, -8)
    moved = np.abs(shifted[inner, inner] - image[inner, np.arange(SIZE)[inner] - px]).mean()
    still = np.abs(shifted[inner, inner] - image[inner, inner].astype(np.float32)).mean()
    assert moved < 0.5 * still  # the content moved by +x ~3 px


def test_light_ramps_brightness_and_colour(frame):
    image, size_mm = frame
    drift = DriftRenderer(parse_drift("light,light_ramp_s=10"), SIZE, size_mm)
    half, full = drift.apply(image, 5.0), drift.apply(image, 20.0)
    base = image.reshape(-1, 3).mean(0)
    assert full.mean() / image.mean() == pytest.approx(0.6, abs=0.03)  # -40 %
    assert half.mean() / image.mean() == pytest.approx(0.8, abs=0.03)
    r, _, b = full.reshape(-1, 3).mean(0) / base
    assert r / b == pytest.approx(1.2 / 0.8, rel=0.05)


def test_settle_creeps_inward_with_its_time_constant(frame):
    spec = parse_drift("settle,settle_mm=1,settle_tau_s=10")
    assert spec.settle_at(0) == 0 and spec.settle_at(10) == pytest.approx(1 - np.exp(-1))
    image, size_mm = frame
    out = DriftRenderer(spec, SIZE, size_mm).apply(image, 1e6)
    assert out.shape == image.shape and out.dtype == np.uint8
    centre = slice(SIZE // 2 - 2, SIZE // 2 + 2)
    assert np.abs(out[centre, centre].astype(int) - image[centre, centre]).mean() < 8
    assert np.abs(out.astype(int) - image).mean() > 2  # the rest moved
