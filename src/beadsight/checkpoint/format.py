"""The beadsight checkpoint format: :class:`PressureModel`, its metadata, saving, and the
safe load of a checkpoint file.

A beadsight checkpoint is a ``torch.save`` file holding only tensors and plain
Python values (it loads with ``weights_only=True``):

``{"beadsight": <JSON metadata str>, "state_dict": <UNet state_dict>, ...training state}``

The metadata carries the model config (``frames`` T, ``frame_stride``, width, ...),
channel order, normalisation, output scale, sensor geometry, units and provenance,
so the file alone rebuilds a working predictor. Versions :data:`READ_VERSIONS` are read:
version 3 added rest-referenced models (``rest_input``), which version 2 files are not;
version 4 added the contrast-normalised rest input (``rest_norm``).

:func:`read_checkpoint_file` reads any checkpoint file with ``weights_only=True``; numpy
arrays are built only by the checked stand-ins of :mod:`beadsight.safe_numpy` (plain
numeric and bool dtypes), and anything else a pickle asks for is refused before it can
run. :func:`model_from` refuses non-finite weights and statistics, a zero ``pixel_std``,
a non-positive output scale and metadata that does not fit the weights, before it builds
the model. The reference's training pickles are read by
:mod:`beadsight.checkpoint.reference`; :func:`beadsight.checkpoint.load_checkpoint` reads
either.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from beadsight import safe_numpy
from beadsight.config import ModelConfig, SensorGeometry
from beadsight.errors import BeadSightError
from beadsight.files import atomic_write_bytes
from beadsight.model import FramesToPressure, UNet, infer_model_config

FORMAT = "beadsight-checkpoint"
FORMAT_VERSION = 4  # written; 3 adds model.rest_input, 4 model.rest_norm
READ_VERSIONS = (2, 3, 4)  # read
UNITS = {"frames": "uint8 0..255", "pressure": "kPa", "force": "N", "position": "mm"}


class CheckpointError(BeadSightError, ValueError):
    """A checkpoint file is missing, unreadable, unsafe, or does not match its use."""


class UnsafeCheckpointError(CheckpointError):
    """The file's pickle asks to run code that is not on the allow-list."""


@dataclass
class CheckpointMeta:
    """Everything needed, besides the weights, to turn frames into kPa."""

    model: ModelConfig
    geometry: SensorGeometry
    pixel_mean: list[float]  # per channel, in ``channel_order``, 0..255 units
    pixel_std: list[float]
    channel_order: str = "RGB"  # order of the channels the network was trained on
    output_scale_kpa: float = 1.0  # network output * this = kPa
    provenance: dict[str, Any] = field(default_factory=dict)
    training: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> str:
        return json.dumps(
            {
                "format": FORMAT,
                "format_version": FORMAT_VERSION,
                "model": self.model.to_dict(),
                "geometry": self.geometry.to_dict(),
                "pixel_mean": [float(v) for v in self.pixel_mean],
                "pixel_std": [float(v) for v in self.pixel_std],
                "channel_order": self.channel_order,
                "output_scale_kpa": float(self.output_scale_kpa),
                "units": UNITS,
                "provenance": self.provenance,
                "training": self.training,
            },
            sort_keys=True,
        )

    @classmethod
    def from_json(cls, text: str, source: str) -> CheckpointMeta:
        try:
            d = json.loads(text)
            if not isinstance(d, dict):
                raise CheckpointError(
                    f"{source}: beadsight metadata is a JSON {type(d).__name__}; expected an object"
                )
            if d.get("format") != FORMAT:
                raise CheckpointError(f"{source}: metadata format is {d.get('format')!r}")
            version = d.get("format_version")
            if version not in READ_VERSIONS:
                newer = isinstance(version, int) and version > FORMAT_VERSION
                raise CheckpointError(
                    f"{source}: checkpoint format_version {version!r}; this beadsight reads "
                    f"versions {READ_VERSIONS}" + ("; upgrade beadsight" if newer else "")
                )
            return cls(
                model=ModelConfig.from_dict(d["model"]),
                geometry=SensorGeometry.from_dict(d["geometry"]),
                pixel_mean=checked_floats(d["pixel_mean"], source, "pixel_mean"),
                pixel_std=checked_floats(d["pixel_std"], source, "pixel_std"),
                channel_order=d["channel_order"],
                output_scale_kpa=checked_number(d["output_scale_kpa"], source, "output_scale_kpa"),
                provenance=d.get("provenance", {}),
                training=d.get("training", {}),
            )
        except CheckpointError:
            raise
        except (KeyError, TypeError, AttributeError, ValueError) as e:  # ConfigError, JSON
            raise CheckpointError(f"{source}: malformed beadsight metadata ({e!r})") from None


class PressureModel:
    """A loaded model: frames in, kPa maps out.

    Wraps a :class:`FramesToPressure` module (``.module``) and its metadata
    (``.meta``). Use :meth:`predict` for numpy arrays; use ``.module`` directly
    for torch tensors, export and training.
    """

    def __init__(self, module: FramesToPressure, meta: CheckpointMeta, source: str = "<memory>"):
        self.module = module.eval()
        self.meta = meta
        self.source = source

    @classmethod
    def create(cls, meta: CheckpointMeta) -> PressureModel:
        """A freshly initialised model described by ``meta``."""
        return cls(_build_module(meta), meta)

    @property
    def frames(self) -> int:
        """T: frames the network sees."""
        return self.meta.model.frames

    @property
    def span(self) -> int:
        """Consecutive frames one input window covers: ``(frames - 1) * frame_stride + 1``."""
        return self.meta.model.span

    @property
    def rest(self) -> int:
        """1 if the model's input starts with a rest image (rest-referenced), else 0."""
        return int(self.meta.model.rest_input)

    @property
    def inputs(self) -> int:
        """Images in one model input: ``rest`` + ``span``."""
        return self.meta.model.inputs

    @property
    def image_size(self) -> int:
        return self.meta.geometry.image_size_px

    @property
    def geometry(self) -> SensorGeometry:
        return self.meta.geometry

    @property
    def device(self) -> torch.device:
        return next(self.module.parameters()).device

    def to(self, device: str | torch.device) -> PressureModel:
        self.module.to(device)
        return self

    def check_frames(self, frames: np.ndarray, what: str = "frames") -> None:
        """Raise a ValueError naming ``what`` unless frames fit this model: ``(inputs, H, W,
        3)`` or ``(B, inputs, H, W, 3)`` uint8 RGB (the rest image first for a
        rest-referenced model)."""
        shape = getattr(frames, "shape", None)
        layout = "rest + span" if self.rest else "span"
        if shape is None or len(shape) not in (4, 5) or shape[-1] != 3:
            raise ValueError(
                f"{what}: expected ({layout}, H, W, 3) or (B, {layout}, H, W, 3) RGB frames, "
                f"got shape {shape}"
            )
        if frames.dtype != np.uint8:
            raise ValueError(f"{what}: expected dtype uint8 (0..255), got {frames.dtype}")
        t, h, w = shape[-4], shape[-3], shape[-2]
        if t != self.inputs:
            rest = "1 rest image + " if self.rest else ""
            raise ValueError(
                f"{what}: window of {t} frames, but the checkpoint {self.source} expects "
                f"{rest}span={self.span} (frames={self.frames}, frame_stride="
                f"{self.meta.model.frame_stride})"
            )
        if (h, w) != (self.image_size, self.image_size):
            raise ValueError(
                f"{what}: frames are {h}x{w} px, but the checkpoint {self.source} expects "
                f"image_size={self.image_size}x{self.image_size}"
            )

    @torch.inference_mode()
    def predict(self, frames: np.ndarray, batch_size: int = 16) -> np.ndarray:
        """frames: (inputs, H, W, 3) or (B, inputs, H, W, 3) uint8 RGB: for a
        rest-referenced model the rest image first, then the window's ``span`` frames,
        oldest first (:func:`beadsight.data.rest.with_rest` builds them).

        returns: (H, W) or (B, H, W) float32 kPa.
        """
        self.check_frames(frames)
        single = frames.ndim == 4
        batch = frames[None] if single else frames
        device = self.device
        out = np.empty((len(batch), *batch.shape[2:4]), dtype=np.float32)
        for i in range(0, len(batch), batch_size):
            x = torch.from_numpy(np.ascontiguousarray(batch[i : i + batch_size])).to(device)
            out[i : i + batch_size] = self.module(x).float().cpu().numpy()
        return out[0] if single else out

    def save(self, path: str | Path, **training_state: Any) -> Path:
        return save_checkpoint(path, self, **training_state)


def _build_module(meta: CheckpointMeta) -> FramesToPressure:
    return FramesToPressure(
        UNet(meta.model),
        pixel_mean=meta.pixel_mean,
        pixel_std=meta.pixel_std,
        channel_order=meta.channel_order,
        output_scale_kpa=meta.output_scale_kpa,
    )


# --- saving -------------------------------------------------------------------------
def atomic_torch_save(obj: Any, path: str | Path) -> Path:
    """torch.save to ``path`` atomically: a crash, Ctrl-C or full disk leaves the previous file.

    Serialised in memory first: torch's zip writer turns a failed write into a
    RuntimeError ("unexpected pos ..."), which would hide the cause; written from bytes,
    a full disk is a WriteError naming the file.
    """
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    return atomic_write_bytes(path, buffer.getbuffer())


def save_checkpoint(path: str | Path, model: PressureModel, **training_state: Any) -> Path:
    """Write ``model`` (weights + metadata) and optional training state atomically.

    ``training_state`` values must be tensors or plain Python values (for example
    ``optimizer=opt.state_dict()``, ``step=1200``) so the file stays weights-only.
    """
    state = {k: v.detach().cpu() for k, v in model.module.net.state_dict().items()}
    return atomic_torch_save(
        {"beadsight": model.meta.to_json(), "state_dict": state, **training_state}, path
    )


# --- loading ------------------------------------------------------------------------
MAX_IMAGE_SIZE_PX = 4096  # far beyond any sensor image; refuses absurd metadata before allocating
MAX_SPAN_FRAMES = 1024  # frames one window covers (~34 s at 30 fps); the predictor buffers them
_ZIP_MAGIC = b"PK\x03\x04"  # torch's zip checkpoints
_PICKLE_MAGIC = b"\x80"  # the PROTO opcode that starts legacy torch files and plain pickles


def looks_like_checkpoint(path: str | Path) -> bool:
    """True if ``path`` starts like a file :func:`read_checkpoint_file` may read (zip or pickle)."""
    try:
        with open(path, "rb") as f:
            head = f.read(4)
    except OSError:
        return False
    return head == _ZIP_MAGIC or head[:1] == _PICKLE_MAGIC


def read_checkpoint_file(path: str | Path) -> dict[str, Any]:
    """torch.load with ``weights_only=True`` and checked numpy arrays, with clear errors.

    numpy arrays are built only for plain numeric and bool dtypes (:mod:`beadsight.safe_numpy`);
    anything else the pickle asks for raises :class:`UnsafeCheckpointError`.
    """
    path = Path(path)
    if path.is_dir():
        raise CheckpointError(f"{path}: is a directory; expected a checkpoint file")
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint file not found")
    try:
        with torch.serialization.safe_globals(safe_numpy.safe_globals()):
            obj = safe_numpy.materialize(torch.load(path, map_location="cpu", weights_only=True))
    except safe_numpy.UnsafeContent as e:
        raise UnsafeCheckpointError(
            f"{path}: refused to load: {e}; only plain numeric numpy arrays are read, and "
            "nothing from the file was executed"
        ) from None
    except Exception as e:  # torch raises UnpicklingError/RuntimeError with long texts
        text = str(e)
        if "Weights only load failed" in text or "GLOBAL" in text:
            lines = [ln.strip() for ln in text.splitlines()]
            detail = next(
                (ln for ln in lines if "GLOBAL" in ln or "Unsupported" in ln),
                "unsupported pickle content",
            )
            raise UnsafeCheckpointError(
                f"{path}: refused to load: not a weights-only checkpoint ({detail}). Only "
                "tensors, numbers, strings and plain numeric numpy arrays are read; nothing "
                "from the file was executed. Convert checkpoints you trust with a trusted tool "
                "first."
            ) from None
        first = text.splitlines()[0] if text else ""
        raise CheckpointError(
            f"{path}: not a readable checkpoint ({type(e).__name__}: {first})"
        ) from None
    if not isinstance(obj, dict):
        raise CheckpointError(f"{path}: expected a dict checkpoint, got {type(obj).__name__}")
    return obj


def checked_floats(value: Any, source: Any, key: str, length: int = 3) -> list[float]:
    """``length`` finite numbers from a list, array or tensor; CheckpointError otherwise."""
    try:
        arr = np.asarray(value.numpy() if isinstance(value, torch.Tensor) else value, dtype=float)
    except (TypeError, ValueError):
        raise CheckpointError(f"{source}: {key} is {value!r:.80}; expected numbers") from None
    arr = arr.reshape(-1)
    if arr.size != length:
        raise CheckpointError(
            f"{source}: {key} has {arr.size} value(s), expected {length} (one per channel)"
        )
    if not np.isfinite(arr).all():
        raise CheckpointError(f"{source}: {key} is {arr.tolist()}; expected finite numbers")
    return arr.tolist()


def checked_number(value: Any, source: Any, key: str) -> float:
    """One finite number (a float, int or 0-d array); CheckpointError otherwise."""
    try:
        arr = np.asarray(value.numpy() if isinstance(value, torch.Tensor) else value, dtype=float)
    except (TypeError, ValueError):
        raise CheckpointError(f"{source}: {key} is {value!r:.80}; expected a number") from None
    if arr.shape != ():
        raise CheckpointError(f"{source}: {key} has shape {arr.shape}; expected a single number")
    if not np.isfinite(arr):
        raise CheckpointError(f"{source}: {key} is {float(arr)}; expected a finite number")
    return float(arr)


def checked_weights(state: Any, path: Path) -> dict[str, torch.Tensor]:
    """A state_dict of dense CPU tensors with finite values; CheckpointError otherwise."""
    if not isinstance(state, dict):
        raise CheckpointError(
            f"{path}: weights are a {type(state).__name__}; expected a state_dict"
        )
    for key, value in state.items():
        if not (
            isinstance(key, str)
            and isinstance(value, torch.Tensor)
            and value.layout == torch.strided
            and value.device.type == "cpu"
            and not value.is_quantized
        ):
            raise CheckpointError(f"{path}: weight {key!r:.80} is not a dense CPU tensor")
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            bad = int((~torch.isfinite(value)).sum())
            raise CheckpointError(
                f"{path}: weight '{key}' has {bad} NaN/inf value(s); expected finite numbers"
            )
    return state


def check_meta(meta: CheckpointMeta, state: dict[str, torch.Tensor], path: Path) -> None:
    """Refuse metadata that would give a model NaN output or allocate absurd buffers."""
    checked_floats(meta.pixel_mean, path, "pixel_mean")
    if min(checked_floats(meta.pixel_std, path, "pixel_std")) <= 0:
        raise CheckpointError(f"{path}: pixel_std is {meta.pixel_std}; expected values > 0")
    if not checked_number(meta.output_scale_kpa, path, "output_scale_kpa") > 0:
        raise CheckpointError(
            f"{path}: output_scale_kpa is {meta.output_scale_kpa}; expected a number > 0"
        )
    if meta.channel_order not in ("RGB", "BGR"):
        raise CheckpointError(
            f"{path}: channel_order is {meta.channel_order!r}; expected RGB or BGR"
        )
    if meta.geometry.image_size_px > MAX_IMAGE_SIZE_PX:
        raise CheckpointError(
            f"{path}: image_size_px is {meta.geometry.image_size_px}; expected at most "
            f"{MAX_IMAGE_SIZE_PX}"
        )
    if meta.model.span > MAX_SPAN_FRAMES:
        raise CheckpointError(
            f"{path}: the model's window spans {meta.model.span} frames; expected at most "
            f"{MAX_SPAN_FRAMES}"
        )
    for key in ("provenance", "training"):
        if not isinstance(getattr(meta, key), dict):
            raise CheckpointError(f"{path}: {key} is not a JSON object")
    try:  # the shapes the metadata describes must be the weights' (before building them)
        have = infer_model_config(state, rest_input=meta.model.rest_input).to_dict()
    except (ValueError, IndexError) as e:
        raise CheckpointError(f"{path}: state_dict: {e}") from None
    for key, value in meta.model.to_dict().items():  # these three are not in the shapes
        if (
            key in have
            and key not in ("dropout", "frame_stride", "rest_norm")
            and have[key] != value
        ):
            raise CheckpointError(
                f"{path}: model {key} is {value} in the metadata but {have[key]} in the weights"
            )


def read_ours(obj: dict[str, Any], path: Path) -> tuple[CheckpointMeta, dict[str, torch.Tensor]]:
    """The metadata and checked weights of a beadsight checkpoint dict (one with a
    ``"beadsight"`` entry, as :func:`read_checkpoint_file` returns it)."""
    meta = CheckpointMeta.from_json(obj["beadsight"], str(path))
    return meta, checked_weights(obj.get("state_dict"), path)


def model_from(
    meta: CheckpointMeta,
    state: dict[str, torch.Tensor],
    path: Path,
    map_location: str | torch.device = "cpu",
) -> PressureModel:
    """The model ``meta`` describes with ``state``'s weights, after :func:`check_meta`;
    CheckpointError naming ``path`` if the weights do not fit."""
    check_meta(meta, state, path)
    module = _build_module(meta)
    try:
        module.net.load_state_dict(state)
    except (RuntimeError, TypeError, AttributeError) as e:
        raise CheckpointError(f"{path}: weights do not fit the described model: {e}") from None
    return PressureModel(module, meta, source=str(path)).to(map_location)
