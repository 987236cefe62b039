"""``forestreg gui``: start the desktop window, or drive it without a display.

Usage::

    forestreg gui [--project P] [--offscreen] [--run] [--screenshot OUT.png]
    forestreg gui --offscreen --trees DIR [--cloud FILE] [--tree ID] --screenshot OUT.png
    forestreg gui --offscreen --coregistration DIR --screenshot OUT.png
    forestreg gui --offscreen --change DIR --screenshot OUT.png
    python -m forestreg.ui.app --offscreen --project P --run --screenshot out.png

``--offscreen`` needs no display at all: Qt draws the window into memory (its "offscreen"
platform) and the 3D view renders through VTK's off-screen EGL/OSMesa path into an image inside
the window (see :mod:`forestreg.ui.scene_view`), so the screenshot shows the points. Without
``--offscreen`` the normal interactive window opens (pyvistaqt's OpenGL view; under Xvfb too).
``--run`` registers the project and waits for the end; ``--screenshot`` saves the whole window
once everything is drawn and exits. ``--trees DIR`` opens the result of ``forestreg trees --out
DIR`` on the Trees tab (map, table, the first tree or ``--tree ID`` in 3D; ``--cloud`` adds the
measured cloud's points), ``--coregistration DIR`` the result of ``forestreg coregister --out DIR``
on the Co-registration tab, ``--change DIR`` the result of ``forestreg change BEFORE AFTER --out DIR``
on the Re-survey tab (its change map and tree table). Exit codes: 0 done, 1 the run failed, 2 bad arguments or an
unreadable project.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable, Optional

DEFAULT_SIZE = (1600, 1000)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="forestreg gui", description="forestreg's desktop window")
    p.add_argument("--project", help="project file to open")
    p.add_argument("--offscreen", action="store_true", help="no display: draw the window in memory (with --screenshot)")
    p.add_argument(
        "--run", action="store_true", help="register the project (scans not registered yet) after opening it"
    )
    p.add_argument(
        "--screenshot",
        metavar="OUT.png",
        help="save a screenshot of the whole window when everything is drawn, then exit",
    )
    p.add_argument(
        "--size",
        default=f"{DEFAULT_SIZE[0]}x{DEFAULT_SIZE[1]}",
        help="window size WIDTHxHEIGHT for screenshots (default %(default)s)",
    )
    p.add_argument("--sample", action="store_true", help="open the simulated sample plot (made on first use)")
    p.add_argument(
        "--trees", metavar="DIR", help="open a trees result folder (forestreg trees --out DIR) on the Trees tab"
    )
    p.add_argument("--cloud", metavar="FILE", help="with --trees: the measured cloud, to draw each tree's points")
    p.add_argument("--tree", type=int, metavar="ID", help="with --trees: the tree to select (default: the first)")
    p.add_argument(
        "--coregistration", metavar="DIR", help="open a co-registration result folder (forestreg coregister --out DIR)"
    )
    p.add_argument(
        "--change", metavar="DIR", help="open a re-survey result folder (forestreg change BEFORE AFTER --out DIR)"
    )
    p.add_argument("--field", metavar="CSV", help="with --trees: evaluate against field records (Field data tab)")
    p.add_argument(
        "--also",
        action="append",
        default=[],
        metavar="NAME=DIR",
        help="with --field: another trees folder shown side by side (e.g. fused=trees_fused)",
    )
    p.add_argument(
        "--results-tab",
        metavar="NAME",
        help="show this tab of the results dock (Links, Scans, Targets, Comparison, Log)",
    )
    p.add_argument(
        "--timeout",
        type=float,
        default=3600.0,
        help="longest wait for the run and the views, seconds (default %(default)s)",
    )
    return p


def _parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError as exc:
        raise SystemExit(f"forestreg gui: --size must be WIDTHxHEIGHT, e.g. 1600x1000 (got {text!r})") from exc
    return max(w, 400), max(h, 300)


def wait_until(predicate: Callable[[], bool], timeout_s: float) -> bool:
    """Run the Qt event loop until ``predicate()`` is true (True) or the time is up (False)."""
    from PySide6.QtCore import QEventLoop
    from PySide6.QtWidgets import QApplication

    app = QApplication.instance()
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return True
        app.processEvents(QEventLoop.ProcessEventsFlag.AllEvents, 50)
        time.sleep(0.01)
    return predicate()


def settle(window, timeout_s: float) -> bool:
    """Wait until no background work is left, then let the views paint."""
    ok = wait_until(lambda: not window.busy and not window.running, timeout_s)
    wait_until(lambda: False, 0.3)
    return ok


def save_screenshot(window, path: str | Path) -> Path:
    """Render the 3D view now and save a picture of the whole window."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    view = window.current_scene_view()
    view.render_now()
    from matplotlib.backends.backend_qtagg import FigureCanvasQTAgg

    wait_until(lambda: False, 0.2)
    for canvas in window.findChildren(FigureCanvasQTAgg):  # at their final size, not a pending idle draw
        if canvas.isVisible():
            canvas.draw()
    wait_until(lambda: False, 0.2)
    if not window.grab().save(str(out)):
        raise OSError(f"cannot write the screenshot {out}")
    return out


def _quiet_offscreen_warnings() -> None:
    """Drop Qt's "offscreen plugin does not support ..." notices; other messages still print."""
    from PySide6.QtCore import qInstallMessageHandler

    def handler(mode, context, message: str) -> None:  # noqa: ANN001 - Qt's signature
        if "does not support" in message and ("plugin" in message or "propagateSizeHints" in message):
            return
        print(message, file=sys.stderr)

    qInstallMessageHandler(handler)


def main(argv: Optional[list[str]] = None) -> int:
    """``forestreg gui`` (see the module docstring)."""
    args = build_parser().parse_args(argv)
    size = _parse_size(args.size)
    if args.offscreen:
        os.environ["QT_QPA_PLATFORM"] = "offscreen"
    from PySide6.QtCore import QSettings
    from PySide6.QtWidgets import QApplication

    from .main_window import APPLICATION, ORGANISATION, MainWindow

    if args.offscreen:
        _quiet_offscreen_warnings()
    app = QApplication.instance()
    if app is None:
        app = QApplication([sys.argv[0] if sys.argv else "forestreg"])
    app.setOrganizationName(ORGANISATION)
    app.setApplicationName(APPLICATION)
    headless = args.offscreen or bool(args.screenshot)
    if headless:  # no window to read: the log goes to the terminal
        import logging

        stream = logging.StreamHandler(sys.stderr)
        stream.setFormatter(logging.Formatter("forestreg gui: %(message)s"))
        logging.getLogger("forestreg").addHandler(stream)
    scratch = tempfile.TemporaryDirectory(prefix="forestreg-gui-") if headless else None
    # a scripted run must not change (or depend on) the user's window layout and recent files
    settings = QSettings(str(Path(scratch.name) / "settings.ini"), QSettings.Format.IniFormat) if scratch else None
    window = MainWindow(settings=settings, interactive=not headless)
    try:
        window.resize(*size)
        window.show()
        if args.project and not window.open_project(args.project):
            print(
                f"forestreg gui: {window.last_error[1] if window.last_error else 'cannot open ' + args.project}",
                file=sys.stderr,
            )
            return 2
        if args.coregistration and not window.open_coregistration(args.coregistration):
            print(
                f"forestreg gui: {window.last_error[1] if window.last_error else 'cannot open ' + args.coregistration}",
                file=sys.stderr,
            )
            return 2
        if args.change and not window.open_change(args.change):
            print(
                f"forestreg gui: {window.last_error[1] if window.last_error else 'cannot open ' + args.change}",
                file=sys.stderr,
            )
            return 2
        if args.trees and not window.open_trees(args.trees, args.cloud, select=args.tree):
            print(
                f"forestreg gui: {window.last_error[1] if window.last_error else 'cannot open ' + args.trees}",
                file=sys.stderr,
            )
            return 2
        if args.field:
            runs = {Path(args.trees).name if args.trees else "trees": args.trees} if args.trees else {}
            for item in args.also:
                name, _, folder = item.partition("=")
                if not folder:
                    print(f"forestreg gui: --also needs NAME=DIR (got {item!r})", file=sys.stderr)
                    return 2
                runs[name] = folder
            if not runs or not window.evaluate_field(args.field, runs):
                print(
                    f"forestreg gui: {window.last_error[1] if window.last_error else '--field needs --trees or --also'}",
                    file=sys.stderr,
                )
                return 2
        if args.sample and not args.project:
            window.open_sample()
            settle(window, args.timeout)
        code = 0
        if args.run:
            settle(window, args.timeout)
            if not window.run():
                print(f"forestreg gui: {window.last_error[1] if window.last_error else 'cannot run'}", file=sys.stderr)
                return 1
            if not wait_until(lambda: not window.running, args.timeout):
                window.cancel_run()
                print("forestreg gui: the run did not end in time; cancelled", file=sys.stderr)
                code = 1
            elif window.last_error is not None and window.last_error[0] == "The registration failed":
                print(f"forestreg gui: {window.last_error[1]}", file=sys.stderr)
                code = 1
        if args.results_tab:
            tabs = window.bottom_tabs
            found = [
                k for k in range(tabs.count()) if tabs.tabText(k).replace("&", "").lower() == args.results_tab.lower()
            ]
            if not found:
                names = ", ".join(tabs.tabText(k).replace("&", "") for k in range(tabs.count()))
                print(f"forestreg gui: no results tab {args.results_tab!r} (one of {names})", file=sys.stderr)
                return 2
            tabs.setCurrentIndex(found[0])
        if args.screenshot:
            settle(window, args.timeout)
            out = save_screenshot(window, args.screenshot)
            view = window.current_scene_view()
            corner = view.mapTo(window, view.rect().topLeft())
            print(f"screenshot: {out}")
            print(f"3d view: {corner.x()} {corner.y()} {view.width()} {view.height()}")
            print(f"3d renderer: {view.renderer}")
            return code
        if headless:
            settle(window, args.timeout)
            return code
        return int(app.exec())
    finally:
        window.close()
        if scratch is not None:
            scratch.cleanup()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
