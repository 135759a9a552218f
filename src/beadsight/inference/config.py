"""The names a runtime and an export accept, in one light module (no torch) that the
runtimes, the exporter and the command line all read."""

from __future__ import annotations

BACKENDS = ("torch", "onnx", "openvino", "int8", "cuda")  # inference runtimes
PRECISIONS = ("fp32", "bf16")  # float runtime precisions ("auto" picks one)
INT8 = "int8"  # the int8 runtime's only precision (OpenVINO after NNCF quantization)
EXPORT_FORMATS = ("onnx", "openvino")  # exported model files
EXPORT_PRECISIONS = ("fp32", "bf16")
