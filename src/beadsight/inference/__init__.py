"""Running a model: runtimes (torch, compile, ONNX, OpenVINO, CUDA), parity checks,
automatic selection, exported files, and the stateful :class:`PressurePredictor`."""
