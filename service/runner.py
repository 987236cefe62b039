"""``python -m forestreg.service.runner ARGS``: run a CLI command with JSON-lines progress.

Used by the service only for a CLI that has no ``--progress jsonl`` option: it feeds the command's
progress callback into the same events the option writes (one JSON object per line on stderr)
and ends with ``{"event": "end", "exit_code": N, "message": ..., "result": ...}``.
"""

from __future__ import annotations

import json
import sys
from typing import Optional, Sequence


def _emit(event: dict) -> None:
    sys.stderr.write(json.dumps(event) + "\n")
    sys.stderr.flush()


class JsonLinesProgress:
    """Stands in for the CLI's progress bar: ``(fraction, message)`` -> a progress event."""

    def __init__(self, enabled: bool = True, desc: str = "") -> None:
        self.step = desc

    def __call__(self, fraction: float, message: str) -> None:
        _emit({"event": "progress", "step": self.step, "fraction": min(max(float(fraction), 0.0), 1.0), "message": str(message)})

    def close(self) -> None:
        pass


def main(argv: Optional[Sequence[str]] = None) -> int:
    from .. import cli
    from .jobs import guess_result

    args = list(sys.argv[1:] if argv is None else argv)
    if hasattr(cli, "ProgressBar"):
        cli.ProgressBar = JsonLinesProgress  # type: ignore[attr-defined]
    message = ""
    try:
        code = cli.main(args)
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 2
    except KeyboardInterrupt:
        code, message = 130, "cancelled"
    except Exception as exc:  # a crash: one line for the job, the traceback in the log
        import traceback

        traceback.print_exc()
        code, message = 3, f"{type(exc).__name__}: {exc}"
    _emit({"event": "end", "exit_code": int(code or 0), "message": message, "result": guess_result(args)})
    return int(code or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
