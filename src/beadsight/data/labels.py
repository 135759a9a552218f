"""Ground-truth pressure maps for dataset frames.

The label of a frame is the finger's uniform-pressure disk at the commanded
position carrying the scale's force, while the frame is in contact (force
hysteresis, see :mod:`beadsight.data.presses`); out of contact it is all zero, so
scale noise at rest does not become phantom pressure.
"""

from __future__ import annotations

import numpy as np

from beadsight.config import SensorGeometry
from beadsight.geometry import disk_maps


def label_maps(force_n, position_mm, contact, geometry: SensorGeometry):
    """force_n: (B,) N; position_mm: (B, 2) mm; contact: (B,) bool.

    returns: (B, S, S) float32 kPa (numpy, or torch on the device of ``force_n``).
    """
    try:
        import torch

        if isinstance(force_n, torch.Tensor):
            contact = torch.as_tensor(contact, device=force_n.device)
            return disk_maps(
                torch.where(contact, force_n, torch.zeros_like(force_n)), position_mm, geometry
            )
    except ImportError:  # pragma: no cover
        pass
    force = np.where(np.asarray(contact, bool), np.asarray(force_n, np.float64), 0.0)
    return disk_maps(force, position_mm, geometry)
