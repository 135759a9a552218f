"""Running a model.

===============  ================================================================
frames           raw camera frame -> model input (the one preprocessing rule)
backend          the runtime interface (``Backend``: ``run``, ``run_incremental``)
runtimes         the backends: torch, compile, ONNX Runtime, OpenVINO, CUDA graphs
parity           probe windows and the check that a runtime agrees with fp32 torch
select           choosing a runtime: by name, from an exported file, or "auto"
machine          CPU threads, the cache folder, a key for this machine
export_format    the exported-file format: write and read ONNX / OpenVINO files
export           export a checkpoint and check the file against torch
predictor        ``PressurePredictor``: frames in, ``PressureReading`` out
===============  ================================================================
"""
