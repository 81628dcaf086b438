"""The placement refiner inside the inference engine (issue 47): the refined graphs
(``engine.RefinedStepGraph`` / ``RefinedOneTrackGraph``: the network step and the refiner's
first pass in one graph) against the reference (the model's own forward, then the refiner in
numpy), the ``"auto"`` check covering them, and steps too large for the memory left.

Tolerances: the float32 backends are held to :data:`seqshape.model.engine.TOLERANCE` on the
shipped weights and on random networks with the refiner's outputs turned up (every estimate
moved by decimetres); ``"onnx-int8"`` to its statistical bound (:data:`INT8_NOISE`).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from _model_data import box_track
from test_engine import _assert_close, _cloud, moving_clouds  # the engine tests' helpers

from seqshape.errors import ConfigError
from seqshape.model import Estimator, ModelConfig, ShapePoseNet
from seqshape.model import engine as engine_module
from seqshape.model import placement as P
from seqshape.model.engine import INT8_NOISE, car_stream
from seqshape.model.estimator import check_backend, deviations, noise_quantiles

pytest.importorskip("onnxruntime")
pytest.importorskip("onnx")

CFG = ModelConfig(num_points=32, encoder1=(16, 32), encoder2=(32, 32), hidden=24,
                  shape_decoder=(32,), pose_decoder=(32,), num_complete=64,
                  shape_frame="canonical", scale_norm="length", motion_input=True,
                  frame_skip=True)


@pytest.fixture(autouse=True)
def _fresh_auto_cache(monkeypatch):
    monkeypatch.setattr(engine_module, "_AUTO_CACHE", {})


def _refiner(seed: int = 0, outputs: int = 6, **config) -> P.PlacementRefiner:
    """A refiner with random weights whose corrections are decimetres (its head scaled up),
    so that a wrong box frame, scale, clip or extent shows."""
    torch.manual_seed(seed)
    net = P.build_net(16, outputs)
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(0.3 * torch.randn_like(p))
        net.head[-1].bias.copy_(torch.tensor([0.3, -0.2, 0.05, 0.1, 0.1, -0.05][:outputs]))
    return P.PlacementRefiner(net, P.RefinerConfig(**config))


def _net(seed: int = 0, **options) -> ShapePoseNet:
    torch.manual_seed(seed)
    return ShapePoseNet(dataclasses.replace(CFG, **options)).eval()


def _steps(seed: int, n_tracks: int = 9, n_steps: int = 6, num_points: int = 32) -> list[dict]:
    """Moving tracks with 0, 1, few, N and more than N points, late starts, size hints that
    make some estimates long (further refiner passes) and change (a recomputed empty frame)."""
    rng = np.random.default_rng(seed)
    steps = []
    for t, idx, pts in moving_clouds(rng, n_tracks, n_steps,
                                     [0, 1, 3, num_points // 2, num_points, 4 * num_points]):
        sizes = [None if i % 2 else (14.0 if (i + t // 3) % 4 == 0 else 4.5) for i in idx]
        steps.append({"track_ids": [f"t{i}" for i in idx], "point_lists": pts,
                      "timestamps": [0.1 * t] * len(idx), "sizes": sizes})
    return steps


def _single(rng, num_points: int, track: str = "solo") -> list[dict]:
    steps = []
    for t, n in enumerate([1, 2, num_points // 2, 0, num_points, 5 * num_points, 3]):
        pose = (12.0 + 0.5 * t, -4.0, -0.9, 0.4)
        steps.append({"track_ids": [track], "point_lists": [_cloud(rng, n, pose)],
                      "timestamps": [0.1 * t]})
    return steps


def _compare(net, refiner, backend: str, steps, resets=(3,)) -> Estimator:
    fast = Estimator(net, backend=backend, refiner=refiner)
    ref = Estimator(net, backend="torch", refiner=refiner)
    assert fast._fused_refiner() is refiner
    for t, step in enumerate(steps):
        if t in resets:
            for est in (fast, ref):
                est.reset(step["track_ids"][0])
        _assert_close(fast.step(**step), ref.step(**step), f"{backend} step {t}")
    return fast


@pytest.mark.parametrize("backend", ["onnx", "torch-lean"])
@pytest.mark.parametrize("options", [{}, {"shape_frame": "sensor"}, {"motion_input": False,
                                                                      "scale_norm": "none"}])
def test_refined_graphs_match_the_reference(backend, options):
    """Many tracks and one track alone (both refined graphs), empty frames (the carried
    correction), a new size hint on an empty frame (recomputed, then the carried
    correction), long estimates (further passes on the refiner's own graph), a reset."""
    net, refiner = _net(**options), _refiner(repeat_min_length=5.0)
    steps = _steps(1) + _single(np.random.default_rng(2), 32, "t1")
    fast = _compare(net, refiner, backend, steps)
    moved = [e for e in fast.step(**steps[0]) if e.num_points]
    plain = Estimator(net, backend=backend).step(**steps[0])
    by_id = {e.track_id: e for e in plain}
    # the refiner did move them (decimetres), so the agreement above means something
    assert np.median([np.abs(e.pose[:2] - by_id[e.track_id].pose[:2]).max()
                      for e in moved]) > 0.05


@pytest.mark.parametrize("config", [{"size": False}, {"size_width": True, "max_resize": 0.1},
                                    {"min_points": 5, "iterations": 1}, {"max_shift": 0.05}])
def test_refined_graphs_follow_the_refiner_config(config):
    net, refiner = _net(3), _refiner(1, **config)
    _compare(net, refiner, "onnx", _steps(4, n_steps=4))


def test_refiner_without_size_head_and_untrained_refiner():
    net = _net(5)
    _compare(net, _refiner(2, outputs=4), "onnx", _steps(6, n_steps=3))
    untrained = P.PlacementRefiner(P.build_net(16))  # the identity: the network's estimate
    fast = Estimator(net, backend="onnx", refiner=untrained)
    plain = Estimator(net, backend="onnx")
    for step in _steps(7, n_steps=3):
        for a, b in zip(fast.step(**step), plain.step(**step), strict=True):
            np.testing.assert_array_equal(a.complete, b.complete)
            np.testing.assert_array_equal(a.pose, b.pose)


def test_box_fixture_tracks_match_the_reference():
    """The fixture tracks of the model tests (box-shaped vehicles, an empty frame each)."""
    tracks = [box_track(f"v{i}", "val", np.random.default_rng(20 + i), 6, empty_frame=2 + i % 3)
              for i in range(7)]
    steps = [{"track_ids": [t.track_id for t in tracks],
              "point_lists": [t.points[k] for t in tracks],
              "timestamps": [float(t.timestamps[k]) for t in tracks]} for k in range(6)]
    _compare(_net(8), _refiner(4), "onnx", steps)


def test_fused_path_is_taken_and_falls_back_when_the_refiner_reads_fewer_points(monkeypatch):
    net, refiner = _net(9), _refiner(5)
    est = Estimator(net, backend="onnx", refiner=refiner, threads=1)
    est.step(**_steps(1, n_steps=1)[0])
    refined = est._engine._refined[1]
    calls = []
    for session in (refined.session, refined.one):
        run = session.run
        monkeypatch.setattr(session, "run", lambda inputs, run=run: calls.append(1) or run(inputs))
    est.step(**_steps(1, n_steps=2)[1])
    assert calls
    fewer = _refiner(5, points=16)  # a subset of the frame's 32 points: numpy's, after the pass
    est.refiner = fewer
    assert est._fused_refiner() is None
    ref = Estimator(net, backend="torch", refiner=fewer)
    est.reset()
    for t, step in enumerate(_steps(2, n_steps=3)):
        _assert_close(est.step(**step), ref.step(**step), f"fallback step {t}")


@pytest.mark.parametrize("kind", ["sequential", "baseline"])
def test_shipped_refiner_on_the_shipped_weights(kind):
    """The shipped networks and refiner: float32 within the engine's tolerance, estimate by
    estimate; int8 (the refiner's last per-point layer too) within its noise bound."""
    net = Estimator.load(kind, backend="torch").model
    refiner = P.load_refiner("pretrained")
    steps = car_stream(net.cfg.num_points, seed=5, n_tracks=24, n_steps=3)
    steps += _single(np.random.default_rng(5), net.cfg.num_points, "car3")
    _compare(net, refiner, "onnx", steps, resets=())
    fast = Estimator(net, backend="onnx-int8", refiner=refiner)
    mine, allowed = noise_quantiles(fast, steps[:3], INT8_NOISE)
    assert np.all(mine <= allowed), (mine, allowed)


def test_auto_check_runs_with_the_refiner(monkeypatch):
    """``"auto"``'s check of a backend runs the estimator with its refiner (the refined
    graphs), and a refiner is part of the cached verdict's key."""
    net, refiner = _net(10), _refiner(6)
    seen = []

    def check(fast):
        seen.append((fast.backend, fast.refiner))
        return fast.backend == "onnx"

    monkeypatch.setattr("seqshape.model.estimator.check_backend", check)
    est = Estimator(net, backend="auto", refiner=refiner)
    assert est.backend == "onnx" and seen == [("onnx-int8", refiner), ("onnx", refiner)]
    Estimator(net, backend="auto", refiner=refiner)  # cached for this model and refiner
    assert len(seen) == 2
    Estimator(net, backend="auto", refiner=_refiner(7))  # another refiner: checked again
    assert len(seen) == 4


def test_check_fails_on_a_refined_graph_that_moves_the_estimates(monkeypatch):
    """A refined graph whose correction is wrong (its centre 5 mm off) fails the float32
    check, so ``"auto"`` would pass it over."""
    net, refiner = _net(11), _refiner(8)
    fast = Estimator(net, backend="onnx", refiner=refiner)
    assert check_backend(fast)
    run = fast._engine.run

    def biased(inputs):
        out = list(run(inputs))
        if inputs.limits is not None:
            out[1] = out[1] + np.array([0.005, 0.0, 0.0, 0.0], out[1].dtype)
        return tuple(out)

    monkeypatch.setattr(fast._engine, "run", biased)
    fast.reset()
    assert not check_backend(fast)


def _allocation_failure(message: str = "BFCArena::AllocateRawInternal Failed to allocate "
                        "memory for requested buffer of size 8589934592"):
    from onnxruntime.capi.onnxruntime_pybind11_state import Fail

    return Fail(f"[ONNXRuntimeError] : 1 : FAIL : {message}")


@pytest.mark.parametrize("refined", [False, True])
def test_a_step_too_large_for_the_memory_left_is_split(monkeypatch, refined):
    """Passes that fail to allocate (ONNX Runtime's arena failure, mocked: any pass of more
    than 3 tracks) are split until they fit, to the same estimates; passes are also cut to
    MAX_PASS_ROWS encoder rows."""
    net = _net(12)
    refiner = _refiner(9) if refined else None
    steps = _steps(13, n_tracks=14, n_steps=3)
    whole = Estimator(net, backend="onnx", refiner=refiner, threads=1)
    split = Estimator(net, backend="onnx", refiner=refiner, threads=1)
    sizes = []
    orig = split._engine._run

    def tight(inputs):
        sizes.append(inputs.points.shape[:2])
        if len(inputs.lengths) > 3:
            raise _allocation_failure()
        return orig(inputs)

    monkeypatch.setattr(split._engine, "_run", tight)
    monkeypatch.setattr(engine_module, "MAX_PASS_ROWS", 4 * 32)
    monkeypatch.setattr("seqshape.model.estimator.MAX_PASS_ROWS", 4 * 32)
    for t, step in enumerate(steps):
        a, b = split.step(**step), whole.step(**step)
        # float32 rounding of passes of other sizes (up to 2e-5 m through the untrained
        # networks), far within the engine's TOLERANCE
        assert np.abs(deviations(a, b)).max() <= 5e-5, f"step {t}"
    assert all(b * n <= 4 * 32 or b == 1 for b, n in sizes)  # cut by rows
    assert any(b > 3 for b, _ in sizes) and any(b <= 3 for b, _ in sizes)  # then split


def test_a_step_that_does_not_fit_is_refused_with_a_config_error(monkeypatch):
    """When one track alone cannot be allocated the step is refused with a ConfigError naming
    its size (never ONNX Runtime's raw Fail), and no track's state changed."""
    net = _net(14)
    est = Estimator(net, backend="onnx", refiner=_refiner(10), threads=1)
    steps = _steps(15, n_tracks=6, n_steps=2)
    est.step(**steps[0])  # tracks 0 and 3; tracks 1 and 4 start in the next step
    before = {t: (st.hidden.copy(), st.last[1].copy()) for t, st in est._states.items()}
    monkeypatch.setattr(est._engine, "_run", lambda inputs: (_ for _ in ()).throw(
        _allocation_failure()))
    size = len(steps[1]["track_ids"])
    with pytest.raises(ConfigError, match=rf"not enough memory for a step of {size} tracks"):
        est.step(**steps[1])
    assert set(est._states) == set(before)
    for t, st in est._states.items():
        np.testing.assert_array_equal(st.hidden, before[t][0])
        np.testing.assert_array_equal(st.last[1], before[t][1])
    # other errors of the runtime are not taken for a lack of memory
    monkeypatch.setattr(est._engine, "_run", lambda inputs: (_ for _ in ()).throw(
        _allocation_failure("Invalid input shape")))
    with pytest.raises(Exception, match="Invalid input shape") as info:
        est.step(**steps[1])
    assert not isinstance(info.value, ConfigError)


def test_memory_error_of_torch_lean_is_split_too(monkeypatch):
    net = _net(16)
    est = Estimator(net, backend="torch-lean", refiner=_refiner(11))
    ref = Estimator(net, backend="torch-lean", refiner=_refiner(11))
    graph = est._engine
    est.step(**_steps(17, n_steps=1)[0])  # the refined graph attached
    refined = graph._refined[1]
    forward = refined.forward

    def tight(*args):
        if args[0].shape[0] > 2:
            raise RuntimeError("[enforce fail at alloc_cpu.cpp:117] DefaultCPUAllocator: "
                               "can't allocate memory: you tried to allocate 999 bytes.")
        return forward(*args)

    monkeypatch.setattr(refined, "forward", tight)
    ref.step(**_steps(17, n_steps=1)[0])
    for step in _steps(17, n_steps=3)[1:]:
        assert np.abs(deviations(est.step(**step), ref.step(**step))).max() <= 1e-5


_CAPPED_STEP = r"""
import resource, sys
import numpy as np
from seqshape.errors import ConfigError
from seqshape.model import Estimator
from seqshape.testing import box_surface

est = Estimator.from_pretrained("sequential", backend="onnx-int8", threads=1)
rng = np.random.default_rng(0)
n = 6000
clouds = [box_surface(256, rng, pose=(10 + i % 50, (i // 50) % 40 - 20, -0.9, 0.3),
                      dtype=np.float32) for i in range(n)]
ids = [f"t{i}" for i in range(n)]
est.step(ids[:3], clouds[:3])
with open("/proc/self/status") as f:
    vm = int(next(line for line in f if line.startswith("VmSize")).split()[1]) // 1024
resource.setrlimit(resource.RLIMIT_AS, ((vm + 600) << 20, resource.RLIM_INFINITY))
try:
    out = est.step(ids, clouds)
    print("ok", len(out))
except ConfigError as exc:
    print("ConfigError", exc)
"""


@pytest.mark.slow
def test_a_step_under_a_real_memory_cap_ends_cleanly(tmp_path):
    """6,000 tracks of 256 points in a process whose address space is capped 600 MB above
    its size after loading (``RLIMIT_AS``): the step either runs (in capped passes) or is
    refused with a ConfigError; never ONNX Runtime's raw Fail, a crash or numpy's
    MemoryError (about 20 s)."""
    import subprocess
    import sys

    if not sys.platform.startswith("linux"):
        pytest.skip("RLIMIT_AS and /proc: Linux")
    script = tmp_path / "capped.py"
    script.write_text(_CAPPED_STEP)
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    last = proc.stdout.strip().splitlines()[-1]
    assert last == "ok 6000" or last.startswith("ConfigError not enough memory for a step of "
                                                "6000 tracks"), last
