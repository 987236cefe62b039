"""``forestreg warmup``: compile every numerical kernel ahead, so that no command pays for it.

The kernels (numba) are compiled for the machine they run on and kept in a per-version cache
folder (:func:`~forestreg.engine.core.jit.kernel_cache_dir`). Without this step the first
command after an install compiles the kernels it needs (about 45 s on 2 cores) and says so once.
The warm-up runs each command once on small simulated data in a temporary folder (the signatures
the commands use, from the same file readers), then records that the cache is complete.
``scripts/setup.sh`` runs it.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Iterator

from .common import say


def add_parser(sub) -> None:
    p = sub.add_parser(
        "warmup",
        help="compile the numerical kernels now, into the per-version cache (scripts/setup.sh runs it; "
        "otherwise the first command after an install does it, about 45 s)",
    )
    p.add_argument(
        "--force", action="store_true", help="compile again even when the cache says the kernels are compiled"
    )
    p.set_defaults(func=cmd_warmup, long_running=False)


def cmd_warmup(args: argparse.Namespace) -> int:
    from ..app.warmup import cache_folder, cache_is_warm, compiled, mark_cache_warm

    if not args.force and cache_is_warm():
        say(f"the kernels are compiled already (in {cache_folder()}; --force compiles them again)", args)
        return 0
    t0 = time.perf_counter()
    os.environ["FORESTREG_WARMUP"] = "1"  # no "compiling ... on the first run" line from the kernels
    try:
        # the commands' own result lines are not the warm-up's (their errors still go to stderr)
        with tempfile.TemporaryDirectory(prefix="forestreg-warmup-") as folder, _silent_stdout():
            code = _run_commands(Path(folder))
    finally:
        os.environ.pop("FORESTREG_WARMUP", None)
    signatures, kernels = compiled()
    if code != 0:
        say(f"warmup: a command failed (exit {code}); the kernels it reached are compiled", args, err=True)
        return code
    mark_cache_warm()
    say(
        f"compiled {signatures} signatures of {kernels} kernels in "
        f"{time.perf_counter() - t0:.0f} s into {cache_folder() or 'memory (no cache folder)'}",
        args,
    )
    return 0


@contextlib.contextmanager
def _silent_stdout() -> Iterator[None]:
    """Standard output (file descriptor 1: also the libraries' C prints) sent to the null device."""
    sys.stdout.flush()
    saved = os.dup(1)
    sink = os.open(os.devnull, os.O_WRONLY)
    os.dup2(sink, 1)
    os.close(sink)
    try:
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def _run_commands(folder: Path) -> int:
    """Each use case once on small simulated data in ``folder`` (the calls the commands make);
    the first non-zero exit code."""
    from ..app.coregistration import coregister_clouds
    from ..app.pair import register_pair
    from ..app.plot import new_project, plot_folder, run_plot
    from ..app.simulation import simulate_scans, simulated_coregistration
    from ..app.trees import measure_trees_file
    from ..engine.params import ProductParams

    params = ProductParams()
    plot = folder / "plot"
    simulate_scans("planted_conifer", [(0.0, 0.0), (8.0, 0.0), (4.0, 7.0)], plot, size_m=30.0, step_deg=0.4)
    scans = [plot / f"scan_0{k}.laz" for k in (1, 2, 3)]
    runs = [
        lambda: register_pair(scans[0], scans[1], folder / "pair", params.registration),
        lambda: run_plot(
            new_project(scans, params.registration, name="plot_out"), plot_folder(folder / "plot_out", scans)
        ),
        lambda: measure_trees_file(scans[0], folder / "trees_tls", params.trees, report=False),
    ]
    case = simulated_coregistration(folder, seed=1, size_m=24.0, ground_extent_m=14.0, tls_step_deg=0.5)
    runs += [
        lambda: coregister_clouds(case.ground, case.uav, folder / "coreg", params.coregistration),
        lambda: measure_trees_file(case.uav, folder / "trees_uav", params.trees, report=False),
    ]
    for run in runs:
        if not run():
            return 1
    return 0
