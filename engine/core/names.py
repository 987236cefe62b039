"""Names a user gives that become file or folder names (batch plot names, a job's private folder).

One rule, checked in one place (:func:`safe_name`): such a name is one plain path component. It
can never climb out of the folder it is written into, replace a sibling, hide itself, or clash
with forestreg's own hidden files (``.forestreg-output``, ``.forestreg-tmp-*``, ``.forestreg-lock-*``,
``.forestreg-batch``). Refused:

- an empty name, or one of only spaces;
- ``.`` and ``..``, and any name starting with ``.``: a hidden file or folder, which a listing does
  not show and which could be taken for one of forestreg's own;
- a name holding ``/`` or ``\\`` (a path, on POSIX or Windows), ``:`` (a drive or a stream on
  Windows), a NUL byte or another control character (a newline, a tab, ...);
- an absolute path (covered by the rules above, named as such in the message);
- a name over :data:`MAX_NAME_BYTES` bytes in UTF-8 (file systems allow 255, and forestreg adds
  prefixes and suffixes such as ``.json`` to it).

Names of folders found on disk (a batch's plot folders) are one component already and are not
passed through it.
"""

from __future__ import annotations

import os
import unicodedata

from .errors import InvalidArgumentError

#: The longest name accepted, in bytes of UTF-8.
MAX_NAME_BYTES = 200


def name_problem(value: object) -> str:
    """Why ``value`` cannot be a file or folder name ("" when it can): see the module's rules."""
    if not isinstance(value, str):
        return f"is a {type(value).__name__}, not a text"
    if not value.strip():
        return "is empty: give a name"
    if value == ".":
        return "is the folder itself ('.'), not a name: give a plain name"
    if value == "..":
        return "is the parent folder ('..'), not a name: give a plain name"
    if (
        value.startswith(("/", "\\"))
        or os.path.isabs(value)
        or (len(value) > 2 and value[1] == ":" and value[0].isalpha() and value[2] in "/\\")
    ):
        return "is an absolute path: give one plain name (no folders)"
    if "\x00" in value:
        return "holds a NUL byte"
    if "/" in value or "\\" in value:
        return "holds '/' or '\\' (a path): give one plain name (no folders)"
    bad = next((c for c in value if unicodedata.category(c) == "Cc"), None)
    if bad is not None:
        return f"holds the control character {bad!r}"
    if ":" in value:
        return "holds ':' (a drive or a stream on Windows)"
    if value.startswith("."):
        return "starts with '.' (a hidden file or folder): give a name that starts otherwise"
    size = len(value.encode("utf-8", "surrogatepass"))
    if size > MAX_NAME_BYTES:
        return f"is {size} bytes long: at most {MAX_NAME_BYTES}"
    return ""


def safe_name(value: object, what: str = "name") -> str:
    """``value`` when it can be a file or folder name (one plain path component), else
    :class:`~forestreg.engine.core.errors.InvalidArgumentError` (bad input: exit 2 in the CLI)
    with one line naming ``what`` and the value, e.g. ``plot '../escape' holds a folder
    separator ...``."""
    problem = name_problem(value)
    if problem:
        shown = (
            repr(value)
            if isinstance(value, str) and len(value) <= 80
            else (repr(value[:77]) + "..." if isinstance(value, str) else "")
        )
        raise InvalidArgumentError(f"{what} {shown} {problem}".replace("  ", " "))
    return value  # type: ignore[return-value]


def same_name_key(value: str) -> str:
    """The key two names share when they would be one file on some file system: equal after
    Unicode normalisation (macOS stores NFD) and case folding (macOS and Windows ignore case)."""
    return unicodedata.normalize("NFC", value).casefold()


__all__ = ["MAX_NAME_BYTES", "name_problem", "safe_name", "same_name_key"]
