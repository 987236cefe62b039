"""The compiled-kernel cache builds on numba's non-public ``numba.core.caching``: the installed
numba lies in the range pyproject.toml pins, has every part the cache uses, and a numba without
one fails at import with a message naming it and the range."""

from __future__ import annotations

import re
from pathlib import Path

import numba
import pytest
from numba.core import caching

from forestreg.engine.core import jit

ROOT = Path(__file__).resolve().parents[1]


def _version(text: str) -> tuple[int, ...]:
    return tuple(int(v) for v in re.findall(r"\d+", text)[:3])


def test_pyproject_pins_the_tested_numba_range():
    pinned = re.search(r'"numba([^"]*)"', (ROOT / "pyproject.toml").read_text()).group(1)
    assert pinned == jit.NUMBA_RANGE
    low, high = (m.group(1) for m in (re.search(r">=([\d.]+)", pinned), re.search(r"<([\d.]+)", pinned)))
    installed = _version(numba.__version__)
    assert _version(low) <= installed < _version(high), (
        f"numba {numba.__version__} is outside the tested range numba{pinned}: run tests/test_jit_numba_api.py and "
        "the kernel tests with it, then move the pin in pyproject.toml and engine/core/jit.py's NUMBA_RANGE"
    )


def test_installed_numba_has_every_part_the_cache_uses():
    locator, impl = jit.numba_cache_api()
    assert issubclass(jit._VersionedLocator, locator) and issubclass(jit._KernelCacheImpl, impl)
    for name, members in jit.NUMBA_CACHE_API.items():
        cls = getattr(caching, name)
        for member in members:
            assert hasattr(cls, member), f"numba {numba.__version__}: numba.core.caching.{name}.{member} is gone"


def test_a_kernel_is_cached_through_it(tmp_path, monkeypatch):
    monkeypatch.setattr(numba.config, "CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(jit, "_LOADED", list(jit._LOADED))  # this process's list for the next one: unchanged

    def twice(x):
        return 2.0 * x

    k = jit.kernel(twice)
    jit._KERNELS.remove(k)
    assert k(1.5) == 3.0
    assert isinstance(k._cache, jit._KernelCache)
    assert list(tmp_path.rglob("*.nbi")) and list(tmp_path.rglob("*.nbc")), "nothing written to the cache folder"


@pytest.mark.parametrize("gone", ["IndexDataCacheFile", "IndexDataCacheFile._save_data"])
def test_a_missing_part_fails_loudly(monkeypatch, gone):
    owner, _, member = gone.partition(".")
    if member:
        monkeypatch.delattr(getattr(caching, owner), member)
    else:
        monkeypatch.delattr(caching, owner)
    with pytest.raises(ImportError) as err:
        jit.numba_cache_api()
    text = str(err.value)
    assert gone in text and numba.__version__ in text and jit.NUMBA_RANGE in text
