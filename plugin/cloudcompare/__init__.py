"""forestreg in CloudCompare (CloudCompare-PythonRuntime).

Select two point clouds (the reference first, then the moving one), run "forestreg: register
selected pair": both clouds are written to temporary binary PLY files in their global
coordinates, ``forestreg register`` runs as a job of the forestreg service (started on first use;
its progress events are printed to the console) through :mod:`forestreg.plugin.adapter`, and the
resulting matrix (``p_reference = matrix @ p_moving``) is
applied to the moving cloud. A failed registration changes nothing and shows the reason.

"forestreg: load trees output folder" draws a ``forestreg trees --out`` folder: one mesh per tree
(its cylinder model) and one polyline per tree (its stem curve), grouped under the run's name
(:mod:`forestreg.plugin.cloudcompare.trees`, geometry in :mod:`forestreg.plugin.geometry`).

The runtime discovers the plugin through the entry point group ``cloudcompare.plugins``::

    [project.entry-points."cloudcompare.plugins"]
    forestreg = "forestreg.plugin.cloudcompare:ForestregCC"

``pycc`` exists only inside CloudCompare, so it is never imported when this module is: the plugin
class ``ForestregCC`` is built on first access (module ``__getattr__``), which is what the
runtime's ``entry_point.load()`` does. The functions below that take no ``pycc`` object
(:func:`register_files`, :func:`local_matrix`, :func:`write_ply`) work and are tested without it.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Optional, Sequence, Union

from .. import adapter

ACTION_NAME = "forestreg: register selected pair"
_plugin_class = None


def register_files(
    reference: Union[str, Path],
    moving: Union[str, Path],
    out_dir: Union[str, Path],
    vop_radius_m: Optional[float] = None,
    cli: Union[None, str, Sequence[str]] = None,
    progress: Optional[adapter.ProgressCallback] = None,
    log: Optional[adapter.LogCallback] = None,
    scanner_positions: Sequence[Sequence[float]] = (),
) -> adapter.HostOutputs:
    """Register two files as a job of the service; the outputs' ``matrix`` is None when the
    registration failed."""
    job = adapter.PairJob(reference, moving, out_dir, vop_radius_m=vop_radius_m, scanner_positions=scanner_positions)
    return adapter.register_pair(job, cli, progress=progress, log=log)


def local_matrix(
    matrix: Sequence[Sequence[float]], reference_shift: Sequence[float], moving_shift: Sequence[float]
) -> list:
    """The matrix to apply to the moving cloud's *local* (CloudCompare-shifted) coordinates.

    CloudCompare stores ``local = global + shift`` per cloud. With ``global_ref = M @ global_mov``:
    ``local_ref = M @ (local_mov - s_mov) + s_ref``, i.e. rotation ``R`` and translation
    ``t - R @ s_mov + s_ref``. The moving cloud then takes the reference's shift.
    """
    r = [[float(matrix[i][j]) for j in range(3)] for i in range(3)]
    t = [float(matrix[i][3]) for i in range(3)]
    rs = [sum(r[i][j] * float(moving_shift[j]) for j in range(3)) for i in range(3)]
    t2 = [t[i] - rs[i] + float(reference_shift[i]) for i in range(3)]
    return [r[0] + [t2[0]], r[1] + [t2[1]], r[2] + [t2[2]], [0.0, 0.0, 0.0, 1.0]]


def write_ply(path: Union[str, Path], points) -> Path:
    """(N, 3) points as a binary little-endian PLY (double x, y, z): a format the CLI reads."""
    import numpy as np

    pts = np.ascontiguousarray(np.asarray(points, dtype="<f8").reshape(-1, 3))
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(pts)}\nproperty double x\nproperty double y\nproperty double z\nend_header\n"
    path = Path(path)
    with path.open("wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(pts.tobytes())
    return path


# ----------------------------------------------------------------------------- pycc side


def _shift(cloud) -> tuple[float, float, float]:
    try:
        s = cloud.getGlobalShift()
        return (float(s.x), float(s.y), float(s.z))
    except Exception:
        return (0.0, 0.0, 0.0)


def _scale(cloud) -> float:
    try:
        return float(cloud.getGlobalScale()) or 1.0
    except Exception:
        return 1.0


def _apply_to_cloud(pycc, cloud, m: list) -> None:
    """Apply the 4x4 ``m`` to a ccPointCloud's coordinates (GL transformation, else the numpy view)."""
    try:
        import cccorelib

        cols = [cccorelib.CCVector3(m[0][k], m[1][k], m[2][k]) for k in range(4)]
        gl = pycc.ccGLMatrix(*cols)
        cloud.setGLTransformation(gl)
        cloud.applyGLTransformation_recursive()
        return
    except Exception:
        pass
    import numpy as np

    pts = cloud.points()  # a writable view of the cloud's float32 coordinates
    mat = np.asarray(m, dtype=np.float64)
    pts[:] = (pts.astype(np.float64) @ mat[:3, :3].T + mat[:3, 3]).astype(pts.dtype)
    for name in ("invalidateBoundingBox", "refreshBB"):
        if hasattr(cloud, name):
            getattr(cloud, name)()


def register_selected(
    vop_radius_m: Optional[float] = None, cli=None, out_dir: Optional[str] = None
) -> Optional[adapter.HostOutputs]:
    """The action: register the two selected clouds (reference first) and move the second."""
    import numpy as np
    import pycc

    cc = pycc.GetInstance()
    clouds = [e for e in cc.getSelectedEntities() if isinstance(e, pycc.ccPointCloud)]
    if len(clouds) != 2:
        raise RuntimeError("select exactly two point clouds: the reference first, then the moving one")
    reference, moving = clouds
    work = Path(out_dir) if out_dir else Path(tempfile.mkdtemp(prefix="forestreg_cc_"))
    work.mkdir(parents=True, exist_ok=True)
    files = []
    for cloud, name in ((reference, "reference.ply"), (moving, "moving.ply")):
        local = np.asarray(cloud.points(), dtype=np.float64)
        files.append(write_ply(work / name, local / _scale(cloud) - np.asarray(_shift(cloud))))
    cc.freezeUI(True)
    try:
        outputs = register_files(
            files[0],
            files[1],
            work / "registration",
            vop_radius_m=vop_radius_m,
            cli=cli,
            progress=lambda f, msg: print(f"forestreg {100 * f:3.0f}% {msg}"),
            log=print,
        )
    finally:
        cc.freezeUI(False)
    if outputs.matrix is None:
        print(f"forestreg: registration failed: {outputs.reason} (nothing was moved; see {outputs.out_dir})")
        return outputs
    m = local_matrix(outputs.matrix, _shift(reference), _shift(moving))
    _apply_to_cloud(pycc, moving, m)
    try:
        s = _shift(reference)
        moving.setGlobalShift(pycc.CCVector3d(*s) if hasattr(pycc, "CCVector3d") else s)
    except Exception:
        pass
    std = (
        outputs.result.icp_std_m
        if outputs.result is not None and outputs.result.icp_std_m is not None
        else float("nan")
    )
    print(
        f"forestreg: ok, {outputs.matched} matched VOPs, ICP std {1000 * std:.1f} mm; "
        f"transform.txt in {outputs.out_dir}"
    )
    cc.updateUI()
    cc.redrawAll()
    return outputs


def _build_plugin_class():
    import pycc

    class ForestregCC(pycc.PythonPluginInterface):
        """The CloudCompare-PythonRuntime plugin: register the two selected clouds; load a trees
        output folder."""

        def __init__(self) -> None:
            pycc.PythonPluginInterface.__init__(self)

        def getActions(self):  # noqa: N802 - runtime naming
            from .trees import LOAD_TREES_ACTION_NAME, load_trees_folder

            return [
                pycc.Action(name=ACTION_NAME, target=register_selected),
                pycc.Action(name=LOAD_TREES_ACTION_NAME, target=load_trees_folder),
            ]

    return ForestregCC


def __getattr__(name: str):
    """``ForestregCC``, built (importing ``pycc``) on first access only."""
    global _plugin_class
    if name == "ForestregCC":
        if _plugin_class is None:
            _plugin_class = _build_plugin_class()
        return _plugin_class
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["register_files", "register_selected", "local_matrix", "write_ply", "ACTION_NAME"]
