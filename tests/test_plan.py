"""The next-scan planner: what a position sees (stems as opaque discs), the plot as the placed
scans saw it, and suggestions that lie in the plot, link to a placed scan (checked by simulating
and registering the suggested scan) and add stem area not seen yet; ``forestreg plan``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from forestreg.cli import main
from forestreg.engine.core.transform import rigid_errors
from forestreg.engine.io import write_scan
from forestreg.engine.tls.params import PlanParams, RegistrationParams
from forestreg.engine.tls.plan import PlotCoverage, StemMap, placed_links, placed_views, plan_scans, sight
from forestreg.engine.tls.plot import ScanCache, register_project
from forestreg.engine.tls.project import Project

TWO = ((0.0, 0.0), (7.0, 3.0))


def _stems(xy, radius) -> StemMap:
    xy = np.asarray(xy, dtype=float)
    return StemMap(xy, np.asarray(radius, dtype=float), tuple(frozenset() for _ in xy), {})


def test_a_stem_hides_what_stands_behind_it():
    stems = _stems([(5.0, 0.0), (10.0, 0.0), (0.0, 8.0)], [0.3, 0.3, 0.2])
    s = sight((0.0, 0.0), stems, reach_m=30.0)
    assert s.visible_fraction.tolist() == [1.0, 0.0, 1.0]
    arcs = s.arcs(stems, 36)
    front = int(180 // 10)  # the arc of the first stem facing the scanner (at 180 deg about its centre)
    assert arcs[0, front] == 1.0 and arcs[0, 0] == 0.0 and not arcs[1].any()
    ground = s.ground(np.array([(7.0, 0.0), (7.0, 3.0), (3.0, 0.0)]), reach_m=30.0)
    assert ground.tolist() == [False, True, True]
    assert not sight((0.0, 0.0), stems, reach_m=4.0).visible_fraction.any(), "nothing beyond reach is seen"
    # a coarser scanner puts fewer points on a far patch than on a near one
    coarse = sight((0.0, 0.0), _stems([(3.0, 0.0), (0.0, 20.0)], [0.2, 0.2]), reach_m=30.0).arcs(
        _stems([(3.0, 0.0), (0.0, 20.0)], [0.2, 0.2]), 36, 0.5, np.radians(0.4)
    )
    assert coarse[0].max() > coarse[1].max() > 0.0


@pytest.fixture(scope="module")
def placed(sim_plot, tmp_path_factory):
    """Two scans of a small simulated plot, registered: (plot, project, scan cache)."""
    plot = sim_plot("mixed_temperate", TWO, seed=41, step=0.4, size=30.0)
    folder = tmp_path_factory.mktemp("placed")
    project = Project(name="placed")
    for s in plot.scans:
        write_scan(s.scan, folder / f"{s.scan.name}.laz")
        project.add_scan(folder / f"{s.scan.name}.laz")
    cache = ScanCache(project, with_intensity=False)
    assert not register_project(project, scans=cache).failed
    project.save(folder / "project.json")
    return plot, project, cache


def test_the_plot_as_the_placed_scans_saw_it(placed):
    plot, project, cache = placed
    views = placed_views(project, cache)
    assert [v.name for v in views] == ["scan_01.laz", "scan_02.laz"]
    m0 = plot.scans[0].pose
    for v, s in zip(views, plot.scans):  # scanners where the truth has them
        assert np.allclose((m0 @ np.r_[v.scanner, 1.0])[:3], s.position, atol=0.05)
    assert abs(views[0].step_rad - np.radians(0.4)) < np.radians(0.05)
    coverage = PlotCoverage(views, PlanParams(radius_m=13.0), project.params)
    world = (m0[:2, :2] @ coverage.stems.xy.T).T + m0[:2, 3]
    trees = np.array([(t.x, t.y) for t in plot.scene.trees])
    nearest = np.min(np.hypot(*(world[:, None, :] - trees[None, :, :]).transpose(2, 0, 1)), axis=1)
    assert np.median(nearest) < 0.1 and len(coverage.stems) >= 20, "the stem map is made of the plot's stems"
    assert 0 < coverage.stems.seen_twice <= len(coverage.stems)
    seen, unseen = coverage.stem_area()
    assert seen > 0 and unseen > 0


def test_suggestions_lie_in_the_plot_link_and_add_unseen_stem_area(placed):
    _, project, cache = placed
    params = PlanParams(radius_m=13.0)
    coverage = PlotCoverage(placed_views(project, cache), params, project.params)
    plan = plan_scans(placed_views(project, cache), params, project.params, n=3)
    assert len(plan.suggestions) == 3 and plan.linking <= plan.candidates
    gains = []
    for s in plan.suggestions:
        assert np.hypot(s.x - plan.centre[0], s.y - plan.centre[1]) <= 13.0 + 1e-9
        assert s.shared_stems >= params.min_shared_stems and s.links_to in plan.scanners
        assert s.new_stem_area_m2 > 0
        d = np.hypot(*(coverage.stems.xy - (s.x, s.y)).T) - coverage.stems.radius
        assert d.min() >= params.clearance_m
        gains.append(s.gain_m2)
    assert gains == sorted(gains, reverse=True), "each later suggestion adds what the earlier ones leave"
    best = coverage.assess((plan.suggestions[0].x, plan.suggestions[0].y))[0]
    assert best[0] == plan.suggestions[0].shared_stems
    # a position next to a placed scanner adds less than the suggestion
    near = coverage.gain(*coverage.assess(plan.centre)[1:])
    assert near[0] < plan.suggestions[0].new_stem_area_m2
    # the placed link matched fewer trunk shadows than the map predicts: predictions fall off with distance
    links = placed_links(project)
    assert [(m, r) for m, r, _ in links] == [("scan_02.laz", "scan_01.laz")] and links[0][2] >= 4
    calibrated = PlotCoverage(placed_views(project, cache), params, project.params, links=links)
    assert calibrated.falloff_m > 0
    far = calibrated.assess((plan.suggestions[0].x, plan.suggestions[0].y))[0]
    assert far[0] <= best[0] and (far[0] < best[0] or not np.isfinite(calibrated.falloff_m))
    # one that links to nothing
    strict = plan_scans(placed_views(project, cache), params.replace(min_shared_stems=1000), project.params)
    assert not strict.suggestions and "would share 1000 trunk shadows" in strict.reason


def test_the_suggested_scan_links_when_it_is_made(placed, tmp_path):
    """The scanner set up where the plan says: the simulated scan there registers into the plot."""
    from forestreg.engine.simulate import simulate_plot

    plot, project, cache = placed
    plan = plan_scans(placed_views(project, cache), PlanParams(radius_m=13.0), project.params, n=1)
    s = plan.suggestions[0]
    m0 = plot.scans[0].pose
    world = (m0 @ np.array([s.x, s.y, 0.0, 1.0]))[:2]
    new = simulate_plot(
        "mixed_temperate", [tuple(world)], scene=plot.scene, seed=7, angular_step_deg=0.4, clearance_m=0.0
    ).scans[0]
    write_scan(new.scan, tmp_path / "scan_03.laz")
    trial = Project.load(project.path)
    trial.add_scan(tmp_path / "scan_03.laz")
    outcome = register_project(trial)
    assert outcome.scans["scan_03.laz"] == "ok", outcome.reasons
    rot, trans = rigid_errors(trial.poses()["scan_03.laz"], np.linalg.solve(m0, new.pose))
    assert rot < 0.05 and trans < 0.03


def test_plan_command_writes_plan_json_and_a_table(placed, tmp_path, capsys):
    _, project, _ = placed
    out = tmp_path / "plan.json"
    assert main(["plan", str(project.path), "--n", "2", "--radius", "13", "--out", str(out), "--progress", "none"]) == 0
    captured = capsys.readouterr()
    text = captured.out
    assert "link scan_02.laz -> scan_01.laz:" in text and "next" in text
    assert "plan.gpkg (the next_scans layer)" in captured.out + captured.err  # the layer's file is said
    doc = json.loads(out.read_text())
    assert doc["format"] == "forestreg-plan" and doc["frame"] == "scan_01.laz" and len(doc["suggestions"]) == 2
    assert doc["plot"]["radius_m"] == 13.0 and doc["stems"]["seen_by_two_or_more"] > 0
    assert doc["links"][0]["strength"] in ("strong", "fair", "weak")
    for row in doc["suggestions"]:
        assert set(row) >= {"x", "y", "links_to", "shared_stems", "new_stem_area_m2", "new_view_m2", "reason"}
    # plan.gpkg beside plan.json: the same suggestions as points of the next_scans layer, local coordinates
    points, srs = _next_scans(tmp_path / "plan.gpkg")
    assert srs == {"next_scans": -1}
    assert [(r["rank"], r["links_to"], r["shared_stems"]) for r in points] == [
        (s["rank"], s["links_to"], s["shared_stems"]) for s in doc["suggestions"]
    ]
    for r, s in zip(points, doc["suggestions"]):
        assert r["xy"] == pytest.approx((s["x"], s["y"]), abs=1e-9)
        assert r["new_stem_area_m2"] == pytest.approx(s["new_stem_area_m2"]) and r["reason"] == s["reason"]
        assert r["reason"].startswith(f"shares {s['shared_stems']} trunk shadows with {s['links_to']}")
    assert not [f for f in tmp_path.iterdir() if f.name.startswith(".")], "no temporary file left"


def _next_scans(path) -> tuple[list[dict], dict]:
    """The rows of the ``next_scans`` layer of a GeoPackage read with sqlite3 (``xy`` the point) and
    the srs_id of each feature layer."""
    import sqlite3

    from forestreg.engine.io.gpkg import decode_geometry

    con = sqlite3.connect(str(path))
    try:
        srs = dict(con.execute("SELECT table_name, srs_id FROM gpkg_geometry_columns"))
        cur = con.execute("SELECT * FROM next_scans ORDER BY fid")
        header = [d[0] for d in cur.description]
        rows = []
        for values in cur:
            row = dict(zip(header, values))
            kind, xy, srs_id = decode_geometry(row.pop("geom"))
            assert kind == "POINT" and srs_id == srs["next_scans"]
            rows.append({**row, "xy": tuple(xy)})
    finally:
        con.close()
    return rows, srs


def test_plan_gpkg_has_the_plot_crs_and_numbered_markers(placed, tmp_path):
    """A plot folder whose layers.gpkg is in a CRS: plan.gpkg is in it too, with a QGIS style
    that numbers the markers by rank."""
    import sqlite3

    from forestreg.app.layers import outline_layer, write_layers
    from forestreg.app.plan import plan_next
    from forestreg.engine.io.crs import parse_crs

    _, project, cache = placed
    folder = tmp_path / "geo"
    folder.mkdir()
    Project.load(project.path).save(folder / "project.json")
    write_layers(
        folder,
        [outline_layer(np.array([(0.0, 0.0), (5.0, 0.0), (0.0, 5.0)]), "plot", "a test ring")],
        parse_crs("EPSG:32633"),
    )
    run = plan_next(folder, n=3, params=PlanParams(radius_m=13.0), scans=cache)
    assert run and run.layers == folder / "plan.gpkg" and run.out == folder / "plan.json" and run.crs.epsg_code == 32633
    points, srs = _next_scans(run.layers)
    assert srs == {"next_scans": 32633} and len(points) == len(run.plan.suggestions) == 3
    assert [r["rank"] for r in points] == [1, 2, 3]
    assert [r["xy"] for r in points] == [(s.x, s.y) for s in run.plan.suggestions]
    con = sqlite3.connect(str(run.layers))
    try:
        org, code = con.execute(
            "SELECT organization, organization_coordsys_id FROM gpkg_spatial_ref_sys WHERE srs_id = 32633"
        ).fetchone()
        extent = con.execute(
            "SELECT min_x, min_y, max_x, max_y FROM gpkg_contents WHERE table_name = 'next_scans'"
        ).fetchone()
        style = con.execute("SELECT styleQML FROM layer_styles WHERE f_table_name = 'next_scans'").fetchone()[0]
    finally:
        con.close()
    assert (org, code) == ("EPSG", 32633)
    xy = np.array([r["xy"] for r in points])
    assert extent == pytest.approx((*xy.min(axis=0), *xy.max(axis=0)))
    assert '<labeling type="simple">' in style and 'fieldName="rank"' in style and 'labelsEnabled="1"' in style


def test_a_plan_without_suggestions_writes_an_empty_layer_and_a_failed_write_replaces_nothing(
    placed, tmp_path, monkeypatch
):
    from forestreg.app.plan import plan_next
    from forestreg.engine.core.errors import ScanWriteError

    _, project, cache = placed
    out = tmp_path / "strict.json"
    run = plan_next(project.path, params=PlanParams(radius_m=13.0, min_shared_stems=1000), out=out, scans=cache)
    assert not run and "would share 1000 trunk shadows" in run.reason and run.layers == tmp_path / "strict.gpkg"
    points, srs = _next_scans(run.layers)
    assert points == [] and srs == {"next_scans": -1}
    before = {p.name: p.read_bytes() for p in (out, run.layers)}

    def refuse(*args, **kwargs):
        raise ScanWriteError("cannot write: the disk is full")

    monkeypatch.setattr("forestreg.engine.io.gpkg.write_geopackage", refuse)
    with pytest.raises(ScanWriteError):
        plan_next(project.path, params=PlanParams(radius_m=13.0), out=out, scans=cache)
    assert {p.name: p.read_bytes() for p in (out, run.layers)} == before, "both files as they were"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["strict.gpkg", "strict.json"]


@pytest.mark.parametrize(
    "args, code, says",
    [
        (["{missing}"], 2, "no such project file"),
        (["{project}", "--n", "4"], 2, "--n must be 1, 2 or 3"),
        (["{project}", "--out", "{dir}"], 2, ".json"),
    ],
)
def test_bad_plan_usage_is_one_line(args, code, says, placed, tmp_path, capsys):
    _, project, _ = placed
    values = {"missing": str(tmp_path / "nothing.json"), "project": str(project.path), "dir": str(tmp_path)}
    assert main(["plan", *[a.format(**values) for a in args], "--progress", "none"]) == code
    err = capsys.readouterr().err
    assert says in err and len(err.strip().splitlines()) == 1, err


def test_a_project_without_placed_scans_cannot_be_planned(tmp_path, capsys):
    project = Project(name="empty", params=RegistrationParams())
    path = project.save(tmp_path / "project.json")
    assert main(["plan", str(path), "--progress", "none"]) == 1
    assert "no scan of the project is placed" in capsys.readouterr().err
