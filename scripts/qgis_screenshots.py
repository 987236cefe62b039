"""Draw the QGIS guide's pictures again, in real headless QGIS (no display).

    .venv/bin/python scripts/qgis_screenshots.py [--out docs/images] [--work DIR]

Two steps. With forestreg's Python: the data, made here from the real clips of ``../shared/data``
(the spanner MLS clip with its CRS, NAD83 / UTM zone 12N, written into the file, and the airborne
clip of the same plot) and a simulated plot: ``forestreg trees`` of the MLS clip, ``forestreg
change`` from its trees to a later survey made from them (2 cm thicker, 0.8 m taller, one tree
cut, two young trees grown in), ``forestreg plot`` of four simulated scans, and canopy height models
(heights above the terrain, 0.5 m cells) of the airborne clip and of the plot's merged cloud.
Then with QGIS's Python (``/usr/bin/python3``, ``QT_QPA_PLATFORM=offscreen``): each CHM written
as a GeoTIFF, the layers of each ``layers.gpkg`` loaded as the plugin loads them (its own
``_load_gpkg_layers``: the QML styles of ``layer_styles``), and the map drawn over the CHM with
``QgsMapRendererCustomPainterJob``, a legend of the layers' own symbols and a scale bar:

- ``qgis_trees.png``: trees graduated by DBH, flagged trees ringed, crowns, plot outline;
- ``qgis_change.png``: tree changes (persisting, removed, new) and the outline;
- ``qgis_plot.png``: scanners, registration links and the plot outline of a registered plot.

Look at every picture before committing it.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
QGIS_PYTHON = "/usr/bin/python3"
#: the CRS of the spanner clips (they declare none)
SPANNER_EPSG = 26912
CHM_RESOLUTION_M = 0.5


# ----------------------------------------------------------------------------- step 1: the data (forestreg's Python)


def forestreg(*args: str) -> None:
    print("$ forestreg " + " ".join(args), flush=True)
    subprocess.run([sys.executable, "-m", "forestreg.cli", *args, "-q"], check=True)


def canopy_height_model(cloud: Path, out: Path) -> dict:
    """The CHM of ``cloud`` (highest height above its terrain per 0.5 m cell) as ``out`` (.npy)
    and its grid: ``x0``, ``y0`` (lower-left corner, the cloud's coordinates), ``resolution_m``."""
    import numpy as np

    from forestreg.engine.io import read_scan
    from forestreg.engine.terrain.dem import terrain_model
    from forestreg.engine.trees.canopy import canopy_height_model as chm_of

    points = np.asarray(read_scan(cloud).file_points, dtype=np.float64)  # the file's coordinates
    origin = points.min(axis=0)
    local = points - origin  # the terrain filter works in a local frame
    terrain = terrain_model(local)
    heights = local[:, 2] - terrain.dem.height_at(local[:, :2])
    chm = chm_of(local, np.clip(heights, 0.0, None), CHM_RESOLUTION_M)
    np.save(out, np.nan_to_num(chm.grid, nan=0.0))
    return {
        "grid": str(out),
        "x0": chm.x0 + float(origin[0]),
        "y0": chm.y0 + float(origin[1]),
        "resolution_m": chm.resolution_m,
    }


def later_survey(trees_csv: Path, out: Path) -> None:
    """A later survey of the plot of ``trees_csv``: every tree 2 cm thicker and 0.8 m taller, the
    tree nearest the plot's centre cut (removed), and two young trees (9 and 12 cm) grown in at the
    two places farthest from any tree, 3 m or more inside the plot (new)."""
    with open(trees_csv, newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    xy = [(float(r["x"]), float(r["y"])) for r in rows]
    cx, cy = sum(x for x, _ in xy) / len(xy), sum(y for _, y in xy) / len(xy)
    cut = min(rows, key=lambda r: (float(r["x"]) - cx) ** 2 + (float(r["y"]) - cy) ** 2)["tree_id"]
    x0, x1 = min(x for x, _ in xy) + 3.0, max(x for x, _ in xy) - 3.0
    y0, y1 = min(y for _, y in xy) + 3.0, max(y for _, y in xy) - 3.0
    grid = [(x0 + (x1 - x0) * i / 40, y0 + (y1 - y0) * j / 40) for i in range(41) for j in range(41)]
    gaps: list = []
    for _ in range(2):
        taken = xy + gaps
        gaps.append(max(grid, key=lambda g: min((g[0] - x) ** 2 + (g[1] - y) ** 2 for x, y in taken)))
    with open(out, "w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        for r in rows:
            if r["tree_id"] == cut:
                continue
            w.writerow(
                {
                    **r,
                    "dbh_m": f"{float(r['dbh_m']) + 0.02:.4f}" if r["dbh_m"] else "",
                    "height_m": f"{float(r['height_m']) + 0.8:.4f}" if r["height_m"] else "",
                }
            )
        for k, ((x, y), dbh, height) in enumerate(zip(gaps, (0.09, 0.12), (8.5, 10.0)), 1):
            w.writerow(
                {
                    **{key: "" for key in rows[0]},
                    "tree_id": str(900 + k),
                    "x": f"{x:.4f}",
                    "y": f"{y:.4f}",
                    "z": rows[0]["z"],
                    "dbh_m": f"{dbh:.4f}",
                    "height_m": f"{height:.4f}",
                }
            )


def make_data(work: Path) -> dict:
    import laspy
    import pyproj

    las = laspy.read(DATA / "spanner_MLS_Clip.laz")
    las.header.add_crs(pyproj.CRS.from_epsg(SPANNER_EPSG))
    mls = work / "mls.laz"
    las.write(mls)
    forestreg("trees", str(mls), "--out", str(work / "trees"), "--no-cylinders", "--no-report")
    later_survey(work / "trees" / "trees.csv", work / "after.csv")
    forestreg(
        "change",
        str(work / "trees" / "trees.csv"),
        str(work / "after.csv"),
        "--out",
        str(work / "change"),
        "--crs",
        f"EPSG:{SPANNER_EPSG}",
        "--no-report",
    )
    forestreg(
        "simulate",
        "planted_conifer",
        "--out",
        str(work / "scans"),
        "--positions=-6,-6;6,-6;6,6;-6,6",
        "--step",
        "0.3",
        "--size",
        "36",
        "--seed",
        "2",
    )
    scans = sorted(str(p) for p in (work / "scans").glob("scan_*.laz"))
    forestreg("plot", *scans, "--out", str(work / "plot"), "--merged", str(work / "plot" / "merged.laz"))
    return {
        "crs": f"EPSG:{SPANNER_EPSG}",
        "als_chm": canopy_height_model(DATA / "spanner_ALS_Clip.laz", work / "als_chm.npy"),
        "plot_chm": canopy_height_model(work / "plot" / "merged.laz", work / "plot_chm.npy"),
        "trees": str(work / "trees"),
        "change": str(work / "change"),
        "plot": str(work / "plot"),
    }


# ----------------------------------------------------------------------------- step 2: the pictures (QGIS's Python)


def write_geotiff(chm: dict, path: Path, epsg) -> None:
    """The CHM grid as a one-band Float32 GeoTIFF (north up) in ``epsg`` (None: no CRS)."""
    import numpy as np
    from osgeo import gdal, osr

    grid = np.load(chm["grid"])[::-1].astype(np.float32)  # row 0 of the grid is its south edge
    res = chm["resolution_m"]
    ds = gdal.GetDriverByName("GTiff").Create(str(path), grid.shape[1], grid.shape[0], 1, gdal.GDT_Float32)
    ds.SetGeoTransform((chm["x0"], res, 0.0, chm["y0"] + grid.shape[0] * res, 0.0, -res))
    if epsg:
        srs = osr.SpatialReference()
        srs.ImportFromEPSG(int(epsg))
        ds.SetProjection(srs.ExportToWkt())
    ds.GetRasterBand(1).WriteArray(grid)
    ds = None


def render(work: Path, out: Path) -> None:
    from qgis.core import (
        QgsApplication,
        QgsBilinearRasterResampler,
        QgsColorRampShader,
        QgsMapRendererCustomPainterJob,
        QgsMapSettings,
        QgsProcessingContext,
        QgsProcessingFeedback,
        QgsProject,
        QgsRasterLayer,
        QgsRasterShader,
        QgsRectangle,
        QgsSingleBandPseudoColorRenderer,
        QgsSymbolLayerUtils,
    )
    from qgis.PyQt.QtCore import QPointF, QRectF, QSize, Qt
    from qgis.PyQt.QtGui import QColor, QFont, QImage, QLinearGradient, QPainter, QPen

    app = QgsApplication([], False)
    app.initQgis()
    from forestreg.plugin.qgis.provider import _load_gpkg_layers

    data = json.loads((work / "data.json").read_text())
    keep = []  # the layers live until QGIS exits

    def chm_layer(key: str, epsg) -> QgsRasterLayer:
        path = work / f"{key}.tif"
        write_geotiff(data[key], path, epsg)
        layer = QgsRasterLayer(str(path), "canopy height model")
        assert layer.isValid(), path
        top = float(layer.dataProvider().bandStatistics(1).maximumValue)
        ramp = QgsColorRampShader(0.0, top)
        ramp.setColorRampType(QgsColorRampShader.Interpolated)
        ramp.setColorRampItemList(
            [
                QgsColorRampShader.ColorRampItem(0.0, QColor(250, 248, 240), "0 m"),
                QgsColorRampShader.ColorRampItem(top / 2, QColor(196, 192, 180), ""),
                QgsColorRampShader.ColorRampItem(top, QColor(92, 88, 84), f"{top:.0f} m"),
            ]
        )
        shader = QgsRasterShader()
        shader.setRasterShaderFunction(ramp)
        layer.setRenderer(QgsSingleBandPseudoColorRenderer(layer.dataProvider(), 1, shader))
        layer.resampleFilter().setZoomedInResampler(QgsBilinearRasterResampler())  # smooth 0.5 m cells when zoomed in
        keep.append(layer)
        return layer

    def vector_layers(folder: str, names: list) -> list:
        context = QgsProcessingContext()
        context.setProject(QgsProject.instance())
        ids = _load_gpkg_layers(folder, Path(folder).name, context, "LAYERS", QgsProcessingFeedback())
        store = context.temporaryLayerStore()
        layers = [store.takeMapLayer(store.mapLayer(ids[n])) for n in names]
        keep.extend(layers)
        return layers

    def picture(name: str, title: str, layers: list, backdrop: QgsRasterLayer, extent_layer, note: str) -> None:
        map_w, legend_w, height, pad = 900, 330, 820, 24
        settings = QgsMapSettings()
        settings.setLayers([*reversed(layers), backdrop])  # first drawn on top
        if backdrop.crs().isValid():
            settings.setDestinationCrs(backdrop.crs())
        extent = QgsRectangle(extent_layer.extent())
        extent.grow(max(extent.width(), extent.height()) * 0.04)
        settings.setOutputSize(QSize(map_w, height))
        settings.setExtent(extent)
        settings.setOutputDpi(110)
        settings.setBackgroundColor(QColor(255, 255, 255))
        settings.setFlag(QgsMapSettings.Antialiasing, True)
        image = QImage(map_w + legend_w, height, QImage.Format_ARGB32)
        image.fill(QColor(255, 255, 255))
        painter = QPainter(image)
        painter.setRenderHint(QPainter.Antialiasing)
        job = QgsMapRendererCustomPainterJob(settings, painter)
        job.renderSynchronously()

        # scale bar (5 m) and the map's CRS, bottom left
        bar = 5.0 / settings.mapUnitsPerPixel()
        crs_text = backdrop.crs().description() or "local coordinates (no CRS)"
        painter.setFont(QFont("DejaVu Sans", 11))
        box_w = max(bar + 60, painter.fontMetrics().horizontalAdvance(crs_text) + 16)
        y = height - pad
        painter.fillRect(QRectF(pad - 8, y - 44, box_w, 56), QColor(255, 255, 255, 225))
        painter.setPen(QPen(QColor(20, 20, 20), 3))
        painter.drawLine(QPointF(pad, y), QPointF(pad + bar, y))
        painter.drawLine(QPointF(pad, y - 7), QPointF(pad, y + 1))
        painter.drawLine(QPointF(pad + bar, y - 7), QPointF(pad + bar, y + 1))
        painter.setPen(QColor(20, 20, 20))
        painter.drawText(QPointF(pad + bar + 8, y + 5), "5 m")
        painter.drawText(QPointF(pad, y - 22), crs_text)

        # legend: the layers' own symbols, as QGIS's legend shows them
        x = map_w + 18
        painter.fillRect(QRectF(map_w, 0, legend_w, height), QColor(248, 248, 248))
        painter.setPen(QColor(20, 20, 20))
        painter.setFont(QFont("DejaVu Sans", 13, QFont.Bold))
        painter.drawText(QPointF(x, 34), title)
        y = 66
        for layer in layers:
            painter.setFont(QFont("DejaVu Sans", 11, QFont.Bold))
            painter.drawText(QPointF(x, y), layer.name().split(" (")[0])
            y += 8
            painter.setFont(QFont("DejaVu Sans", 10))
            for item in layer.renderer().legendSymbolItems():
                icon = QgsSymbolLayerUtils.symbolPreviewPixmap(item.symbol(), QSize(22, 22))
                painter.drawPixmap(int(x), int(y), icon)
                painter.drawText(QPointF(x + 30, y + 16), item.label())
                y += 26
            y += 14
        painter.setFont(QFont("DejaVu Sans", 11, QFont.Bold))
        painter.drawText(QPointF(x, y), "canopy height model")
        gradient = QLinearGradient(x, 0, x + 200, 0)
        for stop, colour in ((0.0, QColor(250, 248, 240)), (0.5, QColor(196, 192, 180)), (1.0, QColor(92, 88, 84))):
            gradient.setColorAt(stop, colour)
        painter.fillRect(QRectF(x, y + 10, 200, 16), gradient)
        painter.setPen(QColor(120, 120, 120))
        painter.drawRect(QRectF(x, y + 10, 200, 16))
        painter.setPen(QColor(20, 20, 20))
        painter.setFont(QFont("DejaVu Sans", 10))
        top = backdrop.dataProvider().bandStatistics(1).maximumValue
        painter.drawText(QPointF(x, y + 44), "0 m")
        painter.drawText(QPointF(x + 200 - 36, y + 44), f"{top:.0f} m")
        painter.setPen(QColor(90, 90, 90))
        painter.setFont(QFont("DejaVu Sans", 9))
        painter.drawText(QRectF(x, height - 120, legend_w - 30, 110), Qt.TextWordWrap | Qt.AlignBottom, note)
        painter.end()
        assert image.save(str(out / name)), name
        print(f"wrote {out / name}", flush=True)

    crs_epsg = data["crs"].split(":")[1]
    als = chm_layer("als_chm", crs_epsg)
    trees, crowns, outline = vector_layers(data["trees"], ["trees", "crowns", "plot_outline"])
    picture(
        "qgis_trees.png",
        "Measure trees",
        [outline, crowns, trees],
        als,
        outline,
        "trees and crowns of layers.gpkg (forestreg:trees of a real MLS clip) over a canopy height model "
        f"of the airborne clip of the same plot; {data['crs']}",
    )
    changes, change_outline = vector_layers(data["change"], ["tree_changes", "plot_outline"])
    picture(
        "qgis_change.png",
        "Re-survey change",
        [change_outline, changes],
        als,
        change_outline,
        "tree_changes of layers.gpkg (forestreg:change: the MLS clip's trees and a later survey of them) over "
        f"the airborne canopy height model; {data['crs']}",
    )
    plot_chm = chm_layer("plot_chm", None)
    scanners, links, plot_outline = vector_layers(data["plot"], ["scanners", "links", "plot_outline"])
    picture(
        "qgis_plot.png",
        "Register plot",
        [plot_outline, links, scanners],
        plot_chm,
        plot_outline,
        "scanners, links and outline of layers.gpkg (forestreg:register_plot of four simulated scans) over a "
        "canopy height model of the merged cloud; the centre scan's coordinates",
    )
    del keep[:], trees, crowns, outline, changes, change_outline, scanners, links, plot_outline, als, plot_chm
    import gc

    gc.collect()  # every layer goes before QGIS's providers do
    app.exitQgis()


# ----------------------------------------------------------------------------- both steps


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="qgis_screenshots.py", description="Draw the QGIS guide's pictures again, headless."
    )
    parser.add_argument(
        "--out", default=str(ROOT / "docs" / "images"), help="folder of the pictures (default docs/images)"
    )
    parser.add_argument(
        "--work", help="folder of the data (default: a temporary folder); with --render, the data made before"
    )
    parser.add_argument(
        "--render", action="store_true", help="(QGIS's Python) draw the pictures from the data of --work"
    )
    args = parser.parse_args(argv)
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    if args.render:
        render(Path(args.work), out)
        return 0
    with tempfile.TemporaryDirectory(prefix="forestreg-qgis-shots-") as tmp:
        work = Path(args.work).resolve() if args.work else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        (work / "data.json").write_text(json.dumps(make_data(work), indent=1))
        plugins = work / "plugins"  # QGIS's Python imports this checkout as the plugin package forestreg
        plugins.mkdir(exist_ok=True)
        if not (plugins / "forestreg").exists():
            (plugins / "forestreg").symlink_to(ROOT, target_is_directory=True)
        env = {**os.environ, "QT_QPA_PLATFORM": "offscreen", "PYTHONPATH": str(plugins)}
        subprocess.run(
            [QGIS_PYTHON, str(Path(__file__).resolve()), "--render", "--work", str(work), "--out", str(out)],
            check=True,
            env=env,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
