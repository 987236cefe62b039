"""Compiled kernels: one decorator for every numba kernel of the engine, and a
helper that runs a kernel over blocks of rows on a pool of threads.

Kernels are compiled on first use and cached on disk, in one folder per forestreg and numba
version (:func:`kernel_cache_dir`; ``NUMBA_CACHE_DIR``, when set, wins; without any writable
place they are compiled in each process). ``forestreg warmup`` (run by ``scripts/setup.sh``)
compiles them all ahead, so that no command pays for it. The cache is safe when several processes
compile at once (batch workers, the service's jobs): a kernel is compiled under a lock file of its
own (one process compiles it, the others wait and load it), an entry's data file is written before
the index that names it (each written whole, then renamed into place), and an entry is loaded only
when it holds the signature asked for; anything else is compiled again. Kernels release the
interpreter lock (``nogil``), so blocks of independent rows run in parallel threads.

The cache subclasses numba's ``numba.core.caching`` rather than using ``numba.njit(cache=True)``:
that cache lives in ``__pycache__`` beside the sources (or ``NUMBA_CACHE_DIR`` for the whole
process), not in a folder per forestreg and numba version; it writes an entry's index before its
data and loads an entry without checking its signature, so two processes compiling one kernel at
once (a batch's workers) can leave an index naming data of another signature, or none.
``numba.core.caching`` is not numba's public API: pyproject.toml pins the numba versions it is
tested with (:data:`NUMBA_RANGE`), and :func:`numba_cache_api` fails at import, naming what is
missing, on a numba that lacks a part of it.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable, Iterable, Optional

import numba
from numba.core import caching, sigutils
from numba.core.compiler_lock import global_compiler_lock

from .atomic import file_lock

__all__ = ["kernel", "kernel_cache_dir", "kernels", "preload", "remember_loaded", "run_blocks", "worker_count"]

log = logging.getLogger(__name__)

#: Every kernel made by :func:`kernel`, in the order their modules defined them.
_KERNELS: list[Any] = []


def kernel(fn: Callable[..., Any] | None = None, **options: Any) -> Any:
    """``numba.njit(nogil=True, **options)``, cached on disk by :class:`_KernelCache` (without a
    writable cache location, uncached). Use as ``@kernel`` or ``@kernel(error_model="numpy")``."""
    if fn is None:
        return lambda f: kernel(f, **options)
    dispatcher = numba.njit(nogil=True, **options)(fn)
    try:
        dispatcher._cache = _KernelCache(dispatcher.py_func)
    except RuntimeError:  # no directory to cache in: compiled in each process
        pass
    else:
        _locked_compile(dispatcher)
    _KERNELS.append(dispatcher)
    return dispatcher


def kernels() -> list[Any]:
    """Every kernel of the modules imported so far (numba dispatchers)."""
    return list(_KERNELS)


def kernel_cache_dir() -> Optional[str]:
    """The folder the compiled kernels are cached in: ``NUMBA_CACHE_DIR`` when set, else one
    folder per forestreg, numba and Python version in the user's cache folder
    (``$XDG_CACHE_HOME/forestreg/kernels/...``, by default ``~/.cache/forestreg/kernels/...``).
    None when neither is set (no home folder)."""
    if numba.config.CACHE_DIR:
        return str(numba.config.CACHE_DIR)
    base = os.environ.get("XDG_CACHE_HOME") or (
        os.path.join(os.path.expanduser("~"), ".cache") if os.path.expanduser("~") != "~" else ""
    )
    if not base:
        return None
    from ..._version import __version__

    tag = f"{__version__}-numba{numba.__version__}-py{sys.version_info[0]}{sys.version_info[1]}"
    return os.path.join(base, "forestreg", "kernels", tag)


#: The file ``forestreg warmup`` writes into :func:`kernel_cache_dir` once every kernel is
#: compiled: the source files of the kernels and a hash of each (JSON).
WARM_MARK = "warmed.json"


def _source_hashes(files: Iterable[str]) -> dict[str, str]:
    import hashlib

    out = {}
    for name in files:
        try:
            with open(name, "rb") as f:
                out[name] = hashlib.sha256(f.read()).hexdigest()
        except OSError:
            out[name] = ""
    return out


def kernel_source_files() -> list[str]:
    """The engine's source files that define compiled kernels (their text holds ``@kernel``)."""
    engine = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    out = []
    for folder, _, names in os.walk(engine):
        for name in names:
            if name.endswith(".py"):
                path = os.path.join(folder, name)
                try:
                    with open(path, encoding="utf-8") as f:
                        if "@kernel" in f.read():
                            out.append(path)
                except (OSError, UnicodeDecodeError):
                    continue
    return sorted(out)


def warm_record() -> dict[str, Any]:
    """What :func:`cache_is_warm` checks: the number of kernels of every module imported so far,
    and a hash of each source file that defines kernels, imported or not (written by
    ``forestreg warmup`` as :data:`WARM_MARK`)."""
    files = sorted({k.py_func.__code__.co_filename for k in _KERNELS} | set(kernel_source_files()))
    return {"kernels": len(_KERNELS), "files": _source_hashes(files)}


def cache_is_warm(files: Optional[Iterable[str]] = None) -> bool:
    """Whether ``forestreg warmup`` has compiled the kernels of the source ``files`` (default:
    every file it recorded, and every engine file that defines kernels now: a new one makes the
    cache cold) into :func:`kernel_cache_dir`, and they have not changed since."""
    import json

    folder = kernel_cache_dir()
    if not folder:
        return False
    try:
        with open(os.path.join(folder, WARM_MARK), encoding="utf-8") as f:
            recorded = json.load(f)["files"]
    except (OSError, ValueError, KeyError, TypeError):
        return False
    if files is None:
        files = sorted(set(recorded) | set(kernel_source_files()))
    files = list(files)
    return bool(files) and all(recorded.get(k) == v for k, v in _source_hashes(files).items())


#: The numba versions the kernel cache is tested with (pyproject.toml pins the same range).
NUMBA_RANGE = ">=0.59,<0.69"

#: What the kernel cache takes from ``numba.core.caching`` (not numba's public API, hence the pin):
#: each class and the members of it that :class:`_VersionedLocator`, :class:`_CheckedCacheFile`
#: and :class:`_KernelCache` use or override.
NUMBA_CACHE_API = {
    "_SourceFileBackedLocatorMixin": ("from_function",),
    "CompileResultCacheImpl": ("_locator_classes",),
    "IndexDataCacheFile": ("save", "load", "_load_index", "_save_index", "_save_data", "_data_name"),
    "FunctionCache": ("load_overload", "_impl_class"),
}


def numba_cache_api() -> tuple[Any, Any]:
    """numba's locator of ``NUMBA_CACHE_DIR`` (``UserProvidedCacheLocator``, public since numba
    0.62, with a leading underscore before) and its ``CompileResultCacheImpl``, after checking that
    every name in :data:`NUMBA_CACHE_API` is there; ImportError naming the missing ones, numba's
    version and :data:`NUMBA_RANGE` otherwise."""
    locator = getattr(caching, "UserProvidedCacheLocator", None) or getattr(caching, "_UserProvidedCacheLocator", None)
    missing = [] if locator is not None else ["UserProvidedCacheLocator"]
    for name, members in NUMBA_CACHE_API.items():
        cls = getattr(caching, name, None)
        if cls is None:
            missing.append(name)
            continue
        missing += [f"{name}.{m}" for m in members if not hasattr(cls, m)]
    if locator is not None and not hasattr(locator, "get_suitable_cache_subpath"):
        missing.append("UserProvidedCacheLocator.get_suitable_cache_subpath")
    if missing:
        raise ImportError(
            f"forestreg's compiled-kernel cache (engine/core/jit.py) builds on numba.core.caching, which in numba "
            f"{numba.__version__} lacks {', '.join(missing)}: install numba{NUMBA_RANGE} (the range forestreg is tested with)"
        )
    return locator, caching.CompileResultCacheImpl


_UserLocator, _ResultCacheImpl = numba_cache_api()


class _VersionedLocator(_UserLocator):
    """numba's locator of ``NUMBA_CACHE_DIR``, pointed at :func:`kernel_cache_dir`."""

    def __init__(self, py_func: Any, py_file: str) -> None:
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno
        self._cache_path = os.path.join(kernel_cache_dir() or "", self.get_suitable_cache_subpath(py_file))

    @classmethod
    def from_function(cls, py_func: Any, py_file: str) -> Any:
        if not kernel_cache_dir():
            return None
        return caching._SourceFileBackedLocatorMixin.from_function.__func__(cls, py_func, py_file)


class _KernelCacheImpl(_ResultCacheImpl):
    # NUMBA_CACHE_DIR (when set), then the per-version folder, then numba's own places
    _locator_classes = [_UserLocator, _VersionedLocator] + [
        c for c in _ResultCacheImpl._locator_classes if c is not _UserLocator
    ]


class _CheckedCacheFile(caching.IndexDataCacheFile):
    """numba's index and data files, with the order of writes made safe and every load checked.

    numba saves an entry by writing the index (naming a data file) and then the data file, each
    atomically; two processes that compile two signatures of one kernel at once may choose the
    same data file for different signatures, and a process killed between the two writes leaves
    an index naming a data file it never wrote. Here the data file is written first, an entry is
    written under the kernel's lock (:func:`_locked_compile`), and a loaded entry is used only
    when it is the signature asked for and unpickles whole; otherwise the kernel is compiled again."""

    def save(self, key: Any, data: Any) -> None:
        overloads = self._load_index()
        name = overloads.get(key)
        if name is None:
            existing = set(overloads.values())
            number = 1
            while self._data_name(number) in existing:
                number += 1
            name = self._data_name(number)
        self._save_data(name, data)
        overloads = self._load_index()  # as it is now (under the kernel's lock: unchanged)
        overloads[key] = name
        self._save_index(overloads)

    def load(self, key: Any) -> Any:
        try:
            data = super().load(key)
        except Exception as exc:  # a damaged file: compiled again (and the entry rewritten)
            log.info("compiled kernel cache: entry not readable (%s: %s); compiling again", type(exc).__name__, exc)
            return None
        if data is None:
            return None
        try:
            wanted = tuple(sigutils.normalize_signature(key[0])[0])
            held = tuple(data[3].args)  # CompileResult._reduce(): (library, fndesc, env, signature, ...)
        except Exception:
            return None
        if held != wanted:
            log.info("compiled kernel cache: an entry holds another signature; compiling again")
            return None
        return data


class _KernelCache(caching.FunctionCache):
    """numba's cache of compiled functions, in :func:`kernel_cache_dir` with checked entries."""

    _impl_class = _KernelCacheImpl

    def __init__(self, py_func: Any) -> None:
        super().__init__(py_func)
        self._cache_file.__class__ = _CheckedCacheFile

    def load_overload(self, sig: Any, target_context: Any) -> Any:
        data = super().load_overload(sig, target_context)
        if data is None:
            _say_compiling(self._py_func.__code__.co_filename)
        return data

    @property
    def lock_path(self) -> str:
        return os.path.join(self._cache_path, self._cache_file._index_name[: -len(".nbi")] + ".lock")


_SAID = False


def _say_compiling(source: str) -> None:
    """Say once in a process that the kernels are being compiled, when ``forestreg warmup`` has
    not compiled them ahead (the first command after an install pays for it); ``source``: the
    file of the kernel being compiled. Compiling leaves much cyclic garbage: Python's collector,
    when a command turned it off (a small pair's ``forestreg register``), is turned on again."""
    import gc

    gc.enable()
    global _SAID
    if _SAID:
        return
    _SAID = True
    if os.environ.get("FORESTREG_WARMUP") or cache_is_warm([source]):
        log.info("compiling a kernel not compiled ahead")
        return
    log.warning(
        "compiling the numerical kernels for this machine: about %d s, only on the first run "
        "('forestreg warmup' does it ahead; they are kept in %s)",
        FIRST_COMPILE_S,
        kernel_cache_dir() or "no cache folder",
    )


#: Seconds the first command after an install spends compiling its kernels (measured on 2 cores).
FIRST_COMPILE_S = 45


def _locked_compile(dispatcher: Any) -> None:
    """Make ``dispatcher.compile`` (numba calls it for every signature not yet in memory) hold
    numba's compiler lock and then the kernel's lock file: of several processes compiling one
    kernel, one compiles and saves it, the others then load it from the cache. The order of the
    two locks is the same everywhere, and a kernel's lock is taken before those of the kernels it
    calls (kernels do not call each other in cycles), so no two holders wait for each other."""
    compile_now = dispatcher.compile
    cache = dispatcher._cache

    def compile(sig: Any) -> Any:
        with global_compiler_lock:
            _blas_module_alone()
            args, _ = sigutils.normalize_signature(sig)
            if tuple(args) in dispatcher.overloads:
                return compile_now(sig)
            with file_lock(cache.lock_path):
                made = compile_now(sig)
            _LOADED.append((dispatcher, tuple(args)))
            return made

    dispatcher.compile = compile


_BLAS_CHECKED = False


def _blas_module_alone() -> None:
    """Load SciPy's ``scipy.linalg.cython_blas`` extension module by itself, under its own name,
    before numba's first compile or load of a kernel in this process (called under numba's
    compiler lock). numba then checks that BLAS is there by importing that module, which imports
    the whole ``scipy.linalg`` package first (~0.1 s of a small pair's run, mostly SciPy's array-API
    layer); found in ``sys.modules``, the module alone serves (numba takes only the addresses of
    its functions), and a later ``import scipy.linalg`` imports the package as usual. Nothing is
    done once ``scipy.linalg`` is imported, or when the module cannot be found where SciPy keeps
    it (numba's own import then runs)."""
    global _BLAS_CHECKED
    if _BLAS_CHECKED:
        return
    _BLAS_CHECKED = True
    name = "scipy.linalg.cython_blas"
    if name in sys.modules or "scipy.linalg" in sys.modules:
        return
    try:
        import importlib.machinery
        import importlib.util

        scipy_spec = importlib.util.find_spec("scipy")
        if scipy_spec is None or not scipy_spec.origin:
            return
        folder = os.path.join(os.path.dirname(scipy_spec.origin), "linalg")
        path = next(
            (
                p
                for p in (os.path.join(folder, "cython_blas" + s) for s in importlib.machinery.EXTENSION_SUFFIXES)
                if os.path.exists(p)
            ),
            None,
        )
        if path is None:
            return
        spec = importlib.util.spec_from_file_location(name, path)
        if spec is None or spec.loader is None:
            return
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    except Exception:  # numba imports it the usual way
        sys.modules.pop(name, None)


#: (kernel, argument types) in the order this process loaded (or compiled) them.
_LOADED: list[tuple[Any, tuple]] = []


def _loaded_list_path(name: str) -> Optional[str]:
    folder = kernel_cache_dir()
    return os.path.join(folder, f"loaded-{name}.pkl") if folder else None


def remember_loaded(name: str) -> None:
    """Keep, in :func:`kernel_cache_dir`, the list of the kernels (and signatures) this process has
    loaded so far, in their order, under ``name`` (a use case, e.g. ``"pair"``), for
    :func:`preload` in the next process; written only when it differs from the one kept."""
    import pickle

    path = _loaded_list_path(name)
    if not path:
        return
    listed = [(k.py_func.__module__, k.py_func.__name__, args) for k, args in list(_LOADED)]
    try:
        with open(path, "rb") as f:
            if pickle.load(f) == listed:
                return
    except Exception:  # none kept yet, or unreadable: written anew
        pass
    try:
        tmp = f"{path}.{os.getpid()}.tmp"
        with open(tmp, "wb") as f:
            pickle.dump(listed, f)
        os.replace(tmp, path)
    except OSError:  # a read-only cache: nothing kept
        pass


def preload(name: str, wait_s: float = 10.0) -> None:
    """Load, in this thread and in their order, the kernels a process running the use case
    ``name`` loaded last time (:func:`remember_loaded`): called in a background thread while the
    inputs are read and the engine is imported, so that the first calls find them loaded. This
    thread imports nothing: a kernel whose module the use case has not imported yet is loaded once
    it has (two threads importing the same modules at once may deadlock; at most ``wait_s``
    without any new module). A
    kernel that cannot be found or loaded is skipped (it is loaded, or its failure reported, where
    it is called)."""
    import pickle
    import time

    path = _loaded_list_path(name)
    try:
        with open(path or "", "rb") as f:
            listed = pickle.load(f)
    except Exception:
        return
    until = time.monotonic() + wait_s
    while listed and time.monotonic() < until:
        # the first in their order whose module is imported (a later one while an earlier waits)
        ready = next((i for i, entry in enumerate(listed) if _imported(entry[0])), None)
        if ready is None:
            time.sleep(0.005)
            continue
        module, fn_name, args = listed.pop(ready)
        until = time.monotonic() + wait_s
        try:
            dispatcher = getattr(sys.modules[module], fn_name)
            if args not in dispatcher.overloads:
                dispatcher.compile(args)
        except Exception:
            pass


def _imported(module: str) -> bool:
    """Whether ``module`` is imported whole (not being imported)."""
    m = sys.modules.get(module)
    return m is not None and not getattr(getattr(m, "__spec__", None), "_initializing", False)


def worker_count() -> int:
    """Cores this process may run on: its CPU affinity, at most ``FORESTREG_THREADS`` when that is
    set (a batch runs each plot's process with the cores it shares out to it)."""
    try:
        cores = max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        cores = max(1, os.cpu_count() or 1)
    try:
        return max(1, min(cores, int(os.environ.get("FORESTREG_THREADS") or cores)))
    except ValueError:
        return cores


def run_blocks(fn: Callable[..., Any], n: int, *args: Any, block: int = 32768, compiles: bool = True) -> None:
    """Call ``fn(start, stop, *args)`` for consecutive blocks of ``block`` rows covering
    ``range(n)``; ``fn`` writes its rows' results into arrays among ``args`` (blocks must be
    independent). The blocks run on the process's pool of one thread per core (:func:`_pool`),
    when there are more than one core; the first block runs alone in the calling thread while
    ``fn`` is a kernel not compiled or loaded yet (one thread compiles it, the others would wait),
    or a Python function (which may call such kernels; ``compiles=False``: it calls none, e.g.
    only NumPy or LAPACK, and all its blocks go to the pool at once). ``fn`` must not wait for
    other blocks (compiled kernels never do): callers in several threads share the pool."""
    if n <= 0:
        return
    starts = list(range(0, n, block))
    if compiles and not getattr(fn, "signatures", None):  # not a kernel, or one not compiled or loaded yet
        fn(0, min(n, block), *args)
        starts = starts[1:]
    if min(worker_count(), len(starts)) <= 1:
        for a in starts:
            fn(a, min(n, a + block), *args)
        return
    pool = _pool()
    for f in [pool.submit(fn, a, min(n, a + block), *args) for a in starts]:
        f.result()


_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()


def _pool() -> ThreadPoolExecutor:
    """The threads :func:`run_blocks` runs blocks on: one per core, made on first use and kept
    (a registration calls it hundreds of times; starting threads each time cost ~0.1 s of an ICP
    run). A forked child makes its own."""
    global _POOL
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(worker_count(), thread_name_prefix="forestreg-blocks")
        return _POOL


def _forget_pool() -> None:
    global _POOL, _POOL_LOCK
    _POOL, _POOL_LOCK = None, threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)
