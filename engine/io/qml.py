"""QGIS layer styles (QML documents) for the layers of ``layers.gpkg``.

A style is a rule-based renderer (QGIS's ``RuleRenderer``): each :class:`Rule` has a filter
expression (QGIS expression syntax, ``""`` for every feature), a legend label and a symbol; every
rule whose filter holds draws its symbol, in order, so a later rule marks features on top of an
earlier one's (a red ring around flagged trees over their DBH class). The symbols carry their
settings both as ``<Option>`` maps (QGIS 3.20 and later) and as ``<prop>`` pairs (earlier QGIS 3).
Sizes and widths are in millimetres on the map. Colours are ``(r, g, b, alpha)``, 0-255.
"""

from __future__ import annotations

import uuid
from dataclasses import dataclass
from typing import Sequence
from xml.sax.saxutils import quoteattr

__all__ = ["Rule", "fill", "labelled", "line", "marker", "rule_style"]

Colour = tuple[int, int, int, int]

#: ``layerGeometryType`` of QML: 0 point, 1 line, 2 polygon.
_GEOMETRY_TYPES = {"POINT": 0, "LINESTRING": 1, "POLYGON": 2}


@dataclass(frozen=True)
class Symbol:
    """One symbol: ``kind`` ("marker", "line", "fill"), the QGIS symbol layer class and its settings."""

    kind: str
    layer_class: str
    props: tuple[tuple[str, str], ...]


def _rgba(c: Colour) -> str:
    return ",".join(str(int(v)) for v in c)


def marker(
    colour: Colour,
    size_mm: float = 2.0,
    *,
    shape: str = "circle",
    outline: Colour = (35, 35, 35, 255),
    outline_mm: float = 0.2,
) -> Symbol:
    """A simple marker (``shape``: circle, square, triangle, star, cross, ...) of ``size_mm``."""
    return Symbol(
        "marker",
        "SimpleMarker",
        (
            ("color", _rgba(colour)),
            ("name", shape),
            ("outline_color", _rgba(outline)),
            ("outline_style", "solid"),
            ("outline_width", f"{outline_mm:g}"),
            ("outline_width_unit", "MM"),
            ("size", f"{size_mm:g}"),
            ("size_unit", "MM"),
        ),
    )


def line(colour: Colour, width_mm: float = 0.5, *, style: str = "solid") -> Symbol:
    """A simple line (``style``: solid, dash, dot) ``width_mm`` wide."""
    return Symbol(
        "line",
        "SimpleLine",
        (
            ("line_color", _rgba(colour)),
            ("line_style", style),
            ("line_width", f"{width_mm:g}"),
            ("line_width_unit", "MM"),
            ("capstyle", "round"),
            ("joinstyle", "round"),
        ),
    )


def fill(
    colour: Colour,
    outline: Colour = (35, 35, 35, 255),
    outline_mm: float = 0.3,
    *,
    outline_style: str = "solid",
    style: str = "solid",
) -> Symbol:
    """A simple fill (``style`` "no" for outline only) with an outline."""
    return Symbol(
        "fill",
        "SimpleFill",
        (
            ("color", _rgba(colour)),
            ("style", style),
            ("outline_color", _rgba(outline)),
            ("outline_style", outline_style),
            ("outline_width", f"{outline_mm:g}"),
            ("outline_width_unit", "MM"),
            ("joinstyle", "round"),
        ),
    )


@dataclass(frozen=True)
class Rule:
    """A rule of a rule-based style: ``label`` in the legend, ``filter`` (a QGIS expression; ""
    for every feature), ``symbol``."""

    label: str
    filter: str
    symbol: Symbol


def _symbol_xml(name: str, s: Symbol) -> str:
    options = "".join(f'<Option type="QString" name={quoteattr(k)} value={quoteattr(v)}/>' for k, v in s.props)
    props = "".join(f"<prop k={quoteattr(k)} v={quoteattr(v)}/>" for k, v in s.props)
    return (
        f'<symbol type="{s.kind}" name={quoteattr(name)} alpha="1" clip_to_extent="1" force_rhr="0">'
        f'<layer class="{s.layer_class}" enabled="1" locked="0" pass="0"><Option type="Map">{options}</Option>{props}</layer>'
        "</symbol>"
    )


def rule_style(name: str, geometry: str, rules: Sequence[Rule]) -> str:
    """The QML document of a rule-based style for a layer ``name`` of ``geometry`` ("POINT",
    "LINESTRING", "POLYGON"); rule keys are derived from the layer's name and the rule's place, so
    the same layer gets the same document every time."""
    ns = uuid.uuid5(uuid.NAMESPACE_URL, f"forestreg:{name}")
    rule_xml = []
    for k, r in enumerate(rules):
        filt = f" filter={quoteattr(r.filter)}" if r.filter else ""
        rule_xml.append(f'<rule key="{{{uuid.uuid5(ns, str(k))}}}" symbol="{k}" label={quoteattr(r.label)}{filt}/>')
    symbols = "".join(_symbol_xml(str(k), r.symbol) for k, r in enumerate(rules))
    return (
        "<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>\n"
        '<qgis version="3.22.0" styleCategories="Symbology">'
        f'<renderer-v2 type="RuleRenderer" symbollevels="0" enableorderby="0" forceraster="0">'
        f'<rules key="{{{ns}}}">{"".join(rule_xml)}</rules><symbols>{symbols}</symbols></renderer-v2>'
        f"<layerGeometryType>{_GEOMETRY_TYPES[geometry]}</layerGeometryType></qgis>\n"
    )


def labelled(
    document: str,
    field: str,
    *,
    size_pt: float = 9.0,
    colour: Colour = (0, 0, 0, 255),
    bold: bool = True,
    buffer: Colour = (255, 255, 255, 255),
    buffer_mm: float = 0.8,
) -> str:
    """The style ``document`` (from :func:`rule_style`) with labels of the column ``field`` drawn
    over each point (QGIS "simple" labelling, placed over the point's centre): a marker numbered
    by its column. ``size_pt`` the text size in points, ``buffer`` a halo ``buffer_mm`` wide."""
    font = ' fontWeight="75" namedStyle="Bold"' if bold else ' fontWeight="50" namedStyle="Regular"'
    labeling = (
        '<labeling type="simple"><settings calloutType="simple">'
        f'<text-style fieldName={quoteattr(field)} isExpression="0" fontSize="{size_pt:g}" fontSizeUnit="Point"'
        f' textColor="{_rgba(colour)}" textOpacity="1"{font} fontItalic="0" fontUnderline="0" fontStrikeout="0"'
        ' multilineHeight="1" previewBkgrdColor="255,255,255,255">'
        f'<text-buffer bufferDraw="1" bufferSize="{buffer_mm:g}" bufferSizeUnits="MM" bufferColor="{_rgba(buffer)}"'
        ' bufferOpacity="1" bufferJoinStyle="128" bufferNoFill="1"/>'
        "</text-style>"
        '<text-format wrapChar="" multilineAlign="1" plussign="0" decimals="3" formatNumbers="0"/>'
        '<placement placement="1" quadOffset="4" xOffset="0" yOffset="0" offsetUnits="MM" offsetType="0" dist="0"'
        ' distUnits="MM" priority="10" placementFlags="10" rotationAngle="0"/>'
        '<rendering drawLabels="1" obstacle="0" displayAll="1" upsidedownLabels="0" limitNumLabels="0" labelPerPart="0"'
        ' mergeLines="0" scaleVisibility="0" fontLimitPixelSize="0" zIndex="1"/>'
        "</settings></labeling>"
    )
    document = document.replace(
        'styleCategories="Symbology"', 'styleCategories="Symbology|Labeling" labelsEnabled="1"', 1
    )
    head, tail = document.rsplit("<layerGeometryType>", 1)
    return f"{head}{labeling}<layerGeometryType>{tail}"
