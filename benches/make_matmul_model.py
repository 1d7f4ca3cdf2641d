"""Writes benches/matmul.onnx: one MatMul of two graph inputs A [M, K] and B [K, N] (dynamic
sizes, no weights), which `cargo bench --bench speed` runs through ONNX Runtime to measure
the machine's FP32 GEMM ceiling with the same library and threads as the engine.

    python benches/make_matmul_model.py
"""

from pathlib import Path

import onnx
from onnx import TensorProto, helper

graph = helper.make_graph(
    [helper.make_node("MatMul", ["A", "B"], ["C"])],
    "matmul",
    [helper.make_tensor_value_info("A", TensorProto.FLOAT, ["M", "K"]),
     helper.make_tensor_value_info("B", TensorProto.FLOAT, ["K", "N"])],
    [helper.make_tensor_value_info("C", TensorProto.FLOAT, ["M", "N"])],
)
model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], producer_name="mcdenoise-bench")
model.ir_version = 8
onnx.checker.check_model(model)
onnx.save(model, Path(__file__).with_name("matmul.onnx"))
