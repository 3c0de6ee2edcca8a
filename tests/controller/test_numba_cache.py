"""The compiled kernels of ``rt_controller/control/`` are cached by numba with a stamp that
covers the whole package (``control/numba_cache.py``): a kernel split across modules never
runs stale machine code of another module."""

from __future__ import annotations

from rt_controller.control import decide_kernel, model_kernels, numba_cache
from rt_controller.control.rhc import dynamics, gmres, kernel, residual


def test_every_kernel_of_the_package_is_stamped_with_the_package():
    for f in (
        kernel.rhc_tick,
        gmres.block_gmres,
        residual.eval_F,
        dynamics.rhs,
        decide_kernel.decide_tick,
        model_kernels.prepare,
    ):
        stamp = f._cache._impl.locator.get_source_stamp()
        assert stamp[1] == numba_cache.package_digest(), f.__name__


def test_a_change_to_any_module_of_the_package_changes_the_stamp(tmp_path, monkeypatch):
    (tmp_path / "sub").mkdir()
    (tmp_path / "a.py").write_text("A = 1\n")
    (tmp_path / "sub" / "b.py").write_text("B = 2\n")
    monkeypatch.setattr(numba_cache, "PACKAGE", tmp_path)
    digests = []
    for edit in (None, "B = 3\n", "B = 3\n"):
        numba_cache.package_digest.cache_clear()
        if edit:
            (tmp_path / "sub" / "b.py").write_text(edit)
        digests.append(numba_cache.package_digest())
    numba_cache.package_digest.cache_clear()
    assert digests[0] != digests[1] == digests[2]
