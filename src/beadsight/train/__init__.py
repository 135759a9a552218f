"""Training: configuration, the trainer (single process or DDP), run folders and windows.

* :mod:`~beadsight.train.config` - :class:`TrainConfig` and how it is resolved;
* :mod:`~beadsight.train.trainer` - :func:`train` and the training loop;
* :mod:`~beadsight.train.prepare` - split, windows and the model a run starts from;
* :mod:`~beadsight.train.step` - one optimizer step of the reference recipe;
* :mod:`~beadsight.train.distributed` - the DDP process group and the device;
* :mod:`~beadsight.train.run` - the run folder and its checkpoints;
* :mod:`~beadsight.train.windows`, :mod:`~beadsight.train.augment` - batches of windows.
"""
