"""Every icon the GUI and the QGIS metadata name exists and renders."""

from __future__ import annotations

import configparser
from pathlib import Path

import pytest

pytest.importorskip("PySide6")

ROOT = Path(__file__).resolve().parents[1]


def test_icons_render(qapp):
    from forestreg.ui.icons import ICON_DIR, icon

    names = sorted(p.stem for p in ICON_DIR.glob("*.svg"))
    assert {
        "open",
        "save",
        "add",
        "sample",
        "run",
        "cancel",
        "before",
        "after",
        "export",
        "report",
        "forestreg",
    } <= set(names)
    for name in names:
        image = icon(name).pixmap(24, 24).toImage()
        assert not image.isNull()
        opaque = sum(image.pixelColor(x, y).alpha() > 0 for x in range(24) for y in range(24))
        assert opaque > 20, f"{name}.svg renders (almost) nothing"


def test_qgis_metadata_icon_exists():
    meta = configparser.ConfigParser()
    meta.read(ROOT / "metadata.txt")
    assert (ROOT / meta.get("general", "icon")).is_file()
