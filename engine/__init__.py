"""forestreg.engine: the headless methods (numpy, scipy, open3d, laspy; never Qt)."""

from .core.errors import (
    Cancelled,
    ForestregError,
    ParameterError,
    ProjectFileError,
    ScanDataError,
    ScanReadError,
    ScanWriteError,
    TargetError,
)
from .core.progress import CancelToken, Progress
from .core.scan import Scan

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
