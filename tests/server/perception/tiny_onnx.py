"""Tiny segmentation networks in the wardmap ONNX contract, built with ``onnx.helper``.

The network is one 1x1 convolution: per pixel, ``logits = W @ rgb + b``. With the default
weights a red pixel (RGB 0..1) is ``person``, a green one ``door``, anything else the
background; every other class has a large negative bias. With ``depth_channel`` the input
has a fourth channel, depth in metres, and a pixel farther than 2.5 m (and neither red nor
green) is a ``chair``. With ``ramp`` the person logit also gets a left-to-right ramp from
``-ramp`` to ``+ramp`` (a network that is not mirror-symmetric). Test helpers only (needs the
``onnx`` package, a dev dependency).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from wardmap.shared.knowledge import KnowledgeGraph


def kg_classes() -> list[str]:
    return ["background", *KnowledgeGraph.load().names]


def write_tiny_seg(
    path: Path,
    *,
    input_wh: tuple[int, int] = (32, 24),
    classes: Sequence[str] | None = None,
    input_name: str = "image",
    output_name: str = "logits",
    out_channels: int | None = None,
    metadata: dict[str, str | None] | None = None,
    depth_channel: bool = False,
    ramp: float = 0.0,
) -> Path:
    """Write the model to ``path``; arguments let tests break one part of the contract."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    names = list(classes) if classes is not None else kg_classes()
    c = out_channels if out_channels is not None else len(names)
    w, h = input_wh
    cin = 4 if depth_channel else 3
    weight = np.zeros((c, cin, 1, 1), np.float32)
    bias = np.full((c,), -100.0, np.float32)
    bias[0] = 0.0
    for name, channel in (("person", 0), ("door", 1)):
        if name in names and names.index(name) < c:
            k = names.index(name)
            weight[k, channel, 0, 0] = 10.0
            bias[k] = -5.0
    if depth_channel and "chair" in names and names.index("chair") < c:
        k = names.index("chair")
        weight[k, :3, 0, 0] = -100.0
        weight[k, 3, 0, 0] = 10.0
        bias[k] = -25.0
    offset = np.zeros((1, c, 1, w), np.float32)
    if ramp and "person" in names and names.index("person") < c:
        offset[0, names.index("person"), 0] = np.linspace(-ramp, ramp, w, dtype=np.float32)
    graph = helper.make_graph(
        [
            helper.make_node("Conv", [input_name, "W", "B"], ["conv"], kernel_shape=[1, 1]),
            helper.make_node("Add", ["conv", "R"], [output_name]),
        ],
        "tiny_seg",
        [helper.make_tensor_value_info(input_name, TensorProto.FLOAT, [1, cin, h, w])],
        [helper.make_tensor_value_info(output_name, TensorProto.FLOAT, [1, c, h, w])],
        initializer=[
            numpy_helper.from_array(weight, "W"),
            numpy_helper.from_array(bias, "B"),
            numpy_helper.from_array(offset, "R"),
        ],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    meta: dict[str, str | None] = {"wardmap.classes": json.dumps(names), "wardmap.input_size": f"{w}x{h}"}
    meta.update(metadata or {})  # None removes a key
    for key, value in meta.items():
        if value is None:
            continue
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.checker.check_model(model)
    path.write_bytes(model.SerializeToString())
    return path
