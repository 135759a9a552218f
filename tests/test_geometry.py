import math

import numpy as np
import pytest
import torch

from beadsight.config import ConfigError, SensorGeometry
from beadsight.geometry import (
    centre_of_pressure_mm,
    contact_area_mm2,
    disk_maps,
    disk_pressure_kpa,
    force_to_newtons,
    mm_to_px,
    pressure_to_kpa,
    px_to_mm,
    total_force_n,
)

G = SensorGeometry()


def test_reference_axis_convention():
    # Centre -> (128, 128); printer +X -> image -column, +Y -> image -row.
    np.testing.assert_allclose(mm_to_px([0, 0], G), [128, 128])
    np.testing.assert_allclose(mm_to_px([10.25, 0], G), [128, 64])
    np.testing.assert_allclose(mm_to_px([0, 10.25], G), [64, 128])
    assert G.mm_per_px == pytest.approx(0.16015625)


def test_mm_px_round_trip():
    xy = np.random.default_rng(0).uniform(-20, 20, (50, 2))
    np.testing.assert_allclose(px_to_mm(mm_to_px(xy, G), G), xy, atol=1e-12)


def test_one_newton_is_8_149_kpa():
    assert disk_pressure_kpa(1.0, G) == pytest.approx(8.149, abs=1e-3)


@pytest.mark.parametrize("xy", [(0, 0), (13.75, -13.75), (-7.3, 2.2), (0.08, 0.08)])
def test_disk_integral_equals_force(xy):
    maps = disk_maps(np.array([12.0]), np.array([xy]), G)
    assert maps.dtype == np.float32 and maps.shape == (1, 256, 256)
    assert total_force_n(maps, G)[0] == pytest.approx(12.0, rel=2e-3)
    np.testing.assert_allclose(centre_of_pressure_mm(maps, G)[0], xy, atol=0.01)
    # Interior pixels carry the uniform pressure F / (pi r^2).
    rc = mm_to_px(np.array(xy), G).astype(int)
    assert maps[0, rc[0], rc[1]] == pytest.approx(disk_pressure_kpa(12.0, G), rel=1e-5)


def test_disk_integral_at_small_image_size():
    g = G.with_image_size(64)
    maps = disk_maps(np.array([5.0, 20.0]), np.array([[3.0, -4.0], [-10.0, 11.0]]), g)
    np.testing.assert_allclose(total_force_n(maps, g), [5.0, 20.0], rtol=5e-3)


def test_disk_area_matches_finger():
    maps = disk_maps(np.array([1.0]), np.zeros((1, 2)), G)
    area = contact_area_mm2(maps[0] > 0.5 * maps.max(), G)
    assert area == pytest.approx(math.pi * 6.25**2, rel=0.02)


def test_torch_and_numpy_disks_agree():
    f = np.array([3.0, 9.0])
    xy = np.array([[1.0, 2.0], [-5.0, 7.5]])
    np.testing.assert_allclose(
        disk_maps(torch.tensor(f), torch.tensor(xy), G).numpy(), disk_maps(f, xy, G), atol=1e-3
    )


def test_zero_force_and_empty_centre_of_pressure():
    maps = disk_maps(np.array([0.0, -1.0]), np.zeros((2, 2)), G)
    assert not maps.any()
    assert np.isnan(centre_of_pressure_mm(maps, G)).all()


def test_units():
    assert force_to_newtons(1000.0, "g") == pytest.approx(9.81)
    assert force_to_newtons(2.0, "N") == 2.0
    assert pressure_to_kpa(1500.0, "Pa") == 1.5
    with pytest.raises(ValueError, match="unknown force unit 'lb'"):
        force_to_newtons(1.0, "lb")


def test_geometry_validation():
    with pytest.raises(ConfigError, match="finger_radius_mm"):
        SensorGeometry(finger_radius_mm=30)
    with pytest.raises(ConfigError, match="image_size_px"):
        SensorGeometry(image_size_px=3)
    assert SensorGeometry.from_dict(G.to_dict()) == G
