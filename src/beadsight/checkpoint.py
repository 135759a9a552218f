"""Self-describing checkpoints, and safe import of the reference training checkpoints.

A beadsight checkpoint is a ``torch.save`` file holding only tensors and plain
Python values (it loads with ``weights_only=True``):

``{"beadsight": <JSON metadata str>, "state_dict": <UNet state_dict>, ...training state}``

The metadata carries the model config (``frames`` T, ``frame_stride``, width, ...),
channel order, normalisation, output scale, sensor geometry, units and provenance,
so the file alone rebuilds a working predictor. Format version 2 names the frame
count ``frames``; version 1 files (``window``) load unchanged.

Reference checkpoints (pickled training dicts with numpy arrays) are read with
``weights_only=True`` and an allow-list of numpy types; anything else a pickle asks
for is refused before it can run.
"""

from __future__ import annotations

import importlib.resources
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from beadsight._compat import renamed_attribute
from beadsight.config import REFERENCE_G_TO_N, ModelConfig, SensorGeometry
from beadsight.files import atomic_write
from beadsight.geometry import PA_PER_KPA
from beadsight.model import FramesToPressure, UNet, infer_model_config

FORMAT = "beadsight-checkpoint"
FORMAT_VERSION = 2  # 2: model "window" renamed "frames" (version 1 files still load)
SHIPPED_MODEL = "sim_model.pt"  # the simulated-sensor model, in the package's assets folder
UNITS = {"frames": "uint8 0..255", "pressure": "kPa", "force": "N", "position": "mm"}


class CheckpointError(ValueError):
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
            if d.get("format") != FORMAT:
                raise CheckpointError(f"{source}: metadata format is {d.get('format')!r}")
            if d.get("format_version", 0) > FORMAT_VERSION:
                raise CheckpointError(
                    f"{source}: checkpoint format_version {d['format_version']} is newer than "
                    f"this beadsight supports ({FORMAT_VERSION}); upgrade beadsight"
                )
            return cls(
                model=ModelConfig.from_dict(ModelConfig.upgrade_keys(d["model"])),
                geometry=SensorGeometry.from_dict(d["geometry"]),
                pixel_mean=list(d["pixel_mean"]),
                pixel_std=list(d["pixel_std"]),
                channel_order=d["channel_order"],
                output_scale_kpa=float(d["output_scale_kpa"]),
                provenance=d.get("provenance", {}),
                training=d.get("training", {}),
            )
        except (KeyError, TypeError, AttributeError, json.JSONDecodeError) as e:
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

    window = renamed_attribute("PressureModel", "window", "span")

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
        """Raise a ValueError naming ``what`` unless frames fit this model."""
        shape = getattr(frames, "shape", None)
        if shape is None or len(shape) not in (4, 5) or shape[-1] != 3:
            raise ValueError(
                f"{what}: expected (span, H, W, 3) or (B, span, H, W, 3) RGB frames, got shape "
                f"{shape}"
            )
        if frames.dtype != np.uint8:
            raise ValueError(f"{what}: expected dtype uint8 (0..255), got {frames.dtype}")
        t, h, w = shape[-4], shape[-3], shape[-2]
        if t != self.span:
            raise ValueError(
                f"{what}: window of {t} frames, but the checkpoint {self.source} expects "
                f"span={self.span} (frames={self.frames}, frame_stride="
                f"{self.meta.model.frame_stride})"
            )
        if (h, w) != (self.image_size, self.image_size):
            raise ValueError(
                f"{what}: frames are {h}x{w} px, but the checkpoint {self.source} expects "
                f"image_size={self.image_size}x{self.image_size}"
            )

    @torch.inference_mode()
    def predict(self, frames: np.ndarray, batch_size: int = 16) -> np.ndarray:
        """frames: (span, H, W, 3) or (B, span, H, W, 3) uint8 RGB, oldest first.

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
    """torch.save to ``path`` atomically: a crash, Ctrl-C or full disk leaves the previous file."""
    return atomic_write(path, lambda f: torch.save(obj, f))


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
def _numpy_safe_globals() -> list:
    """numpy callables a pickled training dict needs, under numpy 1.x and 2.x names."""
    core = getattr(np, "_core", None) or np.core
    reconstruct = core.multiarray._reconstruct
    scalar = core.multiarray.scalar
    allowed: list = [np.ndarray, np.dtype, reconstruct, scalar]
    for mod in ("numpy.core.multiarray", "numpy._core.multiarray"):
        allowed += [(reconstruct, f"{mod}._reconstruct"), (scalar, f"{mod}.scalar")]
    allowed += [
        type(np.dtype(t))
        for t in ("f2", "f4", "f8", "i1", "i2", "i4", "i8", "u1", "u2", "u4", "u8", "b1", "U1", "O")
    ]
    return allowed


def read_checkpoint_file(path: str | Path) -> dict[str, Any]:
    """torch.load with ``weights_only=True`` and the numpy allow-list, with clear errors."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint file not found")
    try:
        with torch.serialization.safe_globals(_numpy_safe_globals()):
            obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises UnpicklingError/RuntimeError with long texts
        text = str(e)
        if "Weights only load failed" in text or "GLOBAL" in text:
            lines = [ln.strip() for ln in text.splitlines()]
            detail = next((ln for ln in lines if "GLOBAL" in ln or "Unsupported" in ln),
                          "unsupported pickle content")
            raise UnsafeCheckpointError(
                f"{path}: refused to load: not a weights-only checkpoint ({detail}). Only tensors, numbers, strings and numpy arrays are read; "
                "nothing from the file was executed. Convert checkpoints you trust with a "
                "trusted tool first."
            ) from None
        first = text.splitlines()[0] if text else ""
        raise CheckpointError(f"{path}: not a readable checkpoint ({type(e).__name__}: {first})") from None
    if not isinstance(obj, dict):
        raise CheckpointError(f"{path}: expected a dict checkpoint, got {type(obj).__name__}")
    return obj


def _array(value: Any, path: Path, key: str, length: int | None = None) -> list[float]:
    arr = np.asarray(value.numpy() if isinstance(value, torch.Tensor) else value, dtype=float)
    arr = arr.reshape(-1)
    if length is not None and arr.size != length:
        raise CheckpointError(f"{path}: {key} has {arr.size} values, expected {length}")
    return arr.tolist()


def _reference_meta(obj: dict[str, Any], path: Path) -> tuple[CheckpointMeta, dict]:
    """Metadata for a reference training dict (BGR, 0..255 mean/std, avg_pressure in Pa)."""
    for key in ("model_state_dict", "pixel_mean", "pixel_std", "avg_pressure"):
        if key not in obj:
            raise CheckpointError(f"{path}: reference checkpoint has no {key!r} entry")
    state = obj["model_state_dict"]
    try:
        model = infer_model_config(state, dropout=float(obj.get("dropout_prob", 0.2)))
    except ValueError as e:
        raise CheckpointError(f"{path}: model_state_dict: {e}") from None
    if "window_size" in obj and int(obj["window_size"]) != model.frames:
        raise CheckpointError(
            f"{path}: window_size is {obj['window_size']} but the weights take "
            f"{model.frames} frames"
        )
    info = obj.get("data_loader_info") or {}
    geometry = SensorGeometry()
    try:
        if "image_size" in info:
            size = np.asarray(info["image_size"]).reshape(-1)
            geometry = geometry.with_image_size(int(size[0]))
        if "sensor_size" in info:
            geometry = SensorGeometry.from_dict(
                {
                    **geometry.to_dict(),
                    "sensor_size_mm": float(np.asarray(info["sensor_size"]).reshape(-1)[0]),
                }
            )
        if "contact_radius" in info:
            geometry = SensorGeometry.from_dict(
                {**geometry.to_dict(), "finger_radius_mm": float(info["contact_radius"])}
            )
    except (ValueError, TypeError) as e:
        raise CheckpointError(f"{path}: data_loader_info: {e}") from None
    avg_pressure_pa = float(np.asarray(obj["avg_pressure"]))
    meta = CheckpointMeta(
        model=model,
        geometry=geometry,
        pixel_mean=_array(obj["pixel_mean"], path, "pixel_mean", 3),
        pixel_std=_array(obj["pixel_std"], path, "pixel_std", 3),
        channel_order="BGR",
        output_scale_kpa=avg_pressure_pa / PA_PER_KPA,
        provenance={
            "source": "reference",
            "file": str(path),
            "epoch": int(obj["epoch"]) if "epoch" in obj else None,
            "dataset_path": str(obj.get("dataset_path", "")),
            "force_unit": str(info.get("force_unit", "g")),
            "g_to_n": REFERENCE_G_TO_N,
        },
    )
    return meta, state


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> PressureModel:
    """Load a beadsight checkpoint or a reference training checkpoint, safely.

    Never executes code from the file: a pickle that asks for anything other than
    tensors, plain values or numpy arrays raises :class:`UnsafeCheckpointError`.
    """
    path = Path(path)
    obj = read_checkpoint_file(path)
    if "beadsight" in obj:
        meta = CheckpointMeta.from_json(obj["beadsight"], str(path))
        state = obj.get("state_dict")
    elif "model_state_dict" in obj:
        meta, state = _reference_meta(obj, path)
    else:
        raise CheckpointError(
            f"{path}: neither a beadsight checkpoint (no 'beadsight' entry) nor a reference "
            f"checkpoint (no 'model_state_dict'); keys: {sorted(map(str, obj))[:10]}"
        )
    module = _build_module(meta)
    try:
        module.net.load_state_dict(state)
    except (RuntimeError, TypeError, AttributeError) as e:
        raise CheckpointError(f"{path}: weights do not fit the described model: {e}") from None
    return PressureModel(module, meta, source=str(path)).to(map_location)


def shipped_model_path() -> Path:
    """Path of the model shipped with the package; :class:`CheckpointError` if this install lacks it."""
    path = Path(str(importlib.resources.files("beadsight").joinpath("assets", SHIPPED_MODEL)))
    if not path.is_file():
        raise CheckpointError(
            f"the shipped sim model {path} is missing from this install; pass --checkpoint PATH "
            "(a model trained with `beadsight train`, or `beadsight demo --train`)"
        )
    return path


def checkpoint_summary(path: str | Path) -> dict[str, Any]:
    """What a checkpoint is and how it was made: architecture, input, output, training."""
    model = load_checkpoint(path)
    meta, training = model.meta, model.meta.training
    init = meta.provenance.get("init")
    return {
        "path": str(path),
        "format": "reference" if meta.provenance.get("source") == "reference" else "beadsight",
        "parameters": sum(p.numel() for p in model.module.parameters()),
        **meta.model.to_dict(),
        "image_size_px": model.image_size,
        "channel_order": meta.channel_order,
        "output_scale_kpa": meta.output_scale_kpa,
        "dataset": meta.provenance.get("dataset") or meta.provenance.get("dataset_path"),
        "initialised_from": init.get("path") if isinstance(init, dict) else None,
        "step": training.get("step"),
        "epoch": training.get("epoch", meta.provenance.get("epoch")),
        "best_val": training.get("best_val"),
        "geometry": meta.geometry.to_dict(),
    }
