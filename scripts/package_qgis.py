"""Package the QGIS plugin as the zip that QGIS's plugin manager installs.

    python scripts/package_qgis.py [--out dist/]        # -> dist/forestreg-qgis-<version>.zip

The zip holds one folder, ``forestreg/`` (the plugin folder and the import package), with
``metadata.txt`` at its top and the package's modules and resources as the wheel ships them
(the ``packages`` and ``package-data`` of ``pyproject.toml``), no tests, no compiled files.
*Plugins > Manage and Install Plugins > Install from ZIP* installs it. ``metadata.txt`` must carry
QGIS's required fields and the package's version (``forestreg.__version__``); otherwise the script
stops with one line (exit 2). The plugin runs forestreg's engine as a background command; how
that gets installed is in the documentation's QGIS page.
"""

from __future__ import annotations

import argparse
import ast
import configparser
import fnmatch
import os
import sys
import tempfile
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: Fields QGIS's plugin manager requires in metadata.txt.
REQUIRED = ("name", "qgisMinimumVersion", "description", "version", "author", "email", "about")
#: Files beside the package that go into the plugin folder when present.
EXTRA_FILES = ("metadata.txt", "README.md", "CHANGELOG.md", "LICENSE")

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


class PackagingError(Exception):
    """What stops the packaging (one line)."""


def package_version(root: Path = ROOT) -> str:
    """``__version__`` of the package's ``__init__.py`` (read, not imported)."""
    tree = ast.parse((root / "__init__.py").read_text(encoding="utf-8"))
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "__version__" for t in node.targets):
            return str(ast.literal_eval(node.value))
    raise PackagingError("__init__.py has no __version__")


def read_metadata(root: Path = ROOT) -> dict[str, str]:
    """metadata.txt's ``[general]`` section, checked: QGIS's required fields present and the
    version equal to the package's."""
    meta = configparser.ConfigParser(interpolation=None)
    path = root / "metadata.txt"
    if not meta.read(path, encoding="utf-8") or not meta.has_section("general"):
        raise PackagingError(f"{path} is missing or has no [general] section")
    general = dict(meta["general"])
    missing = [k for k in REQUIRED if not general.get(k.lower(), "").strip()]
    if missing:
        raise PackagingError(f"metadata.txt lacks {', '.join(missing)}")
    version = package_version(root)
    if general["version"].strip() != version:
        raise PackagingError(f"metadata.txt says version {general['version'].strip()}, the package is {version}: make them equal")
    return general


def plugin_files(root: Path = ROOT) -> list[Path]:
    """The files of the plugin folder, relative to ``root``: every module of the packages that
    ``pyproject.toml`` lists, their package data, and :data:`EXTRA_FILES`."""
    config = tomllib.loads((root / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]
    data = config.get("package-data", {})
    files: set[Path] = set()
    for package in config["packages"]:
        folder = root.joinpath(*package.split(".")[1:])
        if not folder.is_dir():
            raise PackagingError(f"package {package} has no folder {folder}")
        patterns = ["*.py"] + list(data.get(package, []))
        for path in folder.iterdir():
            if path.is_file() and any(fnmatch.fnmatch(path.name, p) for p in patterns):
                files.add(path.relative_to(root))
    files |= {Path(name) for name in EXTRA_FILES if (root / name).is_file()}
    return sorted(files)


def build_zip(out_dir: Path, root: Path = ROOT) -> Path:
    """Write ``out_dir/forestreg-qgis-<version>.zip`` (atomically) and return its path."""
    meta = read_metadata(root)
    folder = "forestreg"  # the import package's name: QGIS imports the plugin folder by it
    target = Path(out_dir) / f"{folder}-qgis-{meta['version'].strip()}.zip"
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".forestreg-qgis-", suffix=".zip", dir=target.parent)
    os.close(fd)
    try:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as z:
            for rel in plugin_files(root):
                z.write(root / rel, f"{folder}/{rel.as_posix()}")
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return target


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="package_qgis.py", description="Package the QGIS plugin as a zip for QGIS's plugin manager.")
    parser.add_argument("--out", default=str(ROOT / "dist"), help="folder for the zip (default: dist/ of the checkout)")
    args = parser.parse_args(argv)
    try:
        target = build_zip(Path(args.out))
    except (PackagingError, OSError) as exc:
        print(f"package_qgis.py: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {target} (install it with QGIS: Plugins > Manage and Install Plugins > Install from ZIP)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
