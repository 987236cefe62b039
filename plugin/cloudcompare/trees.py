"""A trees output folder in CloudCompare: the thin ``pycc`` layer over :mod:`forestreg.plugin.geometry`.

:func:`build_trees_group` turns a :class:`~forestreg.plugin.geometry.TreesScene` into one folder
entity (``ccHObject``) named after the run, holding one ``ccMesh`` per tree (its cylinders as
closed tubes, in the tree's colour) and one ``ccPolyline`` per tree (its stem curve's centre line,
the diameters as the scalar field ``diameter_m`` of the polyline's vertices). The vertex clouds
carry the scene's global shift, so CloudCompare shows file coordinates. :func:`load_trees_folder`
is the plugin's action: it asks for the folder (or takes one), builds the group and adds it to
the database. ``pycc`` is passed in (or imported when called), never at import time.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional, Union

import numpy as np

from ..geometry import DEFAULT_FACETS, StemLine, TreeMesh, TreesScene, trees_scene

LOAD_TREES_ACTION_NAME = "forestreg: load trees output folder"

__all__ = ["LOAD_TREES_ACTION_NAME", "build_trees_group", "load_trees_folder"]


def _cloud(pycc, points: np.ndarray, shift) -> Any:
    """A ccPointCloud of ``points`` (file coordinates) stored as ``points + shift``, with that shift."""
    local = np.asarray(points, dtype=np.float64) + np.asarray(shift, dtype=np.float64)
    cloud = pycc.ccPointCloud(
        np.ascontiguousarray(local[:, 0]), np.ascontiguousarray(local[:, 1]), np.ascontiguousarray(local[:, 2])
    )
    if any(shift):
        _set_shift(pycc, cloud, shift)
    return cloud


def _set_shift(pycc, cloud, shift) -> None:
    """``setGlobalShift`` with a CCVector3d (from pycc or cccorelib, as the runtime has it), else
    with three numbers."""
    makers = [getattr(pycc, "CCVector3d", None)]
    try:
        import cccorelib

        makers.append(getattr(cccorelib, "CCVector3d", None))
    except ImportError:
        pass
    for make in makers:
        if make is None:
            continue
        try:
            cloud.setGlobalShift(make(*shift))
            return
        except Exception:  # noqa: BLE001 - another binding's vector type: try the next
            continue
    cloud.setGlobalShift(*shift)


def _mesh(pycc, item: TreeMesh, shift) -> Any:
    vertices = _cloud(pycc, item.vertices, shift)
    vertices.setName("vertices")
    vertices.setEnabled(False)
    mesh = pycc.ccMesh(vertices)
    if hasattr(mesh, "reserve"):
        mesh.reserve(len(item.triangles))
    for i1, i2, i3 in item.triangles.tolist():
        mesh.addTriangle(i1, i2, i3)
    mesh.addChild(vertices)
    mesh.setName(item.name)
    mesh.setColor(pycc.Rgb(*item.colour))
    mesh.showColors(True)
    return mesh


def _polyline(pycc, item: StemLine, shift) -> Any:
    vertices = _cloud(pycc, item.points, shift)
    vertices.setName("centres")
    vertices.setEnabled(False)
    try:  # the diameters as a scalar field of the centres
        index = vertices.addScalarField("diameter_m")
        sf = vertices.getScalarField(index)
        sf.asArray()[:] = np.asarray(item.diameter_m, dtype=np.float64)
        sf.computeMinAndMax()
        vertices.setCurrentDisplayedScalarField(index)
    except Exception as exc:  # an older runtime: the line without its diameters
        print(f"forestreg: stem curve diameters of tree {item.tree_id} not attached ({exc})")
    line = pycc.ccPolyline(vertices)
    line.addPointIndex(0, len(item.points))
    line.setClosed(False)
    line.addChild(vertices)
    line.setName(item.name)
    line.setColor(pycc.Rgb(*item.colour))
    line.showColors(True)
    return line


def build_trees_group(pycc, scene: TreesScene) -> Any:
    """One ``ccHObject`` named after the run with one mesh and one polyline per tree."""
    group = pycc.ccHObject(scene.name)
    for m in scene.meshes:
        group.addChild(_mesh(pycc, m, scene.shift))
    for ln in scene.lines:
        group.addChild(_polyline(pycc, ln, scene.shift))
    return group


def _ask_folder() -> Optional[str]:
    try:
        from PySide2.QtWidgets import QFileDialog
    except ImportError:  # the runtime's Qt binding differs: the console is the way then
        print("forestreg: no folder dialog; call forestreg.plugin.cloudcompare.trees.load_trees_folder(PATH)")
        return None
    return QFileDialog.getExistingDirectory(None, "forestreg trees output folder") or None


def load_trees_folder(
    folder: Union[None, str, Path] = None, *, facets: int = DEFAULT_FACETS, unit_scale: float = 1.0, pycc=None
) -> Any:
    """The action: read a ``forestreg trees --out`` folder (asked for when not given) and add
    its group to CloudCompare's database; returns the group (None when no folder was chosen)."""
    if pycc is None:
        import pycc  # noqa: F811 - only inside CloudCompare
    folder = folder or _ask_folder()
    if not folder:
        return None
    scene = trees_scene(folder, facets=facets, unit_scale=unit_scale)
    group = build_trees_group(pycc, scene)
    cc = pycc.GetInstance()
    cc.addToDB(group)
    cc.updateUI()
    cc.redrawAll()
    print(f"forestreg: {scene.name}: {len(scene.meshes)} cylinder models, {len(scene.lines)} stem curves")
    return group
