"""Int8 matrix products of an exported step graph, quantised per track (``"onnx-int8"``).

:func:`quantize_onnx` turns the float32 matrix products (``Gemm``, ``MatMul``) of chosen
layers of an ONNX graph into ONNX Runtime's ``MatMulIntegerToFloat`` (its fused int8 product,
``com.microsoft`` domain), so the graph then runs on ONNX Runtime only:

* **Weights**: int8, symmetric, one scale per output channel (``max |w| / 127``).
* **Inputs**: 7 bits in a uint8 (:data:`POS_LEVELS`: no int16 saturation on any x86 CPU),
  quantised at run time with a scale that depends on **one track's values only**. ONNX
  Runtime's own dynamic quantisation (``quantize_dynamic``) takes one scale over the whole
  input tensor, i.e. over every track of the pass, so that a track's estimate moved with the
  other tracks it was batched with (by up to 5 cm on a shape point; docs/history/model.md, "Sixth
  round: int8 per track"). Here:

  - a row of a product is one track (the decoders, the recurrent layers: inputs ``(B, K)``):
    the row is scaled by its own largest magnitude (``x / max |x|``, then 127 steps over
    ``[0, 1]`` after a ReLU, else 126 over ``[-1, 1]`` around the zero point 64), and the
    product's row is scaled back;
  - the encoder's per-point layer that ends in the max-pool (``Reshape`` of a ReLU's
    ``(B, N, K)`` -> product -> ``Reshape (B, N, F)`` -> ``ReduceMax`` over the points): one
    scale per track over its ``N x K`` inputs (``QuantizeLinear`` along axis 0, no extra pass
    over the points), and since the scale is positive and the bias the same for every point,
    both are applied after the max-pool, to ``(B, F)`` only. Padded rows are copies of real
    ones, so the scale is that of the track's own points;
  - any other product (only with every layer quantised): one scale per row (per point).

  A track's result therefore does not depend on the other tracks of its pass (tested: equal
  to 1e-6 whichever tracks share it), and each track's inputs use the whole quantised range.
"""

from __future__ import annotations

import numpy as np

from seqshape.errors import require

#: Opset of ONNX Runtime's contrib operators (``MatMulIntegerToFloat``).
MS_DOMAIN = "com.microsoft"
_EPS = 1e-30  # a row of zeros keeps a positive scale (its products are 0 either way)
#: Largest magnitude of a quantised weight (int8, symmetric).
WEIGHT_LEVELS = 127
#: Quantised inputs (uint8) use 7 bits: 0 .. POS_LEVELS after a ReLU, ZP +- SIGNED_LEVELS
#: otherwise. So that no sum of two adjacent products exceeds int16 (2 x 127 x 127 = 32,258):
#: x86 CPUs without VNNI multiply uint8 by int8 with ``vpmaddubsw``, which saturates there
#: (ONNX Runtime's documentation of its quantisation, "saturation"); with 8-bit inputs the
#: results would then depend on the CPU. Measured: as close to float32 as 8-bit inputs for the
#: sequential model, 1.3x the baseline's deviations; 7-bit weights instead doubled them
#: (docs/history/model.md, "Sixth round: int8 per track").
POS_LEVELS, SIGNED_LEVELS, ZP = 127, 63, 64


def quantize_onnx(graph: bytes, layers: tuple[str, ...] | None = None,
                  rows: tuple[str, ...] = (), sample: np.ndarray | None = None) -> bytes:
    """``graph`` (ONNX bytes, e.g. of :func:`seqshape.model.engine.export_onnx`) with the
    matrix products of ``layers`` (node-name prefixes ``/<layer>/``, the submodule names of
    the step graph, e.g. ``"shape_decoder"``; None: every product with a constant weight) in
    int8, inputs quantised per track (module doc), so that a track's estimate does not depend
    on the other tracks of its pass. Raises :class:`RuntimeError` when ``layers`` names no
    product.

    ``rows``: layers whose per-point products on a ReLU's rows ``(B x N, K)`` are quantised
    on one scale per track, where their graph has one of the two forms of the encoder's
    :func:`~seqshape.model.engine.split_pointnet` (left float otherwise):

    * pooled: ``product -> Reshape (B, N, F) -> ReduceMax`` over the points (the first MLP's
      last layer, into the global feature): the scale, the weights' scales and the bias after
      the max-pool, as the pooled form of the module doc;
    * split: ``product -> Reshape (B, N, F) -> Add g (B, 1, F) -> ReLU -> the pooled int8
      layer of ``layers`` (the folded split layer, :func:`~seqshape.model.engine
      .fold_split_layer`): the product's integer sums ``u`` are never rescaled point by point.
      With ``s`` the track's input scale and ``w_s`` the weights' (per output channel, both
      positive), ``relu(s w_s u + g) = s w_s relu(u + g / (s w_s))``: ``g`` is divided instead
      (``(B, 1, F)``), ``w_s`` is folded into the next layer's weights before they are
      quantised, and ``s`` joins that layer's scale after its max-pool.

    Products of ``rows`` on the same input share one quantisation of it, after its channels
    are equalised (:func:`_equalise`) with ``sample``, typical inputs ``(M, C)`` of the layer
    that makes the ReLU's rows (None: the unit cube's bound)."""
    onnx = require("onnx", "the int8 inference backend", "seqshape[fast]")
    helper, numpy_helper = onnx.helper, onnx.numpy_helper
    proto = onnx.load_from_string(graph)
    g = proto.graph
    nodes_in = list(g.node)  # one set of node objects, kept alive: id() names a node below
    weights = {t.name: t for t in g.initializer}
    producer = {o: n for n in nodes_in for o in n.output}
    consumers: dict[str, list] = {}
    for n in nodes_in:
        for i in n.input:
            consumers.setdefault(i, []).append(n)

    def chosen(n) -> bool:
        return (n.op_type in ("Gemm", "MatMul") and len(n.input) >= 2 and n.input[1] in weights
                and (layers is None or any(n.name.startswith(f"/{name}/") for name in layers)))

    targets = [n for n in nodes_in if chosen(n)]
    if not targets:
        raise RuntimeError(f"int8 quantisation: no matrix product in the layers {layers}")
    order = {id(n): i for i, n in enumerate(nodes_in)}
    row_forms = {}  # id(product) -> (form, its Reshape, the pooled layer or pool node)
    for n in nodes_in:
        if (n.op_type in ("Gemm", "MatMul") and len(n.input) >= 2 and n.input[1] in weights
                and any(n.name.startswith(f"/{name}/") for name in rows)):
            form = _row_form(n, producer, consumers, targets)
            if form is not None:
                row_forms[id(n)] = form
    targets = [n for n in targets if id(n) not in row_forms]
    fold_in: dict[int, tuple[np.ndarray, str]] = {}  # id(pooled layer) -> (w_s, s name)
    new_init: list = []
    replace: dict[int, list] = {}  # id(node) -> the nodes in its place (names may be empty)
    after: dict[int, list] = {}  # id(node) -> nodes to put after it
    before: dict[int, list] = {}  # id(node) -> nodes to put before it
    renamed_inputs: dict[int, tuple[str, str]] = {}  # id(node) -> (an input, its new name)
    renamed: dict[str, str] = {}  # an output renamed by a rewrite: old -> new

    def const(name: str, value) -> str:
        new_init.append(numpy_helper.from_array(np.asarray(value), name))
        return name

    one = const("int8/one", np.array(1.0, np.float32))
    eps = const("int8/eps", np.array(_EPS, np.float32))
    axis1 = const("int8/axis1", np.array([1], np.int64))
    flat = const("int8/flat", np.array([0, -1], np.int64))
    zp_u8 = {0: const("int8/zp0", np.array(0, np.uint8)),
             ZP: const("int8/zp", np.array(ZP, np.uint8))}
    zp_w = const("int8/zp_w", np.array(0, np.int8))
    step = {"pos": const("int8/pos", np.array(1 / POS_LEVELS, np.float32)),
            "signed": const("int8/signed", np.array(1 / SIGNED_LEVELS, np.float32))}

    groups: dict[str, list] = {}  # a ReLU's output -> its row products, in graph order
    for n in nodes_in:
        if id(n) in row_forms:
            groups.setdefault(n.input[0], []).append(n)
    for j, (x, members) in enumerate(groups.items()):
        first = min((row_forms[id(m)][1] for m in members), key=lambda r: order[id(r)])
        p = f"int8/rows{j}"
        width = _width(members[0], weights, numpy_helper)
        gain = _equalise(x, width, members, producer, consumers, weights, numpy_helper, const,
                         p, sample)
        shared = [  # one scale per track over its N x K inputs (N from the reshape's shape)
            helper.make_node("Slice", [first.input[1], const(f"{p}/one", np.array([1])),
                                       const(f"{p}/two", np.array([2]))], [f"{p}/N"]),
            helper.make_node("Mul", [f"{p}/N", const(f"{p}/K", np.array([width]))],
                             [f"{p}/NK"]),
            helper.make_node("Concat", [const(f"{p}/m1", np.array([-1])), f"{p}/NK"],
                             [f"{p}/-1,NK"], axis=0),
            helper.make_node("Reshape", [x, f"{p}/-1,NK"], [f"{p}/rows"]),
            helper.make_node("ReduceMax", [f"{p}/rows"], [f"{p}/max"], axes=[1], keepdims=0),
            helper.make_node("Max", [f"{p}/max", eps], [f"{p}/max+"]),
            helper.make_node("Mul", [f"{p}/max+", step["pos"]], [f"{p}/scale"]),
            helper.make_node("QuantizeLinear", [f"{p}/rows", f"{p}/scale"], [f"{p}/qrows"],
                             axis=0),
            helper.make_node("Reshape", [f"{p}/qrows", const(f"{p}/flat", np.array(
                [-1, width]))], [f"{p}/q"])]
        before.setdefault(id(first), []).extend(shared)  # before the first product's reshape
        for i, m in enumerate(members):
            form, resh, nxt = row_forms[id(m)]
            w, bias = _weight_and_bias(m, weights, numpy_helper)
            w = w * gain[:, None]  # the ReLU's channels came out divided by gain
            scale_w = np.abs(w).max(axis=0) / WEIGHT_LEVELS
            scale_w = np.where(scale_w > 0, scale_w, 1.0).astype(np.float32)
            wq = np.clip(np.rint(w / scale_w), -WEIGHT_LEVELS, WEIGHT_LEVELS).astype(np.int8)
            q = f"{p}/{i}"
            nodes = [helper.make_node(
                "MatMulIntegerToFloat", [f"{p}/q", const(f"{q}/w", wq), one, one, zp_u8[0],
                                         zp_w], [m.output[0]], domain=MS_DOMAIN,
                name=f"{q}/matmul")]
            replace[id(m)] = []
            if form == "pooled":
                pool = nxt
                pooled_out = pool.output[0]
                renamed[pooled_out] = f"{q}/pooled"
                tail = [helper.make_node("Unsqueeze", [f"{p}/scale", axis1], [f"{q}/s2"]),
                        helper.make_node("Mul", [f"{q}/s2", const(f"{q}/w_scale", scale_w)],
                                         [f"{q}/sw"]),
                        helper.make_node("Mul", [f"{q}/pooled", f"{q}/sw"],
                                         [f"{q}/scaled" if bias is not None else pooled_out])]
                if bias is not None:
                    tail.append(helper.make_node("Add", [f"{q}/scaled",
                                                         const(f"{q}/bias", bias)], [pooled_out]))
                after.setdefault(id(pool), []).extend(tail)
            else:  # split: g / (s w_s) into the Add; w_s and s go to the pooled layer
                add, layer = nxt
                g_in = [i for i in add.input if i != resh.output[0]][0]
                den = [helper.make_node("Unsqueeze", [f"{p}/scale", const(
                           f"{q}/axes", np.array([1, 2]))], [f"{q}/s3"]),
                       helper.make_node("Mul", [f"{q}/s3", const(f"{q}/w_scale", scale_w)],
                                        [f"{q}/den"])]
                if bias is not None:
                    den.append(helper.make_node("Add", [g_in, const(f"{q}/bias", bias)],
                                                [f"{q}/g+b"]))
                den.append(helper.make_node("Div", [f"{q}/g+b" if bias is not None else g_in,
                                                    f"{q}/den"], [f"{q}/g'"]))
                before.setdefault(id(add), []).extend(den)  # where g is known
                renamed_inputs[id(add)] = (g_in, f"{q}/g'")
                fold_in[id(layer)] = (scale_w, f"{p}/scale")
            before.setdefault(id(resh), []).extend(nodes)

    for k, n in enumerate(targets):
        w, bias = _weight_and_bias(n, weights, numpy_helper)
        folded = fold_in.get(id(n))
        if folded is not None:  # the split layer's weight scales, folded into this layer's
            w = w * folded[0][:, None]
        scale_w = np.abs(w).max(axis=0) / WEIGHT_LEVELS  # (N,) per output channel; w is (K, N)
        scale_w = np.where(scale_w > 0, scale_w, 1.0).astype(np.float32)
        wq = np.clip(np.rint(w / scale_w), -WEIGHT_LEVELS, WEIGHT_LEVELS).astype(np.int8)
        p = f"int8/{k}"
        wq_name, sw_name = const(f"{p}/w", wq), const(f"{p}/w_scale", scale_w)
        x, y = n.input[0], n.output[0]
        src = producer.get(x)
        pooled = _pooled_encoder_layer(n, src, producer, consumers)
        if pooled is not None:
            relu, pool = pooled
            # quantising y to uint8 with zero point 0 clips its negatives as relu(y) would, and
            # max(relu(y)) = max(max(y), 0): the ReLU pass is left out when nothing else reads it
            alone = len(consumers[relu.output[0]]) == 1
            x3 = relu.input[0] if alone else relu.output[0]
            if alone:
                replace[id(relu)] = []
                replace[id(src)] = []
            nodes = [  # one scale per track over its (N, K) inputs
                helper.make_node("Reshape", [x3, flat], [f"{p}/rows"]),
                helper.make_node("ReduceMax", [f"{p}/rows"], [f"{p}/max"], axes=[1], keepdims=0),
                helper.make_node("Max", [f"{p}/max", eps], [f"{p}/max+"]),
                helper.make_node("Mul", [f"{p}/max+", step["pos"]], [f"{p}/scale"]),
                helper.make_node("QuantizeLinear", [x3, f"{p}/scale"], [f"{p}/q3"], axis=0),
                helper.make_node("Reshape", [f"{p}/q3", src.input[1]], [f"{p}/q"]),
                helper.make_node("MatMulIntegerToFloat", [f"{p}/q", wq_name, one, sw_name,
                                 zp_u8[0], zp_w], [y], domain=MS_DOMAIN, name=f"{p}/matmul")]
            replace[id(n)] = nodes
            pooled_out = pool.output[0]
            renamed[pooled_out] = f"{p}/pooled"
            scale = f"{p}/scale"
            if folded is not None:  # the split layer's per-track input scale as well
                pre = [helper.make_node("Mul", [scale, folded[1]], [f"{p}/scale*"])]
                scale = f"{p}/scale*"
            else:
                pre = []
            tail = pre + [helper.make_node("Unsqueeze", [scale, axis1], [f"{p}/scale2"]),
                    helper.make_node("Mul", [f"{p}/pooled", f"{p}/scale2"],
                                     [f"{p}/pooled_scaled" if bias is not None else pooled_out])]
            if bias is not None:
                tail.append(helper.make_node("Add", [f"{p}/pooled_scaled",
                                                     const(f"{p}/bias", bias)], [pooled_out]))
            after[id(pool)] = tail
            continue
        nonneg = src is not None and src.op_type == "Relu"
        levels, zp = ("pos", 0) if nonneg else ("signed", ZP)
        nodes = []
        mag = x
        if not nonneg:
            nodes.append(helper.make_node("Abs", [x], [f"{p}/abs"]))
            mag = f"{p}/abs"
        nodes += [  # one scale per row
            helper.make_node("ReduceMax", [mag], [f"{p}/max"], axes=[-1], keepdims=1),
            helper.make_node("Max", [f"{p}/max", eps], [f"{p}/max+"]),
            helper.make_node("Div", [x, f"{p}/max+"], [f"{p}/unit"]),
            helper.make_node("QuantizeLinear", [f"{p}/unit", step[levels], zp_u8[zp]], [f"{p}/q"]),
            helper.make_node("MatMulIntegerToFloat", [f"{p}/q", wq_name, step[levels], sw_name,
                             zp_u8[zp], zp_w], [f"{p}/unscaled"], domain=MS_DOMAIN,
                             name=f"{p}/matmul"),
            helper.make_node("Mul", [f"{p}/unscaled", f"{p}/max+"],
                             [f"{p}/scaled" if bias is not None else y])]
        if bias is not None:
            nodes.append(helper.make_node("Add", [f"{p}/scaled", const(f"{p}/bias", bias)], [y]))
        replace[id(n)] = nodes

    out = []
    for n in nodes_in:
        out += before.get(id(n), [])
        if id(n) in replace:
            out += replace[id(n)]
            continue
        for i, name in enumerate(n.output):
            if name in renamed:
                n.output[i] = renamed[name]
        if id(n) in renamed_inputs:
            old_in, new_in = renamed_inputs[id(n)]
            for i, name in enumerate(n.input):
                if name == old_in:
                    n.input[i] = new_in
        out.append(n)
        out += after.get(id(n), [])
    kept = []
    for n in out:  # copies: the old nodes' objects may share storage with the field cleared next
        c = onnx.NodeProto()
        c.CopyFrom(n)
        kept.append(c)
    del g.node[:]
    g.node.extend(kept)
    g.initializer.extend(new_init)
    if not any(o.domain == MS_DOMAIN for o in proto.opset_import):
        proto.opset_import.append(helper.make_opsetid(MS_DOMAIN, 1))
    _drop_unused_initializers(g)
    return proto.SerializeToString()


def _weight_and_bias(n, weights: dict, numpy_helper) -> tuple[np.ndarray, np.ndarray | None]:
    """``(w (K, N) float32, bias (N,) or None)`` of a ``Gemm`` or ``MatMul`` node whose
    weight is a constant (a ``Gemm``'s bias too, and alpha = beta = 1, no transA)."""
    w = numpy_helper.to_array(weights[n.input[1]]).astype(np.float32)
    if n.op_type == "MatMul":
        if w.ndim != 2:
            raise RuntimeError(f"int8 quantisation: {n.name}'s weight is not a matrix")
        return w, None
    attrs = {a.name: a for a in n.attribute}
    get = {k: (a.f if a.type == a.FLOAT else a.i) for k, a in attrs.items()}
    if get.get("alpha", 1.0) != 1.0 or get.get("beta", 1.0) != 1.0 or get.get("transA", 0):
        raise RuntimeError(f"int8 quantisation: {n.name} is not a plain x W + b")
    trans_b = bool(get.get("transB", 0))
    bias = None
    if len(n.input) > 2 and n.input[2]:
        if n.input[2] not in weights:
            raise RuntimeError(f"int8 quantisation: {n.name}'s bias is not a constant")
        bias = numpy_helper.to_array(weights[n.input[2]]).astype(np.float32).reshape(-1)
    return (w.T.copy() if trans_b else w), bias


def _pooled_encoder_layer(n, src, producer: dict, consumers: dict):
    """``(relu, pool)`` (the nodes) when ``n`` is the encoder's per-point product that
    ends in the max-pool: ``Reshape(Relu (B, N, K)) -> n -> Reshape (B, N, F) -> ReduceMax
    over axis 1`` (keepdims 0), each intermediate used once; else None."""
    if src is None or src.op_type != "Reshape":
        return None
    relu = producer.get(src.input[0])
    if relu is None or relu.op_type != "Relu" or len(consumers.get(src.output[0], [])) != 1:
        return None
    after = consumers.get(n.output[0], [])
    if len(after) != 1 or after[0].op_type != "Reshape":
        return None
    pool = consumers.get(after[0].output[0], [])
    if len(pool) != 1 or pool[0].op_type != "ReduceMax":
        return None
    attrs = {a.name: a for a in pool[0].attribute}
    axes = list(attrs["axes"].ints) if "axes" in attrs else None
    keep = attrs["keepdims"].i if "keepdims" in attrs else 1
    if axes != [1] or keep != 0 or len(pool[0].input) != 1:
        return None
    return relu, pool[0]


def _row_form(n, producer: dict, consumers: dict, targets: list):
    """The form of a per-point product on a ReLU's rows (:func:`quantize_onnx`'s ``rows``):
    ``("pooled", its Reshape, the ReduceMax)`` or ``("split", its Reshape, (the Add, the
    pooled layer of ``targets`` after it))``; None for any other graph."""
    src = producer.get(n.input[0])
    after = consumers.get(n.output[0], [])
    if src is None or src.op_type != "Relu" or len(after) != 1 or after[0].op_type != "Reshape":
        return None
    resh = after[0]
    nxt = consumers.get(resh.output[0], [])
    if len(nxt) != 1:
        return None
    if nxt[0].op_type == "ReduceMax":
        attrs = {a.name: a for a in nxt[0].attribute}
        axes = list(attrs["axes"].ints) if "axes" in attrs else None
        keep = attrs["keepdims"].i if "keepdims" in attrs else 1
        return ("pooled", resh, nxt[0]) if axes == [1] and keep == 0 else None
    if nxt[0].op_type != "Add":
        return None
    add = nxt[0]
    relu = consumers.get(add.output[0], [])
    if len(relu) != 1 or relu[0].op_type != "Relu":
        return None
    rows = consumers.get(relu[0].output[0], [])
    layer = consumers.get(rows[0].output[0], []) if len(rows) == 1 else []
    if len(layer) != 1 or not any(layer[0] is t for t in targets) or _pooled_encoder_layer(
            layer[0], rows[0], producer, consumers) is None:
        return None
    return ("split", resh, (add, layer[0]))


def _equalise(x: str, k: int, members: list, producer: dict, consumers: dict, weights: dict,
              numpy_helper, const, p: str, sample: np.ndarray | None = None) -> np.ndarray:
    """Channel gains (K,) of the ReLU's rows ``x`` (``k`` wide) shared by ``members``: its producer's
    output channels divided by them (new weights), so that every channel spans about the
    same range before one scale per track quantises them all (cross-layer equalisation,
    Nagel et al. 2019, ICCV), the layers reading ``x`` multiplied back (the members before
    they are quantised, float readers in new weights). The gain of a channel is its largest
    value on ``sample`` (the producer's typical inputs), or without one the largest it can
    take on the unit cube (the sum of its weights' magnitudes and its bias's); 1 for a
    channel that stays 0. Ones where the producer is not a ``Gemm`` of constants or a reader
    of ``x`` is not a product of a constant weight."""
    relu = producer[x]
    gemm = producer.get(relu.input[0])
    ones = np.ones(k, np.float32)
    mine = {id(m) for m in members}
    others = [c for c in consumers.get(x, []) if id(c) not in mine]
    if (gemm is None or gemm.op_type != "Gemm" or len(gemm.input) < 3
            or gemm.input[1] not in weights or gemm.input[2] not in weights
            or len(consumers.get(relu.input[0], [])) != 1
            or not all(c.op_type in ("Gemm", "MatMul") and len(c.input) >= 2
                       and c.input[0] == x and c.input[1] in weights for c in others)):
        return ones
    w0, b0 = _weight_and_bias(gemm, weights, numpy_helper)  # (C, K), (K,)
    if b0 is None:
        return ones
    if sample is not None and np.shape(sample)[-1] == w0.shape[0]:
        gain = np.maximum(np.asarray(sample, np.float32) @ w0 + b0, 0.0).max(axis=0)
    else:
        gain = np.abs(w0).sum(axis=0) + np.abs(b0)
    gain = np.where(gain > 0, gain, 1.0).astype(np.float32)
    _set_weight(gemm, w0 / gain, const, f"{p}/eq_w")
    gemm.input[2] = const(f"{p}/eq_b", (b0 / gain).astype(np.float32))
    for i, c in enumerate(others):  # float readers of the rows: their inputs scaled back
        _set_weight(c, _weight_and_bias(c, weights, numpy_helper)[0] * gain[:, None], const,
                    f"{p}/eq_w{i}")
    return gain


def _set_weight(n, w: np.ndarray, const, name: str) -> None:
    """Point product ``n`` at a new constant weight ``w`` given as ``(K, N)`` (stored as the
    node reads it: transposed for a ``Gemm`` with ``transB``)."""
    trans_b = n.op_type == "Gemm" and any(a.name == "transB" and a.i for a in n.attribute)
    n.input[1] = const(name, np.ascontiguousarray(w.T if trans_b else w, dtype=np.float32))


def _width(n, weights: dict, numpy_helper) -> int:
    """Columns of the rows that product ``n`` reads (its weight's input width)."""
    return int(_weight_and_bias(n, weights, numpy_helper)[0].shape[0])


def _drop_unused_initializers(g) -> None:
    """Remove the float weights the rewrite left without a reader."""
    used = {i for n in g.node for i in n.input} | {o.name for o in g.output}
    keep = [t for t in g.initializer if t.name in used]
    del g.initializer[:]
    g.initializer.extend(keep)
