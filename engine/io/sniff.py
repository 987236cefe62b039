"""Which format a file holds: by its first bytes, then by its suffix; and whether a text file is
a point list or a table of trees (:func:`is_tree_table`)."""

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
    raise ScanReadError(f"{path}: unknown scan format (not LAS/LAZ, PLY, PCD, E57 or a text point list)")


#: lines of a text file looked at by :func:`is_point_cloud_file`
_SNIFF_LINES = 50


def _head(path: Path, size: int = 8192) -> "bytes | None":
    """The first ``size`` bytes of a file, or None when it cannot be read."""
    try:
        with open(path, "rb") as fh:
            return fh.read(size)
    except OSError:
        return None


def is_point_cloud_file(path: Path) -> bool:
    """Whether a file is meant as a point cloud, by its content: a file whose first bytes name a
    point-cloud format (LAS/LAZ, PLY, PCD, E57), or whose suffix names a binary one (a damaged
    scan is still a scan: reading it says what is wrong), or a text file whose first data line
    holds three or more numbers under no header or a header naming x, y and z. A table of trees
    (:func:`is_tree_table`: ``tree_id,x,y,z,dbh_m``), notes, or anything unreadable is not."""
    path = Path(path)
    head = _head(path)
    if head is None:
        return False
    if sniff_bytes(head[:64]) is not None or format_from_suffix(path) in _BINARY_NAMES:
        return True
    if format_from_suffix(path) != "xyz" or not looks_like_text(head) or is_tree_table(path):
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


# ------------------------------------------------------------------------------------ tables

#: The delimiters a table may use, in the order a tie is decided.
TABLE_DELIMITERS = (",", ";", "\t")
#: Column names (normalised: :func:`column_key`) that only a table of trees has: a file whose
#: header names one of them is a table, never a point list (a tree id or a height can be a
#: point's attribute in a segmented or normalised cloud; a diameter or a species cannot).
TREE_TABLE_MARKERS = frozenset(
    {
        "dbh",
        "dbh_m",
        "dbh_cm",
        "dbh_mm",
        "diameter",
        "diameter_m",
        "diameter_cm",
        "diameter_mm",
        "crown_base_m",
        "crown_area_m2",
        "crown_volume_m3",
        "volume_m3",
        "species",
    }
)


def column_key(name: object) -> str:
    """A column name as tables are matched: no byte-order mark or surrounding space or quotes,
    lower case, spaces and dashes as underscores (``" DBH-cm"`` -> ``"dbh_cm"``)."""
    text = str(name).replace("\ufeff", "").strip().strip("\"'").strip().lower()
    return "_".join(text.replace("-", " ").split())


def table_delimiter(line: str) -> str:
    """The delimiter of a table's header line: the one of ``,`` ``;`` and tab it holds most of
    (a tie, or none, is ``,``)."""
    counts = [line.count(d) for d in TABLE_DELIMITERS]
    return TABLE_DELIMITERS[counts.index(max(counts))] if max(counts) > 0 else ","


def table_header(head: str) -> tuple[str, list[str]] | None:
    """``(delimiter, column names as written)`` of the first line of ``head`` that is neither
    blank nor a ``#`` comment, when it is a header (not every field a number); else None."""
    from .xyz import _is_number

    for line in head.lstrip("\ufeff").splitlines()[:_SNIFF_LINES]:
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        delimiter = table_delimiter(stripped)
        names = [n.strip().strip("\"'") for n in stripped.split(delimiter)]
        if all(_is_number(n) for n in names if n):
            return None
        return delimiter, names
    return None


def is_tree_table_header(names) -> bool:
    """Whether header names (as written, any case) are those of a table of trees: one names a
    tree's diameter, crown, volume or species (:data:`TREE_TABLE_MARKERS`), or x and y are there
    without z (a map of positions, not points)."""
    keys = {column_key(n) for n in names}
    return bool(keys & TREE_TABLE_MARKERS) or ({"x", "y"} <= keys and "z" not in keys)


def is_tree_table(path: Path) -> bool:
    """Whether a text file is a table of trees (``trees.csv`` of ``forestreg trees``, a field
    sheet): its header, in any case and delimited by ``,`` ``;`` or tab, names a tree's diameter
    (or crown, volume, species), or x and y without z (:func:`is_tree_table_header`). A point
    list, with or without an ``x y z`` header (also one with a tree id per point), binary data or
    an unreadable file is not."""
    path = Path(path)
    head = _head(path)
    if head is None:
        return False
    if sniff_bytes(head[:64]) is not None or not looks_like_text(head):
        return False
    found = table_header(head.decode("utf-8", errors="replace"))
    return found is not None and is_tree_table_header(found[1])
