"""Data: datasets (HDF5), press segmentation, training windows, raw recordings, processing."""

from beadsight.data.dataset import Dataset, DatasetError, open_dataset
from beadsight.data.dataset_writer import DatasetWriter
from beadsight.data.reference_file import export_reference, import_reference

__all__ = [
    "Dataset",
    "DatasetError",
    "DatasetWriter",
    "export_reference",
    "import_reference",
    "open_dataset",
]
