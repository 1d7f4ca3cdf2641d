"""Writes the GEMM models that `cargo bench --bench speed` runs through ONNX Runtime to
measure the machine's ceilings with the same library and threads as the engine:

- benches/matmul.onnx: one FP32 MatMul of two graph inputs A [M, K] and B [K, N];
- benches/matmul-int8.onnx: one MatMulInteger of A (uint8) [M, K] and B (int8) [K, N] into
  int32, the u8 x s8 form of the int8 convolutions (`mcdenoise_train.quantize`).

Dynamic sizes, no weights.

    python benches/make_matmul_model.py
"""

from pathlib import Path

import onnx
from onnx import TensorProto, helper


def write(name: str, op: str, a_type: int, b_type: int, c_type: int) -> None:
    graph = helper.make_graph(
        [helper.make_node(op, ["A", "B"], ["C"])],
        name.removesuffix(".onnx"),
        [helper.make_tensor_value_info("A", a_type, ["M", "K"]),
         helper.make_tensor_value_info("B", b_type, ["K", "N"])],
        [helper.make_tensor_value_info("C", c_type, ["M", "N"])],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], producer_name="mcdenoise-bench")
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, Path(__file__).with_name(name))


write("matmul.onnx", "MatMul", TensorProto.FLOAT, TensorProto.FLOAT, TensorProto.FLOAT)
write("matmul-int8.onnx", "MatMulInteger", TensorProto.UINT8, TensorProto.INT8, TensorProto.INT32)
