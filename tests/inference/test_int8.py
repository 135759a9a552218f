"""The int8 runtime (OpenVINO + NNCF) and the metric-level gate it must pass.

Measured here, not assumed: NNCF's default post-training quantization
(:data:`NNCF_DEFAULT`) of the shipped simulator model (64 px, width 8, rest-referenced)
raises its pressure MAE by 18 % and its force error by 31 % on held-out simulated
presses, so the gate must refuse it, by name, with the metric; the default recipe
(:data:`ACCURATE`) keeps every metric within a few % and is accepted.
"""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from beadsight.assets import shipped_model_path
from beadsight.checkpoint import load_checkpoint
from beadsight.data.rest import REST_FRAMES, average_rest, rest_ends
from beadsight.data.windows import stream_windows
from beadsight.errors import ConfigError
from beadsight.inference.int8 import (
    ACCURATE,
    FAST,
    FASTEST,
    NNCF_DEFAULT,
    RECIPES,
    Int8Backend,
    QuantizationRecipe,
    calibration_windows,
    gated_int8,
)
from beadsight.inference.machine import import_openvino
from beadsight.inference.metric_parity import (
    HELDOUT_PRESSES,
    HELDOUT_SEED,
    METRIC_TOLERANCE,
    WINDOWS_PER_PRESS,
    MetricParity,
    MetricParityError,
    _simulated_session,
    fp32_maps,
    metric_parity,
    require_metric_parity,
    simulated_presses,
)
from beadsight.inference.select import build_backend, create_backend, select_backend


@pytest.fixture(scope="module")
def sim_model():
    return load_checkpoint(shipped_model_path())


@pytest.fixture(scope="module")
def heldout(sim_model):
    return simulated_presses(sim_model)


@pytest.fixture(scope="module")
def reference(sim_model, heldout):
    """fp32 torch's maps of the held-out presses, as :func:`metric_parity` computes them
    (read-only: the tests that judge a runtime against them share them)."""
    maps = fp32_maps(sim_model, heldout)
    maps.flags.writeable = False
    return maps


@pytest.fixture(scope="module")
def int8_backend(sim_model, shared_cache):
    """The default recipe's int8 runtime of the shipped model (not gated)."""
    backend = Int8Backend(sim_model, cache_dir=shared_cache)
    yield backend
    backend.close()


def test_heldout_presses_are_presses(sim_model, heldout):
    assert heldout.inputs(0, 2).shape == (2, sim_model.inputs, 64, 64, 3)
    # evenly over each press: approach, contact and release, as evaluate weighs them
    assert 0.2 < heldout.contact.mean() < 0.8 and (heldout.force_n[heldout.contact] > 2).sum() >= 20
    assert len(heldout) == HELDOUT_PRESSES * WINDOWS_PER_PRESS
    assert np.concatenate(list(heldout.batches(100))).shape[0] == len(heldout)
    calib = calibration_windows(sim_model)
    assert not np.array_equal(calib, heldout.inputs(0, len(calib)))  # another seed


def test_heldout_windows_see_the_pouch_as_it_last_rested(sim_model, heldout):
    # the beads re-settle after each press: every window's rest image is the newest
    # unloaded, settled run before it (as `beadsight evaluate` picks it), not the
    # session's first frames
    session = _simulated_session(sim_model.image_size, HELDOUT_SEED, HELDOUT_PRESSES)
    ends = rest_ends(session.force_n, np.ones(len(session.force_n), bool))[heldout.ends]
    first = average_rest(session.frames[:REST_FRAMES])
    for k in (0, len(heldout) // 2, len(heldout) - 1):
        expected = average_rest(session.frames[ends[k] - REST_FRAMES + 1 : ends[k] + 1])
        np.testing.assert_array_equal(heldout.inputs(k, k + 1)[0, 0], expected)
    assert not np.array_equal(heldout.inputs(len(heldout) - 1, len(heldout))[0, 0], first)


def test_an_fp32_runtime_passes_the_metric_gate(sim_model, heldout, reference):
    backend = build_backend(sim_model, "openvino", "fp32", cache_dir=None)
    parity = metric_parity(backend, sim_model, heldout, reference=reference)
    assert parity.ok and parity.meaningful and parity.windows == len(heldout)
    assert max(abs(d) for d in parity.deltas.values()) < 1e-3


def test_metric_gate_judges_relative_change():
    ref = {"mae_kpa": 1.0, "iou": 0.5, "force_error_pct": 10.0}
    zero = {"mae_kpa": 2.0, "iou": 0.0, "force_error_pct": 100.0}
    near = {"mae_kpa": 1.019, "iou": 0.491, "force_error_pct": 10.1}
    assert MetricParity("x", ref, near, 5, zero).ok
    far = MetricParity("x", ref, {"mae_kpa": 1.03, "iou": 0.5, "force_error_pct": 10.0}, 5, zero)
    assert not far.ok and far.worst[0] == "mae_kpa"
    missing = {"mae_kpa": 1.0, "iou": None, "force_error_pct": 10.0}
    assert not MetricParity("x", ref, missing, 5, zero).ok
    # a model no better than an all-zero map: its metrics cannot vouch for a runtime
    useless = MetricParity("x", ref, ref, 5, {"mae_kpa": 0.9, "force_error_pct": 100.0})
    assert not useless.meaningful and not useless.ok and "all-zero map" in str(useless)


def test_an_untrained_model_cannot_pass_the_metric_gate(probe_model, tmp_path):
    backend = build_backend(probe_model, "openvino", "fp32", cache_dir=None)
    parity = metric_parity(backend, probe_model, simulated_presses(probe_model, presses=1))
    assert max(abs(d) for d in parity.deltas.values()) < 1e-3  # the runtime agrees ...
    assert not parity.meaningful and not parity.ok  # ... but the metrics cannot tell


def test_int8_that_moves_the_metrics_is_refused(sim_model, heldout, reference, shared_cache):
    coarse = Int8Backend(sim_model, cache_dir=shared_cache, recipe=NNCF_DEFAULT)
    parity = metric_parity(coarse, sim_model, heldout, reference=reference)
    assert parity.meaningful and not parity.ok
    assert parity.deltas["mae_kpa"] > 0.1  # measured: +18 % (force error +31 %)
    with pytest.raises(MetricParityError) as err:
        require_metric_parity(coarse, sim_model, parity)
    message = str(err.value)
    assert "int8/int8" in message and "relative to fp32 torch" in message
    assert f"allowed {100 * METRIC_TOLERANCE:g} %" in message and "mae_kpa" in message
    assert coarse.request is None  # closed


def test_int8_does_not_cut_the_pressure_map(sim_model, heldout, reference, int8_backend):
    # Harder presses than the calibration's: a quantizer on the output cut every map at the
    # calibration presses' peak (140 kPa for this model against 202 kPa here) in steps of
    # 1/255 of it, and moved the force error by +31 % on these presses.
    calibration_peak = sim_model.predict(calibration_windows(sim_model), batch_size=1).max()
    peaks = reference.max(axis=(1, 2))
    hard = np.flatnonzero(peaks > 1.2 * calibration_peak)
    assert hard.size >= 5  # the held-out presses go beyond the calibration's range
    got = int8_backend.run_batch(heldout.inputs(int(hard[0]), int(hard[-1]) + 1))
    got_peaks = got.max(axis=(1, 2))[hard - hard[0]]
    np.testing.assert_allclose(got_peaks, peaks[hard], rtol=0.05)
    assert np.unique(got[got > 0]).size > 1000  # a continuous map, not 255 levels


def _quantized_inputs(xml_path, types):
    """Names of the ``types`` nodes of an OpenVINO IR whose input comes out of a
    FakeQuantize (NNCF's quantizer)."""
    model = import_openvino().Core().read_model(str(xml_path))
    return sorted(
        op.get_friendly_name()
        for op in model.get_ops()
        if op.get_type_name() in types
        and any(
            i.get_source_output().get_node().get_type_name() == "FakeQuantize" for i in op.inputs()
        )
    )


def _reads_uint8_planes(xml_path) -> list[str]:
    """The nodes that read an OpenVINO IR's input as uint8 planes dequantized
    (Parameter u8 -> Convert -> Subtract -> Multiply -> them); [] for a float input."""
    model = import_openvino().Core().read_model(str(xml_path))
    (param,) = model.get_parameters()
    if param.get_element_type().get_type_name() != "u8":
        return []
    node = param
    for kind in ("Convert", "Subtract", "Multiply"):
        (target,) = node.output(0).get_target_inputs()
        node = target.get_node()
        assert node.get_type_name() == kind
    return sorted(t.get_node().get_friendly_name() for t in node.output(0).get_target_inputs())


def test_fastest_ring_keeps_each_frame_quantized_and_streams_as_it_runs(
    sim_model, heldout, shared_cache
):
    """FASTEST's graph takes uint8 planes: the ring quantizes each frame's once, and a
    stream (one new frame per call) reads what a stateless run of the same windows reads,
    exactly (both quantize the same planes the same way)."""
    backend = Int8Backend(sim_model, cache_dir=shared_cache, recipe=FASTEST)
    try:
        quantizer = backend.planes.quantizer
        assert quantizer is not None and 0 < quantizer.zero_point < 255
        k = int(np.argmax(heldout.force_n))  # the hardest press's window
        end, span = int(heldout.ends[k]), sim_model.span
        rest = heldout.rests[heldout.rest_of[k]]
        frames = heldout.frames
        backend.run_incremental(frames[None, end - span - 5 : end - 5], span, rest)
        peaks = []
        for e in range(end - 5, end + 1):
            window = frames[None, e - span + 1 : e + 1]
            view = backend.planes.update(window, 0, rest)
            assert view.dtype == np.uint8 and view.shape[1] == backend.planes.channels
            got = backend.run_incremental(window, 1, rest)[0]
            want = backend.run_batch(stream_windows(frames, np.array([e]), span, rest[None]))[0]
            np.testing.assert_array_equal(got, want)
            peaks.append(got.max())
        assert min(peaks) > 20  # a press, not an empty map
    finally:
        backend.close()


def test_fp32_blocks_are_whole_only_when_asked(sim_model, shared_cache):
    # OpenVINO names a block's instance norms apart from it (MVN_1234), so a block kept in
    # fp32 by name still has its norms' inputs quantized; whole_blocks keeps them too.
    def block_convs(backend, block):
        convs = _quantized_inputs(backend.quantized_path, {"Convolution"})
        return [c for c in convs if f"/net/{block}/" in c]

    accurate = Int8Backend(sim_model, cache_dir=shared_cache, recipe=ACCURATE)
    fast = Int8Backend(sim_model, cache_dir=shared_cache, recipe=FAST)
    fastest = Int8Backend(sim_model, cache_dir=shared_cache, recipe=FASTEST)
    try:
        assert FAST.whole_blocks and "C9" not in FAST.fp32_blocks
        made = (accurate, fast, fastest)
        norms = {b: len(_quantized_inputs(b.quantized_path, {"MVN"})) for b in made}
        # the shipped model has 7 conv blocks of 2 norms: ACCURATE quantizes all 14 norms'
        # inputs (C1's and C9's too); FAST and FASTEST keep C1's 2 in fp32
        assert norms == {accurate: 14, fast: 12, fastest: 12}
        assert block_convs(accurate, "C1") == block_convs(fast, "C1") == []
        # FASTEST: C1's first conv reads the input planes quantized (the graph takes them
        # as uint8: test below); its second conv does not
        assert block_convs(fastest, "C1") == []
        assert _reads_uint8_planes(fastest.quantized_path) == [
            "/net/C1/layer/layer.0/Conv/WithoutBiases"
        ]
        assert _reads_uint8_planes(accurate.quantized_path) == []
        assert _reads_uint8_planes(fast.quantized_path) == []
        # (C9's first conv reads a Concat of quantized tensors)
        assert block_convs(accurate, "C9") == [] and block_convs(fast, "C9") != []
        with pytest.raises(ConfigError, match="first_conv_int8 applies to blocks kept whole"):
            QuantizationRecipe(first_conv_int8=True)
    finally:
        for backend in made:
            backend.close()


def test_the_gate_runs_the_first_recipe_that_keeps_the_metrics_and_keeps_verdicts(
    sim_model, heldout, tmp_path, caplog
):
    # The default recipe keeps the shipped model's metrics within 2 % on some CPUs and
    # thread counts and not on others (its CoP error moves by +1.7 % with AVX-512 VNNI and
    # 2 threads, +4.9 % with 1 thread, +4.1 / +3.1 % capped at AVX2: docs/live.md), so the
    # accepting path is tested at a 10 % bound; NNCF's defaults fail it (MAE +18 %).
    bound, recipes = 0.10, (NNCF_DEFAULT, ACCURATE)
    backend = gated_int8(sim_model, cache_dir=tmp_path, tolerance=bound, recipes=recipes)
    try:
        assert backend.describe() == "int8/int8" and backend.parity.ok
        assert backend.recipe == ACCURATE  # the first was refused
        assert all(abs(d) <= bound for d in backend.parity.deltas.values())
        assert len(list((tmp_path / "int8").glob("*.xml"))) == 2  # beside the other caches
        verdicts = sorted((tmp_path / "int8").glob("*-parity-*.json"))
        assert [json.loads(v.read_text())["ok"] for v in verdicts].count(False) == 1
        out = backend.run_batch(heldout.inputs(0, 3))
        assert out.shape == (3, 64, 64) and out.dtype == np.float32 and np.isfinite(out).all()
        again = Int8Backend(sim_model, cache_dir=tmp_path)
        assert again.quantized_path == backend.quantized_path
        np.testing.assert_array_equal(again.run_batch(heldout.inputs(0, 3)), out)
        again.close()
        caplog.clear()
        with caplog.at_level(logging.INFO, logger="beadsight.inference.int8"):
            cached = gated_int8(sim_model, cache_dir=tmp_path, tolerance=bound, recipes=recipes)
        assert cached.parity.deltas == backend.parity.deltas and cached.recipe == ACCURATE
        assert "judging" not in caplog.text and "quantizing" not in caplog.text  # all kept
        cached.close()
        with pytest.raises(MetricParityError, match="mae_kpa"):  # every recipe refused
            gated_int8(sim_model, cache_dir=tmp_path, tolerance=bound, recipes=recipes[:1])
    finally:
        backend.close()


def test_evaluate_scores_the_int8_recipe_live_sensing_runs(sim_model, tmp_path):
    # evaluate builds its runtime unchecked (scoring it is the check), live sensing gated:
    # both must run the recipe the gate picks, or evaluate scores a model live never runs
    scored = create_backend(sim_model, "int8", cache_dir=tmp_path, check=False)
    try:
        assert scored.recipe in RECIPES and isinstance(scored.parity, MetricParity)
        try:
            live = create_backend(sim_model, "int8", cache_dir=tmp_path)
        except MetricParityError:  # every recipe refused on this CPU: the last one scored
            assert scored.recipe == RECIPES[-1] and not scored.parity.ok
        else:
            assert live.recipe == scored.recipe and live.parity.deltas == scored.parity.deltas
            live.close()
            # the first that passes: each recipe tried before it was refused
            kept = [json.loads(v.read_text()) for v in (tmp_path / "int8").glob("*-parity-*")]
            assert sorted(v["ok"] for v in kept) == [False] * RECIPES.index(scored.recipe) + [True]
    finally:
        scored.close()


def test_auto_drops_an_int8_candidate_that_fails_the_gate(probe_model, tmp_path):
    # an untrained model's metrics cannot vouch for int8: auto keeps an fp32 runtime
    chosen = select_backend(
        probe_model, cache_dir=tmp_path, candidates=[("int8", "int8"), ("openvino", "fp32")]
    )
    try:
        assert chosen.describe() == "openvino/fp32"
        notes = {c.backend: c.note for c in chosen.selection}
        assert notes["int8"].startswith("rejected") and "all-zero map" in notes["int8"]
        assert not list(tmp_path.glob("int8/*.xml"))  # refused before anything was quantized
    finally:
        chosen.close()


def test_small_simulated_sessions_are_kept_read_only_and_large_ones_are_not(monkeypatch):
    import beadsight.inference.metric_parity as mp

    monkeypatch.setattr(mp, "_sessions", type(mp._sessions)())
    # 16 px: the cache's rules do not depend on the size, and smaller frames simulate faster
    first = mp._simulated_session(16, 77, 1)
    assert mp._simulated_session(16, 77, 1) is first  # simulated once
    assert not first.frames.flags.writeable and not first.force_n.flags.writeable
    assert first.frames.shape[1:] == (16, 16, 3) and first.contact.any()
    other = mp._simulated_session(16, 78, 1)
    assert other is not first and list(mp._sessions) == [(16, 77, 1), (16, 78, 1)]
    monkeypatch.setattr(mp, "SESSION_CACHE_BYTES", first.frames.nbytes + other.frames.nbytes - 1)
    mp._simulated_session(16, 77, 1)  # the most recent now: the other one is dropped first
    mp._simulated_session(16, 79, 1)
    assert (16, 78, 1) not in mp._sessions and list(mp._sessions)[-1] == (16, 79, 1)
    assert sum(s.frames.nbytes for s in mp._sessions.values()) <= mp.SESSION_CACHE_BYTES
    monkeypatch.setattr(mp, "SESSION_CACHE_BYTES", 1)
    mp._simulated_session(16, 80, 1)
    assert not mp._sessions  # too large alone: simulated, returned, not kept
