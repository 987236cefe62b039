"""``forestreg serve`` (the job service) and ``forestreg batch`` (many plots on Dask)."""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from .common import say


def add_parsers(sub) -> None:
    p = sub.add_parser("serve", help="the local job service: queue, watch and cancel forestreg commands over HTTP/JSON")
    p.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to listen on (default 127.0.0.1; another one is reachable from other machines: a warning)",
    )
    p.add_argument(
        "--port", type=int, default=8754, help="port (default 8754; 0: a free port, written to STATE/server.json)"
    )
    p.add_argument(
        "--state",
        metavar="DIR",
        help="job store and token folder (default: $FORESTREG_SERVICE_DIR, else the user's data directory)",
    )
    p.add_argument("--workers", type=int, default=1, help="jobs run at once (default 1)")
    p.add_argument("--idle-exit", type=float, metavar="S", help="stop after S seconds without jobs or requests")
    p.set_defaults(func=cmd_serve, long_running=False)

    p = sub.add_parser("batch", help="process every plot folder of PLOTS_DIR on Dask (a local cluster, or --scheduler)")
    p.add_argument("plots_dir", help="one subfolder per plot (its scans; optional centre.txt, targets.csv)")
    p.add_argument("--out", required=True, help="output folder: OUT/<plot>/, summary.csv, index.html (a rerun resumes)")
    p.add_argument("--workers", type=int, help="local cluster worker processes (default: the number of cores)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="an existing Dask scheduler, e.g. tcp://host:8786")
    p.add_argument(
        "--command",
        choices=("plot", "trees", "coregister", "change"),
        default="plot",
        help="what to run per plot (default plot)",
    )
    p.add_argument(
        "--manifest",
        help="CSV naming each plot's inputs (plot,scans[,centre] / plot,cloud[,transform,field] / plot,ground,uav / plot,before,after)",
    )
    p.add_argument("--params", help="TOML parameter file passed to every plot")
    p.add_argument(
        "--extra",
        metavar="ARGS",
        help="more options for every plot's command, e.g. --extra='--no-cylinders --no-report'",
    )
    p.add_argument(
        "--threads",
        type=int,
        help="threads of each plot's process (default: the cores shared out among the local workers; 1 with --scheduler)",
    )
    p.add_argument(
        "--memory-limit",
        metavar="SIZE",
        help="memory per worker, e.g. 4GB: a plot whose processes hold more is stopped (an error row; "
        "their resident memory is sampled every 0.05 s, so a briefer spike passes and is noted in the row); "
        "also the local workers' Dask memory limit (default: none)",
    )
    p.set_defaults(func=cmd_batch, long_running=True)


def cmd_serve(args: argparse.Namespace) -> int:
    """The local job service (see :mod:`forestreg.service.app`)."""
    from ..engine.core.errors import UsageError

    try:
        from ..service.app import ServiceRunning, serve
        from ..service.jobs import use_parser
    except ImportError as exc:
        raise UsageError(f"the service needs FastAPI and uvicorn (pip install forestreg): {exc}") from None
    use_parser(args.build_parser)
    if args.workers < 1 or not 0 <= args.port < 65536:
        raise UsageError("--workers must be at least 1 and --port 0..65535")
    try:
        return serve(
            args.host,
            args.port,
            Path(args.state) if args.state else None,
            workers=args.workers,
            idle_exit_s=args.idle_exit,
        )
    except (ServiceRunning, OSError) as exc:
        raise UsageError(str(exc)) from None
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the service stopped cleanly (running jobs: interrupted)
        print("forestreg serve: stopped", file=sys.stderr)
        return 0


def cmd_batch(args: argparse.Namespace) -> int:
    """Many plots on Dask distributed (see :mod:`forestreg.service.batch`)."""
    from ..engine.core.errors import UsageError
    from ..service.batch import BatchInterrupted, run_batch
    from ..service.jobs import use_parser

    use_parser(args.build_parser)

    if args.workers is not None and args.workers < 1:
        raise UsageError("--workers must be at least 1")
    if args.threads is not None and args.threads < 1:
        raise UsageError("--threads must be at least 1")
    try:
        extra = shlex.split(args.extra or "")
    except ValueError as exc:
        raise UsageError(f"--extra: {exc}") from None
    memory_limit = 0
    if args.memory_limit:
        from dask.utils import parse_bytes

        try:
            memory_limit = int(parse_bytes(args.memory_limit))
        except (ValueError, TypeError):
            raise UsageError(f"--memory-limit {args.memory_limit!r}: give a size such as 4GB or 500MB") from None
        if memory_limit < 200_000_000:
            raise UsageError(
                f"--memory-limit {args.memory_limit}: at least 200MB (a plot's process alone needs about that)"
            )
    reporter = args.reporter
    try:
        outcome = run_batch(
            Path(args.plots_dir),
            Path(args.out),
            workers=args.workers,
            scheduler=args.scheduler,
            command=args.command,
            manifest=Path(args.manifest) if args.manifest else None,
            extra_args=(["--params", args.params] if args.params else []) + extra,
            progress=reporter,
            threads=args.threads,
            memory_limit=memory_limit,
        )
    except BatchInterrupted as exc:  # the finished plots are kept: say so (not "left as it was")
        reporter.close()
        reporter.done(str(exc))
        print(f"forestreg batch: {exc}", file=sys.stderr)
        return 130
    reporter.close()
    counts, resumed = outcome.counts(), outcome.resumed
    reporter.done("", outcome.summary)
    say(
        f"{len(outcome.rows)} plots: "
        + ", ".join(f"{n} {s}" for s, n in sorted(counts.items()))
        + (f" ({resumed} done before, skipped)" if resumed else "")
        + f", {outcome.seconds:.1f} s -> {outcome.summary}, {outcome.overview}",
        args,
    )
    if not outcome.succeeded:  # exit 0 only when every plot succeeded; the others are written
        bad = outcome.not_ok
        print(
            f"forestreg batch: {len(bad)} of {len(outcome.rows)} plots did not succeed ({', '.join(bad[:10])}"
            f"{', ...' if len(bad) > 10 else ''}): see the reasons in {outcome.summary}",
            file=sys.stderr,
        )
    return 0 if outcome.succeeded else 1
