"""Values set in a nested TOML parameter file reach the step that uses them: the automatic VOP
radii, the scanner-position estimate (through a project and its scan cache, and the project file)
and the survey's loop-closure floors."""

from __future__ import annotations

import numpy as np
import pytest

from forestreg.engine.core.errors import ParameterError
from forestreg.engine.core.scan import Scan
from forestreg.engine.core.transform import matrix_from_yaw
from forestreg.engine.io import write_scan
from forestreg.engine.params import ProductParams, load_params
from forestreg.engine.tls.pair import vop_radii
from forestreg.engine.tls.plot import ScanCache
from forestreg.engine.tls.project import Link, Project
from forestreg.engine.tls.survey import inconsistent_links

TOML = """
[registration]
auto_vop_radii_m = [12.0, 18.0]

[scanner_position]
default_height_m = 2.5

[survey]
min_closure_m = 0.2
"""


@pytest.fixture()
def params(tmp_path):
    path = tmp_path / "params.toml"
    path.write_text(TOML, encoding="utf-8")
    return load_params(path)


def test_automatic_vop_radii_come_from_the_file(params):
    assert vop_radii(params.registration) == (12.0, 18.0)
    assert vop_radii(params.registration.replace(max_range_m=20.0)) == (12.0,)  # within 3 m of the range
    assert vop_radii(ProductParams().registration) == (10.0, 15.0, 20.0, 25.0)


def test_scanner_position_settings_reach_the_scan_cache_and_the_project_file(params, tmp_path):
    """A scan in project coordinates (its scanner 20 m from the file origin) over flat ground:
    the ground profile gives no instrument height, so the file's default height places it."""
    rng = np.random.default_rng(0)
    r, a = rng.uniform(1.5, 25.0, 200000), rng.uniform(0.0, 2 * np.pi, 200000)
    pts = np.column_stack([20.0 + r * np.cos(a), 5.0 + r * np.sin(a), rng.normal(0.0, 0.01, len(r))])
    path = tmp_path / "ground.laz"
    write_scan(Scan.from_points(pts, name="ground"), path)
    heights = []
    for scanner_params in (None, params.scanner_position):
        project = Project(name="p")
        project.add_scan(path)
        if scanner_params is not None:
            project.scanner_params = scanner_params
        project.save(tmp_path / f"project{len(heights)}.json")
        again = Project.load(tmp_path / f"project{len(heights)}.json")
        assert again.scanner_params == project.scanner_params
        scan = ScanCache(again)("ground.laz")
        assert scan.meta["scanner_position"] == "estimated"
        assert np.hypot(scan.scanner_position_file[0] - 20.0, scan.scanner_position_file[1] - 5.0) < 0.05
        heights.append(float(scan.scanner_position_file[2]))
    assert abs(heights[0] - 1.5) < 0.05 and abs(heights[1] - 2.5) < 0.05


def test_survey_closure_floor_comes_from_the_file(params):
    """Three scans whose loop misses by 10 cm with 1 mm stated sigmas: it fails to close at the
    default 3 cm floor and closes at the file's 20 cm."""
    poses = {"a": np.eye(4), "b": matrix_from_yaw(30.0, np.array([10.0, 0.0, 0.0])), "c": matrix_from_yaw(-20.0, np.array([0.0, 10.0, 0.0]))}
    links = []
    for (m, r), off in ((("b", "a"), 0.1), (("c", "b"), 0.0), (("a", "c"), 0.0)):
        truth = np.linalg.inv(poses[r]) @ poses[m]
        truth[0, 3] += off
        link = Link(moving=m, reference=r)
        link.result = {"status": "ok", "matrix": truth.tolist(), "uncertainty": {"translation_m": 0.001, "rotation_deg": 0.001}}
        links.append(link)
    scanner = {n: np.zeros(3) for n in poses}
    default = inconsistent_links(links, scanner, 4.0)
    survey = params.survey
    from_file = inconsistent_links(links, scanner, survey.closure_sigmas, min_closure_m=survey.min_closure_m, min_closure_deg=survey.min_closure_deg)
    assert [row["closes"] for row in default[1] if "closes" in row] == [False] and len(default[0]) == 1  # the weakest link goes
    assert [row["closes"] for row in from_file[1]] == [True] and from_file[0] == []
    from forestreg.app.survey import survey_params

    project = Project(name="p")
    assert survey_params("within:30", project, base=survey).min_closure_m == 0.2  # the command line's pairs, the file's floors


def test_bad_values_in_the_new_sections_are_refused(tmp_path):
    for text in ('[survey]\npairs = "some"\n', "[scanner_position]\ndefault_height_m = 50.0\n", "[registration]\nauto_vop_radii_m = []\n"):
        path = tmp_path / "bad.toml"
        path.write_text(text, encoding="utf-8")
        with pytest.raises(ParameterError):
            load_params(path)
