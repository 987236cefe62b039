"""A trees output folder drawn in CloudCompare: the tube and polyline geometry measured against the
cylinder and stem curve tables (no host), and the ``pycc`` layer run against a fake ``pycc``.

The folder is written by the real writer (:func:`write_trees_tables`) from a small hand-made
inventory with an origin shift, at georeferenced coordinates: the geometry must come out in the
file's coordinates (local + origin shift), which is what ``trees.csv`` holds."""

from __future__ import annotations

import math
import sys
import types
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import pytest

from forestreg.engine.io.results import CYLINDER_COLUMNS, write_trees_tables
from forestreg.plugin import geometry as G

ORIGIN = np.array([512300.0, 6201400.0, 150.0])  # the origin shift of the run (UTM-like)
FACETS = 7


@dataclass
class _Cylinders:
    start: np.ndarray  # local coordinates (the writer adds the origin shift)
    axis: np.ndarray
    length: np.ndarray
    radius: np.ndarray

    def to_table(self):
        n = len(self.start)
        table = {c: np.zeros(n) for c in CYLINDER_COLUMNS}
        table.update(
            cylinder_id=np.arange(n),
            parent_id=np.arange(n) - 1,
            axis_x=self.axis[:, 0],
            axis_y=self.axis[:, 1],
            axis_z=self.axis[:, 2],
            length_m=self.length,
            radius_m=self.radius,
            surface_coverage=np.ones(n),
        )
        return table


def _stem(base, lean, n, rng):
    """A leaning stem of ``n`` cylinders tapering up, plus one branch."""
    axis = np.array([lean, 0.3 * lean, 1.0])
    axis /= np.linalg.norm(axis)
    lengths = rng.uniform(0.4, 0.8, n)
    starts = base + np.concatenate([[0.0], np.cumsum(lengths)[:-1]])[:, None] * axis
    radii = np.linspace(0.18, 0.04, n)
    b_axis = np.array([0.6, -0.5, 0.62])
    b_axis /= np.linalg.norm(b_axis)
    return _Cylinders(
        start=np.vstack([starts, starts[n // 2]]),
        axis=np.vstack([np.tile(axis, (n, 1)), b_axis]),
        length=np.append(lengths, 1.1),
        radius=np.append(radii, 0.03),
    ), axis


def _inventory():
    rng = np.random.default_rng(7)
    trees, rows = [], []
    for tid, (base, lean, n) in {
        3: (np.array([1.0, 2.0, 0.1]), 0.05, 6),
        4: (np.array([-4.0, 3.5, 0.3]), -0.1, 4),
        9: (np.array([2.5, -5.0, 0.0]), 0.0, 5),
    }.items():
        cyl, axis = _stem(base, lean, n, rng)
        heights = np.array([0.5, 1.3, 2.0, 3.0])
        centres = base + heights[:, None] * axis / axis[2]
        if tid == 9:
            centres[2] = np.nan  # a height without a centre: skipped by the line
        curve = SimpleNamespace(
            s_m=heights,
            heights_m=heights,
            diameter_m=np.array([0.36, 0.32, 0.3, 0.26]),
            raw_diameter_m=np.array([0.36, 0.33, 0.3, 0.25]),
            accepted=np.ones(4, bool),
            interpolated=np.zeros(4, bool),
            centres=centres,
            reasons=("", "", "", ""),
        )
        trees.append(SimpleNamespace(tree_id=tid, curve=curve, cylinders=None if tid == 4 else cyl))
        x, y, z = base + ORIGIN
        rows.append({"tree_id": tid, "x": x, "y": y, "z": z, "dbh_m": 0.32, "n_cylinders": len(cyl.start), "flag": ""})
    return SimpleNamespace(trees=trees, origin_shift=ORIGIN, rows=lambda: rows)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    inv = _inventory()
    folder = tmp_path_factory.mktemp("cc_trees") / "plot_07_trees"
    write_trees_tables(folder, inv)
    return inv, folder, G.trees_scene(folder, facets=FACETS)


def _distance_to_axis(p, start, axis):
    d = p - start
    return np.linalg.norm(d - (d @ axis)[:, None] * axis, axis=1)


def test_one_mesh_per_tree_with_a_cylinder_model_one_tube_per_cylinder(run):
    inv, _, scene = run
    assert scene.name == "plot_07_trees"
    models = {t.tree_id: t.cylinders for t in inv.trees if t.cylinders is not None}
    assert [m.tree_id for m in scene.meshes] == sorted(models)  # tree 4 has no cylinder model: no mesh
    for mesh in scene.meshes:
        cyl = models[mesh.tree_id]
        assert mesh.n_cylinders == len(cyl.start)
        assert mesh.vertices.shape == (2 * FACETS * len(cyl.start), 3)
        assert mesh.triangles.shape == ((4 * FACETS - 4) * len(cyl.start), 3)
        assert mesh.colour == G.tree_colour(mesh.tree_id)


def test_tube_vertices_lie_on_the_cylinders_in_file_coordinates(run):
    inv, _, scene = run
    models = {t.tree_id: t.cylinders for t in inv.trees if t.cylinders is not None}
    for mesh in scene.meshes:
        cyl = models[mesh.tree_id]
        for i in range(len(cyl.start)):
            v = mesh.vertices[2 * FACETS * i : 2 * FACETS * (i + 1)]
            start = cyl.start[i] + ORIGIN  # file coordinates: the run's origin shift added
            np.testing.assert_allclose(_distance_to_axis(v, start, cyl.axis[i]), cyl.radius[i], rtol=0, atol=1e-9)
            along = (v - start) @ cyl.axis[i]
            np.testing.assert_allclose(along[:FACETS], 0.0, atol=1e-9)
            np.testing.assert_allclose(along[FACETS:], cyl.length[i], atol=1e-9)
        assert np.abs(mesh.vertices - ORIGIN).max() < 20  # near the trees, not near (0, 0, 0)


def test_tubes_are_closed_and_face_outwards():
    start, axis = np.array([10.0, -3.0, 2.0]), np.array([0.3, 0.2, 0.9]) / np.linalg.norm([0.3, 0.2, 0.9])
    v, t = G.tube(start, axis, 1.5, 0.2, facets=5)
    edges = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert (counts == 2).all()  # every edge shared by two triangles: a closed surface
    centre = start + 0.75 * axis
    normals = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    outwards = v[t].mean(axis=1) - centre
    assert ((normals * outwards).sum(axis=1) > 0).all()
    with pytest.raises(ValueError):
        G.tube(start, axis, 1.0, 0.1, facets=2)


def test_polylines_follow_the_stem_curve_centres_with_diameters(run):
    inv, _, scene = run
    assert [ln.tree_id for ln in scene.lines] == [3, 4, 9]  # every tree with a stem curve
    for ln in scene.lines:
        curve = next(t.curve for t in inv.trees if t.tree_id == ln.tree_id)
        keep = np.isfinite(curve.centres).all(axis=1)
        np.testing.assert_allclose(ln.points, curve.centres[keep] + ORIGIN, atol=1e-6)
        np.testing.assert_allclose(ln.diameter_m, curve.diameter_m[keep])
        assert (np.diff(ln.points[:, 2]) > 0).all()  # bottom to top
    assert len(scene.lines[-1].points) == 3  # the height without a centre is left out


def test_shift_for_georeferenced_coordinates_and_units(run, tmp_path):
    _, folder, scene = run
    shift = np.asarray(scene.shift)
    assert np.abs(scene.meshes[0].vertices + shift).max() < 1e3  # single precision is enough after the shift
    assert (shift % 100 == 0).all()
    local = SimpleNamespace(
        trees=[], origin_shift=np.zeros(3), rows=lambda: [{"tree_id": 1, "x": 1.0, "y": 2.0, "z": 0.0}]
    )
    write_trees_tables(tmp_path / "near", local)
    assert G.trees_scene(tmp_path / "near").shift == (0.0, 0.0, 0.0)
    in_cm = G.trees_scene(folder, facets=FACETS, unit_scale=0.01)  # starts in cm: lengths and radii scaled to them
    v, start = in_cm.meshes[0].vertices, scene.meshes[0].vertices
    r_m = np.linalg.norm(start[0] - start[FACETS // 2])  # any chord: scaled by 100 with the radius
    assert math.isclose(np.linalg.norm(v[0] - v[FACETS // 2]), 100 * r_m, rel_tol=1e-9)


def test_palette_is_the_reports():
    pytest.importorskip("matplotlib")
    from forestreg.engine.report.trees_report import _tree_colours

    ids = np.arange(20)
    assert [tuple(int(c) for c in rgba[:3]) for rgba in _tree_colours(ids)] == [G.tree_colour(i) for i in ids]


# ----------------------------------------------------------------------------- pycc layer (fake)


class _Entity:
    def __init__(self, name=""):
        self.name, self.children, self.colour, self.enabled = name, [], None, True

    def setName(self, name):  # noqa: N802 - pycc naming
        self.name = name

    def addChild(self, child):  # noqa: N802
        self.children.append(child)

    def setColor(self, rgb):  # noqa: N802
        self.colour = rgb

    def showColors(self, on):  # noqa: N802
        self.colours_shown = on

    def setEnabled(self, on):  # noqa: N802
        self.enabled = on


def _fake_pycc():
    pycc = types.ModuleType("pycc")

    class ccHObject(_Entity):  # noqa: N801
        pass

    class ScalarField:
        def __init__(self, n):
            self.values = np.zeros(n, dtype=np.float32)

        def asArray(self):  # noqa: N802
            return self.values

        def computeMinAndMax(self):  # noqa: N802
            pass

    class ccPointCloud(_Entity):  # noqa: N801
        def __init__(self, x, y, z):
            super().__init__()
            self.xyz = np.stack([x, y, z], axis=1).astype(np.float32)  # CloudCompare holds float32
            self.shift, self.fields, self.shown_field = (0.0, 0.0, 0.0), {}, None

        def setGlobalShift(self, v):  # noqa: N802
            self.shift = (v.x, v.y, v.z)

        def addScalarField(self, name):  # noqa: N802
            self.fields[name] = ScalarField(len(self.xyz))
            return list(self.fields).index(name)

        def getScalarField(self, index):  # noqa: N802
            return list(self.fields.values())[index]

        def setCurrentDisplayedScalarField(self, index):  # noqa: N802
            self.shown_field = index

    class ccMesh(_Entity):  # noqa: N801
        def __init__(self, cloud):
            super().__init__()
            self.cloud, self.triangles = cloud, []

        def addTriangle(self, i1, i2, i3):  # noqa: N802
            self.triangles.append((i1, i2, i3))

    class ccPolyline(_Entity):  # noqa: N801
        def __init__(self, cloud):
            super().__init__()
            self.cloud, self.indices, self.closed = cloud, [], None

        def addPointIndex(self, first, last):  # noqa: N802
            self.indices.extend(range(first, last))

        def setClosed(self, closed):  # noqa: N802
            self.closed = closed

    class Instance:
        def __init__(self):
            self.db = []

        def addToDB(self, entity):  # noqa: N802
            self.db.append(entity)

        def updateUI(self):  # noqa: N802
            pass

        def redrawAll(self):  # noqa: N802
            pass

    instance = Instance()
    pycc.ccHObject, pycc.ccPointCloud, pycc.ccMesh, pycc.ccPolyline = ccHObject, ccPointCloud, ccMesh, ccPolyline
    pycc.Rgb = lambda r, g, b: (r, g, b)
    pycc.CCVector3d = lambda x, y, z: SimpleNamespace(x=x, y=y, z=z)
    pycc.GetInstance = lambda: instance
    return pycc


def test_pycc_layer_builds_one_group_of_meshes_and_polylines(run):
    from forestreg.plugin.cloudcompare.trees import build_trees_group, load_trees_folder

    _, folder, scene = run
    pycc = _fake_pycc()
    group = load_trees_folder(folder, facets=FACETS, pycc=pycc)
    assert pycc.GetInstance().db == [group] and isinstance(group, pycc.ccHObject) and group.name == "plot_07_trees"
    meshes = [c for c in group.children if isinstance(c, pycc.ccMesh)]
    lines = [c for c in group.children if isinstance(c, pycc.ccPolyline)]
    assert len(meshes) == len(scene.meshes) == 2 and len(lines) == len(scene.lines) == 3
    assert len(group.children) == len(meshes) + len(lines)
    for mesh, item in zip(meshes, scene.meshes):
        assert mesh.name == item.name and mesh.colour == item.colour
        assert np.array_equal(np.array(mesh.triangles), item.triangles)
        assert mesh.cloud in mesh.children and not mesh.cloud.enabled  # the vertices under their mesh
        # CloudCompare's global coordinates (local - shift) are the file's, to float32 precision
        np.testing.assert_allclose(mesh.cloud.xyz - np.asarray(mesh.cloud.shift), item.vertices, atol=1e-3)
        assert mesh.cloud.shift == scene.shift
    for line, item in zip(lines, scene.lines):
        assert line.indices == list(range(len(item.points))) and line.closed is False
        np.testing.assert_allclose(line.cloud.xyz - np.asarray(line.cloud.shift), item.points, atol=1e-3)
        field = line.cloud.fields["diameter_m"].values
        np.testing.assert_allclose(field, item.diameter_m, rtol=1e-6)
        assert line.cloud.shown_field == 0
    again = build_trees_group(pycc, G.trees_scene(folder, facets=FACETS))
    assert [c.name for c in again.children] == [c.name for c in group.children]


def test_trees_layer_imports_without_pycc():
    import subprocess

    code = (
        "import sys, forestreg.plugin.cloudcompare.trees as m, forestreg.plugin.geometry; "
        "sys.exit(1 if 'pycc' in sys.modules else 0)"
    )
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_global_shift_without_a_vector_type(run):
    from forestreg.plugin.cloudcompare.trees import build_trees_group

    _, _, scene = run
    pycc = _fake_pycc()
    del pycc.CCVector3d  # a runtime whose pycc has no CCVector3d (and no cccorelib here): three numbers

    def set_shift(self, *xyz):
        self.shift = xyz if len(xyz) == 3 else (xyz[0].x, xyz[0].y, xyz[0].z)

    pycc.ccPointCloud.setGlobalShift = set_shift
    group = build_trees_group(pycc, scene)
    assert all(c.cloud.shift == scene.shift for c in group.children)
