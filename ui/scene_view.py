"""The 3D view of the scans, coloured by scan, with two interchangeable renderers.

* **interactive** (a normal desktop, or Xvfb): pyvistaqt's ``QtInteractor``, an OpenGL widget
  inside the window (rotate, zoom, pan with the mouse as in any VTK view).
* **image** (no display: ``--offscreen``, Qt's "offscreen" platform): an off-screen
  ``pyvista.Plotter`` renders into an image shown in a label; dragging the mouse orbits the
  camera and the wheel zooms, re-rendering the image. VTK renders off screen through EGL (or
  OSMesa) without any X server, so a screenshot of the window includes the points.

:func:`choose_renderer` picks "image" on Qt's offscreen/minimal platforms and "interactive"
otherwise; ``FORESTREG_3D=image|interactive`` forces one. If the interactive widget cannot be
created the view falls back to the image renderer and says so in the log.
"""

from __future__ import annotations

import logging
import os
import sys
from typing import Any, Optional

import numpy as np
from PySide6.QtCore import QPoint, QSize, Qt, QTimer, Signal
from PySide6.QtGui import QGuiApplication, QImage, QMouseEvent, QPixmap, QResizeEvent, QWheelEvent
from PySide6.QtWidgets import QLabel, QSizePolicy, QVBoxLayout, QWidget

from .scene_data import Scene

os.environ.setdefault("QT_API", "pyside6")  # pyvistaqt goes through qtpy: use our binding

log = logging.getLogger("forestreg")

BACKGROUND = ("#f4f6f8", "#c9d3de")  # bottom, top


def choose_renderer() -> str:
    """ "image" or "interactive" for the running QGuiApplication (see the module docstring)."""
    forced = os.environ.get("FORESTREG_3D", "").strip().lower()
    if forced in ("image", "interactive"):
        return forced
    platform = QGuiApplication.platformName().lower()
    return "image" if platform in ("offscreen", "minimal", "vnc") else "interactive"


def _prefer_egl_without_display() -> None:
    """Without an X display VTK would first try X and print a warning; ask for EGL directly."""
    if sys.platform.startswith("linux") and not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


def nice_length(extent_m: float) -> float:
    """A round scale-bar length (1, 2 or 5 times a power of ten) near a quarter of ``extent_m``."""
    target = max(float(extent_m) / 4.0, 1e-3)
    power = 10.0 ** np.floor(np.log10(target))
    for step in (5.0, 2.0, 1.0):
        if step * power <= target:
            return float(step * power)
    return float(power)


def add_guides(pl: Any, bounds: Any) -> None:
    """A scale bar and a north arrow in the scene, on the ground at the south-west corner of
    ``bounds`` (xmin, xmax, ymin, ymax, zmin, zmax; metres). North is the frame's +y: grid north
    for geo-referenced data (UTM), the centre scanner's y axis for a TLS plot in its own frame."""
    import pyvista as pv

    x0, x1, y0, y1, z0, z1 = (float(v) for v in bounds)
    if not all(np.isfinite([x0, x1, y0, y1, z0, z1])) or x1 <= x0 or y1 <= y0:
        return
    length = nice_length(max(x1 - x0, y1 - y0, z1 - z0))
    base = np.array([x0, y0 - 0.06 * (y1 - y0), z0])
    # solid bars, not GL lines (line widths are not honoured by every off-screen renderer)
    thick = 0.025 * length
    bar = pv.Line(base, base + [length, 0.0, 0.0]).tube(radius=thick, n_sides=12)
    pl.add_mesh(bar, color="#111111", name="guide:scale", reset_camera=False, pickable=False)
    for k in range(2):
        tick = base + [k * length, 0.0, 0.0]
        pl.add_mesh(
            pv.Line(tick - [0, 0, 0.0], tick + [0, 0, 0.12 * length]).tube(radius=thick, n_sides=12),
            color="#111111",
            name=f"guide:tick{k}",
            reset_camera=False,
            pickable=False,
        )
    text = f"{length:g} m"
    pl.add_point_labels(
        [base + [length / 2.0, 0.0, 0.0]],
        [text],
        name="guide:scale-label",
        font_size=12,
        text_color="#111111",
        shape_color="white",
        shape_opacity=0.7,
        show_points=False,
        always_visible=True,
        pickable=False,
        reset_camera=False,
    )
    tail = base + [-0.08 * length - 0.02 * (x1 - x0), 0.0, 0.0]
    arrow = pv.Arrow(
        start=tail, direction=(0.0, 1.0, 0.0), scale=0.5 * length, tip_length=0.35, tip_radius=0.15, shaft_radius=0.06
    )
    pl.add_mesh(arrow, color="#b42318", name="guide:north", reset_camera=False, pickable=False)
    pl.add_point_labels(
        [tail + [0.0, 0.62 * length, 0.0]],
        ["N"],
        name="guide:north-label",
        font_size=14,
        bold=True,
        text_color="#b42318",
        shape_opacity=0.0,
        show_points=False,
        always_visible=True,
        pickable=False,
        reset_camera=False,
    )


def view_from_south_west(pl: Any) -> None:
    """Look at the scene obliquely from above, from the south-west (35 degrees down): the scale
    bar and the north arrow at the south-west corner are in front."""
    pl.view_vector((-1.0, -1.0, 1.0), viewup=(0.0, 0.0, 1.0))


def add_axes_widget(pl: Any) -> None:
    """The orientation triad (E = x, N = y, Up = z) in the lower right corner (the legend of
    the scans is in the lower left)."""
    try:
        pl.add_axes(xlabel="E", ylabel="N", zlabel="Up", line_width=2, viewport=(0.86, 0.0, 1.0, 0.2))
    except Exception as exc:  # noqa: BLE001 - a view without the triad still works
        log.debug("no axes widget: %s", exc)


class _ImageLabel(QLabel):
    """The image renderer's surface: shows the rendered frame and turns drags into camera moves."""

    def __init__(self, view: "SceneView") -> None:
        super().__init__()
        self.view = view
        self._last: Optional[QPoint] = None
        self._button = Qt.MouseButton.NoButton
        self.setAlignment(Qt.AlignmentFlag.AlignCenter)
        self.setMinimumSize(QSize(200, 150))
        self.setSizePolicy(QSizePolicy.Policy.Expanding, QSizePolicy.Policy.Expanding)
        self.setStyleSheet(f"background: {BACKGROUND[0]};")

    def mousePressEvent(self, event: QMouseEvent) -> None:  # noqa: N802 - Qt API
        self._last = event.position().toPoint()
        self._press = self._last
        self._button = event.button()

    def mouseReleaseEvent(self, event: QMouseEvent) -> None:  # noqa: N802 - Qt API
        pos = event.position().toPoint()
        press = getattr(self, "_press", None)
        self._last = None
        if (
            self.view.pick_mode
            and press is not None
            and (pos - press).manhattanLength() <= 3
            and self._button == Qt.MouseButton.LeftButton
        ):
            self.view.pick_in_image(pos.x(), pos.y(), self.width(), self.height())

    def mouseMoveEvent(self, event: QMouseEvent) -> None:  # noqa: N802 - Qt API
        if self._last is None:
            return
        pos = event.position().toPoint()
        dx, dy = pos.x() - self._last.x(), pos.y() - self._last.y()
        self._last = pos
        self.view.orbit(-0.4 * dx, 0.4 * dy)

    def wheelEvent(self, event: QWheelEvent) -> None:  # noqa: N802 - Qt API
        self.view.zoom(1.1 ** (event.angleDelta().y() / 120.0))


class SceneView(QWidget):
    """Draws a :class:`~forestreg.ui.scene_data.Scene`; ``renderer`` is "interactive" or "image".

    In pick mode (:meth:`set_pick_mode`) a left click on a point emits :attr:`pointPicked` with
    the point in display coordinates (the window maps it to a scan and its file coordinates).
    """

    pointPicked = Signal(object)  # (3,) display coordinates

    def __init__(self, parent: Optional[QWidget] = None, renderer: Optional[str] = None) -> None:
        super().__init__(parent)
        self.renderer = renderer or choose_renderer()
        self.scene: Optional[Scene] = None
        self._layout = QVBoxLayout(self)
        self._layout.setContentsMargins(0, 0, 0, 0)
        self.plotter: Any = None
        self.image_label: Optional[_ImageLabel] = None
        self._render_timer = QTimer(self)
        self._render_timer.setSingleShot(True)
        self._render_timer.setInterval(60)
        self._render_timer.timeout.connect(self._render_image)
        if self.renderer == "interactive":
            try:
                from pyvistaqt import QtInteractor

                self.plotter = QtInteractor(self)
                self._layout.addWidget(self.plotter.interactor)
            except Exception as exc:  # noqa: BLE001 - fall back to images rather than fail
                log.warning("the interactive 3D view is not available here (%s); using rendered images", exc)
                self.plotter = None
                self.renderer = "image"
        if self.renderer == "image":
            import pyvista as pv

            _prefer_egl_without_display()
            self.image_label = _ImageLabel(self)
            self._layout.addWidget(self.image_label)
            try:
                self.plotter = pv.Plotter(off_screen=True, window_size=(800, 600))
            except Exception as exc:  # noqa: BLE001 - a window without 3D beats no window
                self._unavailable(exc)
        if self.plotter is not None:
            self.plotter.set_background(BACKGROUND[0], top=BACKGROUND[1])
            add_axes_widget(self.plotter)
        self._message_actor = None
        self.pick_mode = False
        self.show_scene(None)

    # ------------------------------------------------------------------ picking

    def set_pick_mode(self, on: bool) -> None:
        """Turn point picking on or off (left click on a point emits :attr:`pointPicked`)."""
        self.pick_mode = bool(on)
        pl = self.plotter
        if pl is None or self.renderer != "interactive":
            return
        try:
            if on:
                pl.enable_point_picking(
                    callback=lambda point, *rest: self._picked(point),
                    use_picker=True,
                    show_message="Click a point to place the target",
                    left_clicking=True,
                    show_point=True,
                    color="magenta",
                    point_size=14,
                )
            else:
                pl.disable_picking()
        except Exception as exc:  # noqa: BLE001 - picking is optional
            log.warning("point picking is not available in this 3D view: %s", exc)

    def _picked(self, point: Any) -> None:
        if point is None:
            return
        p = np.asarray(point, dtype=float).reshape(-1)
        if p.shape == (3,) and np.isfinite(p).all():
            self.pointPicked.emit(p)

    def pick_in_image(self, x: int, y: int, width: int, height: int) -> None:
        """Pick at a pixel of the image renderer's label (label coordinates, origin top left)."""
        pl = self.plotter
        if pl is None or self.image_label is None or self.image_label.pixmap() is None:
            return
        from vtkmodules.vtkRenderingCore import vtkPointPicker

        ww, wh = pl.window_size
        pix = self.image_label.pixmap()
        ratio = pix.devicePixelRatio() or 1.0
        pw, ph = pix.width() / ratio, pix.height() / ratio
        # the pixmap is centred in the label
        ox, oy = (width - pw) / 2.0, (height - ph) / 2.0
        u, v = (x - ox) / max(pw, 1) * ww, (y - oy) / max(ph, 1) * wh
        if not (0 <= u < ww and 0 <= v < wh):
            return
        picker = vtkPointPicker()
        picker.SetTolerance(0.01)
        if picker.Pick(u, wh - 1 - v, 0, pl.renderer) and picker.GetPointId() >= 0:
            self._picked(picker.GetPickPosition())

    # ------------------------------------------------------------------ drawing

    def show_scene(self, scene: Optional[Scene], *, message: str = "") -> None:
        """Replace what is drawn; with no scene (or an empty one) show ``message``."""
        self.scene = scene
        pl = self.plotter
        if pl is None:  # closed
            return
        pl.suppress_rendering = True  # one render at the end, not one per actor
        try:
            self._draw(scene, message)
        finally:
            pl.suppress_rendering = False
        self._update()

    def _draw(self, scene: Optional[Scene], message: str) -> None:
        import pyvista as pv

        pl = self.plotter
        pl.clear()
        if scene is None or not scene.clouds:
            text = message or ("No scan to draw." if scene is not None else "Add scans or open a project.")
            if scene is not None and scene.missing:
                text += "\n" + "\n".join(f"{k}: {v}" for k, v in list(scene.missing.items())[:6])
            pl.add_text(text, position="upper_left", font_size=11, color="#444444")
            return
        total = scene.point_count
        size = float(np.clip(3.5 - total / 150_000.0, 1.5, 3.5))
        labels = []
        for cloud in scene.clouds:
            if len(cloud.points):
                pl.add_mesh(
                    pv.PolyData(cloud.points),
                    color=cloud.colour,
                    point_size=size,
                    style="points",
                    render_points_as_spheres=False,
                    name=f"scan:{cloud.name}",
                    reset_camera=False,
                )
            pl.add_mesh(
                pv.Sphere(radius=0.35, center=cloud.scanner),
                color=cloud.colour,
                name=f"scanner:{cloud.name}",
                reset_camera=False,
            )
            labels.append((f"{cloud.name}  ({cloud.total_points:,} points)", cloud.colour))
        title = (
            "Before registration: each scan in its own coordinates"
            if scene.mode == "before"
            else "After registration: scans in the project frame"
        )
        if scene.missing:
            title += f"  (not shown: {', '.join(scene.missing)})"
        pl.add_text(title, position="upper_left", font_size=10, color="#222222", name="title")
        for k, (text, colour) in enumerate(reversed(labels)):
            actor = pl.add_text(text, position=(12, 10 + 22 * k), font_size=9, color=colour, name=f"legend:{k}")
            try:
                actor.prop.background_color = "white"
                actor.prop.background_opacity = 0.75
            except AttributeError:  # older pyvista: plain text
                pass
        shown = sum(len(c.points) for c in scene.clouds)
        pl.add_text(f"{shown:,} points drawn", position="upper_right", font_size=8, color="#555555", name="count")
        drawn = [c.points for c in scene.clouds if len(c.points)]
        if drawn and scene.mode != "before":  # one frame: a scale and north mean something
            allp = np.concatenate(drawn)
            lo, hi = np.percentile(allp, 1.0, axis=0), np.percentile(allp, 99.0, axis=0)
            add_guides(pl, (lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]))
        view_from_south_west(pl)
        pl.reset_camera()
        pl.camera.zoom(1.3)

    def draw(self, painter: Any, *, camera: str = "isometric") -> None:
        """Replace what is drawn by whatever ``painter(plotter)`` adds (other views' contents:
        trees, keypoints), then frame it (``camera`` "isometric" or "top")."""
        self.scene = None
        pl = self.plotter
        if pl is None:
            return
        pl.suppress_rendering = True
        try:
            pl.clear()
            painter(pl)
            if camera == "top":
                pl.view_xy()
            elif camera == "side":  # from the south, a little above: a tree stands upright
                pl.view_xz()
                pl.camera.Elevation(20.0)
                pl.camera.OrthogonalizeViewUp()
            else:
                view_from_south_west(pl)
            pl.reset_camera()
            pl.camera.zoom(1.2 if camera == "top" else 1.0)  # no zoom in: the guides at the edge stay in view
        finally:
            pl.suppress_rendering = False
        self._update()

    def show_markers(self, points: Any, *, colour: str = "#e0007a", label: str = "targets") -> None:
        """Draw the scans' targets (display coordinates, (N, 3)) over the points; empty clears them."""
        import pyvista as pv

        pl = self.plotter
        if pl is None:
            return
        for name in ("markers", "markers-legend"):
            try:
                pl.remove_actor(name, render=False)
            except Exception:  # noqa: BLE001 - nothing drawn yet
                pass
        pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        if len(pts) and self.scene is not None and self.scene.clouds:
            pl.add_mesh(
                pv.PolyData(pts),
                color=colour,
                point_size=11,
                style="points",
                render_points_as_spheres=True,
                name="markers",
                reset_camera=False,
                pickable=False,
            )
            pl.add_text(
                f"\u25cf {len(pts)} {label}",
                position=(12, 10 + 22 * len(self.scene.clouds)),
                font_size=9,
                color=colour,
                name="markers-legend",
            )
        self._update()

    def reset_camera(self) -> None:
        """Look at all points obliquely from above (south-west, 35 degrees down)."""
        pl = self.plotter
        if pl is None:
            return
        view_from_south_west(pl)
        pl.reset_camera()
        pl.camera.zoom(1.3)
        self._update()

    def top_view(self) -> None:
        """Look straight down (north up): the plan view in which registration quality shows as
        trunks drawn once or twice."""
        pl = self.plotter
        if pl is None:
            return
        pl.view_xy()
        pl.reset_camera()
        pl.camera.zoom(1.2)
        self._update()

    def orbit(self, azimuth_deg: float, elevation_deg: float) -> None:
        """Turn the camera about the focal point (used by the image renderer's mouse)."""
        if self.plotter is None:
            return
        cam = self.plotter.camera
        cam.Azimuth(azimuth_deg)
        cam.Elevation(elevation_deg)
        cam.OrthogonalizeViewUp()
        self._update()

    def zoom(self, factor: float) -> None:
        if self.plotter is None:
            return
        self.plotter.camera.zoom(factor)
        self._update()

    def _update(self) -> None:
        if self.plotter is None:
            return
        if self.renderer == "image":
            self._render_timer.start()
        else:
            self.plotter.render()

    def _render_image(self) -> None:
        if self.image_label is None or self.plotter is None:
            return
        w, h = max(self.image_label.width(), 200), max(self.image_label.height(), 150)
        ratio = self.devicePixelRatioF()
        size = (int(w * ratio), int(h * ratio))
        if tuple(self.plotter.window_size) != size:
            self.plotter.window_size = size
        try:
            self.plotter.render()  # after the first frame, screenshot() alone returns the last frame
            img = np.ascontiguousarray(self.plotter.screenshot(return_img=True))
        except Exception as exc:  # noqa: BLE001 - no OpenGL (EGL/OSMesa) here
            self._unavailable(exc)
            return
        qimg = QImage(img.data, img.shape[1], img.shape[0], img.strides[0], QImage.Format.Format_RGB888).copy()
        pix = QPixmap.fromImage(qimg)
        pix.setDevicePixelRatio(ratio)
        self.image_label.setPixmap(pix)

    def _unavailable(self, exc: BaseException) -> None:
        log.warning(
            "the 3D view cannot render here (%s): install Mesa's EGL or OSMesa (Debian: libegl1 libgl1-mesa-dri)", exc
        )
        if self.plotter is not None:
            try:
                self.plotter.close()
            except Exception:  # noqa: BLE001
                pass
        self.plotter = None
        if self.image_label is not None:
            self.image_label.setText(f"The 3D view is not available on this computer:\n{exc}")

    def render_now(self) -> None:
        """Render at once (before a screenshot)."""
        if self.plotter is None:
            return
        if self.renderer == "image":
            self._render_timer.stop()
            self._render_image()
        else:
            self.plotter.render()

    def resizeEvent(self, event: QResizeEvent) -> None:  # noqa: N802 - Qt API
        super().resizeEvent(event)
        if self.renderer == "image":
            self._render_timer.start()

    def close_view(self) -> None:
        """Free the renderer (call once, when the window closes)."""
        if self.plotter is not None:
            try:
                self.plotter.close()
            except Exception:  # noqa: BLE001 - closing must not fail
                pass
            self.plotter = None
            self._render_timer.stop()
