"""Running a model.

===============  ================================================================
frames           raw camera frame -> model input (the one preprocessing rule)
backend          the runtime interface (``Backend``: ``run``, ``run_batch``, ``run_incremental``)
runtimes         the backends: torch, ONNX Runtime, OpenVINO, CUDA graphs
planes           the network alone on float32 planes, and the ring that keeps them per frame
int8             the int8 backend: OpenVINO after NNCF quantization on simulated presses
parity           probe windows and the check that a runtime agrees with fp32 torch
metric_parity    held-out simulated presses; a runtime must keep the paper's metrics
select           choosing a runtime: by name, from an exported file, or "auto"
machine          CPU threads, the cache folder, a key for this machine
export_format    the exported-file format: write and read ONNX / OpenVINO files
export           export a checkpoint and check the file against torch
predictor        ``PressurePredictor``: frames in, ``PressureReading`` out
===============  ================================================================
"""
