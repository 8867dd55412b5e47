"""Dataset formats: one reader/writer module per format, all returning PosedImage records.

See :mod:`planarloc.io.datasets` for the registry (``read_dataset(root, fmt)``).
"""

from planarloc.io.colmap_text import read_colmap
from planarloc.io.datasets import FORMATS, read_dataset
from planarloc.io.format_error import FormatError
from planarloc.io.gravity_file import read_gravity_file
from planarloc.io.hloc_pairs import read_hloc_pairs, write_hloc_pairs
from planarloc.io.kapture import read_kapture
from planarloc.io.kitti import read_kitti
from planarloc.io.openloris import read_openloris
from planarloc.io.pose_list import read_pose_list, write_pose_list
from planarloc.io.tum import associate_timestamps, read_tum

__all__ = [
    "FORMATS",
    "FormatError",
    "associate_timestamps",
    "read_colmap",
    "read_dataset",
    "read_gravity_file",
    "read_hloc_pairs",
    "read_kapture",
    "read_kitti",
    "read_openloris",
    "read_pose_list",
    "read_tum",
    "write_hloc_pairs",
    "write_pose_list",
]
