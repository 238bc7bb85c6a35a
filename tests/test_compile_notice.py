"""A numba compile of one of hairexp's kernels is said once per process (a cold cache, or a code
path not compiled before, took minutes without a word); a kernel loaded from the cache, or another
package's function, says nothing."""

from __future__ import annotations

import logging

import pytest

from hairexp.physics import kernels

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba")


def _fresh(module: str):
    def twice(x):
        return 2.0 * x
    twice.__module__ = module
    return kernels.njit(cache=False)(twice)


def test_the_first_compile_of_a_hairexp_kernel_is_said_once(caplog, monkeypatch):
    monkeypatch.setattr(kernels.COMPILE_NOTICE, "said", False)
    with caplog.at_level(logging.INFO, logger="hairexp"):
        assert _fresh("elsewhere.module")(1.0) == 2.0
        assert "numba is compiling" not in caplog.text
        assert _fresh("hairexp.physics.some_kernels")(2.0) == 4.0
        assert _fresh("hairexp.physics.other_kernels")(3.0) == 6.0
    assert caplog.text.count("numba is compiling hairexp's kernels (twice first)") == 1
