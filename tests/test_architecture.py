"""The layering of the package, measured from its own source (``ast``): which module imports which
(every import, at the top or inside a function; the root package ``forestreg`` is a module of its
own, imported by ``from forestreg import x``, ``import forestreg`` or a relative ``from ... import x``
that reaches it, and importing on use the modules its ``_LAZY`` table names), and which modules
write files.

The rules (README, architecture):

- front doors (``cli``, ``ui``, ``service``, ``plugin``, ``client``) import ``app`` and, below it,
  only ``engine/core``, ``engine/io``, ``engine/report`` and the parameter modules;
- ``app`` and the root package (the Python API, a front door too) are imported by no engine module;
- no engine module writes a file, except the I/O edge :data:`ENGINE_WRITERS` (``engine/io``,
  ``engine/report``, the atomic writers and the compiled-kernel cache); the domain packages
  (``engine/tls``, ``coreg``, ``trees``, ``terrain``, ``geometry``, ``change``, ``simulate``) import
  no ``report``; ``engine/io`` imports no domain package;
- no cycle between packages, and none between modules (imports inside functions counted).
"""

from __future__ import annotations

import ast
from functools import lru_cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "forestreg"
#: top-level folders that are not part of the shipped package's layering
SKIP = {"tests", "benchmarks", "scripts", "docs", "resources", ".venv", "build", "dist"}

FRONT_DOORS = ("cli", "ui", "service", "plugin", "client")
DOMAIN = (
    "engine.tls",
    "engine.coreg",
    "engine.trees",
    "engine.terrain",
    "engine.geometry",
    "engine.change",
    "engine.simulate",
)
#: The engine modules that may write files, and why: everything else under ``engine`` computes
#: and returns (a run reports its progress through callbacks such as ``on_link_done``; the use
#: cases in ``app`` decide what is written where).
ENGINE_WRITERS = {
    "engine.io": "the readers and writers of every file format (point clouds, tables, project file, GeoPackage)",
    "engine.report": "the HTML reports and their figures",
    "engine.core.atomic": "the atomic file and output-folder writers every writer goes through",
    "engine.core.jit": "the cache of compiled kernels (its warm-up mark and the kernels' index) in the user's cache folder",
}
#: what a front door may import below ``app``
FRONT_DOOR_MAY = (
    "app",
    "engine.core",
    "engine.io",
    "engine.report",
    "engine.params",
    "engine.tls.params",
    "cli",
    "ui",
    "service",
    "plugin",
    "client",
    "engine",
)
#: parameter modules a front door may import from a domain package (classes only)
PARAM_MODULES = {"engine.tls.params"}

#: methods that write a file (on a path, a figure, a table, a project)
WRITE_METHODS = {
    "write_text",
    "write_bytes",
    "savefig",
    "tofile",
    "to_csv",
    "to_json",
    "to_parquet",
    "mkdir",
    "touch",
    "write",
    "write_csv",
    "save",
    "checkpoint",
    "symlink_to",
    "unlink",
    "rmdir",
}
#: modules whose ``open(path, mode)`` takes the path first (else ``x.open(mode)`` is a path's open)
OPEN_MODULES = {"io", "os", "gzip", "bz2", "lzma", "codecs", "laspy", "builtins", "tarfile", "zipfile", "h5py", "pye57"}
#: module functions that write or move files, by module
WRITE_MODULE_FUNCTIONS = {
    "os": {"replace", "rename", "makedirs", "mkdir", "remove", "unlink", "symlink", "link"},
    "shutil": {"copy", "copy2", "copyfile", "copytree", "move", "rmtree"},
    "np": {"save", "savez", "savez_compressed", "savetxt"},
    "numpy": {"save", "savez", "savez_compressed", "savetxt"},
    "json": {"dump"},
    "pickle": {"dump"},
}
#: a csv writer over an in-memory buffer: text, not a file (the file is written by one of the others)
IN_MEMORY = {"writer", "writerow", "writerows"}
#: functions that write a file whatever module they come from
WRITE_FUNCTIONS = {"atomic_path", "write_text_atomic", "output_folder", "mkdtemp", "NamedTemporaryFile"}


def module_name(path: Path) -> str:
    """The dotted name of a source file relative to the package root; the root's own
    ``__init__.py`` is :data:`PACKAGE`."""
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts) or PACKAGE


@lru_cache(maxsize=None)
def sources() -> dict[str, tuple[Path, ast.AST]]:
    out = {}
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT)
        if rel.parts[0] in SKIP or any(p.startswith(".") for p in rel.parts):
            continue
        out[module_name(path)] = (path, ast.parse(path.read_text(encoding="utf-8"), str(path)))
    return out


def _resolve(mod: str, is_package: bool, node: ast.ImportFrom) -> list[str]:
    """The modules (relative to the package root; :data:`PACKAGE` for the root itself) an
    ``ImportFrom`` names: the submodule an imported name is, else the module it is taken from."""
    if node.level:
        base = mod.split(".") if mod and mod != PACKAGE else []
        if not is_package:
            base = base[:-1]
        up = node.level - 1
        base = base[: len(base) - up] if up else base
        target = ".".join(base + ([node.module] if node.module else []))
    else:
        if not node.module or not (node.module == PACKAGE or node.module.startswith(PACKAGE + ".")):
            return []
        target = node.module[len(PACKAGE) + 1 :] if node.module != PACKAGE else ""
    names = []
    for alias in node.names:
        sub = f"{target}.{alias.name}" if target else alias.name
        names.append(sub if sub in sources() else (target or PACKAGE))
    return names


def _lazy_table(tree: ast.AST) -> set[str]:
    """The modules a ``_LAZY = {"name": ".module", ...}`` table of a module names (the root
    package imports them on use: ``forestreg.plot_scans`` imports ``app.plot``)."""
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            if any(isinstance(t, ast.Name) and t.id == "_LAZY" for t in targets) and isinstance(node.value, ast.Dict):
                found.update(
                    v.value.lstrip(".")
                    for v in node.value.values
                    if isinstance(v, ast.Constant) and isinstance(v.value, str) and v.value.startswith(".")
                )
    return found


@lru_cache(maxsize=None)
def imports() -> dict[str, set[str]]:
    """module -> the package modules it imports (anywhere in its body), by dotted name."""
    srcs = sources()
    graph: dict[str, set[str]] = {}
    for mod, (path, tree) in srcs.items():
        is_package = path.name == "__init__.py"
        deps: set[str] = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                deps.update(_resolve(mod, is_package, node))
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name.startswith(PACKAGE + "."):
                        deps.add(alias.name[len(PACKAGE) + 1 :])
                    elif alias.name == PACKAGE:
                        deps.add(PACKAGE)
            elif isinstance(node, ast.Call):  # importlib.import_module(".x.y", ...)
                f = node.func
                if (isinstance(f, ast.Attribute) and f.attr == "import_module") or (
                    isinstance(f, ast.Name) and f.id == "import_module"
                ):
                    if node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str):
                        name = node.args[0].value
                        if name.startswith("."):
                            deps.add(name.lstrip("."))
                        elif name.startswith(PACKAGE + "."):
                            deps.add(name[len(PACKAGE) + 1 :])
        deps.update(_lazy_table(tree))
        graph[mod] = {_known(d, srcs) for d in deps if d} - {mod}
    return graph


def _known(name: str, srcs) -> str:
    """``name`` if it is a module of the package, else the nearest enclosing one (a name taken
    from a module, ``engine.tls.plot.register_project``, is an import of ``engine.tls.plot``)."""
    parts = name.split(".")
    while len(parts) > 1 and ".".join(parts) not in srcs:
        parts.pop()
    return ".".join(parts)


def within(mod: str, prefix: str) -> bool:
    return mod == prefix or mod.startswith(prefix + ".")


def package_of(mod: str) -> str:
    """The package a module belongs to: ``engine.<x>`` for the engine, else the top folder."""
    parts = mod.split(".")
    if parts[0] == "engine" and len(parts) > 1 and (ROOT / "engine" / parts[1]).is_dir():
        return "engine." + parts[1]
    return parts[0]


def file_writes() -> dict[str, list[str]]:
    """module -> the file-writing calls in it ("name:line"): ``open`` for writing, a write method
    (``write_text``, ``savefig``, ``mkdir``, a csv writer's ``writerow``, ...), ``os``/``shutil``/
    ``numpy`` file functions, the package's atomic writers, and any call of a function or method
    whose name starts with ``write`` (``write_scan``, ``TreeInventory.write``, ...)."""
    out: dict[str, list[str]] = {}
    for mod, (path, tree) in sources().items():
        hits = []
        for node in ast.walk(tree):
            if not isinstance(node, ast.Call):
                continue
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None
            if name is None:
                continue
            if (
                name == "open"
                and node.args
                and isinstance(node.args[0], ast.Attribute)
                and node.args[0].attr == "devnull"
            ):
                continue  # the null device (silencing a library's output), not a file
            if name == "open":
                if _open_mode(node) != "r":
                    hits.append(f"open:{node.lineno}")
            elif (
                isinstance(f, ast.Attribute)
                and isinstance(f.value, ast.Name)
                and name in WRITE_MODULE_FUNCTIONS.get(f.value.id, ())
            ):
                hits.append(f"{f.value.id}.{name}:{node.lineno}")
            elif name in IN_MEMORY:
                continue
            elif name in WRITE_FUNCTIONS or name.startswith("write"):
                if (
                    isinstance(f, ast.Attribute)
                    and name in ("write",)
                    and isinstance(f.value, ast.Name)
                    and f.value.id in ("buf", "sys")
                ):
                    continue  # an in-memory buffer or the terminal
                hits.append(f"{name}:{node.lineno}")
            elif isinstance(f, ast.Attribute) and name in WRITE_METHODS:
                hits.append(f"{name}:{node.lineno}")
        if hits:
            out[mod] = hits
    return out


def _open_mode(node: ast.Call) -> str:
    """ "r" for an ``open`` call that only reads, else "w" (a mode that writes, appends, creates or
    updates, or one not written as a constant): ``open(path, mode)``, ``io.open``/``laspy.open``
    (path first) and a path's ``p.open(mode)`` (mode first)."""
    f = node.func
    path_first = isinstance(f, ast.Name) or (
        isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name) and f.value.id in OPEN_MODULES
    )
    mode = next((k.value for k in node.keywords if k.arg == "mode"), None)
    if mode is None:
        position = 1 if path_first else 0
        mode = node.args[position] if len(node.args) > position else None
    if mode is None:
        return "r"
    if isinstance(f, ast.Attribute) and f.attr == "open" and isinstance(f.value, ast.Name) and f.value.id == "os":
        return "w"  # os.open(path, flags): flags are not a mode text
    text = mode.value if isinstance(mode, ast.Constant) else None
    return "r" if isinstance(text, str) and not any(c in text for c in "wax+") else "w"


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []
    counter = [0]

    import sys

    sys.setrecursionlimit(10000)

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in graph:
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def module_graph() -> dict[str, set[str]]:
    """Module imports with a package's ``__init__`` left out as a target when the importer lives
    inside that package (importing ``.x`` from a sibling goes through the folder, not its
    ``__init__``)."""
    g = imports()
    out: dict[str, set[str]] = {}
    for mod, deps in g.items():
        keep = set()
        for d in deps:
            if d in g:
                keep.add(d)
        out[mod] = keep
    return out


def package_graph() -> dict[str, set[str]]:
    out: dict[str, set[str]] = {}
    for mod, deps in imports().items():
        p = package_of(mod)
        out.setdefault(p, set())
        for d in deps:
            q = package_of(d)
            if q != p:
                out[p].add(q)
    return out


# ----------------------------------------------------------------------------- reads by string key

#: The front doors whose code reads results through typed attributes (an outcome's fields, the
#: typed records of :mod:`forestreg.app`), never a result dict by string key.
KEY_READ_DOORS = ("cli", "ui", "service", "plugin")

#: The reads by string key left in the front doors, each of something that is not a result, an
#: outcome or a saved record: module -> {the receiver, as written: what it is}. Every other
#: ``x["key"]`` or ``x.get("key")`` in those folders fails :func:`test_front_doors_read_no_result_by_string_key`.
NOT_RESULTS: dict[str, dict[str, str]] = {
    "cli": {"os.environ": "environment variables"},
    "cli.misc": {
        "values": "the gui command's own options (--size, --project, ...), parsed by hand",
        "r": "rows of the parameter table (name, unit, paper, help) that `forestreg params` prints",
    },
    "ui.sample": {"os.environ": "environment variables"},
    "ui.scene_view": {"os.environ": "environment variables"},
    "ui.params_panel": {"row": "rows of the parameter table (name, default, unit, range, paper, help) the panel edits"},
    "ui.tie_points": {"self.combos": "the panel's two combo boxes by side"},
    "ui.trees_view": {
        "t": "a trees.csv row's measure by column name (TreeRow.get; the table's columns are open-ended)",
        "tree": "a trees.csv row's measure by column name (TreeRow.get)",
        "out.tree(int(tree_id))": "a trees.csv row's measure by column name (TreeRow.get)",
    },
    "plugin.adapter": {
        "env": "the environment of the service's process",
        "row": "rows of a *_vops.csv (csv.DictReader), read into the host's records",
        "final": "the service's job record (status, exit code, message) as its HTTP API returns it",
    },
    "plugin.qgis.provider": {"gpkg": "the layers of layers.gpkg loaded into QGIS, by layer name"},
    "plugin.geometry": {
        "c": "a cylinder table's columns by name (read_cylinders_csv: one array per column of CYLINDER_COLUMNS)"
    },
    "service.app": {
        "scope": "the ASGI scope",
        "message": "ASGI messages",
        "request.headers": "HTTP headers",
        "request.query_params": "the URL's query",
        "info": "the service's own state file (url, token, pid)",
        "job": "the service's job records (its SQLite table, served as JSON)",
        "old": "a job record being resubmitted",
        "first": "the first event of a job's event stream",
        "event": "a job's events (progress, log, end)",
        "current": "a job record being polled",
        "app": "the ASGI application's state",
    },
    "service.jobs": {
        "env": "the environment of a job's process",
        "job": "the service's job records (its SQLite table)",
        "event": "the progress events a job prints (one JSON line each)",
        "end": "a job's end event",
        "last": "the last progress event kept",
        "self.store.raw(job_id)": "a job's raw SQLite row",
    },
    "service.store": {
        "row": "SQLite rows of the job table",
        "r": "SQLite rows of the job table",
        "fields": "the columns of a job record being updated",
    },
    "service.batch": {
        "r": "the batch's own summary rows (one per plot: summary.csv, batch.json)",
        "row": "the batch's own summary rows, and a manifest's CSV row (the user's file)",
        "previous": "the batch's own row of a plot done by an earlier run (batch.json)",
        "rows[name]": "a manifest's CSV row (the user's file)",
        "(rows or {}).get(name, {})": "a manifest's CSV row (the user's file)",
        "client.scheduler_info()": "Dask's scheduler description",
        "_read_json(path) or {}": "the batch's own notes of a plot's attempts (.forestreg-batch/<plot>.json)",
        "a": "an attempt of those notes (run, worker, pid, start)",
        "last": "the last attempt noted",
    },
}


def string_key_reads() -> dict[str, list[tuple[str, int, str]]]:
    """module -> every read by a string constant in it: ``(receiver as written, line, the read)``
    for ``x["key"]`` (loads only) and ``x.get("key", ...)``."""
    found: dict[str, list[tuple[str, int, str]]] = {}
    for mod, (_, tree) in sources().items():
        if not any(within(mod, d) for d in KEY_READ_DOORS):
            continue
        for node in ast.walk(tree):
            receiver = None
            if (
                isinstance(node, ast.Subscript)
                and isinstance(node.ctx, ast.Load)
                and isinstance(node.slice, ast.Constant)
                and isinstance(node.slice.value, str)
            ):
                receiver = node.value
            elif (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Attribute)
                and node.func.attr == "get"
                and node.args
                and isinstance(node.args[0], ast.Constant)
                and isinstance(node.args[0].value, str)
            ):
                receiver = node.func.value
            if receiver is not None:
                found.setdefault(mod, []).append((ast.unparse(receiver), node.lineno, ast.unparse(node)))
    return found


def result_key_reads() -> list[str]:
    """The reads by string key in the front doors that :data:`NOT_RESULTS` does not name."""
    return sorted(
        f"{mod}:{line}: {text}"
        for mod, reads in string_key_reads().items()
        for receiver, line, text in reads
        if receiver not in NOT_RESULTS.get(mod, {})
    )


# ----------------------------------------------------------------------------- the rules


def front_door_violations() -> list[str]:
    bad = []
    for mod, deps in imports().items():
        if not any(within(mod, d) for d in FRONT_DOORS):
            continue
        for d in deps:
            if d in PARAM_MODULES or any(within(d, ok) for ok in ("app", "engine.core", "engine.io", "engine.report")):
                continue
            if d in ("engine", "engine.params", "_version", PACKAGE) or any(within(d, f) for f in FRONT_DOORS):
                continue
            bad.append(f"{mod} -> {d}")
    return sorted(bad)


def engine_writes() -> list[str]:
    """The file-writing calls of engine modules outside :data:`ENGINE_WRITERS`."""
    return sorted(
        f"{mod}: {', '.join(hits)}"
        for mod, hits in file_writes().items()
        if within(mod, "engine") and not any(within(mod, w) for w in ENGINE_WRITERS)
    )


def layer_violations() -> list[str]:
    bad = []
    for mod, deps in imports().items():
        for d in deps:
            if any(within(mod, dom) for dom in DOMAIN) and (
                within(d, "engine.report") or within(d, "app") or any(within(d, f) for f in FRONT_DOORS)
            ):
                bad.append(f"{mod} -> {d}")
            if within(mod, "engine.io") and any(within(d, dom) for dom in DOMAIN + ("engine.report", "app")):
                bad.append(f"{mod} -> {d}")
            if (
                within(mod, "engine.core") and not within(d, "engine.core") and d != "_version"
            ):  # the version text, a leaf
                bad.append(f"{mod} -> {d}")
            if within(mod, "engine") and (within(d, "app") or d == PACKAGE or any(within(d, f) for f in FRONT_DOORS)):
                bad.append(f"{mod} -> {d}")
            if within(mod, "app") and d == PACKAGE:
                bad.append(f"{mod} -> {d}")
            if within(mod, "app") and any(within(d, f) for f in FRONT_DOORS):
                bad.append(f"{mod} -> {d}")
    return sorted(set(bad))


def test_front_doors_go_through_app():
    assert front_door_violations() == []


def test_engine_writes_no_files_outside_its_io_edge():
    """Only :data:`ENGINE_WRITERS` write files; every other engine module (the domain packages,
    ``engine/simulate`` among them) returns what it computed."""
    assert engine_writes() == []
    assert all(any(within(mod, w) for mod in sources()) for w in ENGINE_WRITERS), (
        "an allowed writer that no longer exists"
    )


def test_layers_point_down():
    assert layer_violations() == []


def test_no_package_cycles():
    assert cycles(package_graph()) == []


def test_no_module_cycles():
    assert cycles(module_graph()) == []


def test_front_doors_read_no_result_by_string_key():
    """Results reach the front doors typed (an outcome's attributes, :mod:`forestreg.app`'s
    records such as ``link_summary``, ``CoregistrationSummary``, ``SavedResult``): a read by string
    key is of something named in :data:`NOT_RESULTS`, and each entry there is still used."""
    assert result_key_reads() == []
    reads = string_key_reads()
    stale = [
        f"{mod}: {receiver}"
        for mod, named in NOT_RESULTS.items()
        for receiver in named
        if not any(r == receiver for r, _, _ in reads.get(mod, []))
    ]
    assert stale == []


def test_the_key_read_checker_sees_result_reads(monkeypatch):
    """The checker itself: a result dict read by string key, by subscript or ``get``, is found,
    whatever the variable is called; a store is not a read."""
    code = (
        'def show(outcome, link, x):\n    a = outcome.summary["matched"]\n    b = link.result.get("reason")\n'
        '    c = x["status"]\n    x["status"] = "ok"\n'
    )
    fake = {"ui.fake": (Path("fake.py"), ast.parse(code))}
    import sys

    module = sys.modules[__name__]
    monkeypatch.setattr(module, "sources", lambda: fake)
    assert [r.split(": ", 1)[1] for r in result_key_reads()] == [
        "outcome.summary['matched']",
        "link.result.get('reason')",
        "x['status']",
    ]


def _fake_package(monkeypatch, modules: dict[str, str]) -> None:
    """Make the checkers read ``modules`` (dotted name -> source) instead of the package."""
    import sys

    fake = {
        name: (
            Path(*name.split("."), "__init__.py") if name in ("engine", "engine.tls", PACKAGE) else Path(f"{name}.py"),
            ast.parse(code),
        )
        for name, code in modules.items()
    }
    module = sys.modules[__name__]
    monkeypatch.setattr(module, "sources", lambda: fake)
    monkeypatch.setattr(module, "imports", imports.__wrapped__)  # uncached: read from the fake


def test_the_checker_sees_imports_inside_functions_and_of_the_root(monkeypatch):
    """The checker itself: an import inside a function counts for cycles; ``from forestreg import
    x``, ``import forestreg`` and a relative import reaching the root are imports of the root
    package, which imports what its ``_LAZY`` table names; an engine module importing the root is
    a layer violation."""
    _fake_package(
        monkeypatch,
        {
            PACKAGE: '_LAZY = {"plot_scans": ".app.plot"}\n',
            "app.plot": "from ..engine.tls import pair\n",
            "engine.tls.pair": "def f():\n    from ...app import plot\n",
            "engine.tls.plot": "def g():\n    from ... import __version__\n",
            "engine.tls.survey": "def h():\n    from forestreg import plot_scans\n",
            "engine.tls.compare": "import forestreg\n",
            "cli.plot": "from .. import __version__\n",
        },
    )
    graph = imports()
    assert graph["engine.tls.pair"] == {"app.plot"}, "an import inside a function"
    assert graph[PACKAGE] == {"app.plot"}, "the root's lazy table"
    assert graph["engine.tls.plot"] == graph["engine.tls.survey"] == graph["engine.tls.compare"] == {PACKAGE}
    assert cycles(module_graph()) == [["app.plot", "engine.tls.pair"]]
    assert layer_violations() == [
        "engine.tls.compare -> forestreg",
        "engine.tls.pair -> app.plot",
        "engine.tls.plot -> forestreg",
        "engine.tls.survey -> forestreg",
    ]
    assert front_door_violations() == [], "a front door may import the root (the version, its folder)"


def test_the_checker_sees_every_kind_of_write(monkeypatch):
    """The checker itself: each way of writing a file is found in an engine module outside
    :data:`ENGINE_WRITERS` (``engine/simulate`` included), none in reading code, and the I/O edge
    may write."""
    writes = {
        "open(p, 'w')": "open",
        "open(p, mode='ab')": "open",
        "p.open('w')": "open",
        "laspy.open(p, mode='w')": "open",
        "open(p, m)": "open",
        "p.write_text('x')": "write_text",
        "p.write_bytes(b'x')": "write_bytes",
        "np.save(p, a)": "np.save",
        "json.dump(d, fh)": "json.dump",
        "frame.to_csv(p)": "to_csv",
        "las.write(p)": "write",
        "project.save()": "save",
        "write_scan(s, p)": "write_scan",
        "write_text_atomic(p, t)": "write_text_atomic",
        "shutil.rmtree(p)": "shutil.rmtree",
        "os.replace(a, b)": "os.replace",
        "p.mkdir()": "mkdir",
        "fig.savefig(p)": "savefig",
    }
    reads = [
        "open(p)",
        "open(p, 'rb')",
        "p.open()",
        "p.open('r')",
        "laspy.open(p)",
        "json.loads(t)",
        "p.read_text()",
        "dataclasses.replace(x, a=1)",
        "params.replace(a=1)",
        "text.replace('a', 'b')",
        "open(os.devnull, 'w')",
    ]
    body = "".join(f"    {code}\n" for code in list(writes) + reads)
    _fake_package(
        monkeypatch,
        {
            "engine.simulate.plot": f"def f(p, s, a, d, fh, m, t, x):\n{body}",
            "engine.io.simulated": f"def f(p):\n{body}",
        },
    )
    found = file_writes()
    assert [hit.rsplit(":", 1)[0] for hit in found["engine.simulate.plot"]] == list(writes.values())
    assert engine_writes() == [f"engine.simulate.plot: {', '.join(found['engine.simulate.plot'])}"]


if __name__ == "__main__":  # a report of the measures
    print("front door violations:", len(front_door_violations()))
    for line in front_door_violations():
        print("  ", line)
    print("engine writes outside its I/O edge:", len(engine_writes()))
    for line in engine_writes():
        print("  ", line)
    print("layer violations:", len(layer_violations()))
    for line in layer_violations():
        print("  ", line)
    print("package cycles:", cycles(package_graph()))
    print(
        "front-door reads by string key:",
        sum(len(v) for v in string_key_reads().values()),
        "of which not named as a non-result:",
        len(result_key_reads()),
    )
    for line in result_key_reads():
        print("  ", line)
    print("module cycles:", cycles(module_graph()))
