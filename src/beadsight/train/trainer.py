"""Training the BeadSight U-Net: ``train(TrainConfig(data=..., out=...)) -> run folder``.

Reference recipe (defaults): AdamW (lr 1e-4, weight decay 1e-4), batch 64, dropout
0.2, Gaussian input noise (std 0.05 on the normalised frames, training only), all 8
dihedral transforms, MSE on the normalised map ``target_kpa / output_scale_kpa``,
presses split 70/10/20 by a seeded shuffle.

The pieces: :mod:`~beadsight.train.config` (settings), :mod:`~beadsight.train.prepare`
(split, windows, a new / fine-tuned / resumed model), :mod:`~beadsight.train.step`
(one optimizer step), :mod:`~beadsight.train.distributed` (DDP),
:mod:`~beadsight.train.run` (the run folder and its checkpoints) and
:mod:`~beadsight.train.windows` (batches). This module runs the loop.

Learning rate: constant (the reference), or ``lr_schedule="cosine"``, decaying from
``lr`` to ``lr_min`` over the run's total steps. ``init`` starts the weights from an
existing checkpoint (fine-tuning, e.g. the shipped simulated-sensor model on a real
sensor's data).

``budget_min`` stops the run after that much wall-clock time (the schedule then spans
the budget; :mod:`~beadsight.train.budget`); ``presses``/``skip_presses`` train on a
part of the dataset's presses; ``train_layers="decoder"`` keeps the encoder fixed.

Checkpoints are written atomically every epoch, every ``checkpoint_every_steps``
steps and every ``checkpoint_every_min`` minutes, so a killed run loses little;
``resume=True`` continues from ``last.pt`` with the same split, optimizer state,
step count and batch order. A checkpoint that cannot be written (disk full) stops
the run with :class:`~beadsight.files.WriteError`; the previous checkpoint stays.
Under ``torchrun`` (``WORLD_SIZE`` > 1) training is data-parallel (DDP; NCCL on
GPUs, gloo on CPUs): windows are sharded like ``DistributedSampler``,
``batch_size`` is the global batch, and only rank 0 writes.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from beadsight.config import ConfigError
from beadsight.data.dataset import dataset_fingerprint, open_dataset
from beadsight.data.splits import SPLITS
from beadsight.errors import BeadSightError
from beadsight.files import WriteError
from beadsight.train.budget import Clock
from beadsight.train.config import TrainConfig
from beadsight.train.distributed import Distributed, resolve_device
from beadsight.train.prepare import (
    check_image_size,
    init_model,
    load_optimizer_state,
    load_resume,
    new_model,
    prepare_data,
    run_relative,
    split_record,
    split_used_presses,
    tampered_state_errors,
    trainable_parameters,
)
from beadsight.train.qat import QuantizationAware
from beadsight.train.run import CONFIG_FILE, SPLIT_FILE, RunFolder
from beadsight.train.step import autocast, model_inputs, optimizer_step
from beadsight.train.threads import training_threads
from beadsight.train.windows import (
    DeviceFrames,
    DeviceWindows,
    WindowDataset,
    WindowLoader,
    batches_per_epoch,
    choose_loader_mode,
)

logger = logging.getLogger(__name__)

MAX_LOG_INTERVAL_S = 60.0  # single-process runs also log at least this often


class Trainer:
    """One process's part of a training run: ``setup()``, ``loop()``, ``close()``."""

    def __init__(self, config: TrainConfig, dist: Distributed, device: torch.device):
        self.config, self.dist, self.device = config, dist, device
        self.run = RunFolder(config.out)
        self.step = 0
        self.elapsed_s = 0.0
        self.best: dict[str, Any] = {}
        self.resume_state: dict[str, Any] | None = None

    def _info(self, *args: Any) -> None:
        if self.dist.is_main:
            logger.info(*args)

    # --- setup ---
    def setup(self) -> None:
        config = self.config
        self.tuner = training_threads(config.threads, self.device, self.dist.world)
        self.run.check(config.resume)
        if self.dist.is_main and config.resume:
            self.run.remove_stale_temps()
        self.ds = open_dataset(config.data)
        self.ds.require_presses()
        image_size = check_image_size(config, self.ds)
        fingerprint = dataset_fingerprint(self.ds)
        model = None
        if config.resume:
            resumed = load_resume(self.run.last, config, image_size, fingerprint)
            model, split = resumed.model, resumed.split
            self.resume_state, self.step = resumed.state, resumed.step
            self.elapsed_s, self.best = resumed.elapsed_s, resumed.best
        else:
            split = split_used_presses(config, self.ds)
        self.data = prepare_data(config, self.ds, split, image_size, fingerprint)
        if model is None:
            make = init_model if config.init else new_model
            model = make(config, self.ds, self.data, info=self._info)
        self.model = model
        self.module = self.model.module.to(self.device).train()
        self.scale = float(self.model.meta.output_scale_kpa)
        if config.qat:
            self._quantization_aware()
        self._make_optimizer()
        self._make_loaders()
        self._write_run_files()

    def _quantization_aware(self) -> None:
        """Train the U-Net through int8 fake quantizers (train/qat.py)."""
        if self.dist.world > 1:
            raise ConfigError("--qat trains in one process; run it without torchrun")
        self.qat = QuantizationAware(self.model)
        if self.resume_state is not None:
            with tampered_state_errors(self.run.last):
                self.qat.restore(self.resume_state["qat_quantizers"])
        self._info(
            "quantization-aware: training through int8 quantizers at every convolution but "
            "the output's; checkpoints keep fp32 weights"
        )

    def _make_optimizer(self) -> None:
        config = self.config
        net = self.module.net
        self.optimizer = torch.optim.AdamW(
            trainable_parameters(net, config.train_layers),
            lr=config.lr,
            weight_decay=config.weight_decay,
        )
        self.scaler = torch.amp.GradScaler("cuda") if config.precision == "fp16" else None
        self.autocast_dtype = {"bf16": torch.bfloat16, "fp16": torch.float16}.get(config.precision)
        if self.resume_state is not None:
            with tampered_state_errors(self.run.last):
                load_optimizer_state(self.optimizer, self.resume_state["optimizer"])
                if self.scaler is not None and self.resume_state.get("scaler"):
                    self.scaler.load_state_dict(self.resume_state["scaler"])
                self._restore_rng(self.resume_state)
        else:
            torch.manual_seed(config.seed + self.dist.rank)  # noise/dropout differ by rank
        self.ddp = net
        if self.dist.world > 1:
            self.ddp = torch.nn.parallel.DistributedDataParallel(
                net, device_ids=[self.device.index] if self.device.type == "cuda" else None
            )

    def _restore_rng(self, state: dict) -> None:
        rng = state.get("rng_cpu")
        if isinstance(rng, list) and len(rng) > self.dist.rank:
            torch.set_rng_state(rng[self.dist.rank])
        cuda = state.get("rng_cuda")
        if self.device.type == "cuda" and isinstance(cuda, list) and len(cuda) > self.dist.rank:
            torch.cuda.set_rng_state(cuda[self.dist.rank], self.device)

    def _make_loaders(self) -> None:
        config, data, dist = self.config, self.data, self.dist
        if config.batch_size % dist.world:
            raise ConfigError(
                f"batch_size {config.batch_size} is not divisible by the {dist.world} processes"
            )
        per_rank, span = config.batch_size // dist.world, config.span
        copies = dist.local_world if self.device.type == "cpu" else 1
        mode = choose_loader_mode(
            config.loader,
            DeviceFrames.nbytes(data.frame_mask, data.image_size),
            self.device,
            copies,
        )
        if mode == "device":
            store = DeviceFrames.load(
                self.ds,
                data.frame_mask,
                data.image_size,
                self.device,
                progress=config.progress and dist.is_main,
            )
            sources = {name: DeviceWindows(store, data.labels[name], span) for name in data.labels}
        else:
            sources = {
                name: WindowDataset(config.data, data.labels[name], span) for name in data.labels
            }
        common = dict(
            device=self.device,
            seed=config.seed,
            rank=dist.rank,
            world_size=dist.world,
            num_workers=config.num_workers,
        )
        self.train_loader = WindowLoader(
            sources["train"], per_rank, shuffle=True, augment=config.augment, **common
        )
        self.val_loader = WindowLoader(
            sources["val"],
            per_rank,
            shuffle=False,
            augment=False,
            stride=config.val_stride,
            pad=False,
            **common,
        )
        self.loader_mode = mode
        self.steps_per_epoch = batches_per_epoch(len(data.labels["train"]), per_rank, dist.world)
        self._info(
            "%d train windows (%d steps/epoch), %d val windows, %d px, %s loader, device %s, %s",
            len(data.labels["train"]),
            self.steps_per_epoch,
            self.val_loader.num_windows,
            data.image_size,
            mode,
            self.device,
            config.precision,
        )

    def _write_run_files(self) -> None:
        if self.dist.is_main:
            self.run.path.mkdir(parents=True, exist_ok=True)
            resolved = {
                **self.config.to_dict(),
                "data": str(Path(self.config.data).resolve()),
                "out": str(self.run.path.resolve()),
            }
            self.run.write_json(CONFIG_FILE, resolved)
            self.run.write_json(SPLIT_FILE, split_record(self.config, self.ds, self.data))
            if self.config.resume:
                self.run.truncate_metrics(self.step)
                logger.info("resuming %s at step %d", self.run.path, self.step)
        self.dist.barrier()

    # --- checkpoints ---
    def _training_meta(self) -> dict[str, Any]:
        data = self.data
        return {
            "dataset_path": run_relative(self.config.data, self.config),
            "dataset_fingerprint": data.fingerprint,
            "split": {
                **{name: [int(i) for i in data.split[name]] for name in SPLITS},
                "num_presses": int(self.ds.num_presses),
            },
            "split_fractions": list(self.config.split),
            "split_seed": self.config.seed,
            "windows": {name: len(data.labels[name]) for name in data.labels},
            "config": self.config.to_dict(),
            "step": self.step,
            "epoch": self.step // self.steps_per_epoch,
            "steps_per_epoch": self.steps_per_epoch,
            "world_size": self.dist.world,
            "best_val": self.best,
        }

    def _rng_states(self) -> dict[str, Any]:
        """Every rank's RNG states (gathered to rank 0)."""
        cpu = torch.get_rng_state()
        cuda = torch.cuda.get_rng_state(self.device) if self.device.type == "cuda" else None
        cudas = self.dist.gather(cuda)
        return {"rng_cpu": self.dist.gather(cpu), "rng_cuda": cudas if cuda is not None else None}

    def save(self, best: bool = False) -> None:
        """Write last.pt (full training state) and, if ``best``, best.pt; all ranks call it.

        A failed write (disk full, ...) raises WriteError on every rank; the files keep
        their previous contents."""
        rng = self._rng_states()
        failure: WriteError | None = None
        if self.dist.is_main:
            self.model.meta.training = self._training_meta()
            saving = self.qat.saving() if self.config.qat else contextlib.nullcontext({})
            try:
                with saving as qat:  # --qat: the plain U-Net with the trained weights
                    self.run.save_checkpoints(
                        self.model,
                        best,
                        optimizer=self.optimizer.state_dict(),
                        scaler=self.scaler.state_dict() if self.scaler is not None else None,
                        step=self.step,
                        epoch=self.step // self.steps_per_epoch,
                        steps_per_epoch=self.steps_per_epoch,
                        elapsed_s=self._elapsed(),
                        best_val=self.best,
                        **rng,
                        **qat,
                    )
            except WriteError as e:
                failure = e
        if self.dist.any(failure is not None, self.device):  # all ranks stop together
            raise failure or WriteError(f"rank 0 could not write {self.run.last}")
        self._last_save = time.monotonic()

    # --- steps ---
    def _autocast(self):
        return autocast(self.device, self.autocast_dtype)

    def train_step(self, frames: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
        with self.tuner.timed():  # CPU threads chosen by the steps' times
            return optimizer_step(
                self.module,
                self.ddp,
                self.optimizer,
                frames,
                targets,
                output_scale_kpa=self.scale,
                noise_std=self.config.noise_std,
                color_jitter=self.config.color_jitter,
                autocast_dtype=self.autocast_dtype,
                scaler=self.scaler,
            )

    @torch.no_grad()
    def validate(self) -> dict[str, float] | None:
        """Mean squared error of the normalised map and MAE in kPa over the val windows."""
        self.module.eval()
        sums = torch.zeros(3, dtype=torch.float64, device=self.device)
        self.val_loader.set_epoch(0)
        bar = tqdm(
            self.val_loader,
            desc="validating",
            leave=False,
            mininterval=1.0,
            disable=not (self.config.progress and self.dist.is_main),
        )
        for frames, targets in bar:
            x = model_inputs(self.module, frames)  # no noise
            with self._autocast():
                out = self.module.net(x)[:, 0].float()
            sums[0] += ((out - targets / self.scale) ** 2).sum(dtype=torch.float64)
            sums[1] += (out * self.scale - targets).abs().sum(dtype=torch.float64)
            sums[2] += targets.numel()
        self.module.train()
        sums = self.dist.all_reduce(sums).tolist()
        if sums[2] == 0:
            return None
        return {"val_loss": sums[0] / sums[2], "val_mae_kpa": sums[1] / sums[2]}

    # --- the loop ---
    def _elapsed(self) -> float:
        return self.clock.elapsed()

    def _log(self, **values: Any) -> None:
        if self.dist.is_main:
            line = self.run.log(
                step=self.step,
                epoch=round(self.step / self.steps_per_epoch, 4),
                lr=self.optimizer.param_groups[0]["lr"],
                time_s=round(self._elapsed(), 3),
                wall_time=round(time.time(), 3),
                **values,
            )
            logger.debug("metrics %s", line)

    def _new_interval(self) -> dict[str, Any]:
        """The training loss summed since the last log, its steps and when it began."""
        return {"loss_sum": torch.zeros((), device=self.device), "steps": 0, "t0": time.monotonic()}

    def _flush_interval(self) -> tuple[float | None, bool]:
        """Log the mean training loss since the last log (over all ranks); returns it and
        whether a timed checkpoint is due (agreed by all ranks)."""
        iv = self._interval
        due = time.monotonic() - self._last_save >= 60 * self.config.checkpoint_every_min
        if iv["steps"] == 0:
            return None, due
        packed = torch.stack(
            [
                iv["loss_sum"].double(),
                torch.tensor(float(due), device=self.device, dtype=torch.float64),
            ]
        )
        packed = self.dist.all_reduce(packed).tolist()
        loss = packed[0] / (iv["steps"] * self.dist.world)
        if not math.isfinite(loss):
            raise BeadSightError(
                f"training diverged: loss {loss} at step {self.step}; the last good checkpoint is "
                f"{self.run.last} (try a lower lr, or precision fp32)"
            )
        seconds = time.monotonic() - iv["t0"]
        samples = iv["steps"] * self.config.batch_size
        rate, threads = samples / max(seconds, 1e-9), torch.get_num_threads()
        self._log(event="train", train_loss=loss, samples_per_s=rate, threads=threads)
        self._epoch_loss[0] += loss * iv["steps"]
        self._epoch_loss[1] += iv["steps"]
        self._interval = self._new_interval()
        return loss, packed[1] > 0

    def _after_step(self, bar: tqdm) -> None:
        config, single = self.config, self.dist.world == 1
        now = time.monotonic()
        log_due = self.step % config.log_every_steps == 0 or (
            single and now - self._interval["t0"] >= MAX_LOG_INTERVAL_S
        )
        timed_save = False
        if log_due:
            loss, timed_save = self._flush_interval()
            if loss is not None:
                bar.set_postfix(loss=f"{loss:.4g}", refresh=False)
        elif single:  # no collective needed to agree on the clock
            timed_save = now - self._last_save >= 60 * config.checkpoint_every_min
        if single and self.clock.validation_due():
            self._end_of_epoch()  # validates, keeps best.pt, saves last.pt
        elif timed_save or self.step % config.checkpoint_every_steps == 0:
            self.save()

    def _end_of_epoch(self) -> None:
        self._flush_interval()
        total, n = self._epoch_loss
        train_loss = total / n if n else None
        self._epoch_loss = [0.0, 0]
        metrics = self.validate()
        key = "val_loss" if metrics else "train_loss"
        value = metrics["val_loss"] if metrics else train_loss
        improved = value is not None and value < self.best.get(key, math.inf)
        if improved:
            self.best = {
                key: value,
                **(metrics or {}),
                "step": self.step,
                "epoch": self.step // self.steps_per_epoch,
            }
        self._log(event="val", train_loss=train_loss, **(metrics or {}))
        if metrics and self.dist.is_main:
            logger.info(
                "step %d: val loss %.5f, val MAE %.4f kPa%s",
                self.step,
                metrics["val_loss"],
                metrics["val_mae_kpa"],
                " (best)" if improved else "",
            )
        self.save(best=improved or not self.run.best.is_file())
        self.clock.validated()

    def loop(self) -> None:
        config, spe = self.config, self.steps_per_epoch
        total = config.steps if config.steps is not None else config.epochs * spe
        self.clock = clock = Clock(config, self.elapsed_s)
        self._last_save = time.monotonic()
        self._interval = self._new_interval()
        self._epoch_loss = [0.0, 0]
        if self.step >= total or clock.exhausted():
            logger.info("run %s already reached step %d of %d", self.run.path, self.step, total)
            return
        bar = clock.bar(self.step, total, disable=not (config.progress and self.dist.is_main))
        if config.val_at_start and self.step == 0:
            self._end_of_epoch()  # the initial weights are a candidate for best.pt
        try:
            while self.step < total and not self._out_of_time():
                epoch, skip = divmod(self.step, spe)
                self.train_loader.set_epoch(epoch, skip)
                start = self.step
                for frames, targets in self.train_loader:
                    for group in self.optimizer.param_groups:
                        group["lr"] = config.learning_rate(self.step, total, clock.progress())
                    self._interval["loss_sum"] += self.train_step(frames, targets)
                    self._interval["steps"] += 1
                    self.step += 1
                    clock.advance(bar)
                    if self.step % spe == 0 or self.step >= total or self._out_of_time():
                        break  # the epoch's end saves
                    self._after_step(bar)
                if self.step == start:
                    raise RuntimeError(f"epoch {epoch} yielded no training batch (skip {skip})")
                self._end_of_epoch()
        except KeyboardInterrupt:
            if self.dist.world == 1:
                logger.warning("interrupted at step %d: saving %s", self.step, self.run.last)
                self.save()
            raise
        finally:
            bar.close()

    def _out_of_time(self) -> bool:
        """The budget is spent (agreed by all ranks, which stop together)."""
        if self.clock.limit_s is None:
            return False
        return self.dist.any(self.clock.exhausted(), self.device)

    def close(self) -> None:
        if getattr(self, "tuner", None) is not None:
            self.tuner.restore()
        for loader in (getattr(self, "train_loader", None), getattr(self, "val_loader", None)):
            if loader is not None and isinstance(loader.source, WindowDataset):
                loader.source.close()
        if getattr(self, "ds", None) is not None:
            self.ds.close()


def train(config: TrainConfig) -> Path:
    """Train a pressure model as ``config`` says; returns the run folder.

    Under ``torchrun`` every process calls this; it joins (or starts) the process
    group, and only rank 0 writes files.
    """
    device = resolve_device(config.device, config.precision)
    dist = Distributed.start(device)
    trainer = Trainer(config, dist, device)
    try:
        trainer.setup()
        trainer.loop()
    finally:
        trainer.close()
        dist.close()
    return Path(config.out)
