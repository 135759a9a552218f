"""VirtualRig: one simulated pouch behind the virtual printer, scale and camera."""

from __future__ import annotations

import os
import threading
import time

import numpy as np
import pytest

import beadsight.sim.config as sim_config
from beadsight.devices import Camera, Printer, SafetyError, Scale
from beadsight.devices.virtual import VirtualRig

TIME_SCALE = 10.0  # simulated seconds per host second
SETTLE_S = 0.05


def small_rig(**kwargs) -> VirtualRig:
    kwargs.setdefault("time_scale", TIME_SCALE)
    kwargs.setdefault("camera_mode", "sensor")
    kwargs.setdefault("camera_fps", 10.0)
    kwargs.setdefault("scale_rate_hz", 10.0)
    kwargs.setdefault("world_step_s", 0.05)
    return VirtualRig(sim_config.SimConfig(image_size_px=64), seed=0, **kwargs)


def fresh_grams(scale) -> float:
    for _ in range(2):
        reading = scale.wait_for_reading(2.0, after_mono=time.monotonic())
    return reading.grams


def test_press_raises_force_and_changes_frames():
    with small_rig() as rig:
        cx, cy = rig.config.centre_xy_mm
        surface = rig.config.surface_z_mm
        printer, scale = rig.make_printer(timeout_s=3.0, boot_settle_s=SETTLE_S), rig.make_scale()
        assert (
            isinstance(printer, Printer)
            and isinstance(scale, Scale)
            and isinstance(rig.camera, Camera)
        )
        with printer, scale, rig.camera as camera:
            printer.home()
            printer.move(cx + 2.0, cy - 3.0, rig.config.clear_z_mm, 3000)
            printer.wait_for_motion()
            assert rig.force_n == 0.0
            assert abs(fresh_grams(scale)) < 3.0
            before = camera.read_latest(timeout_s=2.0)
            assert before.image.shape == (64, 64, 3)

            printer.move(None, None, surface - 1.2, 200)  # 1.2 mm into the pouch
            printer.wait_for_motion()
            printer.dwell(3000)  # the pouch relaxes (time constant 0.6 s) to a steady force
            x, y, z = printer.position()
            assert (x, y, z) == pytest.approx((cx + 2.0, cy - 3.0, surface - 1.2), abs=0.01)
            assert rig.depth_mm() == pytest.approx(1.2, abs=0.01)
            assert rig.force_n > 2.0
            pressed_g = fresh_grams(scale)
            assert pressed_g == pytest.approx(rig.force_n / 9.81e-3, rel=0.1)
            after = camera.read_latest(timeout_s=2.0)
            assert after.index > before.index
            diff = np.abs(after.image.astype(np.int16) - before.image.astype(np.int16)).mean()
            assert diff > 2.0

            printer.move(None, None, rig.config.clear_z_mm, 700)
            printer.wait_for_motion()
            time.sleep(0.05)
            assert rig.force_n == 0.0
            assert abs(fresh_grams(scale)) < 3.0


def test_rig_envelope_protects_the_sensor():
    with small_rig() as rig, rig.make_printer(timeout_s=3.0, boot_settle_s=SETTLE_S) as printer:
        printer.home()
        cx, cy = rig.config.centre_xy_mm
        with pytest.raises(SafetyError, match="below the safety floor"):
            printer.move(cx, cy, rig.config.surface_z_mm - 10.0, 200)
        with pytest.raises(SafetyError, match="within"):
            printer.move(cx + 30.0, cy, rig.config.surface_z_mm - 1.0, 200)


def test_reference_scale_in_the_rig():
    with small_rig(scale_protocol="reference") as rig, rig.make_scale() as scale:
        assert scale.protocol == "reference"
        assert abs(fresh_grams(scale)) < 3.0


def test_close_removes_ports_and_threads():
    rig = small_rig()
    with rig, rig.camera:
        ports = (rig.printer_port, rig.scale_port)
        assert all(os.path.exists(p) for p in ports)
        mine = {t for t in threading.enumerate() if t.name.startswith("virtual")}
        assert {t.name for t in mine} >= {"virtual printer", "virtual scale", "virtual rig world"}
        rig.camera.read(timeout_s=2.0)
    assert not any(os.path.exists(p) for p in ports)
    assert [t.name for t in mine if t.is_alive()] == []
