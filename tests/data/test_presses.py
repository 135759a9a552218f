import numpy as np

from beadsight.config import REFERENCE_G_TO_N, ContactThresholds
from beadsight.data.presses import contact_state, segment_presses
from beadsight.data.splits import split_presses, window_ends

G = REFERENCE_G_TO_N


def grams(*values):
    return np.array(values, dtype=float) * G


def test_hysteresis_on_slow_ramps():
    # Loading ramp hovers between 10 g and 50 g: no contact until 50 g is reached;
    # unloading hovers between: contact holds until <= 10 g.
    f = grams(0, 20, 45, 30, 49, 50, 80, 40, 20, 11, 30, 10, 5, 45)
    c = contact_state(f, np.ones(len(f), bool), ContactThresholds())
    assert c.tolist() == [0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 1, 0, 0, 0]


def test_last_press_kept_and_cycles_cover_every_frame():
    f = grams(0, 0, 100, 100, 0, 0, 0, 0, 100, 100)  # second press never released
    contact, press_id, presses = segment_presses(f, np.ones(len(f), bool))
    assert presses.tolist() == [[2, 4], [8, 10]]
    assert press_id.tolist() == [0, 0, 0, 0, 0, 0, 1, 1, 1, 1]
    assert contact.sum() == 4


def test_invalid_frames_and_moves_split_presses():
    f = grams(100, 100, 100, 100, 100, 100)
    valid = np.array([1, 1, 0, 1, 1, 1], bool)
    pos = np.array([[0, 0]] * 5 + [[5, 5]], float)
    _, _, presses = segment_presses(f, valid, pos)
    assert presses.tolist() == [[0, 2], [3, 5], [5, 6]]


def test_no_presses():
    contact, press_id, presses = segment_presses(grams(0, 1, 2), np.ones(3, bool))
    assert len(presses) == 0 and (press_id == -1).all() and not contact.any()


def test_split_is_seeded_disjoint_and_complete():
    a, b = split_presses(50, seed=3), split_presses(50, seed=3)
    assert all((a[k] == b[k]).all() for k in a)
    ids = np.concatenate([a["train"], a["val"], a["test"]])
    assert sorted(ids.tolist()) == list(range(50))
    assert (len(a["train"]), len(a["val"]), len(a["test"])) == (35, 5, 10)
    assert not (split_presses(50, seed=4)["test"] == a["test"]).all()


def test_window_ends_cover_valid_history_across_press_boundaries():
    """Issue 13 item 7: a window needs span valid, unbroken frames, whatever press they
    belong to; the end frame's press decides its split."""
    press_id = np.array([0] * 6 + [1] * 6)
    valid = np.ones(12, bool)
    valid[9] = False
    assert window_ends(press_id, valid, 4).tolist() == [3, 4, 5, 6, 7, 8]
    assert window_ends(press_id, valid, 2).tolist() == [1, 2, 3, 4, 5, 6, 7, 8, 11]
    assert window_ends(press_id, valid, 2, presses=[1]).tolist() == [6, 7, 8, 11]
    assert window_ends(press_id, valid, 2, presses=[0]).tolist() == [1, 2, 3, 4, 5]
    # a break (dropped frames) starts the history again, like an invalid frame
    breaks = np.zeros(12, bool)
    breaks[4] = True
    assert window_ends(press_id, valid, 4, breaks=breaks).tolist() == [3, 7, 8]
    # frames of no press cycle (a recording without presses) end no window
    assert window_ends(np.full(12, -1), valid, 2).tolist() == []
