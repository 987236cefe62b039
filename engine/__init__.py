"""forestreg.engine: the headless methods (numpy, scipy, open3d, laspy; never Qt)."""

from .errors import (
    Cancelled,
    ForestregError,
    ParameterError,
    ScanDataError,
    ScanReadError,
    ScanWriteError,
    ProjectFileError,
    TargetError,
)
from .progress import CancelToken, Progress
from .scan import Scan

__all__ = [
    "Cancelled",
    "CancelToken",
    "ForestregError",
    "ParameterError",
    "Progress",
    "Scan",
    "ScanDataError",
    "ScanReadError",
    "ScanWriteError",
    "ProjectFileError",
    "TargetError",
]
