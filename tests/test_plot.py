"""Multi-scan plot projects against the simulator's truth: linking, retries, saving, re-running,
interruption, global adjustment, and the plot/project commands."""

from __future__ import annotations

import json

import numpy as np
import pytest

from forestreg.app.plot import write_poses
from forestreg.cli import main
from forestreg.engine.core.errors import Cancelled, ProjectFileError
from forestreg.engine.core.transform import rigid_errors
from forestreg.engine.io import read_scan, write_scan
from forestreg.engine.tls.plot import adjust_poses, register_project
from forestreg.engine.tls.project import Project

FOUR = ((0.0, 0.0), (10.0, 2.0), (-8.0, 6.0), (3.0, -11.0))
SIX_WITH_TILTED = ((0.0, 0.0), (9.0, 3.0), (-7.0, 7.0), (2.0, -10.0), (-9.0, -5.0), (9.3, 3.2))


def _write_plot(plot, folder):
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for s in plot.scans:
        paths.append(folder / f"{s.scan.name}.laz")
        write_scan(s.scan, paths[-1])
    return paths


def _check_poses(project, plot, names=None):
    poses = project.poses()
    for k, s in enumerate(project.scans):
        if names is not None and s.name not in names:
            continue
        truth = plot.relative_pose(0, k)
        assert poses[s.name] is not None, f"{s.name} not registered"
        rot, trans = rigid_errors(poses[s.name], truth)
        assert rot < 0.05 and trans < 0.02, f"{s.name}: {rot:.4f} deg, {100 * trans:.2f} cm"


@pytest.fixture(scope="module")
def four_scan_files(tmp_path_factory, sim_plot):
    plot = sim_plot("mixed_temperate", FOUR, seed=31, step=0.3, size=45.0)
    return plot, _write_plot(plot, tmp_path_factory.mktemp("four"))


@pytest.fixture(scope="module")
def registered_four(four_scan_files, tmp_path_factory):
    """The four-scan plot registered once: (project file, outcome). Tests load their own copy."""
    plot, paths = four_scan_files
    project = Project(name="four")
    for p in paths:
        project.add_scan(p)
    path = project.save(tmp_path_factory.mktemp("registered") / "project.json")
    outcome = register_project(project)
    project.save()
    return path, outcome


def test_four_scan_plot_registers_every_scan_to_truth(four_scan_files, registered_four):
    plot, paths = four_scan_files
    path, outcome = registered_four
    project = Project.load(path)
    assert outcome.failed == []
    assert [project.link_of(s.name).reference for s in project.scans[1:]] == [paths[0].name] * 3
    _check_poses(project, plot)
    # saved: reopening gives the same poses, and re-running keeps them
    reopened = Project.load(path)
    for name, pose in project.poses().items():
        assert np.allclose(reopened.poses()[name], pose)
    before = {s.name: project.link_of(s.name).result for s in project.scans[1:]}
    register_project(reopened)
    assert {s.name: reopened.link_of(s.name).result for s in reopened.scans[1:]} == before
    register_project(reopened, rerun=True)
    for name, pose in project.poses().items():
        assert rigid_errors(reopened.poses()[name], pose)[1] < 1e-6


def test_six_scan_plot_with_a_tilted_scan(tmp_path, sim_plot):
    plot = sim_plot("planted_conifer", SIX_WITH_TILTED, seed=32, step=0.3, size=45.0, tilted=((5, 30.0),))
    paths = _write_plot(plot, tmp_path / "scans")
    project = Project()
    for p in paths:
        project.add_scan(p)
    project.scans[5].tilted = True
    project.scans[5].level_partner = project.scans[1].name
    outcome = register_project(project)
    assert outcome.failed == []
    assert project.link_of(project.scans[5].name).reference == project.scans[1].name
    _check_poses(project, plot)


def test_a_scan_from_another_plot_is_reported_and_the_rest_registers(four_scan_files, tmp_path, sim_plot):
    plot, paths = four_scan_files
    stranger = sim_plot("mixed_temperate", ((0.0, 0.0), (5.0, 0.0)), seed=33, step=0.3, size=45.0).scans[1].scan
    stranger_path = tmp_path / "stranger.laz"
    write_scan(stranger, stranger_path)
    project = Project()
    for p in paths[:3]:
        project.add_scan(p)
    project.add_scan(stranger_path)
    outcome = register_project(project)
    assert outcome.failed == ["stranger.laz"]
    assert outcome.reasons["stranger.laz"]
    link = project.link_of("stranger.laz")
    assert not link.ok and len(link.result["retried"]) == 2, "a failed link is retried against the registered scans"
    assert project.poses()["stranger.laz"] is None
    _check_poses(project, plot, names=[p.name for p in paths[:3]])


def test_interrupted_run_keeps_finished_links(four_scan_files, tmp_path):
    """The Python API's run (``forestreg.register_project``) saves a project that has a file after
    each finished link: stopped after the first, the file holds that link, and a run of the saved
    project goes on from it. The engine's run itself writes no file: it tells the caller of each
    finished link (``on_link_done``)."""
    import forestreg

    plot, paths = four_scan_files
    project = Project()
    for p in paths:
        project.add_scan(p)
    project.save(tmp_path / "project.json")

    def stop_after_first(link):
        raise Cancelled("stopped by the test")

    with pytest.raises(Cancelled):
        forestreg.register_project(project, on_link=stop_after_first)
    saved = Project.load(tmp_path / "project.json")
    done = [link for link in saved.links if link.result is not None]
    assert len(done) == 1 and done[0].ok
    text = (tmp_path / "project.json").read_text(encoding="utf-8")
    told = []
    outcome = register_project(
        saved, on_link_done=lambda p: told.append(sum(link.result is not None for link in p.links))
    )
    assert outcome.failed == []
    assert told == [2, 3], "each finished link is told, with the project holding it"
    assert (tmp_path / "project.json").read_text(encoding="utf-8") == text, "the engine's run wrote the project file"
    assert saved.link_of(done[0].moving).result == done[0].result, "a finished link is not run again"
    _check_poses(saved, plot)


def test_a_plot_command_stopped_mid_run_resumes_from_its_saved_links(
    four_scan_files, registered_four, tmp_path, capsys
):
    """What ``plot`` leaves when killed after its first link (the project file, no poses.json):
    the same command again keeps that link and registers the rest; other settings, a finished run
    or a scan file changed since start over."""
    import os

    from forestreg.app.plot import resumable_project
    from forestreg.engine.core.atomic import MARKER

    plot, paths = four_scan_files
    stopped = Project.load(registered_four[0])
    first = stopped.scans[1].name
    kept = stopped.link_of(first).result
    for s in stopped.scans[2:]:
        stopped.link_of(s.name).result = None
    out = tmp_path / "four"
    out.mkdir()
    (out / MARKER).write_text("plot\n", encoding="utf-8")
    stopped.save(out / "project.json")

    def fresh(**settings):
        from forestreg.app.plot import new_project
        from forestreg.engine.tls.params import RegistrationParams

        return new_project(paths, RegistrationParams(**settings), name="four")

    assert resumable_project(out, fresh())[1] == 1
    assert resumable_project(out, fresh(max_range_m=25.0))[1] == 0, "other settings: start over"
    before = os.stat(paths[2]).st_mtime
    os.utime(paths[2], (before + 3600, before + 3600))
    try:
        assert resumable_project(out, fresh())[1] == 0, "a scan changed since the run stopped: start over"
    finally:
        os.utime(paths[2], (before, before))

    assert main(["plot", *map(str, paths), "--out", str(out), "--quiet"]) == 0
    assert "1 of 3 links registered before are kept" in capsys.readouterr().err
    resumed = Project.load(out / "project.json")
    assert resumed.link_of(first).result == kept, "the link registered before the stop is not run again"
    _check_poses(resumed, plot)
    assert (out / "poses.json").is_file()
    assert resumable_project(out, fresh())[1] == 0, "a finished run is not resumed"


def test_extra_links_close_a_loop_and_the_adjustment_reports_residuals(four_scan_files, registered_four):
    plot, paths = four_scan_files
    project = Project.load(registered_four[0])
    project.path = None
    project.add_link(paths[2].name, paths[1].name)
    register_project(project)  # runs only the new link: the others are done
    assert sum(link.result is not None for link in project.links) == 4
    adjustment = adjust_poses(project)
    assert adjustment is not None and len(adjustment["links"]) == 4
    for row in adjustment["links"]:
        assert row["after"]["translation_m"] < 0.02
    _check_poses(project, plot)


def test_damaged_or_newer_project_files_are_refused_and_left_alone(tmp_path):
    damaged = tmp_path / "damaged.json"
    damaged.write_text('{"format": "forestreg-project", "version": 1, "scans": [')
    with pytest.raises(ProjectFileError, match="damaged"):
        Project.load(damaged)
    assert damaged.read_text().endswith("[")
    newer = tmp_path / "newer.json"
    newer.write_text(json.dumps({"format": "forestreg-project", "version": 99, "scans": []}))
    with pytest.raises(ProjectFileError, match="newer"):
        Project.load(newer)
    with pytest.raises(ProjectFileError):
        Project.load(tmp_path / "missing.json")


def test_poses_json_layout(four_scan_files, registered_four, tmp_path):
    plot, paths = four_scan_files
    project = Project.load(registered_four[0])
    poses_path = write_poses(project, tmp_path)
    body = json.loads(poses_path.read_text())
    assert body["frame"] == paths[0].name
    assert body["scans"][paths[1].name]["status"] == "ok"
    assert np.allclose(np.loadtxt(tmp_path / f"{paths[1].name}.transform.txt"), body["scans"][paths[1].name]["matrix"])


def test_plot_and_project_commands(four_scan_files, tmp_path, capsys):
    plot, paths = four_scan_files
    out = tmp_path / "out"
    merged = tmp_path / "merged.laz"
    code = main(
        [
            "plot",
            *map(str, paths[:3]),
            "--out",
            str(out),
            "--centre",
            paths[0].name,
            "--merged",
            str(merged),
            "--loops",
            "20",
            "--quiet",
        ]
    )
    assert code == 0
    body = json.loads((out / "poses.json").read_text())
    assert "adjustment" in body, "poses.json always holds the adjustment key (None without loops)"
    assert len(body["adjustment"] or []) == 3, "--loops 20 links the two outer scans (18 m apart) and adjusts"
    assert all(body["scans"][p.name]["uncertainty"]["translation_m"] < 0.1 for p in paths[1:3])
    for k, p in enumerate(paths[:3]):
        rot, trans = rigid_errors(np.array(body["scans"][p.name]["matrix"]), plot.relative_pose(0, k))
        assert rot < 0.05 and trans < 0.02
    cloud = read_scan(merged)
    inputs = [read_scan(p) for p in paths[:3]]
    assert len(cloud) == sum(len(s) for s in inputs)
    # the command reads scans without intensity only when it writes no points: the merged file keeps it
    from forestreg.engine.io.las import intensity_to_uint16

    assert all(s.intensity is not None for s in inputs)
    np.testing.assert_array_equal(cloud.intensity, np.concatenate([intensity_to_uint16(s.intensity) for s in inputs]))
    assert main(["project", "show", str(out / "project.json")]) == 0
    assert "matched VOPs" in capsys.readouterr().out
    assert main(["project", "run", str(out / "project.json"), "--quiet"]) == 0


def test_a_cache_without_intensity_holds_the_same_points(four_scan_files):
    from forestreg.engine.tls.plot import ScanCache

    plot, paths = four_scan_files
    project = Project(name="bare")
    for p in paths[:2]:
        project.add_scan(p)
    bare, full = ScanCache(project, with_intensity=False), ScanCache(project)
    for p in paths[:2]:
        a, b = bare(p.name), full(p.name)
        assert a.intensity is None and b.intensity is not None
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.scanner_position, b.scanner_position)


def test_multi_scan_e57_opens_as_a_project_and_poses_are_written_back(four_scan_files, tmp_path):
    from forestreg.app.plot import write_registered_e57
    from forestreg.engine.io import read_scans, write_e57
    from forestreg.engine.tls.plot import ScanCache, project_from_e57

    plot, paths = four_scan_files
    e57 = tmp_path / "plot.e57"
    write_e57(e57, [read_scan(p) for p in paths[:3]])
    project = project_from_e57(e57)
    assert len(project.scans) == 3 and [s.scan_index for s in project.scans] == [0, 1, 2]
    assert all(s.prior_pose is not None for s in project.scans)
    scans = ScanCache(project)
    outcome = register_project(project, scans=scans)
    assert outcome.failed == []
    _check_poses(project, plot)
    out = tmp_path / "registered.e57"
    assert write_registered_e57(project, out, scans) == 3
    back = read_scans(out)
    for k, scan in enumerate(back):
        rot, trans = rigid_errors(np.asarray(scan.pose), plot.relative_pose(0, k))
        assert rot < 0.05 and trans < 0.02


def test_registered_scans_are_written_one_file_each_in_the_centre_frame(four_scan_files, registered_four, tmp_path):
    from forestreg.app.plot import write_registered_scans

    plot, paths = four_scan_files
    project = Project.load(registered_four[0])
    assert write_registered_scans(project, tmp_path) == 4
    moved = read_scan(tmp_path / f"{paths[2].stem}_registered.laz")
    original = read_scan(paths[2])
    truth = plot.relative_pose(0, 2)
    expected = original.file_points @ truth[:3, :3].T + truth[:3, 3]
    assert len(moved) == len(original) and np.abs(moved.file_points - expected).max() < 0.03


def test_a_plot_larger_than_the_scan_cache_registers_and_merges_the_same(four_scan_files, registered_four, tmp_path):
    """Out of core: with room for one scan in memory, scans are read again when needed; the links
    are bit for bit those of the run that kept every scan, and the merged LAZ (written one scan at a
    time) and PLY (gathered) hold every point of every scan in the centre frame."""
    from forestreg.app.plot import write_merged
    from forestreg.engine.tls.plot import ScanCache

    plot, paths = four_scan_files
    done = Project.load(registered_four[0])
    project = Project(name="small-cache")
    for p in paths[:3]:
        project.add_scan(p)
    scans = ScanCache(project, max_bytes=1)
    register_project(project, scans=scans)
    assert scans.reads > 3 and len(scans._scans) == 1, "scans were let go and read again"
    for p in paths[1:3]:
        assert project.link_of(p.name).reference == done.link_of(p.name).reference
        assert np.array_equal(project.link_of(p.name).matrix, done.link_of(p.name).matrix)

    originals = [read_scan(p) for p in paths[:3]]
    poses = project.poses()
    for suffix in (".laz", ".ply", ".copc.laz"):
        n = write_merged(project, tmp_path / f"merged{suffix}", scans)
        assert n == sum(len(s) for s in originals)
        merged = read_scan(tmp_path / f"merged{suffix}")
        assert len(merged) == n
        expected = np.vstack(
            [s.file_points @ poses[p.name][:3, :3].T + poses[p.name][:3, 3] for s, p in zip(originals, paths)]
        )
        lo, hi = merged.file_points.min(axis=0), merged.file_points.max(axis=0)
        assert np.allclose(lo, expected.min(axis=0), atol=2e-4) and np.allclose(hi, expected.max(axis=0), atol=2e-4)
        if suffix in (".laz", ".copc.laz"):
            import laspy

            las = laspy.read(tmp_path / f"merged{suffix}")
            assert np.bincount(las.scan_id).tolist() == [len(s) for s in originals]
            first = np.column_stack([las.x, las.y, las.z])[las.scan_id == 1]
            want = expected[len(originals[0]) : len(originals[0]) + len(originals[1])]
            if suffix == ".copc.laz":  # laid out node by node: compare the sorted coordinates
                first, want = np.sort(first, axis=0), np.sort(want, axis=0)
                with laspy.CopcReader.open(tmp_path / f"merged{suffix}") as copc:
                    assert len(copc.query()) == n and len(copc.level_query(0)) < n
            assert np.abs(first - want).max() < 2e-4


def test_the_scanner_check_reads_one_scan_when_it_passes(four_scan_files, registered_four):
    """The check before a plot run (no scan near its scanner: refuse) stops at the first scan that
    passes instead of reading every scan first."""
    from forestreg.app.plot import check_scans_near_their_scanners
    from forestreg.engine.tls.plot import ScanCache

    project = Project.load(registered_four[0])
    scans = ScanCache(project)
    check_scans_near_their_scanners(project, scans)
    assert scans.reads == 1


def test_a_link_holds_one_scan_s_points_the_centre_is_read_once(four_scan_files, registered_four):
    """With room for one scan's points, the centre scan is prepared once and its links run on the
    kept preparation: it is not read again for each link (it was: both scans of a link were held),
    and the links are bit for bit those of the run that kept every scan."""
    from forestreg.engine.tls.plot import ScanCache

    plot, paths = four_scan_files
    done = Project.load(registered_four[0])
    project = Project(name="one-scan-room")
    for p in paths[:3]:
        project.add_scan(p)
    scans = ScanCache(project)
    scans.max_bytes = max(read_scan(p).points.nbytes for p in paths[:3]) + 1
    register_project(project, scans=scans)
    assert scans.reads == 3, "each scan read once"
    for p in paths[1:3]:
        assert np.array_equal(project.link_of(p.name).matrix, done.link_of(p.name).matrix)


def test_the_top_view_keeps_no_prepared_scan(four_scan_files, registered_four):
    """The report's top view keeps each scan's slices and VOPs, not its prepared scan (points and
    ICP grid, 0.5 GB at 30 M points): once the cache lets them go, they are freed."""
    import gc
    import weakref

    from forestreg.engine.report.views import compute_top_view
    from forestreg.engine.tls.plot import ScanCache

    project = Project.load(registered_four[0])
    scans = ScanCache(project)
    view = compute_top_view(project, scans)
    assert len(view.scans) == 4
    alive = [weakref.ref(p) for p in scans.prepared._prepared.values()]
    assert alive
    scans.prepared.clear()
    gc.collect()
    assert all(r() is None for r in alive)
    assert len(compute_top_view(project, scans).scans) == 4  # drawn again from what the view kept


def test_the_report_draws_let_go_scans_without_reading_them_again(four_scan_files, registered_four):
    """Scans whose preparations the caches let go during the links are drawn in the report's top
    view from what their preparations left (slice layers, VOPs): no scan is read or prepared again
    (ten 30 M-point scans: minutes, and the run's memory peak), and the view is the same."""
    from forestreg.engine.report.views import compute_top_view
    from forestreg.engine.tls.plot import ScanCache

    plot, paths = four_scan_files
    project = Project(name="one-scan-room")
    for p in paths[:3]:
        project.add_scan(p)
    scans = ScanCache(project)
    scans.max_bytes = max(read_scan(p).points.nbytes for p in paths[:3]) + 1
    scans.prepared.max_bytes = 1  # one preparation kept at a time
    register_project(project, scans=scans)
    reads, made = scans.reads, scans.prepared.made
    view = compute_top_view(project, scans)
    assert (scans.reads, scans.prepared.made) == (reads, made), "no scan read or prepared again"
    full = compute_top_view(project, ScanCache(project))  # every scan prepared for the view
    assert len(view.scans) == 3 and set(view.scans) == set(full.scans)
    for name, a in view.scans.items():
        b = full.scans[name]
        assert np.allclose(a.slice_xy, b.slice_xy) and np.allclose(a.vops_xy, b.vops_xy)


def test_merged_laz_written_in_blocks_keeps_every_point_in_order(
    four_scan_files, registered_four, tmp_path, monkeypatch
):
    """Merging moves each scan in blocks (not kept in the cache): the LAZ holds every point of
    every scan in order, in the centre frame, with its intensity and scan id."""
    import laspy

    from forestreg.app.plot import write_merged
    from forestreg.engine.io.las import intensity_to_uint16
    from forestreg.engine.tls import plot as plot_module

    plot, paths = four_scan_files
    project = Project.load(registered_four[0])
    scans = plot_module.ScanCache(project)
    monkeypatch.setattr(plot_module, "MERGE_BLOCK_POINTS", 7777)
    n = write_merged(project, tmp_path / "merged.laz", scans)
    assert not scans._scans, "the scans were not kept"
    las = laspy.read(tmp_path / "merged.laz")
    poses = project.poses()
    originals = [read_scan(p) for p in paths]
    assert n == len(las) == sum(len(s) for s in originals)
    assert np.bincount(las.scan_id).tolist() == [len(s) for s in originals]
    got = np.column_stack([las.x, las.y, las.z])
    start = 0
    for s, p in zip(originals, paths):
        want = s.file_points @ poses[p.name][:3, :3].T + poses[p.name][:3, 3]
        assert np.abs(got[start : start + len(s)] - want).max() < 2e-4
        if s.intensity is not None:
            assert np.array_equal(np.asarray(las.intensity[start : start + len(s)]), intensity_to_uint16(s.intensity))
        start += len(s)


def test_the_next_scan_is_prepared_while_a_link_runs_and_the_links_are_the_same(
    four_scan_files, registered_four, monkeypatch
):
    """A plot of small scans reads and prepares the next link's scan in a background thread while
    a link runs: every scan is still read and prepared once, and the links are bit for bit those
    of the run that reads and prepares one scan at a time."""
    import threading

    from forestreg.engine.tls import plot as plot_module
    from forestreg.engine.tls import prepare as prepare_module
    from forestreg.engine.tls.plot import ScanCache

    plot, paths = four_scan_files
    where = []
    real = prepare_module.prepare_scan

    def recorded(*args, **kwargs):
        where.append(threading.current_thread().name)
        return real(*args, **kwargs)

    monkeypatch.setattr(prepare_module, "prepare_scan", recorded)
    project = Project(name="ahead")
    for p in paths:
        project.add_scan(p)
    scans = ScanCache(project)
    register_project(project, scans=scans)
    assert (scans.reads, scans.prepared.made) == (4, 4), "each scan read and prepared once"
    assert where.count("forestreg-prepare-ahead") == 3, where  # every moving scan; the centre by its link
    # the ICP search structures kept from link to link are let go once the links are done
    assert not any(("icp_reference",) in p.derived for p in scans.prepared._prepared.values())

    monkeypatch.setattr(plot_module, "SEQUENTIAL_PREPARE_POINTS", 0)  # no scan is small: one at a time
    one_by_one = Project(name="one-by-one")
    for p in paths:
        one_by_one.add_scan(p)
    where.clear()
    register_project(one_by_one)
    assert "forestreg-prepare-ahead" not in where
    for p in paths[1:]:
        assert np.array_equal(project.link_of(p.name).matrix, one_by_one.link_of(p.name).matrix)

    monkeypatch.undo()  # small scans again, but one thread allowed (a batch's plot process on one core)
    monkeypatch.setattr(prepare_module, "prepare_scan", recorded)
    monkeypatch.setenv("FORESTREG_THREADS", "1")
    one_core = Project(name="one-core")
    for p in paths:
        one_core.add_scan(p)
    where.clear()
    register_project(one_core)
    assert where and "forestreg-prepare-ahead" not in where, "no thread prepares ahead on one core"
    for p in paths[1:]:
        assert np.array_equal(project.link_of(p.name).matrix, one_core.link_of(p.name).matrix)


def test_further_pairs_run_two_at_a_time_with_the_same_results(four_scan_files, registered_four, monkeypatch):
    """``--pairs all`` registers the further pairs of a small plot two at a time on the kept
    preparations (the scans' points let go): the same link matrices as one at a time, and no scan
    read again."""
    from forestreg.engine.tls import plot as plot_module
    from forestreg.engine.tls.plot import ScanCache
    from forestreg.engine.tls.survey import SurveyParams, register_survey

    def run(parallel: bool):
        monkeypatch.setattr(plot_module, "small_scans", lambda *a: parallel)  # what ScanCache.small asks
        project = Project.load(registered_four[0])
        scans = ScanCache(project)
        for s in project.scans:  # as the links to the centre leave them (here loaded as done)
            scans.for_link(s.name, project.params)
        messages = []
        register_survey(
            project, SurveyParams(pairs="all"), scans=scans, progress=lambda fraction, message: messages.append(message)
        )
        assert any("two at a time" in m for m in messages) == parallel
        further = {(link.moving, link.reference): link for link in project.links if link.extra}
        return further, scans

    together, scans = run(True)
    assert scans.prepared.made == 4, "no scan prepared again"
    assert len(together) == 3 and sum(link.ok for link in together.values()) >= 2
    assert scans.reads == 4 and len(scans._scans) == 0, "each scan read once, the points let go"
    alone, _ = run(False)
    assert together.keys() == alone.keys()
    for key, link in together.items():
        assert link.ok == alone[key].ok and link.result.get("reason") == alone[key].result.get("reason"), key
        if link.ok:
            assert np.array_equal(link.matrix, alone[key].matrix), key


def test_a_survey_of_every_pair_registers_further_pairs_beside_the_centre_links(four_scan_files, monkeypatch):
    """``--pairs all`` on small scans: the thread that prepares scans ahead registers further pairs
    whose scans are prepared while the links to the centre run (then two at a time); the scans'
    points are let go once prepared, each scan is read and prepared once, and every link matrix and
    the survey's poses are bit for bit those of the run that does one thing at a time."""
    import threading

    from forestreg.engine.tls import plot as plot_module
    from forestreg.engine.tls import survey as survey_module
    from forestreg.engine.tls.plot import ScanCache
    from forestreg.engine.tls.survey import SurveyParams, register_survey

    plot, paths = four_scan_files
    threads: dict[tuple, str] = {}
    real = plot_module._run_link

    def recorded(project, link, *args, **kwargs):
        threads[(link.moving, link.reference)] = threading.current_thread().name
        return real(project, link, *args, **kwargs)

    monkeypatch.setattr(plot_module, "_run_link", recorded)
    monkeypatch.setattr(survey_module, "_run_link", recorded)

    def run():
        project = Project(name="every-pair")
        for p in paths:
            project.add_scan(p)
        scans = ScanCache(project)
        register_survey(project, SurveyParams(pairs="all"), scans=scans)
        return project, scans

    project, scans = run()
    further = {(link.moving, link.reference): link for link in project.links if link.extra}
    assert len(further) == 3 and (scans.reads, scans.prepared.made) == (4, 4) and len(scans._scans) == 0
    assert not any(("icp_reference",) in p.derived for p in scans.prepared._prepared.values()), (
        "ICP structures kept after the links"
    )
    assert any(threads[key] == "forestreg-prepare-ahead" for key in further), threads
    threads.clear()
    monkeypatch.setattr(plot_module, "SEQUENTIAL_PREPARE_POINTS", 0)  # no scan is small: one at a time
    alone, _ = run()
    assert set(threads.values()) == {"MainThread"}
    assert [(link.moving, link.reference, link.extra) for link in alone.links] == [
        (link.moving, link.reference, link.extra) for link in project.links
    ]
    for a, b in zip(project.links, alone.links):
        assert a.ok == b.ok and (not a.ok or np.array_equal(a.matrix, b.matrix)), (a.moving, a.reference)
    for name, pose in project.poses().items():
        assert (pose is None) == (alone.poses()[name] is None) and (
            pose is None or np.array_equal(pose, alone.poses()[name])
        ), name


def test_cancelling_a_survey_of_every_pair_stops_every_thread_quietly(four_scan_files, monkeypatch):
    """Cancelled while the links to the centre run and further pairs are registered beside them:
    the run ends with Cancelled, no background thread dies with an error, and no thread starts
    another link afterwards."""
    import threading
    import time

    from forestreg.engine.core.progress import CancelToken
    from forestreg.engine.tls import plot as plot_module
    from forestreg.engine.tls.plot import ScanCache
    from forestreg.engine.tls.survey import SurveyParams, register_survey

    plot, paths = four_scan_files
    died: list = []
    monkeypatch.setattr(threading, "excepthook", lambda args: died.append(args.exc_value))
    started: list = []
    real = plot_module._run_link

    def recorded(project, link, *args, **kwargs):
        started.append(time.monotonic())
        return real(project, link, *args, **kwargs)

    monkeypatch.setattr(plot_module, "_run_link", recorded)
    project = Project(name="cancelled")
    for p in paths:
        project.add_scan(p)
    token = CancelToken()

    def progress(fraction: float, message: str) -> None:
        if "registering scan_04" in message or fraction >= 0.3:
            token.cancel()

    with pytest.raises(Cancelled):
        register_survey(project, SurveyParams(pairs="all"), scans=ScanCache(project), progress=progress, cancel=token)
    stopped = time.monotonic()
    time.sleep(3.0)  # a link under way in another thread ends at its next step
    assert died == [], died
    assert all(t <= stopped for t in started), "a link started after the run was cancelled"


def test_a_scan_s_bounds_come_from_its_las_header_without_reading_its_points(four_scan_files, tmp_path):
    """The scan cache's bounds of a LAS/LAZ scan are its header's (read by the LAS reader of
    ``engine.io``, no point read); a damaged header is not passed over: the scan is read and the
    reader says what is wrong."""
    from forestreg.engine.core.errors import ScanReadError
    from forestreg.engine.tls.plot import ScanCache

    _, paths = four_scan_files
    broken = tmp_path / "broken.laz"
    broken.write_bytes(b"LASF" + bytes(300))
    project = Project()
    for p in (paths[0], broken):
        project.add_scan(p)
    scans = ScanCache(project)
    lo, hi = scans.bounds(paths[0].name)
    assert scans.reads == 0
    scan = read_scan(paths[0])
    points = scan.points + scan.origin_shift
    np.testing.assert_allclose(lo, points.min(axis=0), atol=0.002)
    np.testing.assert_allclose(hi, points.max(axis=0), atol=0.002)
    with pytest.raises(ScanReadError, match="broken.laz"):
        scans.bounds("broken.laz")
