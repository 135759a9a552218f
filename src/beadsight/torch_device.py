"""Which torch device to run on: the one rule for training, evaluation, prediction and demos.

* ``"auto"``: CUDA when torch sees a GPU, else the CPU. Apple's MPS is never chosen
  automatically: nothing here is tested on it, and its float results differ from the
  CPU's that the parity checks and tests are measured against.
* ``"cpu"``, ``"cuda"``, ``"cuda:N"``: as named; CUDA must be available and ``N`` must
  be one of its devices.
* ``"mps"``: accepted when asked for by name and available (single process only:
  distributed training refuses it).

Anything else is refused with :class:`DeviceError` naming the setting, what was asked
and what is possible here.
"""

from __future__ import annotations

import torch

from beadsight.config import DEVICE_CHOICES
from beadsight.errors import BeadSightError


class DeviceError(BeadSightError):
    """A device setting names a device that is not a torch device or not available here."""


def mps_available() -> bool:
    """True when this torch build has Apple's MPS backend and the machine has the GPU."""
    mps = getattr(torch.backends, "mps", None)
    return bool(mps is not None and mps.is_available())


def resolve_device(name: str | torch.device = "auto", what: str = "device") -> torch.device:
    """The torch device for ``name`` (see the module docstring).

    what: how the setting is called where it came from (``"--device"``, ``"device"``),
    for the error message.
    """
    if isinstance(name, str) and name.strip().lower() == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except (RuntimeError, TypeError) as e:
        raise DeviceError(
            f"{what} {name!r}: not a torch device ({e}); expected {DEVICE_CHOICES}"
        ) from None
    if device.type == "cuda":
        _check_cuda(device, name, what)
    elif device.type == "mps" and not mps_available():
        raise DeviceError(f"{what} {name!r}: MPS is not available on this machine")
    elif device.type not in ("cpu", "cuda", "mps"):
        raise DeviceError(f"{what} {name!r}: unsupported device type; expected {DEVICE_CHOICES}")
    return device


def _check_cuda(device: torch.device, name: object, what: str) -> None:
    if not torch.cuda.is_available():
        raise DeviceError(f"{what} {name!r}: CUDA is not available on this machine")
    count = torch.cuda.device_count()
    if device.index is not None and device.index >= count:
        raise DeviceError(
            f"{what} {name!r}: this machine has {count} CUDA device(s) (cuda:0..cuda:{count - 1})"
        )
