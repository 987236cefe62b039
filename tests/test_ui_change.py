"""The Re-survey tab: a ``forestreg change`` folder shown as its map and table (offscreen), every
figure shown checked against the folder."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pytestqt")

sys.path.insert(0, str(Path(__file__).parent))
from test_change import _resurvey_tables, _run, _table_epoch, _stand, _write_table  # noqa: E402


@pytest.fixture(scope="module")
def change_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ui_change")
    before, after, truth = _resurvey_tables(211.0, seed=8)
    _write_table(folder / "before.csv", before)
    _write_table(folder / "after.csv", after)
    assert _run("change", str(folder / "before.csv"), str(folder / "after.csv"), "--out", str(folder / "out")) == 0
    _write_table(folder / "other.csv", _table_epoch(*_stand(seed=11)))
    assert _run("change", str(folder / "before.csv"), str(folder / "other.csv"), "--out", str(folder / "failed")) == 1
    return folder, truth


def test_change_folder_map_table_and_filters(qtbot, window, change_dir):
    folder, truth = change_dir
    assert window.open_change(folder / "out")
    view = window.change_view
    assert window.central_tabs.currentWidget() is view
    summary = json.loads((folder / "out" / "result.json").read_text())
    counts = summary["trees"]
    text = view.headline.text()
    assert "registered" in text and f"{counts['removed']} removed" in text and f"{counts['new']} new" in text
    assert view.map.pixmap() is not None and not view.map.pixmap().isNull()
    total = sum(counts.values())
    assert view.table.rowCount() == total
    view.filter.setCurrentText("removed")
    assert view.table.rowCount() == counts["removed"] == len(truth["removed"])
    assert all(view.table.item(i, 0).text() == "removed" for i in range(view.table.rowCount()))
    view.filter.setCurrentText("persisting")
    growth_col = 5
    values = [float(view.table.item(i, growth_col).text()) for i in range(view.table.rowCount())]
    assert values and all(0.0 < v < 35.0 for v in values)  # mm


def test_failed_comparison_and_a_wrong_folder(qtbot, window, change_dir, tmp_path):
    folder, _ = change_dir
    assert window.open_change(folder / "failed")
    assert "Not compared" in window.change_view.headline.text()
    assert window.change_view.table.rowCount() == 0
    assert not window.open_change(tmp_path)
    assert window.last_error is not None and "re-survey" in window.last_error[0]
