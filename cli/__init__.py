"""The ``forestreg`` command line.

Every command is a thin wrapper over the engine's API; none holds algorithm code. One module per
family: :mod:`.register` (pair), :mod:`.plot` (plot, project, compare, targets), :mod:`.coreg`
(coregister, fuse), :mod:`.trees` (trees, evaluate), :mod:`.change` (change), :mod:`.misc` (simulate, demo, gui, params), :mod:`.service`
(serve, batch);
:mod:`.common` holds what they share.

Exit codes: 0 ok; 1 the data do not allow the result (a registration that failed, with its reason);
2 bad input or usage (one line on stderr, never a traceback); 130 interrupted (Ctrl-C).
Global flags (``-v``, ``-q``, ``--progress bar|jsonl|none``) go before or after the command.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import struct
import sys
import threading
from typing import Optional, Sequence

# imported here, not in the signal handler: an interrupt may arrive inside the import machinery
from .common import (
    EXIT_BAD_INPUT,
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    INTERRUPTED,
    Reporter,
    add_global_flags,
    progress_mode,
)

__all__ = ["build_parser", "entry", "main"]


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (exit 2) and the global flags on every sub-command."""

    last_error = ""

    def error(self, message: str) -> None:  # type: ignore[override]
        import re

        message = re.sub(r"^argument (\S+): \1: ", r"argument \1: ", message)
        _Parser.last_error = f"{self.prog}: {message}"
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__
    from . import change, coreg, misc, plot, register, service, trees, warmup

    parser = _Parser(
        prog="forestreg",
        description="Marker-free registration of forest laser scans, co-registration with UAV LiDAR, and tree measurements.",
    )
    parser.add_argument("--version", action="version", version=f"forestreg {__version__}")
    add_global_flags(parser, top=True)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser)
    register.add_parser(sub)
    plot.add_parsers(sub, add_global_flags)
    coreg.add_parsers(sub)
    trees.add_parsers(sub)
    change.add_parsers(sub)
    misc.add_parsers(sub)
    service.add_parsers(sub)
    warmup.add_parser(sub)
    for name, p in sub.choices.items():
        if name not in ("gui", "project"):
            add_global_flags(p)
    # the job service and batches check their jobs' arguments with this very parser: handed over
    # to them (they never import the CLI, which starts them)
    parser.set_defaults(build_parser=build_parser)
    return parser


def main(argv: Optional[Sequence[str]] = None, *, tune_malloc: bool = False) -> int:
    """Run one command; returns its exit code. ``tune_malloc`` (the ``forestreg`` process
    itself, not a caller's): the registration commands tune glibc's malloc (:func:`_tune_malloc`)."""
    from ..engine.core.errors import DataError, ForestregError

    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["gui"]:  # the GUI parses its own options
        from .misc import cmd_gui

        try:
            return cmd_gui(argparse.Namespace(gui_args=argv[1:]))
        except (ForestregError, argparse.ArgumentTypeError) as exc:
            _error(_one_line(exc))
            return EXIT_BAD_INPUT
        except KeyboardInterrupt:
            _error("interrupted")
            return EXIT_INTERRUPTED
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # usage errors (2), --help and --version (0)
        code = int(exc.code or 0) if not isinstance(exc.code, str) else EXIT_BAD_INPUT
        if _wants_jsonl(argv):
            Reporter("jsonl", "forestreg").end(code, (_Parser.last_error or "bad usage (see --help)") if code else "")
        return code
    if not logging.getLogger().handlers:
        logging.basicConfig(
            level=logging.INFO if args.verbose else logging.WARNING,
            format="%(levelname)s %(name)s: %(message)s",
            stream=sys.stderr,
        )
    elif args.verbose:
        logging.getLogger("forestreg").setLevel(logging.INFO)
    # the libraries' own reports of a file they cannot read come before forestreg's one line that
    # says which file and why (laspy logs a damaged LAZ as an error of its own)
    for library in ("laspy", "distributed"):
        logging.getLogger(library).setLevel(logging.DEBUG if args.verbose else logging.CRITICAL)
    if tune_malloc and args.command in MALLOC_TUNED_COMMANDS and _small_scans(args):
        _tune_malloc()
        if args.command == "register":
            _without_cyclic_collector()
    elif tune_malloc and args.command in MALLOC_LEAN_COMMANDS:
        _tune_malloc(MALLOC_LEAN_OPTIONS)
    mode = progress_mode(args)
    if not getattr(args, "long_running", False) and mode == "bar":
        mode = "none"
    args.reporter = Reporter(mode, args.command)
    code, message = EXIT_BAD_INPUT, ""
    previous_term = _terminate_as_interrupt()
    try:
        code = args.func(args)
        return code
    except BrokenPipeError:  # output piped into head & co.
        code = 0
        return 0
    except KeyboardInterrupt:
        INTERRUPTED.set()  # also when Python's own handler raised it (Ctrl-C off our handler)
        code = EXIT_INTERRUPTED
        said = getattr(args, "interrupted_message", None)  # a command's own account of what it kept
        message = (said() if callable(said) else "") or "interrupted: the output was left as it was before the run"
        _error(message)
        return code
    except DataError as exc:
        code, message = EXIT_FAILED, f"failed: {_one_line(exc)}"
        _error(message, prefix="")
        return code
    except (ForestregError, argparse.ArgumentTypeError) as exc:
        code, message = EXIT_BAD_INPUT, _one_line(exc)
        _error(message)
        return code
    except MemoryError:
        code, message = EXIT_FAILED, "not enough memory for this data (try thinning the clouds first)"
        _error(message)
        return code
    except OSError as exc:  # disk full, permission denied, ... on a path forestreg did not foresee
        code, message = (
            EXIT_BAD_INPUT,
            f"{exc.filename + ': ' if getattr(exc, 'filename', None) else ''}{exc.strerror or exc}",
        )
        _error(message)
        return code
    except Exception as exc:  # a bug: one line (the traceback with -v), never a half-written output
        code, message = (
            EXIT_FAILED,
            f"internal error ({type(exc).__name__}: {_one_line(exc)}); please report it (-v shows the traceback)",
        )
        if args.verbose:
            import traceback

            traceback.print_exc()
        _error(message)
        return code
    finally:
        args.reporter.end(code, message)
        if previous_term is not None:
            for signum, previous in zip((signal.SIGTERM, signal.SIGINT), previous_term):
                if previous is not None:
                    signal.signal(signum, previous)


def entry() -> None:
    """The ``forestreg`` command (and ``python -m forestreg.cli``): :func:`main`, then the process
    ends at once with its exit code.

    Every output is written and closed when :func:`main` returns, so the interpreter's teardown
    (freeing every module and object: 0.2-0.3 s after a registration) is skipped: stdout, stderr
    and the log handlers are flushed, and the process leaves with :func:`os._exit`. A worker thread
    still reading or preparing a scan after Ctrl-C is not waited for either. The desktop
    application (``gui``) exits the usual way (Qt tears its windows down itself)."""
    if sys.argv[1:2] != ["gui"]:  # the desktop application keeps its libraries whole (pyvista's downloads)
        _without_http_client()
    _one_blas_thread()
    try:
        code = main(tune_malloc=True)
    except KeyboardInterrupt:  # Ctrl-C before the command's own handling began (building the parser)
        code = EXIT_INTERRUPTED
        _error("interrupted")
        if _wants_jsonl(sys.argv[1:]):
            Reporter("jsonl", "forestreg").end(code, "interrupted")
    if sys.argv[1:2] == ["gui"]:
        sys.exit(code)
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:  # a closed pipe (output piped into head): nothing more to say
            pass
    logging.shutdown()
    os._exit(code)


#: The commands run with glibc's malloc tuned (:func:`_tune_malloc`): the registrations of small
#: scans, where it was measured faster. Trees (+83 MB, no faster: :data:`MALLOC_LEAN_COMMANDS`
#: instead), co-registration (+26 MB, 0.95x) and plots of large scans (ten 30 M-point scans:
#: +226 MB) keep the defaults.
MALLOC_TUNED_COMMANDS = ("register", "plot")
#: Points a scan may hold for :func:`_tune_malloc` (the engine's limit for preparing two at once)
MALLOC_TUNED_MAX_POINTS = 15_000_000


def _small_scans(args) -> bool:
    """Whether every scan of a register / plot command is a LAS/LAZ file of at most
    :data:`MALLOC_TUNED_MAX_POINTS` points, from the point count in its header (read here with
    ``struct``: no import). False when any count is unknown."""
    paths = [args.reference, args.moving] if args.command == "register" else list(getattr(args, "scans", []) or [])
    if not paths:
        return False
    for path in paths:
        try:
            if not os.path.isfile(path):  # a pipe or a device would block open(); the command says why
                return False
            with open(path, "rb") as f:
                head = f.read(255)
        except (OSError, TypeError):
            return False
        if len(head) < 111 or head[:4] != b"LASF":
            return False
        legacy = struct.unpack_from("<I", head, 107)[0]
        count = struct.unpack_from("<Q", head, 247)[0] if head[25] >= 4 and len(head) >= 255 else legacy
        if not 0 < max(count, legacy) <= MALLOC_TUNED_MAX_POINTS:
            return False
    return True


#: glibc's malloc settings for a command (see :func:`_tune_malloc`): bytes, bytes, bytes, arenas
MALLOC_MMAP_THRESHOLD = 512 * 2**20
MALLOC_TRIM_THRESHOLD = 64 * 2**20
MALLOC_TOP_PAD = 64 * 2**20
MALLOC_ARENA_MAX = 2
#: :func:`_tune_malloc`'s options (``mallopt`` parameter numbers: M_MMAP_THRESHOLD,
#: M_TRIM_THRESHOLD, M_TOP_PAD, M_ARENA_MAX) and values
MALLOC_FAST_OPTIONS = (
    (-3, MALLOC_MMAP_THRESHOLD),
    (-1, MALLOC_TRIM_THRESHOLD),
    (-2, MALLOC_TOP_PAD),
    (-8, MALLOC_ARENA_MAX),
)
#: The commands whose threads share two malloc arenas (:data:`MALLOC_LEAN_OPTIONS`) and nothing
#: else changed. ``trees``: glibc gives each thread (the stems' thread, the kernels' and the
#: mixture's pools) an arena of its own, and what one thread freed then stays in its arena
#: while another asks for more. Measured on ``LPine1_demo`` (1.5 M points, 3 runs each): peak
#: 415 -> 407-409 MB, wall time unchanged (21.5-21.9 s / 21.0-22.7 s).
MALLOC_LEAN_COMMANDS = ("trees",)
MALLOC_LEAN_OPTIONS = ((-8, MALLOC_ARENA_MAX),)


def _tune_malloc(options: Sequence[tuple[int, int]] = MALLOC_FAST_OPTIONS) -> None:
    """Keep freed large arrays for the next ones instead of returning them to the system
    (``options``: pairs of a ``mallopt`` parameter and its value; the default is the tuning
    described here, :data:`MALLOC_LEAN_OPTIONS` only shares two arenas between the threads).

    A registration allocates and frees point-sized arrays (tens of MB) thousands of times. glibc
    serves each above 32 MB with a fresh ``mmap`` and returns the heap's free top at once, and
    the kernel zeroes every page again on first touch: on a 4-scan plot, 2.3 s of system time in
    11 s. Here large blocks come from the heap (``M_MMAP_THRESHOLD`` 512 MB), which grows by 64 MB
    more than asked (``M_TOP_PAD``) and is given back only beyond 64 MB free
    (``M_TRIM_THRESHOLD``); the threads share two arenas (``M_ARENA_MAX``), so a block one thread
    freed serves the next. Measured (A/B, 5 runs each): 4-scan plot system time 2.26 -> 1.35 s,
    wall 0.96x, peak +45 MB; pair 0.95x, +16 MB. Not for large scans (:func:`_small_scans`: a
    plot of ten 30 M-point scans peaked 226 MB higher with it). Only with glibc, and not when the
    user set a ``MALLOC_*`` variable or ``GLIBC_TUNABLES`` (theirs win)."""
    if any(name.startswith("MALLOC_") for name in os.environ) or os.environ.get("GLIBC_TUNABLES"):
        return
    try:
        if not (os.confstr("CS_GNU_LIBC_VERSION") or "").startswith("glibc"):
            return
        import ctypes

        libc = ctypes.CDLL(None)
        for option, value in options:
            libc.mallopt(option, value)
    except (OSError, ValueError, AttributeError):  # no glibc to ask (macOS, Windows, musl): the defaults stay
        return


def _without_cyclic_collector() -> None:
    """Turn Python's cyclic garbage collector off for the rest of the ``forestreg`` process: a
    ``register`` of small scans (:func:`_small_scans`), which ends after its one pair. Its passes
    over the million objects the imports leave (NumPy, numba's typing tables) held the interpreter
    lock 0.1-0.2 s of a 0.1 M- and a 1 M-point pair (two full passes, one of them during ICP); a
    pair leaves little cyclic garbage (the 0.1 M and 1 M pairs' peaks unchanged). Compiling
    kernels leaves much: the engine turns the collector back on when it compiles one
    (:func:`~forestreg.engine.core.jit.kernel`)."""
    import gc

    gc.disable()


def _without_http_client() -> None:
    """Mark the ``requests`` package absent in the ``forestreg`` process (not in a caller's, nor
    in the desktop application's).

    laspy imports it, when it is installed, for reading COPC files over HTTP: 35 ms and ~7 MB of
    objects (``requests``, ``urllib3``, ``charset_normalizer``) in every command, which read and
    write local files only. laspy is written for its absence (its HTTP reading then says that
    ``requests`` is needed). Nothing is changed when either is imported already."""
    if "requests" not in sys.modules and "laspy" not in sys.modules:
        sys.modules["requests"] = None  # an import of it raises ModuleNotFoundError


def _one_blas_thread() -> None:
    """Let the BLAS libraries of NumPy and SciPy (OpenBLAS) start one thread, not one per core, in
    the ``forestreg`` process; a user's ``OPENBLAS_NUM_THREADS`` is kept. Does nothing once NumPy
    is imported (the variable is read when the library loads).

    The engine runs its own threads, one per core (:mod:`forestreg.engine.core.jit`), and its
    algebra is on 3 x 3 and N x 3 arrays, which OpenBLAS's threads do not speed up. Those threads
    start when NumPy and SciPy are imported and wait busily: measured, 0.25 s of CPU taken from
    the reading of the scans in every command. A/B in turns: the 3 M-point pair 3.56-3.87 ->
    3.49-3.76 s (5 runs each, 0.3 s less CPU); ``coregister`` 8.70-9.02 -> 8.62-8.84 s and
    ``trees`` of 2.9 M points the same, 26.8-27.8 vs 27.0-28.2 s (3 runs each); the peaks the same."""
    if "numpy" not in sys.modules:
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def _terminate_as_interrupt():
    """SIGTERM (a job service stopping a run) unwinds like Ctrl-C: temporary folders are removed
    and the exit code is 130. Both are latched (:data:`~forestreg.cli.common.INTERRUPTED`): the
    next progress step raises again should a library swallow the first KeyboardInterrupt. Returns
    the previous (SIGTERM, SIGINT) handlers (None off the main thread). A Ctrl-C ignored from the
    start (a command run with nohup or "&") stays ignored, unless ``FORESTREG_INTERRUPTIBLE=1``
    (set by the job service, which cancels its jobs with SIGINT); then its entry is None."""
    if threading.current_thread() is not threading.main_thread():
        return None
    INTERRUPTED.clear()
    _quiet_collateral_after_interrupt()

    current = signal.getsignal(signal.SIGINT)
    wanted = current is signal.default_int_handler or (
        current == signal.SIG_IGN and os.environ.get("FORESTREG_INTERRUPTIBLE") == "1"
    )
    previous_int = signal.signal(signal.SIGINT, _interrupt) if wanted else None
    return signal.signal(signal.SIGTERM, _interrupt), previous_int


#: seconds after which an interrupt that came inside Python's import machinery is delivered again
_IMPORT_RETRY_S = 0.02


def _interrupt(signum, frame) -> None:
    """The Ctrl-C / SIGTERM handler: latch the interrupt and raise KeyboardInterrupt.

    Not inside Python's import machinery (``importlib._bootstrap`` frames): an exception raised
    between its lock calls can leave the global import lock held, and the next import in any
    thread (a scan being read beside the engine's import) then waits forever, and the run with it.
    There the signal is sent again a moment later, until it lands in ordinary code."""
    INTERRUPTED.set()
    if frame is not None and frame.f_code.co_filename.startswith("<frozen importlib"):
        timer = threading.Timer(_IMPORT_RETRY_S, _deliver_again, (signum,))
        timer.daemon = True
        timer.start()
        return
    raise KeyboardInterrupt


def _deliver_again(signum: int) -> None:
    # only while the run still has this handler (the run may have ended meanwhile)
    if signal.getsignal(signum) is _interrupt:
        os.kill(os.getpid(), signum)


def _quiet_collateral_after_interrupt() -> None:
    """After Ctrl-C / SIGTERM, errors raised in a library's ``__del__`` go to the log, not stderr.

    The KeyboardInterrupt can land inside a library's constructor (llvmlite building a compiled
    kernel, for one); the half-built object's ``__del__`` then fails when it is collected and
    Python prints "Exception ignored in ..." with a traceback under the one-line "interrupted".
    Those are consequences of the interrupt, so they go to the ``forestreg`` logger at debug
    level. Without an interrupt, unraisable errors are printed as usual. Installed once a process;
    the previous hook is kept and called."""
    previous = sys.unraisablehook
    if getattr(previous, "_forestreg", False):
        return

    def hook(unraisable) -> None:
        if INTERRUPTED.is_set():
            logging.getLogger("forestreg").debug(
                "after the interrupt, ignored in %r: %s: %s",
                unraisable.object,
                type(unraisable.exc_value).__name__,
                unraisable.exc_value,
            )
            return
        previous(unraisable)

    hook._forestreg = True  # type: ignore[attr-defined]
    sys.unraisablehook = hook


def _wants_jsonl(argv: Sequence[str]) -> bool:
    return "--progress=jsonl" in argv or any(a == "--progress" and b == "jsonl" for a, b in zip(argv, argv[1:]))


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    if isinstance(exc, KeyError) and text.startswith(("'", '"')):
        text = text[1:-1]
    return " ".join(text.split())


def _error(message: str, prefix: str = "forestreg: error: ") -> None:
    print(f"{prefix}{message}", file=sys.stderr, flush=True)
