"""The HTML plot report: a registered simulated plot, with a failed scan, with an adjustment, a
manual loop link and a marker-free/manual comparison; embedded figures, table values, escaping."""

from __future__ import annotations

import base64
import copy
import io
import re
import time
from pathlib import Path

import numpy as np
import pytest

from forestreg.engine.core.errors import ScanWriteError
from forestreg.engine.io import write_scan
from forestreg.engine.report.plot_report import format_cm, write_plot_report
from forestreg.engine.report.views import compute_top_view
from forestreg.engine.tls.plot import ScanCache, register_project
from forestreg.engine.tls.project import Project

POSITIONS = ((0.0, 0.0), (10.0, 2.0), (-8.0, 6.0))
ODD_NAME = "scan <b>2<b> & co"  # markup and an ampersand (a slash would make it a path: refused)
EXAMPLE_HTML = Path("/tmp/plot_report_example.html")
EXAMPLE_TOP_VIEW = Path("/tmp/plot_report_topview.png")


@pytest.fixture(scope="module")
def registered(tmp_path_factory, sim_plot):
    """A registered three-scan project (the second scan has a name that needs escaping)."""
    plot = sim_plot("mixed_temperate", POSITIONS, seed=5, step=0.3, size=40.0)
    folder = tmp_path_factory.mktemp("plot_report")
    project = Project(name="Plot <A> & B")
    for k, s in enumerate(plot.scans):
        path = folder / f"{s.scan.name}.laz"
        write_scan(s.scan, path)
        project.add_scan(path, name=ODD_NAME if k == 1 else None)
    outcome = register_project(project)
    assert outcome.failed == [], outcome.reasons
    return project, ScanCache(project), folder


def _images(text: str) -> dict[str, bytes]:
    found = re.findall(r'<img id="([^"]+)"[^>]*src="data:image/png;base64,([A-Za-z0-9+/=]+)"', text)
    return {ident: base64.b64decode(data) for ident, data in found}


def _check_png(png: bytes, *, min_bytes: int = 5_000, min_colours: int = 20, min_ink: float = 0.02) -> tuple[int, int]:
    from PIL import Image

    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(png) > min_bytes
    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))
    h, w, _ = img.shape
    assert w >= 400 and h >= 250
    colours = len(np.unique(img.reshape(-1, 3), axis=0))
    ink = float(np.mean(np.any(img < 235, axis=2)))
    assert colours >= min_colours, f"only {colours} colours: blank figure?"
    assert ink >= min_ink, f"only {ink:.1%} non-white pixels: blank figure?"
    return w, h


def _check_html(text: str) -> None:
    assert text.startswith("<!DOCTYPE html>")
    assert text.rstrip().endswith("</html>")
    for tag in ("html", "head", "body", "style", "title"):
        assert text.count(f"<{tag}") == 1 and text.count(f"</{tag}>") == 1, tag
    assert text.count("<table") == text.count("</table>")
    assert text.count("<tr") == text.count("</tr>")
    # self-contained: no external assets
    assert not re.search(r'(src|href)="(?!data:)', text)


def test_report_of_a_registered_plot(registered, tmp_path):
    project, scans, _ = registered
    out = tmp_path / "report.html"
    t0 = time.perf_counter()
    write_plot_report(project, out, scans=scans)
    elapsed = time.perf_counter() - t0
    assert elapsed < 20.0
    text = out.read_text(encoding="utf-8")
    _check_html(text)
    EXAMPLE_HTML.write_text(text, encoding="utf-8")

    images = _images(text)
    assert {"topview", "icpbars"} <= set(images)
    w, h = _check_png(images["topview"], min_bytes=30_000, min_colours=50)
    assert w >= 800 and h >= 700
    _check_png(images["icpbars"])
    EXAMPLE_TOP_VIEW.write_bytes(images["topview"])

    # summary and per-link table values are the link results
    assert "All 3 scans are registered" in text
    for link in project.links:
        r = link.result
        assert f'<td class="num"><b>{r["matched"]}</b></td>' in text
        assert f'<td class="num"><b>{format_cm(r["icp"]["std_m"])}</b></td>' in text
        assert f'<td class="num">{r["reference_vops"]}</td><td class="num">{r["moving_vops"]}</td>' in text
        assert f'<td class="num">{r["matched"] - r["second_matched"]}</td>' in text
        assert f"{sum(r['timings'].values()):.1f}" in text
    assert format_cm(0.020043966) == "2.00"

    # every piece of user text is escaped
    assert "scan &lt;b&gt;2&lt;b&gt; &amp; co" in text
    assert "Plot &lt;A&gt; &amp; B" in text
    assert ODD_NAME not in text and "<A>" not in text


def test_top_view_puts_the_scans_where_they_stand(registered):
    project, scans, _ = registered
    view = compute_top_view(project, scans)
    assert set(view.scans) == {s.name for s in project.scans}
    centre = view.scans[project.centre].scanner
    for s, (x, y) in zip(project.scans, POSITIONS):
        distance = np.linalg.norm(view.scans[s.name].scanner[:2] - centre[:2])
        assert abs(distance - np.hypot(x, y)) < 0.05, s.name
        assert 0 < len(view.scans[s.name].slice_xy) <= 100_000
        assert len(view.scans[s.name].vops_xy) >= 10
    # VOPs of both scans of each link coincide in the project frame about as often as they matched
    assert len(view.links) == 2
    for lv in view.links:
        matched = project.link_of(lv.moving).result["matched"]
        assert abs(len(lv.pairs) - matched) <= max(3, 0.25 * matched), (lv.moving, len(lv.pairs), matched)
        gaps = np.linalg.norm(lv.pairs[:, 0] - lv.pairs[:, 1], axis=1)
        assert gaps.max() < project.params.match_distance_m


def test_report_names_a_failed_scan_and_its_reason(registered, tmp_path):
    project, scans, _ = registered
    failed = copy.deepcopy(project)
    third = failed.scans[2].name
    link = failed.link_of(third)
    link.result = {
        "status": "failed",
        "reason": "only 2 VOPs match (need 4): the scans share <too few> trunks",
        "matrix": None,
        "reference_vops": 31,
        "moving_vops": 12,
        "matched": 2,
        "second_matched": 2,
        "vop_radius_m": 10.0,
        "icp": None,
        "timings": {"prepare_reference": 1.5, "coarse": 0.25},
        "retried": [{"reference": ODD_NAME, "reason": "ambiguous"}],
    }
    out = tmp_path / "failed.html"
    write_plot_report(failed, out, scans=scans, title="Failed <scan> test")
    text = out.read_text(encoding="utf-8")
    _check_html(text)
    assert "<title>Failed &lt;scan&gt; test</title>" in text
    failbox = text[text.index('class="failbox"') :]
    failbox = failbox[: failbox.index("</div>")]
    assert "1 of 3 scans could not be registered" in failbox
    assert third in failbox
    assert "the scans share &lt;too few&gt; trunks" in failbox
    assert "also tried onto scan &lt;b&gt;2&lt;b&gt; &amp; co: ambiguous" in failbox
    assert "<too few>" not in text
    # the failed link's row: its evidence and no ICP figure
    row = text[text.index(f"{third} \u2192") :]
    row = row[: row.index("</tr>")]
    assert '<td class="num">31</td><td class="num">12</td><td class="num"><b>2</b></td>' in row
    assert '<td class="num"><b>\u2013</b></td>' in row and "1.8" in row and "failed" in row
    # not drawn, the others still are
    view = compute_top_view(failed, scans)
    assert third not in view.scans and len(view.scans) == 2
    images = _images(text)
    _check_png(images["topview"], min_bytes=20_000, min_colours=30)


def test_report_with_adjustment_manual_loop_link_and_comparison(registered, tmp_path):
    project, scans, _ = registered
    p = copy.deepcopy(project)
    names = [s.name for s in p.scans]
    poses = p.poses()
    loop = p.add_link(names[2], names[1], method="manual")
    loop.result = {  # what engine.manual's ManualResult.to_dict gives (fewer keys: tolerated)
        "method": "manual (targets + ICP)",
        "status": "ok",
        "reason": "",
        "matrix": (np.linalg.inv(poses[names[1]]) @ poses[names[2]]).tolist(),
        "target_fit": {"target_ids": ["T1", "T2", "T3", "T4"], "rmse_m": 0.012, "residuals_m": {}},
        "icp": {"std_m": 0.0031, "fitness": 0.41},
        "timings": {"fit": 0.01, "icp": 2.0},
    }
    p.adjustment = {
        "poses": {k: (None if v is None else v.tolist()) for k, v in poses.items()},
        "links": [
            {
                "moving": names[1],
                "reference": names[0],
                "before": {"rotation_deg": 0.02, "translation_m": 0.031},
                "after": {"rotation_deg": 0.004, "translation_m": 0.0072},
            },
            {
                "moving": names[2],
                "reference": names[1],
                "before": {"rotation_deg": 0.05, "translation_m": 0.052},
                "after": {"rotation_deg": None},
            },
        ],
    }
    comparison = {
        "pairs": [
            {
                "moving": names[1],
                "reference": names[0],
                "auto": {"status": "ok", "matched": 18, "icp_std_m": 0.0123, "reference_vops": 45, "moving_vops": 50},
                "manual": {"status": "ok", "icp_std_m": 0.0117, "targets": 5},
                "rotation_difference_deg": 0.0213,
                "translation_difference_m": 0.0089,
            },
            {
                "moving": names[2],
                "reference": names[0],
                "auto": {
                    "status": "failed",
                    "matched": 3,
                    "icp_std_m": None,
                    "reference_vops": 44,
                    "moving_vops": None,
                },
                "manual": {"status": "ok", "icp_std_m": 0.0098, "targets": 4},
                "rotation_difference_deg": None,
                "translation_difference_m": None,
            },
        ],
        "auto_target_residual_m": 0.024,
        "manual_target_residual_m": 0.0233,
        "targets": {"auto": {"T1": 0.021, "T2 <n>": 0.027, "T10": 0.03}, "manual": {"T1": 0.02, "T2 <n>": 0.026}},
    }
    out = tmp_path / "comparison.html"
    write_plot_report(p, out, scans=scans, comparison=comparison)
    text = out.read_text(encoding="utf-8")
    _check_html(text)
    images = _images(text)
    assert {"topview", "icpbars", "adjbars", "cmppairs", "cmpdiff", "cmptargets"} <= set(images)
    for key in ("adjbars", "cmppairs", "cmptargets"):
        _check_png(images[key])
    # manual loop link row
    assert "manual (targets + ICP)" in text and "4 targets, fit RMSE 1.2 cm" in text
    assert '<td class="num"><b>0.31</b></td>' in text
    assert "loop link" in text
    # adjustment table: cm and deg, a missing value as a dash
    assert "3.10" in text and "0.72" in text and "5.20" in text and "0.004" in text
    # comparison: table 4 and table 5 values
    assert '<td class="num"><b>1.23</b></td><td class="num"><b>1.17</b></td>' in text
    assert '<td class="num"><b>\u2013</b></td><td class="num"><b>0.98</b></td>' in text
    assert '<td class="num">0.021</td><td class="num">0.89</td>' in text
    assert '<td class="num"><b>2.40</b></td>' in text and '<td class="num"><b>2.33</b></td>' in text
    assert "<td>T2 &lt;n&gt;</td>" in text and "T2 <n>" not in text
    # natural order of target ids: T1, T2 <n>, T10
    assert text.index("<td>T1</td>") < text.index("<td>T2 &lt;n&gt;</td>") < text.index("<td>T10</td>")


def test_report_tolerates_unrun_and_sparse_links(registered, tmp_path):
    project, scans, _ = registered
    p = copy.deepcopy(project)
    names = [s.name for s in p.scans]
    p.link_of(names[1]).result = {"status": "failed"}
    p.link_of(names[2]).result = None
    out = tmp_path / "sparse.html"
    write_plot_report(p, out, scans=scans)
    text = out.read_text(encoding="utf-8")
    _check_html(text)
    assert "2 of 3 scans could not be registered" in text
    assert "status failed (no reason recorded)" in text
    assert "not registered yet" in text and "not run" in text
    assert "icpbars" not in text  # no ICP figure to draw
    _check_png(_images(text)["topview"], min_bytes=10_000)


def test_report_is_written_atomically(registered, tmp_path):
    project, scans, _ = registered
    with pytest.raises(ScanWriteError):
        write_plot_report(project, tmp_path / "missing" / "report.html", scans=scans)
    out = tmp_path / "report.html"
    out.write_text("old", encoding="utf-8")
    write_plot_report(project, out, scans=scans)
    assert out.read_text(encoding="utf-8").startswith("<!DOCTYPE html>")
    assert [f.name for f in tmp_path.iterdir()] == ["report.html"]
