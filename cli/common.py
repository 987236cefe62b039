"""What every command shares: argument types, global flags, progress (bar or JSON lines), output
checks, and the mapping of errors onto exit codes (0 ok, 1 the data do not allow it, 2 bad input,
130 interrupted)."""

from __future__ import annotations

import argparse
import json
import logging
import math
import re
import sys
import threading
from pathlib import Path
from typing import Optional

from ..app.units import UNITS  # noqa: F401 - the ``--units`` choices

log = logging.getLogger("forestreg")

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130


# ----------------------------------------------------------------------------- argument types


def floats(text: str, count: Optional[int] = None, what: str = "value") -> tuple[float, ...]:
    """Comma-separated finite numbers (``count`` of them when given)."""
    try:
        values = tuple(float(v) for v in text.replace(";", ",").split(",") if v.strip())
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"{what}: {text!r} is not a comma-separated list of numbers") from exc
    if count is not None and len(values) != count:
        raise argparse.ArgumentTypeError(f"{what}: expected {count} numbers, got {text!r}")
    if not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"{what}: {text!r} holds NaN or infinite values")
    return values


def direction(what: str):
    """An argparse type: three finite numbers forming a non-zero vector (a direction)."""

    def parse(text: str) -> tuple[float, float, float]:
        v = floats(text, 3, what)
        if math.sqrt(sum(c * c for c in v)) < 1e-9:
            raise argparse.ArgumentTypeError(f"{what}: {text!r} is the zero vector, not a direction")
        return v  # type: ignore[return-value]

    return parse


def number(what: str, *, minimum: Optional[float] = None, positive: bool = False, integer: bool = False):
    """An argparse type: a finite number, optionally > 0 or >= ``minimum``, optionally whole."""

    def parse(text: str):
        try:
            value = int(text) if integer else float(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(f"{what}: {text!r} is not a{' whole' if integer else ''} number") from exc
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"{what}: {text!r} is not a finite number")
        if positive and value <= 0:
            raise argparse.ArgumentTypeError(f"{what}: must be greater than 0, got {text}")
        if minimum is not None and value < minimum:
            raise argparse.ArgumentTypeError(f"{what}: must be at least {minimum:g}, got {text}")
        return value

    return parse


def offsets(text: str) -> tuple[float, ...]:
    return floats(text, what="--dh")


# ----------------------------------------------------------------------------- global flags


def add_global_flags(parser: argparse.ArgumentParser, *, top: bool = False) -> None:
    """-v, -q and --progress, accepted before the command (``top``) and after it."""
    default = (lambda v: v) if top else (lambda v: argparse.SUPPRESS)
    parser.add_argument("-v", "--verbose", action="store_true", default=default(False), help="log every step to stderr")
    parser.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        default=default(False),
        help="no progress on stderr (results and errors still printed)",
    )
    parser.add_argument(
        "--progress",
        choices=("bar", "jsonl", "none"),
        default=default(None),
        help='progress on stderr: a bar (default), JSON lines ({"event": "progress", ...}, last '
        '{"event": "end", ...}) for programs, or none',
    )


# ----------------------------------------------------------------------------- progress


def step_id(message: str) -> str:
    """A short machine id of a progress message: its first words, lower case, joined by '-'."""
    head = re.split(r"[(:;,.\d]", message, maxsplit=1)[0]
    words = re.findall(r"[a-z]+", head.lower())[:3]
    return "-".join(words) or "work"


#: Set by the command line's Ctrl-C / SIGTERM handler: every later progress step raises
#: KeyboardInterrupt again, so an interrupt is never lost.
INTERRUPTED = threading.Event()


class Reporter:
    """Progress of one command on stderr (tqdm bar, JSON lines, or nothing) and its final line.

    Called as ``reporter(fraction, message)`` (the engine's progress callback). ``done(message,
    result)`` records the one-line outcome and the result file for the final ``end`` event, which
    also lists the files the use case reported it wrote (:func:`run_outcome`: its outcome's
    ``result_file`` and ``outputs``).
    """

    def __init__(self, mode: str, command: str) -> None:
        from ..engine.core.atomic import held_output_locks

        self.mode = mode
        self.command = command
        self.message: str = ""
        self.result: Optional[str] = None
        self.outputs: list[str] = []
        self._bar = None
        self._last = None
        self._last_fraction = -1.0
        self._locks_before = set(held_output_locks())

    # engine callback
    def __call__(self, fraction: float, message: str = "") -> None:
        if INTERRUPTED.is_set():
            # Ctrl-C / SIGTERM came and its KeyboardInterrupt was swallowed on the way (a library's
            # broad "except:"): stop at this step instead of finishing as if nothing happened
            raise KeyboardInterrupt
        f = min(max(float(fraction), 0.0), 1.0)
        if self.mode == "jsonl":
            self._emit(
                {
                    "event": "progress",
                    "step": step_id(message or self.command),
                    "fraction": round(f, 4),
                    "message": message,
                }
            )
        elif self.mode == "bar":
            if not sys.stderr.isatty():  # a log: one line per new step (or 10 % more), never cut
                if message != self._last or f >= self._last_fraction + 0.1 or (f == 1.0 and self._last_fraction < 1.0):
                    # "<command>: <message>  NN%|": the layout the plugin hosts have parsed so far
                    print(f"{self.command}: {message} {100 * f:3.0f}%|", file=sys.stderr, flush=True)
                    self._last, self._last_fraction = message, f
                return
            from tqdm import tqdm

            if self._bar is None:
                self._bar = tqdm(
                    total=1000,
                    file=sys.stderr,
                    bar_format="{desc}{percentage:3.0f}%|{bar:30}| {elapsed}",
                    desc=f"{self.command} ",
                    leave=False,
                )
            if message != self._last:  # the whole message on its own line above the bar: never cut
                tqdm.write(f"{self.command}: {message}", file=sys.stderr)
                self._last = message
            self._bar.n = int(round(1000 * f))
            self._bar.refresh()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def done(self, message: str, result: Optional[str | Path] = None) -> None:
        self.message = message
        if result is not None:
            self.result = str(result)

    def end(self, exit_code: int, message: str = "") -> None:
        """The last event (JSON lines only). The command has ended: the output folders it locked
        are released and their lock files removed (the process may then leave without its exit
        handlers, and a command run inside a longer-lived process holds no lock after it)."""
        self.close()
        from ..engine.core.atomic import held_output_locks, release_output_folder

        for folder in set(held_output_locks()) - self._locks_before:
            release_output_folder(folder)
        if self.mode == "jsonl":
            self._emit(
                {
                    "event": "end",
                    "exit_code": int(exit_code),
                    "message": (message or self.message).splitlines()[0] if (message or self.message) else "",
                    "result": self.result,
                    "outputs": self.outputs or ([self.result] if self.result else []),
                }
            )

    @staticmethod
    def _emit(event: dict) -> None:
        sys.stderr.write(json.dumps(event) + "\n")
        sys.stderr.flush()


def reporter_of(args: argparse.Namespace) -> Reporter:
    return args.reporter


def progress_mode(args: argparse.Namespace) -> str:
    mode = getattr(args, "progress", None)
    if mode:
        return mode
    return "none" if getattr(args, "quiet", False) else "bar"


# ----------------------------------------------------------------------------- parameters


PARAMS_HELP = "TOML parameter file: any of the sections [registration], [scanner_position], [survey], [coregistration], [fusion], [trees], [change] (see 'forestreg params --toml'); options given on the command line win"


def product_params(args: argparse.Namespace):
    """Every parameter of the product: the defaults, or the TOML file of ``--params``."""
    from ..engine.params import ProductParams, load_params

    return load_params(args.params) if getattr(args, "params", None) else ProductParams()


def file_section(args: argparse.Namespace, name: str):
    """The section ``name`` of the TOML file of ``--params`` (e.g. ``scanner_position``,
    ``survey``); None without a file (the use case then takes its defaults)."""
    return getattr(product_params(args), name) if getattr(args, "params", None) else None


def params_from_args(args: argparse.Namespace):
    """Registration parameters: the TOML file (``--params``) with the command line's overrides."""
    if getattr(args, "params", None):
        params = product_params(args).registration
    else:  # the defaults, without importing every product's parameter classes (~0.5 s)
        from ..engine.tls.params import RegistrationParams

        params = RegistrationParams()
    changes = {}
    if getattr(args, "dr", None) is not None:
        changes["vop_radius_m"] = args.dr
    if getattr(args, "dh", None) is not None:
        changes["slice_offsets_m"] = tuple(args.dh)
    if getattr(args, "dc", None) is not None:
        changes["max_range_m"] = args.dc
    return params.replace(**changes) if changes else params


def run_outcome(reporter: "Reporter", use_case, *args, progress=None, **kwargs):
    """``use_case(*args, progress=progress or reporter, **kwargs)`` (a use case of
    :mod:`forestreg.app`): its outcome, the reporter's bar closed after it whatever happened. The
    result file and the files the outcome lists (``result_file``, ``outputs``) go to the final
    ``end`` event."""
    try:
        outcome = use_case(*args, progress=progress or reporter, **kwargs)
    finally:
        reporter.close()
    if getattr(outcome, "result_file", None) is not None:
        reporter.result = str(outcome.result_file)
    reporter.outputs = [str(p) for p in getattr(outcome, "outputs", ()) or ()]
    return outcome


def say(message: str, args: Optional[argparse.Namespace] = None, *, err: bool = False) -> None:
    """One result line on stdout (stderr with ``err``), remembered for the final event."""
    print(message, file=sys.stderr if err else sys.stdout, flush=True)
    if args is not None and getattr(args, "reporter", None) is not None:
        args.reporter.message = message


def add_units_params(p: argparse.ArgumentParser, units_help: str, func) -> None:
    """The ``--units`` and ``--params`` options that end a long-running command, and its handler."""
    p.add_argument("--units", choices=sorted(UNITS), default="m", help=units_help)
    p.add_argument("--params", help=PARAMS_HELP)
    p.set_defaults(func=func, long_running=True)


def add_crs_option(p: argparse.ArgumentParser, what: str) -> None:
    """The ``--crs`` option: the coordinate reference system of inputs whose files declare none
    (``what`` says which outputs take it)."""
    p.add_argument(
        "--crs",
        metavar="EPSG:CODE",
        help=f"coordinate reference system of the input coordinates when a file declares none, or the one that wins "
        f"over the files' (e.g. EPSG:32618, or a WKT): {what}",
    )


def shown(path) -> Path:
    """A path as printed: relative to the working folder when inside it (as the user typed it)."""
    p = Path(path)
    try:
        return p.relative_to(Path.cwd())
    except ValueError:
        return p
