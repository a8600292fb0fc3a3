"""Consumers of a job's output: a PyTorch-ready dataset, WebDataset/Omnidata export, previews.

bpy-free (the API imports the previews); torch is optional (`pip install -e '.[torch]'`).
"""

from services.datasets.dataset import OmnidataDataset
from services.datasets.decode import decode_cue
from services.datasets.point_info import camera_of
from services.datasets.source import DatasetIntegrityError
from services.datasets.splits import assign_splits, read_split_csv, split_of

__all__ = [
    "DatasetIntegrityError",
    "OmnidataDataset",
    "assign_splits",
    "camera_of",
    "decode_cue",
    "read_split_csv",
    "split_of",
]
