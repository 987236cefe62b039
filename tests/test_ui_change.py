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
from test_change import _resurvey_tables, _run, _stand, _table_epoch, _write_table  # noqa: E402


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


def test_gui_change_screenshot_offscreen(change_dir, tmp_path):
    """``forestreg gui --change DIR --screenshot PNG``: the Re-survey tab drawn without a display,
    its change map in colour and the tree table filled."""
    import os
    import subprocess

    import numpy as np
    from PySide6.QtGui import QImage

    folder, _ = change_dir
    out = tmp_path / "change.png"
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "QT_QPA_PLATFORM")}
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "forestreg.cli",
            "gui",
            "--offscreen",
            "--change",
            str(folder / "out"),
            "--screenshot",
            str(out),
            "--size",
            "1400x900",
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert out.is_file() and out.stat().st_size > 20_000
    img = QImage(str(out)).convertToFormat(QImage.Format.Format_RGB888)
    assert (img.width(), img.height()) == (1400, 900)
    arr = np.frombuffer(img.constBits(), dtype=np.uint8).reshape(img.height(), img.bytesPerLine())[:, : img.width() * 3]
    rgb = arr.reshape(img.height(), img.width(), 3).astype(int)
    colours = np.unique(rgb.reshape(-1, 3)[::5], axis=0)
    assert len(colours) > 200, f"only {len(colours)} distinct colours: the window looks blank"
    saturated = (rgb.max(axis=2) - rgb.min(axis=2)) > 80  # the map's growth colours and removed/new markers
    assert saturated.sum() > 2000, "no change map in the screenshot"

    # a folder that is not a change result: one line, exit 2, no picture
    bad = tmp_path / "bad.png"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "forestreg.cli",
            "gui",
            "--offscreen",
            "--change",
            str(tmp_path),
            "--screenshot",
            str(bad),
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 2 and "re-survey" in done.stderr.lower() and not bad.exists()
