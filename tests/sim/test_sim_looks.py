"""Look families: deterministic, measurably different, held-out families kept out of training."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from beadsight.cli import main
from beadsight.data.dataset import open_dataset
from beadsight.errors import ConfigError
from beadsight.sim import PouchSimulator, SimConfig, SimulatedSession, simulate_dataset
from beadsight.sim.looks import (
    FAMILIES,
    FAMILY_NAMES,
    LOOK_SPLITS,
    LookDraws,
    family_table,
    resolve_looks,
    sample_look,
)

SIZE = 48
DT = 1 / 30

# sha256 (first 16 hex digits) of the reference look's frames, recorded before looks
# existed: the shipped model and many tests depend on these exact renders.
REFERENCE_SIM64 = "3650d861fcdcfcb9"  # PouchSimulator(SimConfig(image_size_px=64), 7), 12 frames
REFERENCE_SESSION64 = "bcf48315126b72d5"  # SimulatedSession(64 px, seed 3, 2 presses, 1 per pouch)


def _digest(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()[:16]


def family_frames(family: str, seed: int, size: int = SIZE, pressed: bool = True) -> np.ndarray:
    """(2, S, S, 3) uint8: a pouch of ``family`` at rest and pressed ((1, S, S, 3): at rest
    only, unless ``pressed``)."""
    look = sample_look(np.random.default_rng(seed), family, SimConfig(image_size_px=size))
    sim = PouchSimulator(look.config, seed)
    sim.step(DT, (0.0, 0.0), -1.0)
    rest = sim.render()
    if not pressed:
        return rest[None]
    for _ in range(15):
        sim.step(DT, (3.0, -2.0), 1.3)
    return np.stack([rest, sim.render()])


def test_the_reference_look_is_unchanged():
    sim = PouchSimulator(SimConfig(image_size_px=64), 7)
    digests = []
    for k in range(12):
        sim.step(DT, (3.0, -2.0), 0.12 * k)
        digests.append(_digest(sim.render()))
    assert _digest(np.array(digests)) == REFERENCE_SIM64
    session = SimulatedSession(SimConfig(image_size_px=64), 3, 2, presses_per_pouch=1)
    assert _digest(np.stack([f.frame_rgb for f in session])) == REFERENCE_SESSION64


def test_splits_cover_every_family_and_hold_two_out():
    assert len(FAMILIES) >= 5
    train, heldout = set(LOOK_SPLITS["train"]), set(LOOK_SPLITS["heldout"])
    assert len(heldout) == 2 and not train & heldout
    assert train | heldout == set(FAMILY_NAMES)
    assert all(FAMILIES[f].doc.startswith("HELD OUT") for f in heldout)


@pytest.mark.parametrize("family", FAMILY_NAMES)
def test_every_family_renders_deterministically(family):
    a, b, c = family_frames(family, 5), family_frames(family, 5), family_frames(family, 6)
    assert a.shape == (2, SIZE, SIZE, 3) and a.dtype == np.uint8
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    assert a[0].std() > 8  # beads are visible
    assert np.abs(a[1].astype(int) - a[0]).mean() > 0.5  # a press shows


def _stats(family: str) -> np.ndarray:
    """Mean over 3 pouches of per-channel mean and std and the saturation of a frame."""
    rows = []
    for seed in range(3):
        f = family_frames(family, seed, pressed=False)[0].reshape(-1, 3).astype(float)
        saturation = (f.max(1) - f.min(1)).mean()
        rows.append([*f.mean(0), *f.std(0), saturation])
    return np.mean(rows, axis=0)


def test_families_differ_measurably():
    stats = {f: _stats(f) for f in FAMILY_NAMES}
    ref = PouchSimulator(SimConfig(image_size_px=SIZE), 0)
    ref.step(DT, (0, 0), -1)
    f = ref.render().reshape(-1, 3).astype(float)
    stats["reference"] = np.array([*f.mean(0), *f.std(0), (f.max(1) - f.min(1)).mean()])
    names = list(stats)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            if {a, b} == {"coloured", "reference"}:
                continue  # the coloured family is today's look, give or take
            distance = np.abs(stats[a] - stats[b]).max()
            assert distance > 8, (a, b, stats[a].round(1), stats[b].round(1))


def test_heldout_families_never_appear_under_train():
    draws = LookDraws("train", 11)
    assert {draws.drawn(i)[0] for i in range(200)} == set(LOOK_SPLITS["train"])
    rng = np.random.default_rng(0)
    assert {sample_look(rng, "heldout").family for _ in range(40)} == set(LOOK_SPLITS["heldout"])
    assert {sample_look(rng, "mono").family for _ in range(5)} == {"mono"}


def test_a_bad_family_name_names_the_valid_ones():
    with pytest.raises(ConfigError) as err:
        resolve_looks("pink")
    message = str(err.value)
    assert "'pink'" in message and all(name in message for name in (*LOOK_SPLITS, *FAMILY_NAMES))
    with pytest.raises(ConfigError, match="looks must be"):
        SimulatedSession(SimConfig(image_size_px=SIZE), 0, 1, looks="pink")


def test_bad_look_fields_are_refused():
    with pytest.raises(ConfigError, match="background_pattern"):
        SimConfig(background_pattern="plaid")
    with pytest.raises(ConfigError, match="n_leds"):
        SimConfig(n_leds=0)


def test_session_draws_a_look_per_pouch_on_top_of_its_build():
    cfg = SimConfig(image_size_px=SIZE)
    a = SimulatedSession(cfg, 4, 6, presses_per_pouch=1, looks="train", render=False)
    b = SimulatedSession(cfg, 4, 6, presses_per_pouch=1, looks="train", render=False)
    families = [a.pouch_look(i).family for i in range(6)]
    assert families == [b.pouch_look(i).family for i in range(6)]
    assert a.pouch_config(2) == a.pouch_look(2).config
    # the mechanics' and plan's streams are those of a session without looks
    plain = SimulatedSession(cfg, 4, 6, presses_per_pouch=1, render=False)
    assert [p.xy_mm.tolist() for p in plain.presses] == [p.xy_mm.tolist() for p in a.presses]
    with_variety = SimulatedSession(cfg, 4, 2, looks="clear", variety="train", render=False)
    build, look = with_variety.pouch_build(0), with_variety.pouch_look(0)
    assert look.config.n_beads == build.config.n_beads  # the build's pouch ...
    assert look.config.bead_clarity > 0  # ... with the look's beads
    with pytest.raises(ConfigError, match="no looks"):
        plain.pouch_look(0)


def test_dataset_and_cli_record_each_pouchs_family(tmp_path):
    # 10 fps: a third of the frames; what is checked here is the provenance, not the frames.
    out = simulate_dataset(
        tmp_path / "looks.h5",
        3,
        seed=2,
        image_size=32,
        fps=10.0,
        pouches=3,
        looks="heldout",
        progress=False,
    )
    with open_dataset(out) as ds:
        looks = ds.provenance["simulator"]["looks"]
    assert looks["looks"] == "heldout" and len(looks["pouch_families"]) == 3
    assert set(looks["pouch_families"]) <= set(LOOK_SPLITS["heldout"])
    session = SimulatedSession(
        SimConfig(image_size_px=32, fps=10.0), 2, 3, presses_per_pouch=1, looks="heldout"
    )
    assert looks["pouch_families"] == [session.pouch_look(i).family for i in range(3)]
    cli = tmp_path / "cli.h5"
    argv = ["simulate", "--out", str(cli), "--presses", "4", "--pouches", "4", "--seed", "1"]
    argv += ["--image-size", "32", "--fps", "10", "--looks", "train", "--workers", "2"]
    argv += ["--no-progress"]
    assert main(argv) == 0
    with open_dataset(cli) as ds:
        looks = ds.provenance["simulator"]["looks"]
        assert ds.num_presses == 4
    assert len(looks["pouch_families"]) == 4 and len(looks["pouch_values"]) == 4
    assert set(looks["pouch_families"]) <= set(LOOK_SPLITS["train"])


def test_family_table_lists_every_family_and_is_the_documented_one():
    table = family_table()
    assert all(f"`{name}`" in table for name in FAMILY_NAMES)
    doc = (Path(__file__).parents[2] / "docs" / "simulator.md").read_text(encoding="utf-8")
    assert table in doc  # the documented ranges are the code's
