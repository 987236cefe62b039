"""GeoPackage writing and reading (OGC 12-128r18, GeoPackage 1.2 vector features), with plain sqlite3.

Why this writer: a GeoPackage is an SQLite file with a few metadata tables and a small binary
header in front of each WKB geometry, all of it in the standard library's :mod:`sqlite3`. GDAL
(through pyogrio or fiona) would add a large native dependency for one small file per run; this
writer needs nothing beyond Python and numpy, writes 1,000 trees with their crown polygons in a few
hundredths of a second, and its files open in QGIS, GDAL/OGR and any other GeoPackage reader.

What is written (:func:`write_geopackage`):

* ``gpkg_spatial_ref_sys`` with the three rows the standard requires (EPSG:4326, the undefined
  Cartesian ``-1`` and geographic ``0``) and, for a known CRS, its row: ``srs_id`` the EPSG code
  (organization "EPSG"), or :data:`CUSTOM_SRS_ID` (organization "NONE") for a CRS without a single
  code (a compound of horizontal and vertical); ``definition`` the CRS's WKT1 (GDAL flavour), else
  its WKT2. Layers without a CRS use ``-1`` (local coordinates, metres);
* ``gpkg_contents`` (one ``features`` row per layer, with its extent) and ``gpkg_geometry_columns``;
* one feature table per layer: ``fid`` (integer primary key), ``geom`` (GeoPackage binary: the
  ``GP`` header, little-endian, with the x/y envelope, then little-endian ISO WKB: POINT,
  LINESTRING, POLYGON, each optionally Z) and the attribute columns (INTEGER, REAL, TEXT,
  BOOLEAN from the values; NaN and None as NULL);
* ``layer_styles``, the table QGIS reads a layer's default style from: one QML document per layer
  that has one (``useAsDefault`` 1).

The file is written to a temporary file beside the target and renamed onto it
(:func:`~forestreg.engine.core.atomic.atomic_path`): complete or absent, like every output.
:func:`read_layer` and :func:`decode_geometry` read a layer back (tests, scripts).
"""

from __future__ import annotations

import datetime
import math
import sqlite3
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import numpy as np

from ..core.atomic import atomic_path
from ..core.errors import ParameterError, ScanReadError, ScanWriteError

__all__ = [
    "CUSTOM_SRS_ID",
    "Layer",
    "decode_geometry",
    "encode_geometry",
    "layer_names",
    "read_layer",
    "srs_of",
    "write_geopackage",
]

#: ``srs_id`` of a CRS that has no single EPSG code (the first of GDAL's own range).
CUSTOM_SRS_ID = 100000
#: ``srs_id`` of local coordinates (the standard's undefined Cartesian SRS).
LOCAL_SRS_ID = -1
#: GeoPackage 1.2 (``PRAGMA user_version``) and its application id "GPKG".
_USER_VERSION = 10200
_APPLICATION_ID = 0x47504B47
_WKB_TYPES = {"POINT": 1, "LINESTRING": 2, "POLYGON": 3}
_GEOMETRY_NAMES = {v: k for k, v in _WKB_TYPES.items()}
#: GeoPackage binary flags: little-endian (bit 0), envelope [minx, maxx, miny, maxy] (bits 1-3 = 1)
_FLAGS_XY_ENVELOPE = 0b0000_0011
_FLAGS_EMPTY = 0b0001_0001


@dataclass(frozen=True)
class Layer:
    """One feature layer.

    ``name`` (the table; letters, digits and ``_``), ``geometry`` ("POINT", "LINESTRING" or
    "POLYGON"), ``columns`` (attribute names, in order), ``rows`` (one mapping per feature; a
    missing key is NULL), ``shapes`` (one per row: a point (2,) or (3,), a line (M, 2|3), a polygon's
    outer ring (M, 2|3), closed on writing; None for a feature without a geometry), all in the
    coordinates of the layer's CRS; ``z`` whether coordinates have a height; ``description``;
    ``style`` a QML document (``layer_styles``) or ""; ``types`` column -> SQL type where the values
    do not decide it (e.g. a column empty in every row)."""

    name: str
    geometry: str
    columns: Sequence[str]
    rows: Sequence[Mapping[str, Any]]
    shapes: Sequence[Optional[np.ndarray]]
    z: bool = False
    description: str = ""
    style: str = ""
    types: Mapping[str, str] = field(default_factory=dict)


# ----------------------------------------------------------------------------- geometry


def encode_geometry(kind: str, coords: Optional[np.ndarray], srs_id: int, z: bool) -> Optional[bytes]:
    """The GeoPackage binary of one geometry (``kind`` "POINT", "LINESTRING", "POLYGON";
    ``coords`` as :class:`Layer` ``shapes``), None for None; a point with NaN, or a line or polygon
    with too few points, is written as an empty geometry."""
    if coords is None:
        return None
    dim = 3 if z else 2
    code = _WKB_TYPES[kind] + (1000 if z else 0)
    c = np.asarray(coords, dtype="<f8")
    if kind == "POINT":
        c = c.reshape(-1)
        if len(c) < dim:
            c = np.concatenate([c, np.zeros(dim - len(c))])
        c = c[:dim]
        if not np.isfinite(c).all():
            return _empty(kind, srs_id, z)
        env = struct.pack("<4d", c[0], c[0], c[1], c[1])
        return (
            b"GP\x00"
            + bytes([_FLAGS_XY_ENVELOPE])
            + struct.pack("<i", srs_id)
            + env
            + struct.pack("<BI", 1, code)
            + c.tobytes()
        )
    c = c.reshape(len(c), -1)
    if c.shape[1] < dim:
        c = np.hstack([c, np.zeros((len(c), dim - c.shape[1]))])
    c = np.ascontiguousarray(c[:, :dim], dtype="<f8")
    c = c[np.isfinite(c).all(axis=1)]
    if kind == "POLYGON":
        if len(c) and not np.array_equal(c[0], c[-1]):
            c = np.vstack([c, c[:1]])
        if len(c) < 4:
            return _empty(kind, srs_id, z)
        body = struct.pack("<BIII", 1, code, 1, len(c)) + c.tobytes()
    else:
        if len(c) < 2:
            return _empty(kind, srs_id, z)
        body = struct.pack("<BII", 1, code, len(c)) + c.tobytes()
    env = struct.pack("<4d", c[:, 0].min(), c[:, 0].max(), c[:, 1].min(), c[:, 1].max())
    return b"GP\x00" + bytes([_FLAGS_XY_ENVELOPE]) + struct.pack("<i", srs_id) + env + body


def _empty(kind: str, srs_id: int, z: bool) -> bytes:
    """An empty geometry: no envelope, the empty flag; a point as NaN coordinates (the standard's
    encoding of an empty point)."""
    code = _WKB_TYPES[kind] + (1000 if z else 0)
    if kind == "POINT":
        body = struct.pack("<BI", 1, code) + np.full(3 if z else 2, np.nan).tobytes()
    else:
        body = struct.pack("<BII", 1, code, 0)
    return b"GP\x00" + bytes([_FLAGS_EMPTY]) + struct.pack("<i", srs_id) + body


_ENVELOPE_DOUBLES = {0: 0, 1: 4, 2: 6, 3: 6, 4: 8}


def decode_geometry(blob: Optional[bytes]) -> tuple[Optional[str], Optional[np.ndarray], Optional[int]]:
    """``(kind, coordinates, srs_id)`` of a GeoPackage binary geometry: "POINT" with a (D,) array,
    "LINESTRING" with (M, D), "POLYGON" with its outer ring (M, D) (closed, as stored); D is 2 or 3.
    ``(None, None, None)`` for NULL. Raises :class:`~forestreg.engine.core.errors.ScanReadError`
    for a blob that is not GeoPackage binary."""
    if blob is None:
        return None, None, None
    b = bytes(blob)
    if len(b) < 8 or b[:2] != b"GP":
        raise ScanReadError("not a GeoPackage geometry (no 'GP' header)")
    flags = b[3]
    order = "<" if flags & 1 else ">"
    srs_id = struct.unpack(order + "i", b[4:8])[0]
    envelope = (flags >> 1) & 0b111
    pos = 8 + 8 * _ENVELOPE_DOUBLES.get(envelope, 0)
    wkb_order = "<" if b[pos] == 1 else ">"
    code = struct.unpack(wkb_order + "I", b[pos + 1 : pos + 5])[0]
    pos += 5
    base, has_z = code % 1000, code // 1000 in (1, 3)
    dim = 3 if has_z else 2
    dt = np.dtype(wkb_order + "f8")
    kind = _GEOMETRY_NAMES.get(base)
    if kind == "POINT":
        return kind, np.frombuffer(b, dtype=dt, count=dim, offset=pos).astype(np.float64), srs_id
    if kind == "LINESTRING":
        n = struct.unpack(wkb_order + "I", b[pos : pos + 4])[0]
        return (
            kind,
            np.frombuffer(b, dtype=dt, count=n * dim, offset=pos + 4).reshape(n, dim).astype(np.float64),
            srs_id,
        )
    if kind == "POLYGON":
        rings = struct.unpack(wkb_order + "I", b[pos : pos + 4])[0]
        if rings == 0:
            return kind, np.zeros((0, dim)), srs_id
        n = struct.unpack(wkb_order + "I", b[pos + 4 : pos + 8])[0]
        return (
            kind,
            np.frombuffer(b, dtype=dt, count=n * dim, offset=pos + 8).reshape(n, dim).astype(np.float64),
            srs_id,
        )
    raise ScanReadError(f"unsupported WKB geometry type {code}")


# ----------------------------------------------------------------------------- writing


def srs_of(crs) -> tuple[int, Optional[tuple[str, str, int, str, str]]]:
    """The ``srs_id`` of a :class:`~forestreg.engine.io.crs.Crs` (None: :data:`LOCAL_SRS_ID`) and its
    ``gpkg_spatial_ref_sys`` row (srs_name, organization, organization_coordsys_id, definition,
    description), None for the local one (a row the standard requires anyway)."""
    if crs is None:
        return LOCAL_SRS_ID, None
    code = crs.epsg_code
    definition = crs.wkt1 or crs.wkt
    if code is not None:
        return code, (crs.name, "EPSG", code, definition, crs.label)
    return CUSTOM_SRS_ID, (crs.name, "NONE", CUSTOM_SRS_ID, definition, crs.label)


_WGS84_WKT = (
    'GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563,AUTHORITY["EPSG","7030"]],'
    'AUTHORITY["EPSG","6326"]],PRIMEM["Greenwich",0,AUTHORITY["EPSG","8901"]],UNIT["degree",0.0174532925199433,'
    'AUTHORITY["EPSG","9122"]],AXIS["Latitude",NORTH],AXIS["Longitude",EAST],AUTHORITY["EPSG","4326"]]'
)

_SCHEMA = """
CREATE TABLE gpkg_spatial_ref_sys (srs_name TEXT NOT NULL, srs_id INTEGER NOT NULL PRIMARY KEY, organization TEXT NOT NULL,
  organization_coordsys_id INTEGER NOT NULL, definition TEXT NOT NULL, description TEXT);
CREATE TABLE gpkg_contents (table_name TEXT NOT NULL PRIMARY KEY, data_type TEXT NOT NULL, identifier TEXT UNIQUE,
  description TEXT DEFAULT '', last_change DATETIME NOT NULL DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ','now')), min_x DOUBLE,
  min_y DOUBLE, max_x DOUBLE, max_y DOUBLE, srs_id INTEGER,
  CONSTRAINT fk_gc_r_srs_id FOREIGN KEY (srs_id) REFERENCES gpkg_spatial_ref_sys(srs_id));
CREATE TABLE gpkg_geometry_columns (table_name TEXT NOT NULL, column_name TEXT NOT NULL, geometry_type_name TEXT NOT NULL,
  srs_id INTEGER NOT NULL, z TINYINT NOT NULL, m TINYINT NOT NULL,
  CONSTRAINT pk_geom_cols PRIMARY KEY (table_name, column_name), CONSTRAINT uk_gc_table_name UNIQUE (table_name),
  CONSTRAINT fk_gc_tn FOREIGN KEY (table_name) REFERENCES gpkg_contents(table_name),
  CONSTRAINT fk_gc_srs FOREIGN KEY (srs_id) REFERENCES gpkg_spatial_ref_sys (srs_id));
CREATE TABLE layer_styles (id INTEGER PRIMARY KEY AUTOINCREMENT, f_table_catalog TEXT(256), f_table_schema TEXT(256),
  f_table_name TEXT(256), f_geometry_column TEXT(256), styleName TEXT(30), styleQML TEXT, styleSLD TEXT, useAsDefault BOOLEAN,
  description TEXT, owner TEXT(30), ui TEXT(30), update_time DATETIME DEFAULT (strftime('%Y-%m-%dT%H:%M:%fZ','now')));
"""


def _quote(name: str) -> str:
    return '"' + str(name).replace('"', '""') + '"'


def _cell(value: Any) -> Any:
    """A value as SQLite stores it: numpy scalars as Python numbers, NaN and None as NULL, booleans
    as 0/1, anything else as text."""
    if value is None:
        return None
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, (int, str)):
        return value
    return str(value)


def _column_type(values: Sequence[Any], given: Optional[str]) -> str:
    """The SQL type of a column: ``given``, else from its non-NULL values (BOOLEAN, INTEGER, REAL,
    TEXT); REAL when every value is NULL."""
    if given:
        return given
    kinds = set()
    for v in values:
        if v is None or (isinstance(v, (float, np.floating)) and not math.isfinite(float(v))):
            continue
        if isinstance(v, (bool, np.bool_)):
            kinds.add("BOOLEAN")
        elif isinstance(v, (int, np.integer)):
            kinds.add("INTEGER")
        elif isinstance(v, (float, np.floating)):
            kinds.add("REAL")
        else:
            kinds.add("TEXT")
    if not kinds:
        return "REAL"
    if len(kinds) == 1:
        return kinds.pop()
    if "TEXT" in kinds:
        return "TEXT"
    return "REAL" if "REAL" in kinds else "INTEGER"


def _check_layers(layers: Sequence[Layer]) -> None:
    names = set()
    for layer in layers:
        if (
            not layer.name
            or not all(ch.isalnum() or ch == "_" for ch in layer.name)
            or layer.name.lower().startswith(("gpkg_", "rtree_", "sqlite_"))
        ):
            raise ParameterError(f"layer name {layer.name!r}: use letters, digits and '_' (not gpkg_/rtree_/sqlite_)")
        if layer.name.lower() in names or layer.name.lower() == "layer_styles":
            raise ParameterError(f"layer {layer.name!r} is given twice (or is the styles table)")
        names.add(layer.name.lower())
        if layer.geometry not in _WKB_TYPES:
            raise ParameterError(
                f"layer {layer.name}: geometry must be one of {', '.join(_WKB_TYPES)}, got {layer.geometry!r}"
            )
        if len(layer.shapes) != len(layer.rows):
            raise ParameterError(f"layer {layer.name}: {len(layer.shapes)} shapes for {len(layer.rows)} rows")
        if {c.lower() for c in layer.columns} & {"fid", "geom"} or len({c.lower() for c in layer.columns}) != len(
            layer.columns
        ):
            raise ParameterError(f"layer {layer.name}: column names must be unique and not 'fid' or 'geom'")


def write_geopackage(path, layers: Sequence[Layer], crs=None) -> Path:
    """Write ``layers`` into the GeoPackage ``path`` (replaced as a whole, atomically), every layer
    in ``crs`` (a :class:`~forestreg.engine.io.crs.Crs`; None: local coordinates, ``srs_id`` -1).
    Returns the path. Raises :class:`~forestreg.engine.core.errors.ParameterError` for bad layers
    and :class:`~forestreg.engine.core.errors.ScanWriteError` when the file cannot be written."""
    target = Path(path)
    layers = list(layers)
    _check_layers(layers)
    srs_id, srs_row = srs_of(crs)
    now = _change_time()
    try:
        with atomic_path(target) as tmp:
            tmp.unlink(missing_ok=True)  # sqlite3 makes a new database at the empty name
            con = sqlite3.connect(str(tmp), isolation_level=None)
            try:
                _fill(con, layers, srs_id, srs_row, now)
            finally:
                con.close()
    except sqlite3.Error as exc:
        raise ScanWriteError(f"cannot write {target}: {exc}") from exc
    return target


def _change_time() -> str:
    """The GeoPackage's change times (``last_change``, ``update_time``): ``SOURCE_DATE_EPOCH``
    (seconds, UTC) when set, else 1970-01-01: the same inputs give the same bytes on every run,
    as every other output does."""
    import os

    try:
        seconds = int(os.environ.get("SOURCE_DATE_EPOCH", "0"))
    except ValueError:
        seconds = 0
    stamp = datetime.datetime.fromtimestamp(seconds, datetime.timezone.utc)
    return stamp.strftime("%Y-%m-%dT%H:%M:%S.") + "000Z"


def _fill(con: sqlite3.Connection, layers: Sequence[Layer], srs_id: int, srs_row, now: str) -> None:
    con.execute(f"PRAGMA application_id = {_APPLICATION_ID}")
    con.execute(f"PRAGMA user_version = {_USER_VERSION}")
    con.execute("PRAGMA journal_mode = OFF")  # the file is renamed into place only when complete
    con.execute("PRAGMA synchronous = OFF")
    con.execute("BEGIN")
    for statement in _SCHEMA.strip().split(";"):
        if statement.strip():
            con.execute(statement)
    srs = [
        (
            "WGS 84 geodetic",
            4326,
            "EPSG",
            4326,
            _WGS84_WKT,
            "longitude/latitude coordinates in decimal degrees on the WGS 84 spheroid",
        ),
        ("Undefined cartesian SRS", -1, "NONE", -1, "undefined", "undefined cartesian coordinate reference system"),
        ("Undefined geographic SRS", 0, "NONE", 0, "undefined", "undefined geographic coordinate reference system"),
    ]
    if srs_row is not None and srs_id not in (4326, -1, 0):
        name, org, org_id, definition, description = srs_row
        srs.append((name, srs_id, org, org_id, definition, description))
    con.executemany("INSERT INTO gpkg_spatial_ref_sys VALUES (?, ?, ?, ?, ?, ?)", srs)
    for layer in layers:
        _write_layer(con, layer, srs_id, now)
    styled = [layer for layer in layers if layer.style]
    con.execute(
        "INSERT INTO gpkg_contents (table_name, data_type, identifier, description, last_change, srs_id) "
        "VALUES ('layer_styles', 'attributes', 'layer_styles', 'QGIS layer styles (QML)', ?, NULL)",
        (now,),
    )
    con.executemany(
        "INSERT INTO layer_styles (f_table_catalog, f_table_schema, f_table_name, f_geometry_column, styleName, styleQML, "
        "styleSLD, useAsDefault, description, owner, ui, update_time) VALUES ('', '', ?, 'geom', ?, ?, '', 1, ?, '', '', ?)",
        [(layer.name, layer.name, layer.style, f"forestreg style of {layer.name}", now) for layer in styled],
    )
    con.execute("COMMIT")


def _write_layer(con: sqlite3.Connection, layer: Layer, srs_id: int, now: str) -> None:
    columns = list(layer.columns)
    rows = list(layer.rows)
    types = [_column_type([r.get(c) for r in rows], layer.types.get(c)) for c in columns]
    defs = ", ".join(f"{_quote(c)} {t}" for c, t in zip(columns, types))
    con.execute(
        f"CREATE TABLE {_quote(layer.name)} (fid INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, geom {layer.geometry}"
        + (f", {defs}" if defs else "")
        + ")"
    )
    blobs = [encode_geometry(layer.geometry, s, srs_id, layer.z) for s in layer.shapes]
    placeholders = ", ".join("?" for _ in range(len(columns) + 1))
    names = ", ".join(["geom", *(_quote(c) for c in columns)])
    con.executemany(
        f"INSERT INTO {_quote(layer.name)} ({names}) VALUES ({placeholders})",
        [(blob, *(_cell(r.get(c)) for c in columns)) for blob, r in zip(blobs, rows)],
    )
    extent = _extent([s for s in layer.shapes if s is not None])
    con.execute(
        "INSERT INTO gpkg_contents (table_name, data_type, identifier, description, last_change, min_x, min_y, max_x, max_y, srs_id) "
        "VALUES (?, 'features', ?, ?, ?, ?, ?, ?, ?, ?)",
        (layer.name, layer.name, layer.description, now, *extent, srs_id),
    )
    con.execute(
        "INSERT INTO gpkg_geometry_columns VALUES (?, 'geom', ?, ?, ?, 0)",
        (layer.name, layer.geometry, srs_id, 1 if layer.z else 0),
    )


def _extent(shapes: Sequence[np.ndarray]) -> tuple[Optional[float], ...]:
    """(min_x, min_y, max_x, max_y) of the shapes' finite coordinates, Nones without any."""
    parts = [
        np.asarray(s, dtype=np.float64).reshape(-1, np.asarray(s).shape[-1])[:, :2]
        for s in shapes
        if np.asarray(s).size
    ]
    xy = np.vstack(parts) if parts else np.zeros((0, 2))
    xy = xy[np.isfinite(xy).all(axis=1)]
    if not len(xy):
        return (None, None, None, None)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    return (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))


# ----------------------------------------------------------------------------- reading


def _connect(path) -> sqlite3.Connection:
    p = Path(path)
    if not p.is_file():
        raise ScanReadError(f"{p}: no such GeoPackage")
    try:
        return sqlite3.connect(f"file:{p}?mode=ro", uri=True)
    except sqlite3.Error as exc:
        raise ScanReadError(f"{p}: cannot be opened as a GeoPackage ({exc})") from exc


def layer_names(path) -> list[str]:
    """The feature layers of a GeoPackage, in the order of ``gpkg_contents``."""
    con = _connect(path)
    try:
        return [
            r[0]
            for r in con.execute("SELECT table_name FROM gpkg_contents WHERE data_type = 'features' ORDER BY rowid")
        ]
    except sqlite3.Error as exc:
        raise ScanReadError(f"{path}: not a GeoPackage ({exc})") from exc
    finally:
        con.close()


def read_layer(path, name: str) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """The features of layer ``name`` (each a dict of its columns, ``geom`` decoded to
    ``(kind, coordinates)`` as :func:`decode_geometry` gives them) and the layer's facts:
    ``geometry_type``, ``srs_id``, ``z``, ``organization``, ``organization_coordsys_id``,
    ``definition`` (the CRS's WKT, or "undefined") and ``extent`` (min_x, min_y, max_x, max_y)."""
    con = _connect(path)
    try:
        found = con.execute(
            "SELECT g.geometry_type_name, g.srs_id, g.z, s.organization, s.organization_coordsys_id, s.definition, "
            "c.min_x, c.min_y, c.max_x, c.max_y FROM gpkg_geometry_columns g JOIN gpkg_spatial_ref_sys s ON s.srs_id = g.srs_id "
            "JOIN gpkg_contents c ON c.table_name = g.table_name WHERE g.table_name = ?",
            (name,),
        ).fetchone()
        if found is None:
            raise ScanReadError(f"{path}: no feature layer {name!r}")
        cur = con.execute(f"SELECT * FROM {_quote(name)} ORDER BY fid")
        header = [d[0] for d in cur.description]
        rows = []
        for values in cur:
            row = dict(zip(header, values))
            kind, coords, _ = decode_geometry(row.get("geom"))
            row["geom"] = (kind, coords)
            rows.append(row)
    except sqlite3.Error as exc:
        raise ScanReadError(f"{path}: cannot read layer {name!r} ({exc})") from exc
    finally:
        con.close()
    facts = {
        "geometry_type": found[0],
        "srs_id": found[1],
        "z": bool(found[2]),
        "organization": found[3],
        "organization_coordsys_id": found[4],
        "definition": found[5],
        "extent": tuple(found[6:10]),
    }
    return rows, facts


def read_crs(path):
    """The CRS of a GeoPackage's feature layers (:class:`~forestreg.engine.io.crs.Crs`, from the
    first layer's ``gpkg_spatial_ref_sys`` row: its EPSG code, else its definition), None for local
    coordinates, no layer, or a file that is not a GeoPackage."""
    from .crs import as_crs, parse_crs

    try:
        con = _connect(path)
    except ScanReadError:
        return None
    try:
        found = con.execute(
            "SELECT s.srs_id, s.organization, s.organization_coordsys_id, s.definition FROM gpkg_geometry_columns g "
            "JOIN gpkg_spatial_ref_sys s ON s.srs_id = g.srs_id ORDER BY g.rowid LIMIT 1"
        ).fetchone()
    except sqlite3.Error:
        return None
    finally:
        con.close()
    if found is None or found[0] in (-1, 0) or str(found[3]).strip().lower() == "undefined":
        return None
    try:
        if str(found[1]).upper() == "EPSG":
            return parse_crs(f"EPSG:{int(found[2])}", str(path))
        return as_crs(str(found[3]), str(path))
    except Exception:  # noqa: BLE001 - a definition pyproj cannot read: local
        return None
