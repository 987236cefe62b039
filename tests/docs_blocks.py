"""The code blocks of README.md and docs/: found, classified, turned into runs, and the sample data
they run on (used by ``tests/test_docs_examples.py``).

Classification (what a writer sees in the Markdown)
---------------------------------------------------
An *example* is a fenced block whose language is a shell (``bash``, ``sh``, ``shell``,
``console``), Python (``python``, ``py``), or none. An HTML comment on the line right before its
fence decides what the tests do with it::

    <!-- docs-test: skip REASON -->           not run (installation, GUI, QGIS, a cluster, ...)
    <!-- docs-test: output -->                printed output, not a command
    <!-- docs-test: output demo -->           the printed lines of `forestreg demo`: their format is
                                              checked against a demo run's output folder
    <!-- docs-test: run [exit=N] [creates=PATH,...] [service] [timeout=S] -->

Without a comment, a shell block made only of ``forestreg ...`` commands, and a Python block, are
run (the default decision). Every other example (an unlabelled block, another program, or a line
that installs, opens a window, starts a server, needs a cluster, or reads like a synopsis) must
carry a comment: the tests fail for it, naming what to decide.

A run happens in a new folder holding the sample data (:func:`make_sample_data`). Each command
must end with exit status 0 (or ``exit=N``), and what it promises must exist afterwards: the
``--out``, ``--merged``, ``--registered-dir`` and ``--e57-out`` paths and ``> FILE`` of every
``forestreg`` command, the ``"--out", "DIR"`` of a command list in Python, the paths a comment of
the block names inside one of those folders (``# pair/result.json, pair/transform.txt``), and
``creates=``. ``service``: a job service runs in the private home folder before the block.
"""

from __future__ import annotations

import csv
import io
import re
import shlex
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

ROOT = Path(__file__).resolve().parents[1]

SHELL = {"bash", "sh", "shell", "console", "zsh"}
PYTHON = {"python", "py", "python3"}
MARKER = re.compile(r"^\s*<!--\s*docs-test:\s*(.*?)\s*-->\s*$")
FENCE = re.compile(r"^(?P<indent>\s*)(?P<fence>`{3,}|~{3,})\s*(?P<info>[^`\s]*)[^`]*$")

#: Lines that need a writer's decision, with what they are. A block matching one of these and
#: carrying no comment fails (the default "run" does not apply to it).
NEEDS_DECISION = (
    (
        re.compile(r"\bpip3? install\b|\bsetup\.sh\b|\bapt(-get)?\b|\bpython3? -m (build|venv)\b|\bforestreg warmup\b"),
        "installation",
    ),
    (re.compile(r"\bmkdocs\b"), "the documentation site"),
    (re.compile(r"\bforestreg gui\b"), "the desktop GUI"),
    (re.compile(r"\bforestreg serve\b"), "a server that runs until stopped"),
    (re.compile(r"CloudCompare|\bqgis\b|package_qgis", re.I), "a host application"),
    (re.compile(r"tcp://|\bdask (scheduler|worker)\b|dask_jobqueue|SLURM|PBS"), "a cluster"),
    (re.compile(r"\bbenchmarks[/.]"), "a benchmark"),
    (re.compile(r"\[--|\bSCAN \.\.\.|\bPLOTS_DIR\b|--out (DIR|OUT)\b"), "a synopsis (placeholders, [options])"),
)

#: Options of ``forestreg`` commands whose value is a path the command writes.
OUTPUT_OPTIONS = ("--out", "--merged", "--registered-dir", "--e57-out")

#: Data variants: before a command that matches, the files of ``variants/<name>/`` replace those of
#: the same names in the run's folder (the docs use ``a.laz`` / ``b.laz`` for files in mm and for
#: georeferenced files).
VARIANTS = (
    (re.compile(r"--units mm\b"), "mm"),
    (re.compile(r"--scanner-position 512301\.2,5401220\.7,310\.4\b"), "utm"),
)


class ClassificationError(Exception):
    """An example without a decision, or a comment the harness does not understand."""


@dataclass(frozen=True)
class Block:
    path: str  # relative to the repository root
    line: int  # of the opening fence, 1-based
    language: str
    text: str  # dedented to the fence's indentation
    marker: Optional[str]  # the text after "docs-test:", or None

    @property
    def id(self) -> str:
        return f"{self.path}:{self.line}"

    @property
    def is_example(self) -> bool:
        return self.language in SHELL or self.language in PYTHON or self.language == ""


@dataclass
class Decision:
    kind: str  # "run", "skip", "output"
    reason: str = ""
    exit_codes: tuple[int, ...] = (0,)
    creates: tuple[str, ...] = ()
    service: bool = False
    timeout: float = 600.0
    demo: bool = False
    implicit: bool = False


def markdown_files(root: Path = ROOT) -> list[Path]:
    return [root / "README.md"] + sorted((root / "docs").rglob("*.md"))


def blocks_of(path: Path, root: Path = ROOT) -> list[Block]:
    """Every fenced block of a Markdown file, with the docs-test comment right before it."""
    lines = path.read_text(encoding="utf-8").splitlines()
    out: list[Block] = []
    k = 0
    while k < len(lines):
        m = FENCE.match(lines[k])
        if not m:
            k += 1
            continue
        indent, fence, info = len(m["indent"]), m["fence"], m["info"].lower()
        end = k + 1
        while end < len(lines) and not re.match(rf"^\s*{re.escape(fence[0])}{{{len(fence)},}}\s*$", lines[end]):
            end += 1
        body = [line[indent:] if line[:indent].strip() == "" else line.lstrip() for line in lines[k + 1 : end]]
        before = k - 1
        while before >= 0 and not lines[before].strip():
            before -= 1
        mark = MARKER.match(lines[before]) if before >= 0 else None
        out.append(
            Block(str(path.relative_to(root)), k + 1, info, "\n".join(body) + "\n", mark.group(1) if mark else None)
        )
        k = end + 1
    return out


def examples(root: Path = ROOT) -> list[Block]:
    return [b for f in markdown_files(root) for b in blocks_of(f, root) if b.is_example]


def shell_text(block: Block) -> str:
    """The shell code of a block: a ``console`` block's prompt lines (``$ `` taken off, with their
    continuation lines), the printed lines between them left out; any other block as it is."""
    if block.language != "console":
        return block.text
    kept, going = [], False
    for line in block.text.splitlines():
        if line.startswith("$ ") or going:
            kept.append(line[2:] if line.startswith("$ ") and not going else line)
            going = line.rstrip().endswith("\\")
    return "\n".join(kept) + "\n"


def commands_of(text: str) -> list[str]:
    """A shell block's commands: continuation lines joined, blank and comment lines left out
    (a command keeps its trailing comment)."""
    out: list[str] = []
    current = ""
    for line in text.splitlines():
        if not current and (not line.strip() or line.lstrip().startswith("#")):
            continue
        if line.rstrip().endswith("\\"):
            current += line.rstrip()[:-1].strip() + " "
            continue
        out.append(current + line.strip())
        current = ""
    if current.strip():
        out.append(current.strip())
    return out


def parse_marker(text: str) -> Decision:
    words = text.split()
    if not words:
        raise ClassificationError("empty docs-test comment: write 'run', 'skip REASON' or 'output'")
    kind, rest = words[0], words[1:]
    if kind == "skip":
        if not rest:
            raise ClassificationError(
                "'docs-test: skip' needs a reason, e.g. <!-- docs-test: skip (the desktop GUI) -->"
            )
        return Decision("skip", reason=" ".join(rest))
    if kind == "output":
        if rest not in ([], ["demo"]):
            raise ClassificationError(f"'docs-test: output' takes only 'demo', not {' '.join(rest)!r}")
        return Decision("output", demo=rest == ["demo"])
    if kind == "run":
        d = Decision("run")
        for word in rest:
            key, eq, value = word.partition("=")
            if key == "exit" and eq:
                d.exit_codes = tuple(int(v) for v in value.split(","))
            elif key == "creates" and eq:
                d.creates = tuple(v for v in value.split(",") if v)
            elif key == "timeout" and eq:
                d.timeout = float(value)
            elif word == "service":
                d.service = True
            else:
                raise ClassificationError(
                    f"'docs-test: run' does not know {word!r} (exit=N, creates=PATH,..., service, timeout=S)"
                )
        return d
    raise ClassificationError(f"docs-test comment {text!r}: the first word must be run, skip or output")


def undecided(block: Block) -> list[str]:
    """Why a block cannot take the default decision (empty: it can)."""
    reasons = [what for pattern, what in NEEDS_DECISION if pattern.search(block.text)]
    if block.language == "":
        reasons.append("an unlabelled block (output, a synopsis or text?)")
    elif block.language in SHELL:
        others = sorted({c.split()[0] for c in commands_of(shell_text(block)) if c.split()[0] != "forestreg"})
        if others:
            reasons.append(f"commands other than forestreg ({', '.join(others)})")
    return reasons


def decide(block: Block) -> Decision:
    """The block's decision: its comment, else the default (run), else :class:`ClassificationError`."""
    if block.marker is not None:
        return parse_marker(block.marker)
    reasons = undecided(block)
    if reasons:
        raise ClassificationError(
            f"{block.id}: this example has no docs-test decision and cannot be run as it is ({'; '.join(dict.fromkeys(reasons))}). "
            "Put a comment on the line before its fence: <!-- docs-test: skip REASON -->, <!-- docs-test: output --> "
            "or <!-- docs-test: run ... --> (see tests/docs_blocks.py)"
        )
    return Decision("run", implicit=True)


# ----------------------------------------------------------------------------- what a block promises


def outputs_of_command(command: str) -> list[str]:
    """The paths a ``forestreg`` command (or ``... > FILE``) writes."""
    try:
        words = shlex.split(command, comments=True)
    except ValueError:
        return []
    out: list[str] = []
    for k, w in enumerate(words):
        name, eq, value = w.partition("=")
        if name in OUTPUT_OPTIONS:
            target = value if eq else (words[k + 1] if k + 1 < len(words) else "")
            if target and "forestreg" in words[:1] + words[:2]:
                out.append(target)
        if w == ">" and k + 1 < len(words):
            out.append(words[k + 1])
    return out


PY_OUT = re.compile(r"""["']--out["']\s*,\s*["']([^"']+)["']""")
PATH_IN_COMMENT = re.compile(r"(?<![\w/.~$-])((?:[\w.-]+/)+[\w.-]+\.\w+)")


def promised_paths(block: Block, decision: Decision) -> list[str]:
    """Everything the block promises to write, relative to its folder."""
    if block.language in PYTHON:
        outs = PY_OUT.findall(block.text)
    else:
        outs = [p for c in commands_of(shell_text(block)) for p in outputs_of_command(c)]
    tops = {Path(p).parts[0] for p in outs if not Path(p).is_absolute()}
    named: list[str] = []
    for line in block.text.splitlines():
        if "#" in line:
            comment = line.split("#", 1)[1]
            named += [p for p in PATH_IN_COMMENT.findall(comment) if Path(p).parts[0] in tops]
    return list(dict.fromkeys(outs + named + list(decision.creates)))


# ----------------------------------------------------------------------------- the run


def shell_script(block: Block, rc_file: Path, data: Path) -> str:
    """A bash script running the block's commands in order in one shell (variables carry over),
    each announced on stderr and its exit status appended to ``rc_file``."""
    lines = []
    for command in commands_of(shell_text(block)):
        for pattern, variant in VARIANTS:
            if pattern.search(command):
                lines.append(
                    f"printf '%s\\n' {shlex.quote(f'[docs-test] the files of sample variant {variant!r} for the next command')} >&2"
                )
                lines.append(f"cp -f {shlex.quote(str(data / 'variants' / variant))}/* .")
        lines.append(f"printf '\\n%s\\n' {shlex.quote('[docs-test] $ ' + command)} >&2")
        lines.append(command)
        lines.append(f"echo $? >> {shlex.quote(str(rc_file))}")
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- the demo's printed lines

NUMBER = re.compile(r"(?<![\w.])-?\d[\d,]*(?:\.\d+)?")


def line_shape(line: str) -> str:
    """A printed line with its numbers replaced by ``#`` (the format, not the figures)."""
    return NUMBER.sub("#", line.strip())


def shapes_agree(documented: str, printed: str) -> bool:
    """A documented line agrees with a printed one when their shapes are equal; a documented line
    ending in ``...`` need only begin like the printed one."""
    doc, out = line_shape(documented), line_shape(printed)
    if doc.endswith("..."):
        head = doc[:-3].rstrip().rstrip(",;")
        return out.startswith(head)
    return doc == out


def shape_key(line: str) -> str:
    """What pairs a documented line with a printed one: its first three words' shape."""
    return " ".join(line_shape(line).split()[:3])


# ----------------------------------------------------------------------------- the sample data

UTM_FIRST_SCANNER = (512301.2, 5401220.7, 310.4)  # docs/guide/cli.md: --scanner-position of a.laz
SECOND_SCANNER_OFFSET = (9.8, 4.4)  # ... and of b.laz: 512311.0,5401225.1 (10.7 m away)


def make_sample_data(folder: Path) -> dict:
    """Write the files the examples name into ``folder`` (about 10 s, 25 MB); returns what was
    simulated (the true poses) for the record.

    - ``scan1.laz``, ``scan2.laz`` (and ``A.laz``, ``B.laz``, ``a.laz``, ``b.laz``): two scans of a
      simulated conifer plot 10.7 m apart; ``scans/`` the plot's three scans; ``utm/`` the same three
      scans (each in its scanner's coordinates) with ``gnss.csv`` (``scan,x,y,z,heading_deg`` in
      UTM, 0.3 m and 2 deg off); ``plots/plot1``, ``plots/plot2``: two plots of two scans each;
      ``variants/mm``: ``a.laz``, ``b.laz`` in millimetres; ``variants/utm``: ``a.laz``, ``b.laz``
      georeferenced, their scanners at the positions docs/guide/cli.md gives;
    - ``backpack.laz`` (merged TLS scans, turned 120 deg and shifted), ``uav.laz``, ``field.csv``
      and ``fused.laz`` (both fused with the true transform): a 24 m plot;
    - ``plot_2021.laz``, ``plot_2026.laz``: a simulated re-survey five years later in another frame;
      ``trees_2021/trees.csv``, ``trees_2026/trees.csv``: its trees as tables, also as
      ``trees_2026.csv`` and ``trees_2016.csv`` (the earlier table, positions in feet);
    - ``params.toml``: every parameter at its default.
    """
    import json
    import shutil

    import numpy as np

    from forestreg.app.fusion import fuse_clouds
    from forestreg.app.simulation import simulated_coregistration
    from forestreg.engine.core.scan import Scan
    from forestreg.engine.io import read_scan, write_scan
    from forestreg.engine.io.simulated import write_resurvey, write_simulated_plot
    from forestreg.engine.params import params_toml
    from forestreg.engine.simulate import simulate_plot
    from forestreg.engine.simulate.resurvey import simulate_resurvey

    folder = Path(folder)
    work = folder / ".generated"
    work.mkdir(parents=True, exist_ok=True)
    record: dict = {}

    # System A: one plot of three scans
    dx, dy = SECOND_SCANNER_OFFSET
    plot = write_simulated_plot(
        simulate_plot(
            "planted_conifer", [(0.0, 0.0), (dx, dy), (-6.0, 8.0)], seed=1, angular_step_deg=0.4, size_m=40.0
        ),
        work / "plot",
    )
    files = [work / "plot" / f"{s.name}.laz" for s in plot.scans]
    for name, src in (
        ("scan1.laz", files[0]),
        ("scan2.laz", files[1]),
        ("A.laz", files[0]),
        ("B.laz", files[1]),
        ("a.laz", files[0]),
        ("b.laz", files[1]),
    ):
        shutil.copyfile(src, folder / name)
    for sub in ("scans", "utm"):
        (folder / sub).mkdir()
        for f in files:
            shutil.copyfile(f, folder / sub / f.name)
    for plot_name, pair in (("plot1", (0, 1)), ("plot2", (0, 2))):
        (folder / "plots" / plot_name).mkdir(parents=True)
        for k in pair:
            shutil.copyfile(files[k], folder / "plots" / plot_name / files[k].name)
    shift = np.array(UTM_FIRST_SCANNER) - plot.scans[0].position
    rng = np.random.default_rng(7)
    rows = ["scan,x,y,z,heading_deg"]
    for s in plot.scans:
        x, y, z = s.position + shift + np.r_[rng.normal(0, 0.3, 2), 0.0]
        heading = np.degrees(np.arctan2(s.pose[1, 0], s.pose[0, 0])) + rng.normal(0, 2.0)
        rows.append(f"{s.name}.laz,{x:.2f},{y:.2f},{z:.2f},{heading:.1f}")
    (folder / "gnss.csv").write_text("\n".join(rows) + "\n")
    for variant in ("mm", "utm"):
        (folder / "variants" / variant).mkdir(parents=True)
    for name, s in (("a.laz", plot.scans[0]), ("b.laz", plot.scans[1])):
        scan = read_scan(work / "plot" / f"{s.name}.laz")
        write_scan(scan, folder / "variants" / "mm" / name, matrix=np.diag([1000.0, 1000.0, 1000.0, 1.0]))
        world = Scan.from_points(s.world_points() + shift, name=s.name, intensity=scan.intensity)
        write_scan(world, folder / "variants" / "utm" / name)
    record["plot"] = {s.name: {"utm_position": (s.position + shift).tolist()} for s in plot.scans}

    # System B: ground-based and UAV clouds of one plot, with field records
    case = simulated_coregistration(work / "system_b", seed=1, size_m=24.0, ground_extent_m=14.0, tls_step_deg=0.5)
    shutil.copyfile(case.ground, folder / "backpack.laz")
    shutil.copyfile(case.uav, folder / "uav.laz")
    shutil.copyfile(case.field, folder / "field.csv")
    fuse_clouds(case.ground, case.uav, folder / "fused.laz", matrix=case.truth)
    record["coregistration"] = np.asarray(case.truth).tolist()

    # a re-survey: clouds, and the trees of each survey as tables
    resurvey = write_resurvey(
        simulate_resurvey(
            size_m=24.0,
            seed=1,
            angular_step_deg=0.5,
            years=5.0,
            before_positions=((-5.0, -5.0), (5.0, -5.0), (0.0, 5.0)),
            after_positions=((0.0, -7.0), (6.0, 3.0), (-6.0, 3.0)),
        ),
        work / "resurvey",
    )
    shutil.copyfile(resurvey.files["before"], folder / "plot_2021.laz")
    shutil.copyfile(resurvey.files["after"], folder / "plot_2026.laz")
    inverse = np.linalg.inv(resurvey.matrix)  # scene (BEFORE) -> AFTER frame
    tables: dict[str, str] = {}
    for year, when, scene, to_frame in (
        ("2021", "before", resurvey.before_scene, np.eye(4)),
        ("2026", "after", resurvey.after_scene, inverse),
    ):
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(["tree_id", "x", "y", "z", "dbh_m", "height_m", "source", "dbh_quality", "height_quality", "flag"])
        k = 0
        for fate in resurvey.fates():
            if fate[f"dbh_{when}_m"] is None:
                continue
            k += 1
            p = to_frame @ np.array([fate["x"], fate["y"], scene.ground_z(fate["x"], fate["y"]), 1.0])
            w.writerow(
                [
                    k,
                    f"{p[0]:.3f}",
                    f"{p[1]:.3f}",
                    f"{p[2]:.3f}",
                    f"{fate[f'dbh_{when}_m']:.4f}",
                    f"{fate[f'height_{when}_m']:.2f}",
                    "stem",
                    "stem curve; high",
                    "top; high",
                    "",
                ]
            )
        (folder / f"trees_{year}").mkdir()
        (folder / f"trees_{year}" / "trees.csv").write_text(buf.getvalue())
        tables[year] = buf.getvalue()
    # the same surveys as loose tables, the earlier one in feet (positions; sizes stay in metres)
    (folder / "trees_2026.csv").write_text(tables["2026"])
    rows = list(csv.reader(io.StringIO(tables["2021"])))
    with open(folder / "trees_2016.csv", "w", newline="") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow(rows[0])
        for r in rows[1:]:
            w.writerow([r[0]] + [f"{float(v) / 0.3048:.3f}" for v in r[1:4]] + r[4:])
    record["resurvey"] = resurvey.matrix.tolist()

    (folder / "params.toml").write_text(params_toml())
    shutil.rmtree(work)
    (folder.parent / f"{folder.name}.truth.json").write_text(json.dumps(record, indent=1))
    return record
