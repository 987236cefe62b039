"""Atomic file writing: write to a temporary file beside the target, then rename over it."""

from __future__ import annotations

import atexit
import contextlib
import os
import tempfile
import threading
from pathlib import Path
from typing import Iterator

from .errors import ScanWriteError


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; on success rename it onto ``path``.

    The temporary file keeps the target's suffix (writers pick the format from it). If the body
    raises, the temporary file is removed and ``path`` is left as it was.
    """
    target = Path(path)
    folder = target.parent if str(target.parent) else Path(".")
    if not folder.is_dir():
        raise ScanWriteError(f"cannot write {target}: folder {folder} does not exist")
    fd, tmp_name = tempfile.mkstemp(prefix=f".{target.stem}.", suffix=f".tmp{target.suffix}", dir=folder)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        os.chmod(tmp, _final_mode(target))
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def write_text_atomic(path: str | os.PathLike[str], text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def _final_mode(target: Path) -> int:
    """The mode the written file should get: the replaced file's, else 0666 less the umask
    (``mkstemp`` creates 0600 files)."""
    try:
        return target.stat().st_mode & 0o777
    except FileNotFoundError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


# ----------------------------------------------------------------------------- folder transactions

#: Name of the marker file every output folder of forestreg holds (its kind: "register", ...).
MARKER = ".forestreg-output"
#: Start of the name of every temporary file or folder forestreg makes beside its outputs.
TMP_PREFIX = ".forestreg-tmp-"
#: The folder transaction's temporaries beside ``OUT``: the new folder being written
#: (``.forestreg-tmp-new-OUT.XXXXXXXX``) and an earlier one moved aside while the new one is put in
#: its place (``.forestreg-tmp-old-OUT.XXXXXXXX``); both are removed when the transaction ends.
_NEW, _OLD = TMP_PREFIX + "new-", TMP_PREFIX + "old-"
#: Start of the name of the lock file beside ``OUT`` while a run writes it (``.forestreg-lock-OUT``).
LOCK_PREFIX = ".forestreg-lock-"


def is_unfinished_output(path: str | os.PathLike[str], target: str | os.PathLike[str] | None = None) -> bool:
    """Whether ``path`` is a temporary folder a folder transaction (:func:`output_folder`) left
    when its process was killed before the transaction ended: the unfinished new folder or an
    earlier one moved aside. With ``target``, only those of that output folder (beside it, of its
    name; ``.forestreg-tmp-new-x.*`` is never taken for one of ``new-x``)."""
    p = Path(path)
    name = p.name
    for prefix in (_NEW, _OLD):
        if name.startswith(prefix):
            of, dot, random = name[len(prefix) :].rpartition(".")
            if not (dot and of and random) or not all(c.isascii() and (c.isalnum() or c == "_") for c in random):
                return False
            if target is None:
                return True
            t = Path(target)
            return of == t.name and os.path.abspath(p.parent) == os.path.abspath(t.parent if str(t.parent) else ".")
    return False


def temporary_folder(inside: str | os.PathLike[str], what: str) -> Path:
    """A new empty folder in the existing folder ``inside``, named ``.forestreg-tmp-<what>.XXXXXXXX``:
    a run's products before each is moved into place. :func:`check_output_folder` passes over it,
    and it is never taken for a folder transaction's (:func:`is_unfinished_output`): ``what`` may
    not start with theirs (``new-``, ``old-``)."""
    if what.startswith((_NEW[len(TMP_PREFIX) :], _OLD[len(TMP_PREFIX) :])) or not what:
        raise ValueError(f"a temporary folder's name may not start with {_NEW!r} or {_OLD!r}: {what!r}")
    return Path(tempfile.mkdtemp(prefix=f"{TMP_PREFIX}{what}.", dir=inside))


def unfinished_outputs(folder: str | os.PathLike[str], target: str | os.PathLike[str] | None = None) -> list[Path]:
    """The temporary folders of unfinished folder transactions in ``folder`` (of the output
    folder ``target`` only, when given), in name order; none when ``folder`` cannot be listed."""
    try:
        entries = list(Path(folder).iterdir())
    except OSError:
        return []
    return sorted(e for e in entries if is_unfinished_output(e, target) and e.is_dir())


def check_output_folder(path: str | os.PathLike[str], kind: str, *, inputs: "tuple | list" = ()) -> Path:
    """Refuse an output folder that would lose a user's file, before any work.

    The folder may be absent, empty, or an earlier output folder of forestreg (it holds the
    :data:`MARKER` file); a file, an input, a folder holding an input, or a folder of other files
    raises :class:`~forestreg.engine.core.errors.OutputPathError`. Returns the resolved path.
    """
    from .errors import OutputPathError

    target = Path(path).expanduser()
    resolved = target.resolve()
    for item in inputs:
        if item is None:
            continue
        p = Path(item).expanduser().resolve()
        if p == resolved:
            raise OutputPathError(f"--out {target} is an input file: give a new folder")
        if resolved in p.parents:
            raise OutputPathError(f"--out {target} holds the input {Path(item).name}: give a new folder")
    if target.exists() and not target.is_dir():
        raise OutputPathError(f"--out {target} is an existing file, not a folder: give a new folder")
    if target.is_dir():
        entries = [e for e in target.iterdir() if not e.name.startswith((TMP_PREFIX, LOCK_PREFIX))]
        if entries and not (target / MARKER).is_file():
            raise OutputPathError(
                f"--out {target} already holds other files (not a forestreg output folder): give a new or empty folder"
            )
        if entries:
            try:
                earlier = (target / MARKER).read_text(encoding="utf-8").strip()
            except (OSError, UnicodeDecodeError):
                earlier = ""
            if earlier and earlier != kind:
                raise OutputPathError(
                    f"--out {target} holds the output of 'forestreg {earlier}', not of '{kind}': give another folder"
                )
    parent = resolved.parent
    nearest = next(a for a in (parent, *parent.parents) if a.exists())
    if not nearest.is_dir():
        raise OutputPathError(f"--out {target}: {nearest} is a file, not a folder: give a new folder")
    if not parent.exists():
        try:
            parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputPathError(f"cannot create the folder {parent}: {exc.strerror or exc}") from exc
    if not os.access(parent, os.W_OK):
        raise OutputPathError(f"cannot write into {parent}: permission denied")
    lock_output_folder(resolved, shown=target)
    return resolved


def check_output_file(
    path: str | os.PathLike[str], *, inputs: "tuple | list" = (), suffixes: "tuple[str, ...]" = ()
) -> Path:
    """Refuse an output file that is an input, a folder, of another kind than ``suffixes``, or in a
    folder that cannot be written, before any work. Returns the resolved path."""
    from .errors import OutputPathError

    target = Path(path).expanduser()
    resolved = target.resolve()
    for item in inputs:
        if item is not None and Path(item).expanduser().resolve() == resolved:
            raise OutputPathError(f"{target} is an input file: it would be overwritten; give a new file name")
    if target.is_dir():
        raise OutputPathError(f"{target} is a folder, not a file")
    if suffixes and target.suffix.lower() not in suffixes:
        raise OutputPathError(f"{target}: the output must end in {' or '.join(suffixes)}")
    parent = resolved.parent
    if not parent.is_dir():
        raise OutputPathError(f"cannot write {target}: folder {parent} does not exist")
    if not os.access(parent, os.W_OK):
        raise OutputPathError(f"cannot write into {parent}: permission denied")
    return resolved


@contextlib.contextmanager
def output_folder(path: str | os.PathLike[str], kind: str) -> Iterator[Path]:
    """A folder transaction: yield a fresh temporary folder beside ``path``; when the body returns,
    it becomes ``path`` (an earlier output folder there is replaced in one rename); when it raises
    (error, Ctrl-C, full disk) it is removed and ``path`` is left as it was.

    Call :func:`check_output_folder` first (before the work) to refuse a folder of other files;
    it takes the folder's lock (:func:`lock_output_folder`), which the transaction takes too when
    it was not, and releases when it ends.
    """
    import shutil

    from .errors import ScanWriteError

    target = Path(path).expanduser().resolve()
    target.parent.mkdir(parents=True, exist_ok=True)
    lock_output_folder(target)
    try:
        try:
            tmp = Path(tempfile.mkdtemp(prefix=f"{_NEW}{target.name}.", dir=target.parent))
        except OSError as exc:
            raise ScanWriteError(f"cannot write into {target.parent}: {exc.strerror or exc}") from exc
        try:
            yield tmp
            (tmp / MARKER).write_text(kind + "\n", encoding="utf-8")
            os.chmod(tmp, _final_dir_mode())
            _swap_in(tmp, target)
        except OSError as exc:
            shutil.rmtree(tmp, ignore_errors=True)
            raise ScanWriteError(f"cannot write {target}: {exc.strerror or exc}") from exc
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
    finally:
        release_output_folder(target)


def _swap_in(tmp: Path, target: Path, attempts: int = 20) -> None:
    """Put the folder ``tmp`` where ``target`` is: an earlier folder there is moved aside first and
    removed after. Another run swapping in at the same moment makes a rename fail with
    ENOTEMPTY/EEXIST: then try again (the last run to finish wins; each folder stays whole)."""
    import errno
    import shutil

    for attempt in range(attempts):
        old = None
        if target.exists():
            old = Path(tempfile.mkdtemp(prefix=f"{_OLD}{target.name}.", dir=target.parent))
            try:
                os.replace(target, old / "x")
            except FileNotFoundError:  # another run moved it first
                pass
        try:
            os.replace(tmp, target)
        except OSError as exc:
            if old is not None and (old / "x").exists() and not target.exists():
                os.replace(old / "x", target)  # put the earlier result back
            if old is not None:
                shutil.rmtree(old, ignore_errors=True)
            if exc.errno in (errno.ENOTEMPTY, errno.EEXIST) and attempt + 1 < attempts:
                continue
            raise
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        return


def _final_dir_mode() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return 0o777 & ~umask


# ----------------------------------------------------------------------------- one run per output folder

#: Output folders this process holds the lock of: resolved path -> (lock file descriptor, pid of
#: the process that took it; a forked child never releases its parent's lock).
_OUTPUT_LOCKS: dict[str, tuple[int, int]] = {}
_OUTPUT_LOCKS_GUARD = threading.Lock()


def output_lock_path(path: str | os.PathLike[str]) -> Path:
    """The lock file of the output folder ``path``: ``.forestreg-lock-<name>`` beside it (a hash
    of the name when the name is too long for a file name)."""
    target = Path(path)
    name = target.name
    if len((LOCK_PREFIX + name).encode("utf-8", "surrogateescape")) > 240:
        import hashlib

        name = hashlib.sha1(name.encode("utf-8", "surrogateescape")).hexdigest()
    return target.parent / f"{LOCK_PREFIX}{name}"


def lock_output_folder(path: str | os.PathLike[str], *, shown: str | os.PathLike[str] | None = None) -> None:
    """Take the exclusive lock of the output folder ``path`` for this process, or refuse at once
    with :class:`~forestreg.engine.core.errors.OutputPathError` naming the process that holds it:
    two runs writing one folder would each say done while the folder holds one run's result.

    The lock is ``flock`` on :func:`output_lock_path` (beside the folder, since the folder itself
    is replaced by a rename): the operating system drops it when the process ends, however it
    ends, so a lock file left by a killed run never blocks a later one. It is released by
    :func:`release_output_folder` (the end of a folder transaction) or when the process exits
    (its file is then removed). Taking it again in the same process does nothing. Without
    ``fcntl`` (Windows), or where the lock file cannot be made, there is no lock."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows
        return
    from .errors import OutputPathError

    target = Path(path).expanduser().resolve()
    key = str(target)
    lock = output_lock_path(target)
    with _OUTPUT_LOCKS_GUARD:
        held = _OUTPUT_LOCKS.get(key)
        if held is not None and held[1] == os.getpid():
            return
        for _ in range(20):
            try:
                fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
            except OSError:
                return  # no lock file here (a read-only parent is refused by the checks)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = _lock_holder(fd)
                os.close(fd)
                raise OutputPathError(
                    f"{shown if shown is not None else target} is being written by another forestreg run "
                    f"({f'pid {holder}' if holder else 'pid unknown'}): wait for it to end, or give another "
                    "output folder"
                ) from None
            except OSError:  # no locks on this file system (some network mounts)
                os.close(fd)
                return
            try:  # the file the lock was taken on must still be the lock file: its holder removes it
                same = os.path.samestat(os.fstat(fd), os.stat(lock))  # when it ends, maybe between our open and flock
            except OSError:
                same = False
            if not same:
                os.close(fd)
                continue
            try:
                os.ftruncate(fd, 0)
                os.write(fd, f"{os.getpid()}\n".encode())
            except OSError:
                pass
            _OUTPUT_LOCKS[key] = (fd, os.getpid())
            return


def _lock_holder(fd: int) -> str:
    """The pid a lock file names (its holder writes it just after taking the lock)."""
    import time

    for _ in range(10):
        try:
            text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
        except OSError:
            return ""
        if text:
            return text
        time.sleep(0.02)
    return ""


def release_output_folder(path: str | os.PathLike[str]) -> None:
    """Release this process's lock of the output folder ``path`` (taken by
    :func:`check_output_folder` or :func:`lock_output_folder`) and remove its lock file; nothing
    when this process does not hold it."""
    key = str(Path(path).expanduser().resolve())
    with _OUTPUT_LOCKS_GUARD:
        held = _OUTPUT_LOCKS.get(key)
        if held is None or held[1] != os.getpid():
            return
        del _OUTPUT_LOCKS[key]
        fd = held[0]
        lock = output_lock_path(key)
        try:  # removed while still held: a run that opened it meanwhile sees it is gone and makes a new one
            if os.path.samestat(os.fstat(fd), os.stat(lock)):
                os.unlink(lock)
        except OSError:
            pass
        finally:
            os.close(fd)


def held_output_locks() -> list[str]:
    """The output folders whose lock this process holds."""
    with _OUTPUT_LOCKS_GUARD:
        return sorted(k for k, (_, pid) in _OUTPUT_LOCKS.items() if pid == os.getpid())


@atexit.register
def _release_all_output_locks() -> None:
    for key in held_output_locks():
        release_output_folder(key)


# ----------------------------------------------------------------------------- locks between processes

#: Lock files this process holds (path -> depth); changed by one thread at a time (the caller's lock).
_HELD_LOCKS: dict[str, int] = {}


@contextlib.contextmanager
def file_lock(path: str) -> Iterator[None]:
    """An exclusive lock on ``path`` between processes (``flock``; re-entrant within this process,
    whose threads take it one at a time under the caller's own lock, e.g. numba's compiler
    lock). Without ``fcntl`` (Windows), or when the file cannot be made, no lock."""
    if path in _HELD_LOCKS:
        _HELD_LOCKS[path] += 1
        try:
            yield
        finally:
            _HELD_LOCKS[path] -= 1
        return
    try:
        import fcntl

        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    except (ImportError, OSError):
        yield
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        _HELD_LOCKS[path] = 1
        try:
            yield
        finally:
            del _HELD_LOCKS[path]
            fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)
