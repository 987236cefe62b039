"""Take the desktop application's screenshots of the documentation again, offscreen.

    python scripts/docs_screenshots.py [--demo DIR] [--out docs/images]

Each picture is the whole window, drawn without a display (``forestreg gui --offscreen ...
--screenshot``, 1600x1000), from data made here: the simulated sample plot registered in the
window (``gui_main.png``), and the System B demo (``forestreg demo --system b``, or an earlier
``--demo DIR``) for the co-registration, trees and field-data tabs. Look at every picture before
committing it. The other screenshots of the guide (survey quality, targets, comparison) come from
the desktop tests' own projects.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SIZE = "1600x1000"


def forestreg(*args: str) -> None:
    command = [sys.executable, "-m", "forestreg.cli", *args]
    print("$ forestreg " + " ".join(args), flush=True)
    subprocess.run(command, check=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="docs_screenshots.py", description="Take the documentation's screenshots of the desktop application again."
    )
    parser.add_argument(
        "--demo", help="output folder of an earlier 'forestreg demo --system b' (default: run it, about 3 minutes)"
    )
    parser.add_argument(
        "--out", default=str(ROOT / "docs" / "images"), help="folder of the pictures (default docs/images)"
    )
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="forestreg-shots-") as tmp:
        demo = Path(args.demo) if args.demo else Path(tmp) / "demo"
        if not args.demo:
            forestreg("demo", "--system", "b", "--out", str(demo), "-q")
        b = demo / "system_b"
        shots = [
            ("gui_main.png", ["--sample", "--run"]),
            ("gui_coregistration.png", ["--coregistration", str(b / "coregistration")]),
            ("gui_trees.png", ["--trees", str(b / "trees_fused"), "--cloud", str(b / "fused.laz"), "--tree", "14"]),
            (
                "gui_field_data.png",
                [
                    "--trees",
                    str(b / "trees_ground"),
                    "--field",
                    str(b / "data" / "field.csv"),
                    "--also",
                    f"fused={b / 'trees_fused'}",
                ],
            ),
        ]
        for name, options in shots:
            forestreg("gui", "--offscreen", *options, "--screenshot", str(out / name), "--size", SIZE)
    return 0


if __name__ == "__main__":
    sys.exit(main())
