"""Package the QGIS plugin as the zip that QGIS's plugin manager installs.

    python scripts/package_qgis.py [--out dist/]        # -> dist/forestreg-qgis-<version>.zip

The zip holds one folder, ``forestreg/`` (the plugin folder and the import package), with
``metadata.txt`` at its top and the package's modules and resources as the wheel ships them
(the ``packages`` and ``package-data`` of ``pyproject.toml``), no tests, no compiled files.
*Plugins > Manage and Install Plugins > Install from ZIP* installs it. The zip and its files are
readable by everyone (files 0644, folders 0755), as a plugin folder installed by QGIS must be.

``metadata.txt`` must carry every field the QGIS plugin repository requires (:data:`REQUIRED`)
and the ones it recommends (:data:`RECOMMENDED`), with values it accepts: an e-mail address that
is not a placeholder, web addresses for the repository, tracker and home page, the package's
version (``forestreg.__version__``). Otherwise the script stops with one line naming every problem
(exit 2) and writes nothing. The plugin runs forestreg's engine as a background command; how that
gets installed is in the documentation's QGIS page.
"""

from __future__ import annotations

import argparse
import ast
import configparser
import os
import re
import stat
import sys
import tempfile
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: Fields the QGIS plugin repository (plugins.qgis.org) requires in metadata.txt.
REQUIRED = ("name", "qgisMinimumVersion", "description", "about", "version", "author", "email", "repository")
#: Fields it recommends; this package carries them too, so they are checked as well.
RECOMMENDED = ("tracker", "homepage", "tags")
#: Modes of the zip, its files and its folders: readable by everyone, as an installed plugin must be.
FILE_MODE = 0o644
DIR_MODE = 0o755
#: Domains reserved for examples and tests (RFC 2606, RFC 6761): an address there is a placeholder.
PLACEHOLDER_DOMAIN = re.compile(r"(^|\.)(example(\.(com|net|org))?|invalid|test|localhost)$", re.I)
EMAIL = re.compile(r"^[^@\s]+@([A-Za-z0-9-]+\.)+[A-Za-z]{2,}$")
URL = re.compile(r"^https?://[^\s/]+\.[^\s/]+(/\S*)?$")
#: Files beside the package that go into the plugin folder when present.
EXTRA_FILES = ("metadata.txt", "README.md", "CHANGELOG.md", "LICENSE")

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


class PackagingError(Exception):
    """What stops the packaging (one line)."""


def package_version(root: Path = ROOT) -> str:
    """``__version__`` of the package's ``_version.py`` (read, not imported)."""
    tree = ast.parse((root / "_version.py").read_text(encoding="utf-8"))
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "__version__" for t in node.targets):
            return str(ast.literal_eval(node.value))
    raise PackagingError("_version.py has no __version__")


def read_metadata(root: Path = ROOT) -> dict[str, str]:
    """metadata.txt's ``[general]`` section, checked (:func:`metadata_problems`); raises
    :class:`PackagingError` naming every problem."""
    meta = configparser.ConfigParser(interpolation=None)
    path = root / "metadata.txt"
    try:
        found = meta.read(path, encoding="utf-8")
    except configparser.Error as exc:
        raise PackagingError(f"{path} is not a valid metadata file: {' '.join(str(exc).split())}") from None
    if not found or not meta.has_section("general"):
        raise PackagingError(f"{path} is missing or has no [general] section")
    general = {k: v.strip() for k, v in meta["general"].items()}
    problems = metadata_problems(general, package_version(root))
    if problems:
        raise PackagingError(f"metadata.txt: {'; '.join(problems)}")
    return general


def metadata_problems(general: dict[str, str], version: str) -> list[str]:
    """What the QGIS plugin repository would refuse in a ``[general]`` section (keys in lower
    case, as configparser gives them), in words; empty when it is fine."""
    value = {k.lower(): (v or "").strip() for k, v in general.items()}
    problems = []
    missing = [k for k in REQUIRED if not value.get(k.lower())]
    if missing:
        problems.append(f"lacks {', '.join(missing)}, required by the QGIS plugin repository")
    missing = [k for k in RECOMMENDED if not value.get(k.lower())]
    if missing:
        problems.append(f"lacks {', '.join(missing)}, recommended by the QGIS plugin repository")
    email = value.get("email", "")
    if email and not EMAIL.match(email):
        problems.append(f"email {email!r} is not an e-mail address")
    elif email and PLACEHOLDER_DOMAIN.search(email.rsplit("@", 1)[1]):
        problems.append(f"email {email!r} is a placeholder (a domain reserved for examples)")
    for key in ("repository", "tracker", "homepage"):
        url = value.get(key, "")
        if url and not URL.match(url):
            problems.append(f"{key} {url!r} is not a web address (http:// or https://)")
        elif url and PLACEHOLDER_DOMAIN.search(url.split("/")[2].split(":")[0]):
            problems.append(f"{key} {url!r} is a placeholder (a domain reserved for examples)")
    minimum = value.get("qgisminimumversion", "")
    if minimum and not re.fullmatch(r"\d+\.\d+(\.\d+)?", minimum):
        problems.append(f"qgisMinimumVersion {minimum!r} is not a version such as 3.22")
    tags = value.get("tags", "")
    if tags and not all(t.strip() for t in tags.split(",")):
        problems.append(f"tags {tags!r} has an empty tag (tags are separated by commas)")
    if value.get("version") and value["version"] != version:
        problems.append(f"metadata.txt says version {value['version']}, the package is {version}: make them equal")
    return problems


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
        patterns = ["*.py"] + list(data.get(package, []))  # relative to the package's folder ("models/*.model3")
        for pattern in patterns:
            files |= {path.relative_to(root) for path in folder.glob(pattern) if path.is_file()}
    files |= {Path(name) for name in EXTRA_FILES if (root / name).is_file()}
    return sorted(files)


def build_zip(out_dir: Path, root: Path = ROOT) -> Path:
    """Write ``out_dir/forestreg-qgis-<version>.zip`` (atomically, mode 0644; its files 0644 and
    folders 0755) and return its path."""
    meta = read_metadata(root)
    folder = "forestreg"  # the import package's name: QGIS imports the plugin folder by it
    target = Path(out_dir) / f"{folder}-qgis-{meta['version'].strip()}.zip"
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".forestreg-qgis-", suffix=".zip", dir=target.parent)
    os.close(fd)
    try:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as z:
            written: set[str] = set()
            for rel in plugin_files(root):
                name = f"{folder}/{rel.as_posix()}"
                parts = name.split("/")[:-1]
                for k in range(1, len(parts) + 1):
                    directory = "/".join(parts[:k]) + "/"
                    if directory not in written:
                        z.writestr(_entry(directory, DIR_MODE, root / Path(*parts[1:k])), b"")
                        written.add(directory)
                z.writestr(_entry(name, FILE_MODE, root / rel), (root / rel).read_bytes())
        os.chmod(tmp, FILE_MODE)
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return target


def _entry(name: str, mode: int, source: Path) -> zipfile.ZipInfo:
    """A zip entry for ``name`` (a folder when it ends with ``/``) with the Unix ``mode`` and the
    time of ``source``, whatever the file's own mode on disk."""
    is_dir = name.endswith("/")
    info = zipfile.ZipInfo.from_file(source, name)
    info.create_system = 3  # Unix: unzip and QGIS's installer take the mode from external_attr
    info.external_attr = ((stat.S_IFDIR if is_dir else stat.S_IFREG) | mode) << 16
    if is_dir:
        info.external_attr |= 0x10  # the MS-DOS directory flag
        info.compress_type = zipfile.ZIP_STORED
        info.file_size = 0
    else:
        info.compress_type = zipfile.ZIP_DEFLATED
    return info


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="package_qgis.py", description="Package the QGIS plugin as a zip for QGIS's plugin manager."
    )
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
