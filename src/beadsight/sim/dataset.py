"""Record a simulated calibration session as a dataset in this project's format.

Ground truth is made the way a real rig makes it, so nothing leaks that a real
recording would not hold:

* **force** is the simulated *scale's* readings (HX711 rate, averaging, noise,
  tare drift, two decimals), linearly interpolated to the frame timestamps, as
  the processing of a real recording interpolates its force log. The true
  contact force is never stored;
* **position** is the *commanded* printer XY (the last press position sent);
* **valid** is False for frames outside the span of the scale's log (before its
  first reading or after its last), as for real recordings.

Frames stream to :class:`~beadsight.data.dataset_writer.DatasetWriter` in small chunks
(memory stays bounded for any number of presses); a frame is written as soon as
the scale has read past its timestamp.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from pathlib import Path

import numpy as np

from beadsight import __version__
from beadsight.config import REFERENCE_G_TO_N
from beadsight.data.dataset import open_dataset
from beadsight.data.dataset_writer import DatasetWriter
from beadsight.errors import BeadSightError
from beadsight.files import free_bytes
from beadsight.sim.config import PRESET_BEAD_COUNTS, SimConfig
from beadsight.sim.looks import resolve_looks
from beadsight.sim.press import check_profile
from beadsight.sim.session import SimFrame, SimulatedSession
from beadsight.sim.variety import FACTOR_NAMES, SPLITS

logger = logging.getLogger(__name__)

WRITE_CHUNK_FRAMES = 64  # frames buffered before a write
# Per-pouch factors are stored in the provenance (an HDF5 attribute) up to this size;
# beyond it only the seed, which re-draws them (see variety_provenance).
MAX_BUILDS_JSON_BYTES = 32_000
FACTOR_DIGITS = 5  # significant digits of the stored factors
# size of the frames written, as a fraction of raw uint8, measured on 300 simulated 256 px
# frames (h5py, one frame per chunk): none 59.0 MB, gzip 51.9 MB, lzf 57.2 MB
COMPRESSED_FRACTION = {None: 1.0, "gzip": 0.88, "lzf": 0.97}
LABEL_BYTES_PER_FRAME = 64  # force, position, valid, timestamp, contact, press id
SPACE_MARGIN = 1.1  # free space asked for beyond the expected size


class SimulationError(BeadSightError, ValueError):
    """Bad arguments for a simulation (the message names the argument or file)."""


def sim_config_for(
    n_beads: int | None = None,
    image_size: int | None = None,
    fps: float | None = None,
    config: SimConfig | None = None,
) -> SimConfig:
    """A :class:`SimConfig`: ``config`` (default: the preset for ``n_beads``, or 100 beads)
    with ``n_beads``, ``image_size`` and ``fps`` applied where given."""
    if config is None:
        beads = 100 if n_beads is None else int(n_beads)
        config = (
            SimConfig.preset(beads) if beads in PRESET_BEAD_COUNTS else SimConfig(n_beads=beads)
        )
    changes = {}
    if n_beads is not None and n_beads != config.n_beads:
        changes["n_beads"] = int(n_beads)
    if image_size is not None:
        changes["image_size_px"] = int(image_size)
    if fps is not None:
        changes["fps"] = float(fps)
    return dataclasses.replace(config, **changes) if changes else config


class ScaleLog:
    """The scale's readings so far, and interpolation of them to frame times (as datasets label)."""

    def __init__(self) -> None:
        self.t: list[float] = []
        self.grams: list[float] = []

    def add(self, readings) -> None:
        for t, g in readings:
            self.t.append(t)
            self.grams.append(g)

    @property
    def last_s(self) -> float:
        return self.t[-1] if self.t else -np.inf

    def at(self, timestamp_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Force (N) interpolated at ``timestamp_s`` and ``valid`` (inside the log's span)."""
        if not self.t:
            return np.zeros(len(timestamp_s)), np.zeros(len(timestamp_s), bool)
        t = np.asarray(self.t)
        force = np.interp(timestamp_s, t, np.asarray(self.grams)) * REFERENCE_G_TO_N
        valid = (timestamp_s >= t[0]) & (timestamp_s <= t[-1])
        return force, valid


def simulate_dataset(
    out: str | Path,
    presses: int,
    seed: int = 0,
    n_beads: int | None = None,
    image_size: int | None = None,
    fps: float | None = None,
    *,
    config: SimConfig | None = None,
    compression: str | None = None,
    pouches: int = 1,
    variety: str | None = None,
    profile: str = "reference",
    overwrite: bool = False,
    progress: bool = True,
    workers: int = 1,
    looks: str | None = None,
) -> Path:
    """Simulate ``presses`` presses and write them as a dataset at ``out``. Returns the path.

    n_beads / image_size / fps override ``config`` (default: the preset for
    ``n_beads``, 100 beads, 256 px, 30 fps). compression: HDF5 filter for the
    frames (None or "gzip"/"lzf"). pouches: spread the presses over this many
    pouches (a fresh pouch every ``ceil(presses / pouches)`` presses), so a model
    trained on the dataset meets more than one bead arrangement and look. variety:
    ``"train"`` or ``"heldout"``: each pouch is a different build drawn from that
    split of :mod:`beadsight.sim.variety` (``config`` is the base: image size, fps,
    rig). profile: how the presses move, one of :data:`~beadsight.sim.press.PROFILES`
    (``"mixed"``: long holds, slow ramps and depth changes while held, for
    rest-referenced training; see :func:`~beadsight.sim.press.draw_profile`). An existing ``out`` is refused unless ``overwrite``. Frames are RGB;
    provenance records the seed, the pouches, the full config and each build's factors.
    looks: ``"train"``, ``"heldout"`` or a family of :mod:`beadsight.sim.looks`: each
    pouch draws a look (on top of its build, with ``variety``); provenance records
    each pouch's family (``simulator.looks.pouch_families``) and drawn values.
    workers > 1: simulate in that many processes, each a shard of whole pouches with
    its own seed (spawned from ``seed``), joined into ``out`` in shard order (see
    :func:`simulate_sharded`); the same seed and workers give the same dataset.
    """
    out = Path(out)
    _check_arguments(
        out, presses, pouches, compression, variety, workers, overwrite, profile, looks
    )
    cfg = sim_config_for(n_beads, image_size, fps, config)
    if workers > 1 and pouches > 1:
        return simulate_sharded(
            out,
            presses,
            seed,
            cfg,
            pouches,
            int(workers),
            compression=compression,
            variety=variety,
            profile=profile,
            progress=progress,
            looks=looks,
        )
    per_pouch = math.ceil(presses / pouches) if pouches > 1 else None
    session = SimulatedSession(
        cfg,
        seed,
        int(presses),
        presses_per_pouch=per_pouch,
        variety=variety,
        profile=profile,
        looks=looks,
    )
    provenance = {
        "source": "sim",
        "simulator": {
            "seed": int(seed),
            "presses": int(presses),
            "pouches": int(pouches),
            "presses_per_pouch": per_pouch,
            "profile": profile,
            "config": cfg.to_dict(),
            "beadsight_version": __version__,
            **({} if variety is None else {"variety": variety_provenance(session, pouches)}),
            **({} if looks is None else {"looks": looks_provenance(session, pouches)}),
        },
        "force": "simulated HX711 scale readings (grams), linearly interpolated to frame times",
        "position": "commanded printer XY, mm from the sensor centre",
    }
    total = session.num_frames()
    expected = check_free_space(out, total, cfg.image_size_px, compression)
    logger.info(
        "simulating %d presses (%d frames, %d px) -> %s, about %.2f GB",
        presses,
        total,
        cfg.image_size_px,
        out,
        expected / 1e9,
    )
    with DatasetWriter(
        out, cfg.geometry, fps=cfg.fps, provenance=provenance, compression=compression
    ) as writer:
        _record(session, writer, total, progress)
    return out


def check_free_space(out: Path, frames: int, image_size: int, compression: str | None) -> int:
    """The expected size of the dataset in bytes (:data:`COMPRESSED_FRACTION`);
    SimulationError if ``out``'s disk has not that much free (with :data:`SPACE_MARGIN`)."""
    frame = image_size * image_size * 3 * COMPRESSED_FRACTION[compression]
    expected = int(frames * (frame + LABEL_BYTES_PER_FRAME))
    free = free_bytes(out.resolve().parent if out.parent.exists() else Path.cwd())
    if free < expected * SPACE_MARGIN:
        raise SimulationError(
            f"{out}: the dataset needs about {expected / 1e9:.2f} GB ({frames} frames of "
            f"{image_size} px, compression {compression or 'none'}), and its disk has "
            f"{free / 1e9:.2f} GB free; free space, or simulate fewer presses or a smaller "
            "--image-size"
        )
    return expected


def _check_arguments(
    out, presses, pouches, compression, variety, workers, overwrite, profile, looks=None
) -> None:
    def positive_int(value) -> bool:
        return not isinstance(value, bool) and int(value) == value and value >= 1

    if not positive_int(presses):
        raise SimulationError(f"presses must be a positive integer, got {presses!r}")
    if out.exists() and not overwrite:
        raise SimulationError(f"{out}: already exists; choose another --out or remove it")
    if not positive_int(pouches) or pouches > presses:
        raise SimulationError(f"pouches must be an integer in [1, presses], got {pouches!r}")
    if compression not in (None, "gzip", "lzf"):
        raise SimulationError(f"compression must be None, 'gzip' or 'lzf', got {compression!r}")
    if variety is not None and variety not in SPLITS:
        raise SimulationError(f"variety must be None or one of {SPLITS}, got {variety!r}")
    check_profile(profile)  # a ConfigError naming the profiles
    if not positive_int(workers):
        raise SimulationError(f"workers must be a positive integer, got {workers!r}")
    if looks is not None:
        resolve_looks(looks)  # a ConfigError naming the splits and families


def variety_provenance(session: SimulatedSession, pouches: int) -> dict:
    """What a variety dataset records of its builds: the split, and each pouch's factors
    (rounded; omitted past MAX_BUILDS_JSON_BYTES - the session's seed re-draws them:
    ``SimulatedSession(config, seed, presses, presses_per_pouch=..., variety=split)
    .pouch_build(i)``). Pouch ``i`` holds presses ``i * presses_per_pouch ...``."""
    rows = [
        [
            float(f"{session.pouch_build(i).factors[name]:.{FACTOR_DIGITS}g}")
            for name in FACTOR_NAMES
        ]
        for i in range(pouches)
    ]
    record: dict = {"split": session.variety, "factor_names": list(FACTOR_NAMES)}
    if len(json.dumps(rows)) <= MAX_BUILDS_JSON_BYTES:
        record["pouch_factors"] = rows
    else:
        record["pouch_factors"] = f"omitted ({pouches} pouches): re-draw them from the seed"
    return record


def looks_provenance(session: SimulatedSession, pouches: int) -> dict:
    """What a looks dataset records: the split or family asked for, and each pouch's
    drawn family and values (values omitted past MAX_BUILDS_JSON_BYTES; the session's
    seed re-draws them: ``SimulatedSession(..., looks=...).pouch_look(i)``)."""
    drawn = [session.pouch_look(i) for i in range(pouches)]
    record: dict = {
        "looks": session.looks,
        "pouch_families": [d.family for d in drawn],
    }
    values = [
        {k: (round(v, FACTOR_DIGITS) if isinstance(v, float) else v) for k, v in d.values.items()}
        for d in drawn
    ]
    if len(json.dumps(values)) <= MAX_BUILDS_JSON_BYTES:
        record["pouch_values"] = values
    else:
        record["pouch_values"] = f"omitted ({pouches} pouches): re-draw them from the seed"
    return record


def _record(
    session: SimulatedSession, writer: DatasetWriter, total: int | None, progress: bool
) -> None:
    from tqdm import tqdm

    log = ScaleLog()
    pending: list[SimFrame] = []
    with tqdm(total=total, unit="frame", desc="simulate", disable=not progress) as bar:
        for frame in session:
            log.add(frame.scale_readings)
            pending.append(frame)
            # A frame can be written once the scale has read past it.
            ready = sum(1 for f in pending if f.timestamp_s <= log.last_s)
            if ready >= WRITE_CHUNK_FRAMES:
                _flush(writer, pending[:ready], log)
                del pending[:ready]
            bar.update(1)
        if pending:
            _flush(writer, pending, log)


def _flush(writer: DatasetWriter, frames: list[SimFrame], log: ScaleLog) -> None:
    t = np.array([f.timestamp_s for f in frames])
    force, valid = log.at(t)
    writer.append(
        np.stack([f.frame_rgb for f in frames]),
        force,
        np.stack([f.commanded_xy_mm for f in frames]),
        valid,
        t,
    )


SHARD_GAP_S = 1.0  # idle time between two shards joined into one dataset


def _shard_plan(presses: int, pouches: int, workers: int, seed: int) -> list[tuple[int, int, int]]:
    """(presses, pouches, seed) of each shard: whole pouches, as even as they split."""
    per_pouch = math.ceil(presses / pouches)
    pouch_counts = [len(a) for a in np.array_split(np.arange(pouches), min(workers, pouches))]
    seeds = [
        int(s.generate_state(1)[0]) for s in np.random.SeedSequence(seed).spawn(len(pouch_counts))
    ]
    plan, left = [], presses
    for count, shard_seed in zip(pouch_counts, seeds, strict=True):
        n = min(left, count * per_pouch)
        if n > 0:
            plan.append((n, min(count, n), shard_seed))
            left -= n
    return plan


def simulate_sharded(
    out: str | Path,
    presses: int,
    seed: int,
    cfg: SimConfig,
    pouches: int,
    workers: int,
    *,
    compression: str | None = None,
    variety: str | None = None,
    profile: str = "reference",
    progress: bool = True,
    looks: str | None = None,
) -> Path:
    """Simulate shards of whole pouches in ``workers`` processes and join them into ``out``.

    Shard ``k`` is a session of its own (seed ``SeedSequence(seed).spawn(...)[k]``);
    the joined dataset keeps each shard's frames and labels and shifts its timestamps
    to follow the previous shard after ``SHARD_GAP_S`` (presses are found from force,
    so they stay as they were). Shard files live in a temporary folder beside ``out``
    and are removed; ``out`` appears only when complete.
    """
    import tempfile
    from concurrent.futures import ProcessPoolExecutor

    from tqdm import tqdm

    out = Path(out)
    plan = _shard_plan(presses, pouches, workers, seed)
    with tempfile.TemporaryDirectory(prefix=f".{out.name}.shards-", dir=out.parent) as tmp:
        paths = [str(Path(tmp) / f"shard{k:03d}.h5") for k in range(len(plan))]
        with ProcessPoolExecutor(max_workers=workers) as pool:
            shard_args = dict(
                config=cfg, compression=compression, variety=variety, profile=profile, looks=looks
            )
            jobs = [
                pool.submit(simulate_dataset, path, n, s, pouches=p, progress=False, **shard_args)
                for path, (n, p, s) in zip(paths, plan, strict=True)
            ]
            for job in tqdm(jobs, unit="shard", desc="simulate", disable=not progress):
                job.result()
        with open_dataset(paths[0]) as first:
            provenance = {k: v for k, v in first.provenance.items() if k != "created_unix"}
        shard_looks = []
        for path in paths if looks is not None else ():
            with open_dataset(path) as shard:
                shard_looks.append(shard.provenance["simulator"]["looks"])
        sim = provenance["simulator"]
        sim.update(
            seed=int(seed),
            presses=int(presses),
            pouches=int(pouches),
            workers=int(workers),
            presses_per_pouch=math.ceil(presses / pouches),
            shards=[{"presses": n, "pouches": p, "seed": s} for n, p, s in plan],
        )
        if variety is not None:
            sim["variety"]["pouch_factors"] = "per shard: re-draw them from each shard's seed"
        if looks is not None:  # every pouch's family, in the joined dataset's order
            sim["looks"]["pouch_families"] = [f for s in shard_looks for f in s["pouch_families"]]
            values = (
                [v for s in shard_looks for v in s["pouch_values"]]
                if all(isinstance(s["pouch_values"], list) for s in shard_looks)
                else "per shard: re-draw them from each shard's seed"
            )
            if len(json.dumps(values)) > MAX_BUILDS_JSON_BYTES:
                values = "per shard: re-draw them from each shard's seed"
            sim["looks"]["pouch_values"] = values
        with DatasetWriter(
            out, cfg.geometry, fps=cfg.fps, provenance=provenance, compression=compression
        ) as writer:
            _join(writer, paths)
    return out


def _join(writer: DatasetWriter, paths: list[str]) -> None:
    next_start = None
    for path in paths:
        with open_dataset(path) as shard:
            t = shard.timestamp_s
            shift = 0.0 if next_start is None else next_start - t[0]
            for a in range(0, len(shard), 1024):
                b = min(a + 1024, len(shard))
                writer.append(
                    shard.read_frames(a, b),
                    shard.force_n[a:b],
                    shard.position_mm[a:b],
                    shard.valid[a:b],
                    t[a:b] + shift,
                )
            next_start = t[-1] + shift + SHARD_GAP_S
