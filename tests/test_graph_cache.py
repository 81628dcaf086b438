"""The disk cache of exported ONNX graphs (:mod:`seqshape.model.graph_cache`): a second engine
reads the graphs instead of exporting them and runs the same arithmetic; the key follows the
weights, the configuration and the graph's kind; a damaged file is reported and rebuilt; an
unwritable folder and ``SEQSHAPE_CACHE_DIR=none`` fall back to exporting; old graphs are
pruned."""

from __future__ import annotations

import copy
import hashlib
import os
import warnings

import numpy as np
import pytest
import torch

from seqshape.model import ModelConfig, ShapePoseNet, graph_cache
from seqshape.model import engine as engine_module
from seqshape.model.engine import example_inputs, make_engine
from seqshape.model.graph_cache import cache_dir, cached_graph, graph_key

pytest.importorskip("onnxruntime")
pytest.importorskip("onnx")

TINY = ModelConfig(num_points=32, encoder1=(8, 16), encoder2=(16, 24), hidden=20,
                   shape_decoder=(32,), pose_decoder=(16,), num_complete=40)


@pytest.fixture
def folder(tmp_path, monkeypatch):
    """The cache on, in a fresh folder; warnings not yet given."""
    monkeypatch.setenv(graph_cache.ENV, str(tmp_path / "cache"))
    monkeypatch.setattr(graph_cache, "_warned", set())
    return tmp_path / "cache"


def _net(seed: int = 0) -> ShapePoseNet:
    torch.manual_seed(seed)
    return ShapePoseNet(TINY, True).eval()


def _inputs(seed: int):
    return example_inputs(_net(), batch=4, points=9, seed=seed)


def _graphs(folder) -> list:
    return sorted(folder.glob(f"{graph_cache.PREFIX}*.onnx"))


def _name(net, kind: str) -> str:
    """The cache's file name of graph ``kind`` of ``net``."""
    return f"{graph_cache.PREFIX}{graph_key(net, kind)}.onnx"


def test_second_engine_reads_the_graphs_and_computes_the_same(folder, monkeypatch):
    net = _net()
    first = make_engine(net, "onnx")
    assert len(_graphs(folder)) == 2  # the batch and the one-track graph
    expected = [np.asarray(a) for a in first.run(_inputs(3))]

    def no_export(*args, **kwargs):
        raise AssertionError("exported although the graph is cached")

    monkeypatch.setattr(engine_module, "export_onnx", no_export)
    second = make_engine(copy.deepcopy(net), "onnx")  # the same weights in another object
    for a, b in zip(second.run(_inputs(3)), expected, strict=True):
        np.testing.assert_array_equal(a, b)
    assert len(_graphs(folder)) == 2


def test_key_follows_weights_configuration_and_kind():
    net = _net()
    key = graph_key(net, "step")
    assert graph_key(copy.deepcopy(net), "step") == key
    assert graph_key(net, "one") != key
    other = copy.deepcopy(net)
    with torch.no_grad():
        p = next(other.parameters())
        p.view(-1)[0] = torch.nextafter(p.view(-1)[0], torch.tensor(np.inf))  # one ulp
    assert graph_key(other, "step") != key
    assert graph_key(ShapePoseNet(TINY, False), "step") != graph_key(ShapePoseNet(TINY, True),
                                                                     "step")


def test_a_damaged_file_is_reported_and_rebuilt(folder):
    net = _net()
    expected = [np.asarray(a) for a in make_engine(net, "onnx").run(_inputs(5))]
    path = folder / _name(net, "step")
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.warns(RuntimeWarning, match=f"{path.name}.*damaged"):
        engine = make_engine(net, "onnx")
    for a, b in zip(engine.run(_inputs(5)), expected, strict=True):
        np.testing.assert_array_equal(a, b)
    stored = path.read_bytes()  # written again, whole
    assert hashlib.sha256(stored[:-32]).digest() == stored[-32:]


def test_truncated_and_empty_files_are_rebuilt(folder):
    calls = []

    def build():
        calls.append(1)
        return b"graph bytes"

    assert cached_graph(_net(), "k", build) == b"graph bytes"
    path = _graphs(folder)[0]
    for broken in (path.read_bytes()[:-5], b"", b"x" * 10):
        path.write_bytes(broken)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            assert cached_graph(_net(), "k", build) == b"graph bytes"
    assert len(calls) == 4
    assert cached_graph(_net(), "k", build) == b"graph bytes" and len(calls) == 4


def test_cache_off_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    for off in ("none", "off", "NONE"):
        monkeypatch.setenv(graph_cache.ENV, off)
        assert cache_dir() is None
        assert cached_graph(_net(), "k", lambda: b"g") == b"g"
    assert not any(tmp_path.rglob("*.onnx"))


def test_default_folders(tmp_path, monkeypatch):
    monkeypatch.delenv(graph_cache.ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_dir() == tmp_path / "xdg" / "seqshape" / "onnx"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert cache_dir() == tmp_path / "home" / ".cache" / "seqshape" / "onnx"
    monkeypatch.setenv(graph_cache.ENV, str(tmp_path / "mine"))
    assert cache_dir() == tmp_path / "mine"


def test_unwritable_folder_exports_and_warns_once(tmp_path, monkeypatch):
    blocker = tmp_path / "a-file"
    blocker.write_bytes(b"not a folder")
    monkeypatch.setenv(graph_cache.ENV, str(blocker / "cache"))
    monkeypatch.setattr(graph_cache, "_warned", set())
    net = _net()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        engine = make_engine(net, "onnx")  # two graphs, one warning
    messages = [str(w.message) for w in caught if w.category is RuntimeWarning]
    assert len(messages) == 1, messages
    assert messages[0].startswith(f"{blocker / 'cache'}: cannot write the ONNX graph cache")
    assert f"set {graph_cache.ENV} to a writable folder" in messages[0]
    reference = make_engine(net, "torch-lean")
    for a, b in zip(engine.run(_inputs(2)), reference.run(_inputs(2)), strict=True):
        np.testing.assert_allclose(a, b, atol=2e-3)
    assert blocker.read_bytes() == b"not a folder"


def test_least_recently_used_graphs_are_pruned(folder, monkeypatch):
    monkeypatch.setattr(graph_cache, "MAX_FILES", 2)
    net = _net()
    folder.mkdir(parents=True)
    (folder / "users-own-model.onnx").write_bytes(b"not ours")  # never removed
    for t, kind in enumerate("abc"):
        cached_graph(net, kind, lambda kind=kind: kind.encode())
        os.utime(folder / _name(net, kind), (1000 + t, 1000 + t))
    names = {p.name for p in _graphs(folder)}
    assert names == {_name(net, k) for k in "bc"}
    assert cached_graph(net, "b", lambda: b"rebuilt") == b"b"  # a hit refreshes its time
    cached_graph(net, "d", lambda: b"d")
    assert {p.name for p in _graphs(folder)} == {_name(net, k) for k in "bd"}
    # the byte budget: a large graph pushes the others out, and is itself kept
    monkeypatch.setattr(graph_cache, "MAX_FILES", 10)
    monkeypatch.setattr(graph_cache, "MAX_BYTES", 100)
    cached_graph(net, "e", lambda: b"e" * 90)
    assert {p.name for p in _graphs(folder)} == {_name(net, "e")}
    cached_graph(net, "f", lambda: b"f" * 200)  # over the budget alone: kept, being the newest
    assert {p.name for p in _graphs(folder)} == {_name(net, "f")}
    assert (folder / "users-own-model.onnx").read_bytes() == b"not ours"


# --------------------------------------------------------- the verdicts of "auto"'s check


def _verdicts(folder) -> list:
    return sorted(folder.glob(f"{graph_cache.VERDICT_PREFIX}*.json"))


class _Check:
    """A backend check that counts its runs."""

    def __init__(self, ok: bool = True):
        self.ok, self.runs = ok, 0

    def __call__(self) -> bool:
        self.runs += 1
        return self.ok


def test_a_verdict_is_checked_once_per_model_and_machine(folder, monkeypatch):
    from seqshape.model.graph_cache import cached_verdict

    net = _net()
    for ok in (True, False):
        check = _Check(ok)
        name = f"onnx-{ok}"
        assert cached_verdict(net, name, check) is ok and check.runs == 1
        assert cached_verdict(net, name, check) is ok and check.runs == 1  # read back
    assert len(_verdicts(folder)) == 2
    check = _Check()
    cached_verdict(_net(seed=1), "onnx-True", check)  # other weights: checked
    assert check.runs == 1
    monkeypatch.setattr(graph_cache, "machine_id", lambda: "another CPU")
    cached_verdict(net, "onnx-True", check)  # another machine's arithmetic: checked
    assert check.runs == 2


def test_a_damaged_verdict_is_checked_again_and_errors_store_nothing(folder):
    from seqshape.errors import MissingDependencyError
    from seqshape.model.graph_cache import cached_verdict, verdict_key

    net = _net()
    check = _Check()
    cached_verdict(net, "onnx", check)
    (path,) = _verdicts(folder)
    assert path.name == f"{graph_cache.VERDICT_PREFIX}{verdict_key(net, 'onnx')}.json"
    for junk in ("{not json", '{"backend": "onnx", "ok": "yes"}', '{"backend": "x", "ok": true}',
                 "[1]"):
        path.write_text(junk)
        assert cached_verdict(net, "onnx", check) is True
    assert check.runs == 5 and path.read_text() == '{"backend": "onnx", "ok": true}'

    def missing():
        raise MissingDependencyError("no runtime")

    with pytest.raises(MissingDependencyError):
        cached_verdict(net, "onnx-int8", missing)
    assert len(_verdicts(folder)) == 1


def test_verdicts_off_with_the_cache_and_pruned(folder, monkeypatch):
    from seqshape.model.graph_cache import cached_verdict

    monkeypatch.setattr(graph_cache, "MAX_VERDICTS", 3)
    check = _Check()
    for seed in range(5):
        cached_verdict(_net(seed), "onnx", check)
    assert len(_verdicts(folder)) == 3 and check.runs == 5
    monkeypatch.setenv(graph_cache.ENV, "none")
    cached_verdict(_net(), "onnx", check)
    cached_verdict(_net(), "onnx", check)
    assert check.runs == 7


def test_auto_reads_the_verdicts_of_an_earlier_process(folder, monkeypatch):
    """``select_backend`` in a later process (its in-process cache empty) asks no check."""
    from seqshape.model.engine import select_backend

    net = _net()
    asked = []

    def check(name):
        asked.append(name)
        return name == "onnx"

    monkeypatch.setattr(engine_module, "_AUTO_CACHE", {})
    assert select_backend(net, check, ("onnx-int8", "onnx")) == "onnx"
    assert asked == ["onnx-int8", "onnx"]
    monkeypatch.setattr(engine_module, "_AUTO_CACHE", {})
    assert select_backend(net, check, ("onnx-int8", "onnx")) == "onnx"
    assert asked == ["onnx-int8", "onnx"]


def test_machine_id_names_the_cpu():
    mid = graph_cache.machine_id()
    assert mid == graph_cache.machine_id() and "|" in mid
    if os.path.exists("/proc/cpuinfo"):
        with open("/proc/cpuinfo") as fh:
            text = fh.read()
        if "flags" in text:
            flag = next(ln for ln in text.splitlines() if ln.startswith("flags")).split()[-1]
            assert any(flag in part.split() for part in mid.split("|"))
