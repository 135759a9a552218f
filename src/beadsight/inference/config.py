"""The names a runtime and an export accept, in one light module (no torch) that the
runtimes, the exporter and the command line all read."""

from __future__ import annotations

BACKENDS = ("torch", "compile", "onnx", "openvino", "cuda")  # inference runtimes
PRECISIONS = ("fp32", "bf16")  # runtime precisions ("auto" picks one)
EXPORT_FORMATS = ("onnx", "openvino")  # exported model files
EXPORT_PRECISIONS = ("fp32", "bf16")
