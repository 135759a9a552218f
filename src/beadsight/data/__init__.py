"""Data: datasets (HDF5), press segmentation, training windows, raw recordings, processing."""

from beadsight.data.dataset import (
    Dataset,
    DatasetError,
    DatasetWriter,
    import_reference,
    open_dataset,
)

__all__ = ["Dataset", "DatasetError", "DatasetWriter", "import_reference", "open_dataset"]
