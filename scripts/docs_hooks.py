"""The documentation's references, generated from the code, and the MkDocs hook that adds them.

``mkdocs.yml`` names this file under ``hooks``: at every build :func:`on_files` adds three pages
that are never edited by hand,

- ``reference/cli.md``: every command, sub-command and option, read from the command line's own
  parser (:func:`forestreg.cli.build_parser`, and the desktop application's parser for ``gui``);
- ``reference/parameters.md``: every parameter with its default, unit, range, the paper's symbol
  and its help, read from the parameter classes (:class:`forestreg.engine.params.ProductParams`);
- ``reference/columns.md``: the columns of the CSV files the commands write, read from the
  column constants of the code, each with its description from :data:`COLUMN_HELP`.

A new option, parameter or column therefore shows up in the next build without a hand edit.
:func:`problems` lists what the references cannot document: an option or parameter without a
help text, a number without a unit, a column without a description. The build logs each as a
warning, so ``mkdocs build --strict`` fails on it, and ``tests/test_docs.py`` asserts the list
is empty.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
from typing import Any, Iterator

log = logging.getLogger("mkdocs.plugins.forestreg")

#: Pages generated at build time (path in the site -> function making its Markdown).
GENERATED = {
    "reference/cli.md": "cli_reference",
    "reference/parameters.md": "parameters_reference",
    "reference/columns.md": "columns_reference",
    "reference/api.md": "api_reference",
}

#: Options every command takes (documented once, at the top of the command reference).
GLOBAL_FLAGS = {"-v", "--verbose", "-q", "--quiet", "--progress", "-h", "--help", "--version"}


# ----------------------------------------------------------------------------- command line


def _gui_parser() -> argparse.ArgumentParser | None:
    try:
        from forestreg.ui.app import build_parser
    except ImportError:  # the GUI's extras absent: its options are left out, said on the page
        return None
    return build_parser()


def _subcommands(parser: argparse.ArgumentParser) -> list[tuple[str, str, argparse.ArgumentParser]]:
    """(name, help, parser) of each sub-command, in the parser's order."""
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help or "" for a in action._choices_actions}
            for name, sub in action.choices.items():
                out.append((name, helps.get(name, ""), sub))
    return out


def _option_rows(parser: argparse.ArgumentParser) -> Iterator[argparse.Action]:
    for action in parser._actions:
        if isinstance(action, (argparse._SubParsersAction, argparse._HelpAction, argparse._VersionAction)):
            continue
        if set(action.option_strings) & GLOBAL_FLAGS:
            continue
        yield action


def _cell(text: Any) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def _value(action: argparse.Action) -> str:
    if action.nargs == 0:
        return ""
    if action.choices:
        return " | ".join(f"`{c}`" for c in action.choices)
    if not action.option_strings and not action.choices:
        return ""
    metavar = action.metavar or action.dest.upper()
    if isinstance(metavar, tuple):
        metavar = " ".join(metavar)
    if action.nargs in ("+", "*", argparse.REMAINDER):
        metavar += " ..."
    return f"`{metavar}`"


def _default(action: argparse.Action) -> str:
    d = action.default
    if d is None or d is argparse.SUPPRESS or d is False or (action.nargs == 0 and d is not True) or d == []:
        return ""
    return f"`{d}`"


def _usage(parser: argparse.ArgumentParser) -> str:
    """The usage lines as ``--help`` prints them on a 100-column terminal (whatever the build's)."""
    import os

    before = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100"
    try:
        return parser.format_usage().strip()
    finally:
        if before is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = before


def _command_section(
    title: str, help_text: str, parser: argparse.ArgumentParser, issues: list[str], level: int = 2
) -> list[str]:
    lines = [f"{'#' * level} `{title}`", ""]
    if help_text:
        lines += [help_text[0].upper() + help_text[1:] + ("" if help_text.endswith(".") else "."), ""]
    else:
        issues.append(f"command '{title}' has no help text")
    usage = _usage(parser)
    usage = usage[len("usage: ") :] if usage.startswith("usage: ") else usage
    lines += ["```", usage, "```", ""]
    rows = list(_option_rows(parser))
    subs = _subcommands(parser)
    if rows:
        lines += ["| argument | value | default | what it does |", "|---|---|---|---|"]
        for a in rows:
            name = ", ".join(f"`{s}`" for s in a.option_strings) if a.option_strings else f"`{a.metavar or a.dest}`"
            if not (a.help or "").strip() or a.help is argparse.SUPPRESS:
                issues.append(f"'{title}': argument {name.replace('`', '')} has no help text")
            text = (a.help or "").replace("%(default)s", str(a.default))
            if a.required and a.option_strings:
                text = "required; " + text
            lines.append(f"| {name} | {_cell(_value(a))} | {_cell(_default(a))} | {_cell(text)} |")
        lines.append("")
    for name, sub_help, sub in subs:
        lines += _command_section(f"{title} {name}", sub_help, sub, issues, level + 1)
    return lines


def cli_reference(issues: list[str] | None = None) -> str:
    """The command reference in Markdown, from the command line's own parser."""
    from forestreg.cli import build_parser

    issues = [] if issues is None else issues
    parser = build_parser()
    lines = [
        "# Commands and options",
        "",
        "Generated from the command line's own parser at every build of this site: it lists",
        "exactly what `forestreg COMMAND --help` shows.",
        "",
        "Every command except `gui` also takes the global flags, before or after the command:",
        "",
        "| flag | what it does |",
        "|---|---|",
    ]
    for a in parser._actions:
        if set(a.option_strings) & GLOBAL_FLAGS and not set(a.option_strings) & {"--version"}:
            lines.append(f"| {', '.join(f'`{s}`' for s in a.option_strings)} | {_cell(a.help or '')} |")
    lines += [
        "",
        "Exit codes: `0` ok; `1` the data do not allow a result (the reason is printed and saved);",
        "`2` bad input or usage (one line on stderr); `130` interrupted (Ctrl-C or SIGTERM).",
        "`forestreg --version` prints the version.",
        "",
    ]
    for name, help_text, sub in _subcommands(parser):
        if name == "gui":
            gui = _gui_parser()
            if gui is None:
                lines += [
                    "## `forestreg gui`",
                    "",
                    help_text,
                    "",
                    "(The desktop application's options need the `gui` extra.)",
                    "",
                ]
                continue
            lines += _command_section("forestreg gui", help_text, gui, issues)
            continue
        lines += _command_section(f"forestreg {name}", help_text, sub, issues)
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- parameters


def _is_number(v: Any) -> bool:
    if isinstance(v, bool):
        return False
    if isinstance(v, (int, float)):
        return True
    return isinstance(v, tuple) and bool(v) and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)


def _fmt(v: Any) -> str:
    if v is None:
        return "automatic"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, tuple):
        return ", ".join(_fmt(x) for x in v) if v else "(none)"
    if isinstance(v, float) and v == int(v) and abs(v) < 1e6:
        return f"{v:.1f}"
    return str(v)


def _range(lo: Any, hi: Any) -> str:
    if lo is None and hi is None:
        return ""
    return f"{_fmt(lo) if lo is not None else '-inf'} to {_fmt(hi) if hi is not None else 'inf'}"


def _sections(params: Any, name: str) -> Iterator[tuple[str, type, list[tuple[dataclasses.Field, Any]]]]:
    """(section name, class, its own fields with their defaults) depth first, as the TOML file
    nests them; a nested set's defaults are those its field holds (a product's own ICP)."""
    from forestreg.engine.core.params import Params

    values = [(f, getattr(params, f.name)) for f in dataclasses.fields(params)]
    yield name, type(params), [(f, v) for f, v in values if not isinstance(v, Params)]
    for f, v in values:
        if isinstance(v, Params):
            yield from _sections(v, f"{name}.{f.name}")


def parameters_reference(issues: list[str] | None = None) -> str:
    """The parameter reference in Markdown, from the parameter classes."""
    from forestreg.engine.params import ProductParams

    issues = [] if issues is None else issues
    lines = [
        "# Parameters",
        "",
        "Generated from the parameter classes at every build of this site. Every command that has",
        "parameters reads one TOML file with `--params FILE`; a file sets only what it changes, and a",
        "misspelt name is refused with its section and the known names. `forestreg params` prints",
        "every value, `forestreg params --toml > my.toml` writes them all as a template (the same as",
        '`resources/default_params.toml`). From Python: `forestreg.load_params("my.toml")` or',
        "`forestreg.ProductParams()`, and `params.registration.replace(vop_radius_m=15.0)`.",
        "",
        "Units: `m` metres, `deg` degrees, `1` a dimensionless ratio, fraction or factor; a count",
        "names what it counts. *Paper* is the symbol and value in the method's paper where it gives",
        "one (Guan et al. 2020 for `[registration]`, Fekry et al. 2022 for the others).",
        "",
    ]
    defaults = ProductParams()
    for f in dataclasses.fields(ProductParams):
        for section, cls, own in _sections(getattr(defaults, f.name), f.name):
            if not own:
                continue
            doc = (cls.__doc__ or "").strip().split("\n\n")[0].replace("\n", " ")
            lines += [f"## `[{section}]`", ""]
            if doc and not doc.startswith(cls.__name__ + "("):
                lines += [doc, ""]
            lines += ["| name | default | unit | range | paper | what it sets |", "|---|---|---|---|---|---|"]
            for p, default in own:
                meta = p.metadata
                unit, help_text, paper = meta.get("unit", ""), meta.get("help", ""), meta.get("paper", "")
                lo, hi = meta.get("range", (None, None))
                if not help_text.strip():
                    issues.append(f"parameter [{section}] {p.name} has no help text")
                if (_is_number(default) or default is None) and not unit:
                    issues.append(f"parameter [{section}] {p.name} (a number) has no unit")
                lines.append(
                    f"| `{p.name}` | {_cell(_fmt(default))} | {_cell(unit)} | {_cell(_range(lo, hi))} | {_cell(paper)} | {_cell(help_text)} |"
                )
            lines.append("")
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- CSV columns

#: What each column of the CSV files means (the generated page fails the build for a column
#: missing here). Coordinates are in the file's own frame and unit unless said.
COLUMN_HELP: dict[str, str] = {
    # VOPs and keypoints
    "id": "running number of the point in this file",
    "x": "position, file coordinates",
    "y": "position, file coordinates",
    "z": "position, file coordinates",
    "radius_m": "estimated trunk radius at the slice, metres",
    "support_points": "slice points of the trunk's shadow edge that support the VOP",
    "matched_with": "id of the matched point in the other file (empty when unmatched)",
    "peak_z": "height of the cluster's density peak, file coordinates",
    "cluster_size": "canopy points in the keypoint's cluster",
    # targets
    "scan": "scan file name (without folder)",
    "target": "target id, the same for one target in every scan",
    # trees.csv
    "tree_id": "tree number within this inventory",
    "dbh_m": "diameter at breast height (1.3 m above the ground), metres; empty when not measured",
    "height_m": "tree height above the ground, metres: the tree's highest point, or the plot's height-diameter curve where that point is not the tree's top (see `height_source`)",
    "height_source": "where the height comes from: `points` (the tree's highest point) or `curve` (the plot's height-diameter curve at the DBH: the top was hidden or a neighbour's)",
    "height_points_m": "the tree's highest point above the ground, metres, whether or not it was taken as the height",
    "crown_base_m": "height of the live crown's base above the ground, metres",
    "crown_width_ew_m": "crown width east-west, metres",
    "crown_width_ns_m": "crown width north-south, metres",
    "crown_area_m2": "crown projection area, pi * a * b / 4, square metres",
    "crown_volume_m3": "crown volume, pi * CD^2 * CL / 8, cubic metres",
    "volume_m3": "wood volume of the cylinder model (stem and branches), cubic metres",
    "stem_volume_m3": "stem volume of the cylinder model, cubic metres",
    "branch_volume_m3": "branch volume of the cylinder model, cubic metres",
    "qsm_dbh_m": "diameter of the cylinder model at its breast height (`[trees.qsm] breast_height_m`, 1.3 m), metres",
    "n_cylinders": "cylinders in the tree's model",
    "n_branches": "branches in the tree's model",
    "lean_deg": "lean of the stem from the vertical, degrees",
    "dbh_arc_coverage": "fraction of the breast-height circle covered by points (0-1)",
    "dbh_rms_mm": "RMS distance of the breast-height points from the fitted circle, millimetres",
    "dbh_sigma_m": "1-sigma uncertainty of the DBH against the girth-equivalent diameter (perimeter / pi): the fit's noise and the part of the section not seen (a stem seen from one side may be oval), metres",
    "dbh_ovality": "ovality of the breast-height section (1 - minor / major axis), where the stem was seen around at least 70 % of it",
    "n_points": "points assigned to the tree",
    "wood_fraction": "fraction of the tree's points classed as wood (0-1)",
    "stem_form_factor": "stem volume / (basal area * height); outside the plausible bounds the volume is flagged",
    "source": "how the tree was found: `stem` (a stem in the cloud) or `canopy` (the canopy height model)",
    "dbh_quality": "how the DBH was obtained; trust `high`, `medium`, `low` or `none`",
    "height_quality": "how the height was obtained; trust `high`, `medium`, `low` or `none`",
    "crown_quality": "how the crown was obtained; trust `high`, `medium`, `low` or `none`",
    "volume_quality": "how the volume was obtained; trust `high`, `medium`, `low` or `none`",
    "flag": "why a value of this tree is doubtful (empty when none is)",
    # tree_changes.csv
    "tree_id_before": "the tree's `tree_id` in the BEFORE survey (empty when not found there)",
    "tree_id_after": "the tree's `tree_id` in the AFTER survey (empty when not found there)",
    "dbh_before_m": "DBH in the BEFORE survey, metres; empty when not measured",
    "dbh_after_m": "DBH in the AFTER survey, metres; empty when not measured",
    "dbh_change_m": "DBH growth (after minus before; paired stem sections 1.0-2.6 m where both clouds hold them), metres; empty where a survey cannot support it",
    "height_before_m": "tree height in the BEFORE survey, metres",
    "height_after_m": "tree height in the AFTER survey, metres",
    "height_change_m": "height growth (after minus before), metres; empty where a survey cannot support it (top unseen)",
    "dbh_before_sigma_m": "1-sigma uncertainty of `dbh_before_m`, metres",
    "dbh_after_sigma_m": "1-sigma uncertainty of `dbh_after_m`, metres",
    "dbh_change_sigma_m": "1-sigma uncertainty of `dbh_change_m`, metres",
    "height_before_sigma_m": "1-sigma uncertainty of `height_before_m`, metres",
    "height_after_sigma_m": "1-sigma uncertainty of `height_after_m`, metres",
    "height_change_sigma_m": "1-sigma uncertainty of `height_change_m`, metres",
    "match_distance_m": "distance between the tree's stems of the two surveys after the registration, metres",
    # batch summary
    "plot": "plot folder name",
    "status": "`ok`, `failed` (the data did not allow every result) or `error` (bad input, crash); in `tree_changes.csv`: `persisting`, `removed`, `new` or `outside` (the other survey did not cover the place)",
    "scans": "scans found in the plot folder",
    "registered": "scans registered",
    "seconds": "wall time of the plot, seconds",
    "reason": "why the plot failed or ended in error",
    "command": "the forestreg command run for the plot",
    "exit_code": "the command's exit code",
    "trees": "trees found (`--command trees`) or compared (`--command change`)",
    "worker": "the Dask worker that ran the plot",
    "resumed": "`true` when an earlier run's result was kept",
    "peak_mb": "peak memory of the plot's processes (the command and any process it started), MB",
    "cpu_s": "CPU time of the plot's processes (user + system), seconds",
    "threads": "threads each plot's process was given (`--threads`)",
    "attempts": "times the plot was started in this run (more than 1: its worker was lost and Dask ran it again)",
    "retried_after": "why the plot was started again: `worker lost (ADDRESS)` (the lost worker, in this run) or `an earlier batch stopped during the plot`; then `resumed with K of N links done` when the registered links were kept",
}


def _column_tables() -> list[tuple[str, str, tuple[str, ...]]]:
    """(file, where it comes from, columns) of every CSV the commands write."""
    from forestreg.engine.change.matching import CHANGE_COLUMNS
    from forestreg.engine.io.tables import KEYPOINT_COLUMNS, VOP_COLUMNS
    from forestreg.engine.tls.manual import CSV_COLUMNS
    from forestreg.engine.trees.inventory import TREE_COLUMNS
    from forestreg.service.batch import SUMMARY_FIELDS

    return [
        (
            "`reference_vops.csv`, `moving_vops.csv`",
            "`forestreg register`: the visual occlusion points (trunk axes at the slice) of each scan",
            tuple(VOP_COLUMNS),
        ),
        (
            "`keypoints_ground.csv`, `keypoints_uav.csv`",
            "`forestreg coregister`: the canopy keypoints of each cloud",
            tuple(KEYPOINT_COLUMNS),
        ),
        (
            "targets CSV",
            "`--targets` of `plot`, `compare`, `project create`; written by `forestreg targets`: one row per target and scan, coordinates in that scan's own frame",
            tuple(CSV_COLUMNS),
        ),
        (
            "`trees.csv`",
            "`forestreg trees`: one row per tree, positions in the cloud's file coordinates",
            tuple(TREE_COLUMNS),
        ),
        (
            "`tree_changes.csv`",
            "`forestreg change`: one row per tree of either survey, `x`, `y` in BEFORE's file coordinates",
            tuple(CHANGE_COLUMNS),
        ),
        ("`summary.csv`", "`forestreg batch`: one row per plot", tuple(SUMMARY_FIELDS)),
    ]


def columns_reference(issues: list[str] | None = None) -> str:
    """The CSV column reference in Markdown, from the code's column constants."""
    issues = [] if issues is None else issues
    lines = [
        "# CSV columns",
        "",
        "Generated from the code's column lists at every build of this site. The folders these files",
        "are written to, `result.json` and the frames are described in [outputs and frames](outputs.md).",
        "",
    ]
    for name, where, columns in _column_tables():
        lines += [f"## {name}", "", where[0].upper() + where[1:] + ".", "", "| column | meaning |", "|---|---|"]
        for c in columns:
            text = COLUMN_HELP.get(c, "")
            if not text:
                issues.append(
                    f"column '{c}' of {name.replace('`', '')} has no description in scripts/docs_hooks.py COLUMN_HELP"
                )
            lines.append(f"| `{c}` | {_cell(text)} |")
        lines.append("")
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- Python API

#: Headings of the API page, by the defining module's family.
API_GROUPS = (
    ("Scans, errors, progress", (".engine.core", ".engine.io", ".engine.terrain")),
    ("Parameters", (".engine.params",)),
    ("System A: pairs, plots, surveys, targets", (".engine.tls",)),
    ("System B: co-registration and fusion", (".engine.coreg",)),
    ("Trees and evaluation", (".engine.trees",)),
)


def api_reference(issues: list[str] | None = None) -> str:
    """The Python API page: every public name of ``forestreg`` (``forestreg.__all__``), rendered
    by mkdocstrings from its docstring, grouped by family, then the service's client."""
    import forestreg

    issues = [] if issues is None else issues
    lazy: dict[str, str] = dict(forestreg._LAZY)
    lines = [
        "# Python API",
        "",
        "Every public name of `forestreg` (`forestreg.__all__`), generated at every build from the",
        "docstrings. `import forestreg` is cheap and loads no Qt; each name is imported on first use.",
        "Conventions: metres, degrees; a matrix maps the moving (or ground-based) cloud's file",
        "coordinates onto the reference (or UAV) cloud's, `p_reference = matrix @ p_moving`.",
        "",
    ]
    seen: set[str] = set()
    for title, prefixes in API_GROUPS:
        names = [n for n in sorted(lazy, key=lambda n: (lazy[n], n)) if lazy[n].startswith(prefixes) and n not in seen]
        if not names:
            continue
        lines += [f"## {title}", ""]
        for name in names:
            seen.add(name)
            lines += [f"::: forestreg{lazy[name]}.{name}", "    options:", "      heading_level: 3", ""]
    rest = sorted(set(lazy) - seen)
    if rest:
        lines += ["## Other", ""]
        for name in rest:
            lines += [f"::: forestreg{lazy[name]}.{name}", "    options:", "      heading_level: 3", ""]
    lines += [
        "## The job service's client",
        "",
        "::: forestreg.client.connect",
        "    options:",
        "      heading_level: 3",
        "",
        "::: forestreg.client.Client",
        "    options:",
        "      heading_level: 3",
        "",
    ]
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- checks and hook


def problems() -> list[str]:
    """Everything the generated references cannot document (empty when all is documented)."""
    issues: list[str] = []
    for fn in GENERATED.values():
        globals()[fn](issues)
    return issues


def _nav_paths(nav: Any) -> set[str]:
    out: set[str] = set()
    if isinstance(nav, str):
        out.add(nav)
    elif isinstance(nav, dict):
        for v in nav.values():
            out |= _nav_paths(v)
    elif isinstance(nav, list):
        for v in nav:
            out |= _nav_paths(v)
    return out


def on_config(config, **kwargs):
    """MkDocs hook: a page of ``docs/`` that ``mkdocs.yml``'s nav does not name yet (one added
    beside the code, e.g. a design note) goes at the end of the nav, titled by its first heading,
    instead of failing the strict build as an omitted file."""
    from pathlib import Path

    nav = config.get("nav")
    if not nav:
        return config
    named = _nav_paths(nav) | set(GENERATED)
    docs = Path(config["docs_dir"])
    extra = []
    for path in sorted(docs.rglob("*.md")):
        rel = path.relative_to(docs).as_posix()
        if rel in named:
            continue
        title = next(
            (line[2:].strip() for line in path.read_text(encoding="utf-8").splitlines() if line.startswith("# ")), rel
        )
        extra.append({title: rel})
    nav.extend(extra)  # after the last page (architecture)
    return config


def on_files(files, config, **kwargs):
    """MkDocs hook: add the generated reference pages; each problem is a warning (fatal under
    ``--strict``)."""
    from mkdocs.structure.files import File

    issues: list[str] = []
    for path, fn in GENERATED.items():
        content = globals()[fn](issues)
        existing = files.get_file_from_path(path)
        if existing is not None:
            files.remove(existing)
        files.append(File.generated(config, path, content=content))
    for issue in issues:
        log.warning("reference: %s", issue)
    return files
