import os
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch

from beadsight import load_checkpoint
from beadsight.checkpoint import CheckpointError, UnsafeCheckpointError, checkpoint_summary
from beadsight.config import ModelConfig
from beadsight.model import UNet


def reference_training_dict(net: UNet, image_size: int) -> dict:
    """A dict shaped like the reference training checkpoints (numpy arrays inside)."""
    return {
        "epoch": 7,
        "model_state_dict": net.state_dict(),
        "optimizer_state_dict": torch.optim.AdamW(net.parameters(), lr=1e-4).state_dict(),
        "train_losses": [0.5, 0.4],
        "test_losses": [0.6],
        "val_losses": [0.55],
        "pixel_mean": np.array([101.5, 112.25, 120.0]),  # BGR, 0..255
        "pixel_std": np.array([31.0, 29.5, 33.25]),
        "avg_pressure": np.float64(1873.4),  # Pa
        "data_loader_info": {
            "average_force": np.float64(812.0),
            "pixel_mean": np.array([101.5, 112.25, 120.0]),
            "pixel_std": np.array([31.0, 29.5, 33.25]),
            "image_size": (image_size, image_size),
            "sensor_size": (41, 41),
            "contact_radius": 6.25,
            "force_unit": "g",
            "dist_unit": "mm",
        },
        "train_indices": np.arange(20),
        "test_indices": np.arange(20, 25),
        "dataset_path": "/data/hour1.hdf5",
        "lr": 1e-4,
        "weight_decay": 1e-4,
        "dropout_prob": 0.2,
        "window_size": net.config.frames,
        "batch_size": 64,
        "noise_std": 0.05,
    }


def reference_pipeline(net, ref, frames_rgb):
    """The reference inference path written out longhand: BGR, (x - mean)/std, channel 3t+c."""
    bgr = frames_rgb[..., ::-1].astype(np.float64)
    x = (bgr - ref["pixel_mean"]) / ref["pixel_std"]  # (T, H, W, 3)
    t, h, w, _ = x.shape
    x = np.concatenate([x[i].transpose(2, 0, 1) for i in range(t)], axis=0)  # (3T, H, W)
    with torch.no_grad():
        out = net.eval()(torch.tensor(x[None], dtype=torch.float32))[0, 0].numpy()
    return out * float(ref["avg_pressure"]) / 1000.0  # Pa -> kPa


@pytest.mark.parametrize("up_kernel", [1, 3])
def test_reference_checkpoint_matches_reference_pipeline(tmp_path, up_kernel):
    torch.manual_seed(0)
    net = UNet(ModelConfig(frames=15, width=8, up_kernel=up_kernel))
    # Push the weights away from init so the output is not ~zero.
    with torch.no_grad():
        net.pred.bias.fill_(0.3)
    ref = reference_training_dict(net, 64)
    torch.save(ref, tmp_path / "ref.pt")
    model = load_checkpoint(tmp_path / "ref.pt")
    assert model.meta.channel_order == "BGR"
    assert model.meta.model == ModelConfig(frames=15, width=8, up_kernel=up_kernel, dropout=0.2)
    assert model.image_size == 64 and model.meta.output_scale_kpa == pytest.approx(1.8734)
    frames = np.random.default_rng(0).integers(0, 256, (15, 64, 64, 3), dtype=np.uint8)
    expected = reference_pipeline(net, ref, frames)
    got = model.predict(frames)
    assert got.shape == (64, 64) and got.dtype == np.float32
    assert expected.max() > 0.1
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-4 * expected.max())
    batch = model.predict(np.stack([frames, frames[::-1]]))
    np.testing.assert_allclose(batch[0], got, rtol=1e-4, atol=1e-5)


def test_reference_size_model_loads(tmp_path):
    net = UNet()
    assert sum(p.numel() for p in net.parameters()) == 504_449
    torch.save(reference_training_dict(net, 256), tmp_path / "ref.pt")
    model = load_checkpoint(tmp_path / "ref.pt")
    assert model.frames == model.span == 15 and model.image_size == 256
    assert len(model.module.net.state_dict()) == 42
    summary = checkpoint_summary(tmp_path / "ref.pt")
    assert (summary["format"], summary["parameters"], summary["epoch"]) == ("reference", 504_449, 7)
    assert summary["channel_order"] == "BGR" and summary["dataset"] == "/data/hour1.hdf5"


def test_own_checkpoint_round_trip(tmp_path, tiny_model):
    path = tiny_model.save(tmp_path / "m.pt", step=3)
    loaded = load_checkpoint(path)
    assert loaded.meta.to_json() == tiny_model.meta.to_json()
    frames = np.random.default_rng(1).integers(0, 256, (15, 64, 64, 3), dtype=np.uint8)
    np.testing.assert_array_equal(loaded.predict(frames), tiny_model.predict(frames))
    # The file is weights-only: plain torch.load(weights_only=True) reads it.
    assert torch.load(path, weights_only=True)["step"] == 3


class _RunsCode:
    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_malicious_pickle_is_refused_and_never_runs(tmp_path):
    marker = tmp_path / "pwned"
    torch.save({"model_state_dict": _RunsCode(marker)}, tmp_path / "evil.pt")
    with open(tmp_path / "evil.pkl", "wb") as f:  # a legacy plain pickle too
        pickle.dump({"model_state_dict": _RunsCode(marker)}, f)
    for name in ("evil.pt", "evil.pkl"):
        with pytest.raises(UnsafeCheckpointError, match=f"{name}: refused to load"):
            load_checkpoint(tmp_path / name)
    assert not marker.exists()


def test_bad_checkpoints_have_clear_errors(tmp_path, tiny_model):
    with pytest.raises(CheckpointError, match="missing.pt: checkpoint file not found"):
        load_checkpoint(tmp_path / "missing.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint at all")
    with pytest.raises(CheckpointError, match="junk.pt: refused to load: not a weights-only"):
        load_checkpoint(tmp_path / "junk.pt")
    (tmp_path / "trunc.pt").write_bytes((tmp_path / "junk.pt").read_bytes()[:0] + b"PK\x03\x04")
    with pytest.raises(CheckpointError, match="trunc.pt: not a readable checkpoint"):
        load_checkpoint(tmp_path / "trunc.pt")
    torch.save({"weights": torch.zeros(3)}, tmp_path / "foreign.pt")
    with pytest.raises(CheckpointError, match="foreign.pt: neither a beadsight checkpoint"):
        load_checkpoint(tmp_path / "foreign.pt")
    ref = reference_training_dict(UNet(ModelConfig(width=8)), 64)
    ref["window_size"] = 10
    torch.save(ref, tmp_path / "window.pt")
    with pytest.raises(CheckpointError, match="window_size is 10 but the weights take 15"):
        load_checkpoint(tmp_path / "window.pt")
    ref = reference_training_dict(UNet(ModelConfig(width=8)), 64)
    del ref["model_state_dict"]["pred.bias"]
    torch.save(ref, tmp_path / "partial.pt")
    with pytest.raises(CheckpointError, match="partial.pt: weights do not fit"):
        load_checkpoint(tmp_path / "partial.pt")


@pytest.mark.parametrize(
    "frames, message",
    [
        (np.zeros((15, 64, 64), np.uint8), r"expected \(span, H, W, 3\)"),
        (np.zeros((15, 64, 64, 4), np.uint8), r"expected \(span, H, W, 3\)"),
        (np.zeros((15, 64, 64, 3), np.float32), "expected dtype uint8"),
        (
            np.zeros((14, 64, 64, 3), np.uint8),
            r"window of 14 frames.*expects span=15 \(frames=15, frame_stride=1\)",
        ),
        (np.zeros((15, 32, 32, 3), np.uint8), "32x32 px.*expects image_size=64x64"),
    ],
)
def test_predict_rejects_bad_frames(tiny_model, frames, message):
    with pytest.raises(ValueError, match=message):
        tiny_model.predict(frames)
