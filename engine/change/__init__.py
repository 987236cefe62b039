"""Re-surveys: a plot measured again years later, registered on what persisted, tree by tree changes.

- :mod:`.epoch`: the trees of one survey (:func:`epoch_from_cloud`, :func:`epoch_from_table`);
- :mod:`.registration`: persisting stems from any heading, refined on stem slices and terrain;
- :mod:`.matching`: persisting, removed and new trees with DBH and height changes;
- :func:`detect_change`: both, as a :class:`ChangeResult`.

Example::

    from forestreg.engine.change import ChangeParams, detect_change, epoch_from_cloud
    result = detect_change(epoch_from_cloud(before_xyz), epoch_from_cloud(after_xyz))
    result.matrix            # p_before = matrix @ p_after
    [t.status for t in result.trees]
"""

from .detect import ChangeResult, detect_change, file_matrix
from .epoch import EpochTrees, epoch_from_cloud, epoch_from_table, position_unit_mismatch
from .matching import CHANGE_COLUMNS, STATUSES, TreeChange, match_trees
from .params import ChangeParams
from .registration import StemMatch, persisting_stems, refine_on_stems

__all__ = [
    "CHANGE_COLUMNS",
    "ChangeParams",
    "ChangeResult",
    "EpochTrees",
    "STATUSES",
    "StemMatch",
    "TreeChange",
    "detect_change",
    "epoch_from_cloud",
    "epoch_from_table",
    "file_matrix",
    "match_trees",
    "persisting_stems",
    "position_unit_mismatch",
    "refine_on_stems",
]
