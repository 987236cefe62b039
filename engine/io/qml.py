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

__all__ = ["Rule", "fill", "line", "marker", "rule_style"]

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


def marker(colour: Colour, size_mm: float = 2.0, *, shape: str = "circle", outline: Colour = (35, 35, 35, 255),
           outline_mm: float = 0.2) -> Symbol:
    """A simple marker (``shape``: circle, square, triangle, star, cross, ...) of ``size_mm``."""
    return Symbol("marker", "SimpleMarker", (("color", _rgba(colour)), ("name", shape), ("outline_color", _rgba(outline)),
                                              ("outline_style", "solid"), ("outline_width", f"{outline_mm:g}"),
                                              ("outline_width_unit", "MM"), ("size", f"{size_mm:g}"), ("size_unit", "MM")))


def line(colour: Colour, width_mm: float = 0.5, *, style: str = "solid") -> Symbol:
    """A simple line (``style``: solid, dash, dot) ``width_mm`` wide."""
    return Symbol("line", "SimpleLine", (("line_color", _rgba(colour)), ("line_style", style), ("line_width", f"{width_mm:g}"),
                                         ("line_width_unit", "MM"), ("capstyle", "round"), ("joinstyle", "round")))


def fill(colour: Colour, outline: Colour = (35, 35, 35, 255), outline_mm: float = 0.3, *, outline_style: str = "solid",
         style: str = "solid") -> Symbol:
    """A simple fill (``style`` "no" for outline only) with an outline."""
    return Symbol("fill", "SimpleFill", (("color", _rgba(colour)), ("style", style), ("outline_color", _rgba(outline)),
                                         ("outline_style", outline_style), ("outline_width", f"{outline_mm:g}"),
                                         ("outline_width_unit", "MM"), ("joinstyle", "round")))


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
    return (f'<symbol type="{s.kind}" name={quoteattr(name)} alpha="1" clip_to_extent="1" force_rhr="0">'
            f'<layer class="{s.layer_class}" enabled="1" locked="0" pass="0"><Option type="Map">{options}</Option>{props}</layer>'
            "</symbol>")


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
    return ("<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>\n"
            '<qgis version="3.22.0" styleCategories="Symbology">'
            f'<renderer-v2 type="RuleRenderer" symbollevels="0" enableorderby="0" forceraster="0">'
            f'<rules key="{{{ns}}}">{"".join(rule_xml)}</rules><symbols>{symbols}</symbols></renderer-v2>'
            f"<layerGeometryType>{_GEOMETRY_TYPES[geometry]}</layerGeometryType></qgis>\n")
