"""Does a runtime agree with fp32 torch? Probe windows, the tolerance, and the check.

A backend is refused when its output on the probe windows (:func:`probe_windows`)
differs from fp32 torch by more than 1 % of ``max(peak, PARITY_FLOOR_KPA)``
(:data:`PARITY_TOLERANCE`). The floor, the pressure of the 50 g contact force spread
over the finger (~4 kPa), keeps the check meaningful when the probe's map is nearly
empty (an untrained or unlucky model): errors are then judged against a
contact-sized pressure.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from beadsight.checkpoint import PressureModel
from beadsight.config import ContactThresholds, SensorGeometry
from beadsight.geometry import disk_pressure_kpa
from beadsight.inference.backend import Backend, BackendError

PROBE_SEED = 0
PROBE_TEXTURE_STD = 1.5  # probe background contrast, in units of the pixel std
PROBE_DEPTH_STD = 2.0  # darkening under the probe's finger at full press, in pixel stds
PARITY_FLOOR_KPA = float(disk_pressure_kpa(ContactThresholds().contact_n, SensorGeometry()))


class ParityError(BackendError):
    """The backend's output differs from fp32 torch by more than the tolerance."""


@dataclass(frozen=True)
class ParityTolerance:
    """Allowed max abs error: ``max(abs_kpa, fraction * max(peak_kpa, floor_kpa))``."""

    fraction: float = 0.01  # 1 % of the map's peak
    floor_kpa: float = PARITY_FLOOR_KPA  # peak used when the map's own peak is smaller
    abs_kpa: float = 0.0  # never stricter than this

    def tolerance_kpa(self, peak_kpa: float) -> float:
        return max(self.abs_kpa, self.fraction * max(float(peak_kpa), self.floor_kpa))


PARITY_TOLERANCE = ParityTolerance()


@dataclass(frozen=True)
class ParityResult:
    """Max abs error of a backend against fp32 torch on one window."""

    backend: str
    max_abs_err_kpa: float
    peak_kpa: float
    tolerance_kpa: float

    @property
    def ok(self) -> bool:
        return bool(self.max_abs_err_kpa <= self.tolerance_kpa)

    @property
    def max_abs_err_pct(self) -> float:
        """Error in % of the peak the tolerance uses (``max(peak, floor)``)."""
        scale = max(self.peak_kpa, PARITY_TOLERANCE.floor_kpa)
        return 100.0 * self.max_abs_err_kpa / scale

    def __str__(self) -> str:
        return (
            f"{self.backend}: max abs error {self.max_abs_err_kpa:.3g} kPa "
            f"({self.max_abs_err_pct:.3g} % of max(peak {self.peak_kpa:.3g}, floor "
            f"{PARITY_TOLERANCE.floor_kpa:.3g}) kPa; allowed {self.tolerance_kpa:.3g} kPa)"
        )


def _press_probe(
    model: PressureModel, rng: np.random.Generator, centre_px: tuple[float, float]
) -> np.ndarray:
    """A textured window with a dark disk deepening over time, like a finger press
    (``model.inputs`` images: a rest-referenced model's rest image is the undented first)."""
    n, s = model.inputs, model.image_size
    mean = np.asarray(model.meta.pixel_mean, dtype=np.float64)
    std = np.asarray(model.meta.pixel_std, dtype=np.float64)
    if model.meta.channel_order == "BGR":
        mean, std = mean[::-1], std[::-1]
    texture = rng.normal(0.0, PROBE_TEXTURE_STD, size=(s, s, 1)) * std + mean
    rows, cols = np.mgrid[0:s, 0:s] + 0.5
    radius = model.geometry.finger_radius_mm / model.geometry.mm_per_px
    disk = np.clip(radius - np.hypot(rows - centre_px[0], cols - centre_px[1]) + 0.5, 0, 1)
    depth = np.linspace(0.0, 1.0, n)[:, None, None, None]
    frames = texture[None] - depth * disk[None, :, :, None] * PROBE_DEPTH_STD * std
    frames = frames + rng.normal(0.0, 1.0, size=frames.shape)
    return np.clip(np.rint(frames), 0, 255).astype(np.uint8)


def probe_windows(model: PressureModel, seed: int = PROBE_SEED) -> np.ndarray:
    """(K, inputs, S, S, 3) uint8 RGB model inputs the parity check runs on.

    A synthetic press (textured frames at the checkpoint's pixel statistics with
    a darkening finger disk, at the centre and off-centre) and uniform noise:
    maps with pressure in them for a trained model, and inputs far from the
    training data that stress a reduced precision.
    """
    rng = np.random.default_rng(seed)
    n, s = model.inputs, model.image_size
    offset = s / 4
    return np.stack(
        [
            _press_probe(model, rng, (s / 2, s / 2)),
            _press_probe(model, rng, (s / 2 - offset, s / 2 + offset)),
            rng.integers(0, 256, size=(n, s, s, 3), dtype=np.uint8),
        ]
    )


def probe_window(model: PressureModel, seed: int = PROBE_SEED) -> np.ndarray:
    """The (1, inputs, S, S, 3) probe input whose fp32 torch map peaks highest."""
    windows = probe_windows(model, seed)
    return windows[peak_index(model.predict(windows, batch_size=1))][None]


def peak_index(maps: np.ndarray) -> int:
    """Index of the (K, S, S) map with the highest peak."""
    return int(np.argmax(maps.max(axis=(1, 2))))


def check_parity(
    backend: Backend,
    model: PressureModel,
    windows: np.ndarray | None = None,
    expected: np.ndarray | None = None,
    tolerance: ParityTolerance | None = None,
) -> ParityResult:
    """Compare ``backend.run`` with fp32 torch (``model.predict``), window by window.

    windows: (K, inputs, S, S, 3) uint8 RGB (default :func:`probe_windows`); expected:
    their (K, S, S) fp32 maps if already computed. Each window is judged against
    its own peak; the result is the worst one (largest error / tolerance).
    """
    windows = probe_windows(model) if windows is None else windows
    expected = model.predict(windows, batch_size=1) if expected is None else expected
    tolerance = tolerance or PARITY_TOLERANCE
    worst: ParityResult | None = None
    for window, reference in zip(windows, expected, strict=True):
        got = backend.run(window[None])[0]
        peak = float(np.abs(reference).max())
        err = float(np.abs(got.astype(np.float64) - reference).max())
        result = ParityResult(backend.describe(), err, peak, tolerance.tolerance_kpa(peak))
        if worst is None or _ratio(result) > _ratio(worst):
            worst = result
    return worst


def _ratio(result: ParityResult) -> float:
    return result.max_abs_err_kpa / result.tolerance_kpa if result.tolerance_kpa > 0 else np.inf


def require_parity(backend: Backend, model: PressureModel) -> None:
    """Check ``backend`` on the probes; set ``backend.parity``; close it and raise
    :class:`ParityError` if it disagrees."""
    parity = check_parity(backend, model)
    backend.parity = parity
    if not parity.ok:
        backend.close()
        raise ParityError(
            f"backend {backend.describe()} disagrees with fp32 torch for checkpoint "
            f"{model.source}: {parity}; choose another backend or precision"
        )
