"""The compiled kernels' on-disk cache follows the laws compiled into them."""

from __future__ import annotations


def test_the_kernel_cache_is_dropped_when_a_compiled_in_law_changes(monkeypatch, tmp_path) -> None:
    """numba keys the kernels' cache on ``simloop.py`` only; a changed ``laws.py`` must drop
    them (``simloop._drop_stale_cache``), an unchanged one must keep them."""
    import shutil
    from pathlib import Path

    from dvt_identify import simloop

    here = tmp_path / "pkg"
    (here / "__pycache__").mkdir(parents=True)
    fake_laws = tmp_path / "laws.py"
    shutil.copy(Path(simloop.laws.__file__), fake_laws)
    monkeypatch.setattr(simloop, "__file__", str(here / "simloop.py"))
    monkeypatch.setattr(simloop.laws, "__file__", str(fake_laws))
    kernel = here / "__pycache__" / "simloop.loop-1.py311.nbi"
    kernel.write_text("cached")
    simloop._drop_stale_cache()  # no digest yet: dropped, digest written
    assert not kernel.exists()
    kernel.write_text("cached")
    simloop._drop_stale_cache()  # same sources: kept
    assert kernel.exists()
    fake_laws.write_text(fake_laws.read_text() + "\n# a changed law\n")
    simloop._drop_stale_cache()  # changed: dropped
    assert not kernel.exists()
