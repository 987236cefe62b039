"""Which format a file holds: by its first bytes, then by its suffix."""

from __future__ import annotations

from pathlib import Path

from ..core.errors import ScanReadError

#: format name -> suffixes read as that format when the content does not say otherwise
READ_SUFFIXES: dict[str, tuple[str, ...]] = {
    "las": (".las", ".laz"),
    "ply": (".ply",),
    "pcd": (".pcd",),
    "e57": (".e57",),
    "xyz": (".xyz", ".txt", ".csv", ".pts", ".asc"),
}

#: Formats recognised by magic bytes; a file with such a suffix but other content is an error.
_BINARY_NAMES = {"las": "LAS/LAZ", "ply": "PLY", "pcd": "PCD", "e57": "E57"}
_MAGIC_HINT = {
    "las": "it does not start with 'LASF'",
    "ply": "it does not start with 'ply'",
    "pcd": "it has no PCD header",
    "e57": "it does not start with 'ASTM-E57'",
}


def sniff_bytes(head: bytes) -> str | None:
    """Return the format named by the first bytes of a file, or ``None`` if they say nothing."""
    if head.startswith(b"LASF"):
        return "las"
    if head.startswith(b"ASTM-E57"):
        return "e57"
    if head[:4] in (b"ply\n", b"ply\r", b"ply ") or head.rstrip() == b"ply":
        return "ply"
    stripped = head.lstrip(b"\xef\xbb\xbf")
    if stripped.startswith(b"# .PCD") or stripped.startswith(b"VERSION"):
        return "pcd"
    return None


def format_from_suffix(path: Path) -> str | None:
    """Return the format a suffix stands for, or ``None``."""
    suffix = path.suffix.lower()
    for fmt, suffixes in READ_SUFFIXES.items():
        if suffix in suffixes:
            return fmt
    return None


def looks_like_text(head: bytes) -> bool:
    """True if the first bytes look like text (no NUL bytes, mostly printable)."""
    if not head or b"\x00" in head:
        return False
    sample = head[:4096]
    printable = sum(1 for b in sample if b in (9, 10, 13) or 32 <= b < 127 or b >= 128)
    return printable >= 0.98 * len(sample)


def detect_format(path: Path) -> str:
    """Return the format of an existing, non-empty file: ``las``, ``ply``, ``pcd``, ``e57`` or ``xyz``.

    The content decides (magic bytes); the suffix is used only when the content says nothing,
    i.e. for ASCII text.

    Raises
    ------
    ScanReadError
        The content does not match its binary suffix, or the format is unknown.
    """
    try:
        with open(path, "rb") as fh:
            head = fh.read(64)
            more = head + fh.read(4096 - len(head))
    except OSError as exc:
        raise ScanReadError(f"{path}: cannot be read ({exc.strerror or exc})") from exc
    fmt = sniff_bytes(head)
    if fmt is not None:
        return fmt
    by_suffix = format_from_suffix(path)
    if by_suffix in _BINARY_NAMES:
        raise ScanReadError(
            f"{path}: is not a valid {_BINARY_NAMES[by_suffix]} file ({_MAGIC_HINT[by_suffix]}); "
            "the file is corrupt or has the wrong suffix"
        )
    if by_suffix == "xyz" or looks_like_text(more):
        if not looks_like_text(more):
            raise ScanReadError(f"{path}: is binary data, not a text point list")
        return "xyz"
    raise ScanReadError(
        f"{path}: unknown scan format (not LAS/LAZ, PLY, PCD, E57 or a text point list)"
    )


#: lines of a text file looked at by :func:`is_point_cloud_file`
_SNIFF_LINES = 50


def is_point_cloud_file(path: Path) -> bool:
    """Whether a file is meant as a point cloud, by its content: a file whose first bytes name a
    point-cloud format (LAS/LAZ, PLY, PCD, E57), or whose suffix names a binary one (a damaged
    scan is still a scan: reading it says what is wrong), or a text file whose first data line
    holds three or more numbers under no header or a header naming x, y and z. A table of other
    columns (``tree_id,x,y,dbh_m``), notes, or anything unreadable is not."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(8192)
    except OSError:
        return False
    if sniff_bytes(head[:64]) is not None or format_from_suffix(path) in _BINARY_NAMES:
        return True
    if format_from_suffix(path) != "xyz" or not looks_like_text(head):
        return False
    from .xyz import _is_number, _words

    header: list[str] = []
    for line in head.decode("latin-1").splitlines()[:_SNIFF_LINES]:
        stripped = line.strip()
        if not stripped:
            continue
        words = _words(stripped)
        if len(words) >= 3 and all(_is_number(w) for w in words):
            names = {h.lower() for h in header}
            return not header or {"x", "y", "z"} <= names
        header = words
    return False
