"""The sphere tables kept between processes (tracking/sphere.py): read back as computed, a
file that is not the arguments' tables computed again and replaced, a cache that cannot be
written only not kept. A small r_max keeps each computation short."""

import numpy as np
import pytest

from humantele.tracking import sphere

R_MAX = 3.0


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """An empty cache folder, and no tables kept in this process."""
    folder = tmp_path / "cache"
    monkeypatch.setenv(sphere.CACHE_DIR_ENV, str(folder))
    sphere.sphere_tables.cache_clear()
    yield folder
    sphere.sphere_tables.cache_clear()


def fresh(sigma: float = 0.7) -> sphere.SphereTables:
    """The tables as a new process gets them (nothing kept in memory)."""
    sphere.sphere_tables.cache_clear()
    return sphere.sphere_tables(sigma, R_MAX)


def test_tables_are_kept_and_read_back_as_computed(cache):
    computed = sphere.compute_sphere_tables(0.7, R_MAX)
    first = fresh()
    (kept,) = cache.glob("sphere-*.npz")
    assert np.array_equal(first.cg, computed.cg) and first.sigma_px == computed.sigma_px
    assert np.array_equal(first.r_grid, computed.r_grid) and first.rho_step == computed.rho_step
    # what a later process gets is the file's: changed in the file, changed in the tables
    with np.load(kept) as f:
        fields = dict(f)
    np.savez(kept, **{**fields, "cg": fields["cg"] * 0.5})
    assert np.array_equal(fresh().cg, computed.cg * 0.5)
    # another PSF is another file
    other = fresh(0.9)
    assert len(list(cache.glob("sphere-*.npz"))) == 2
    assert not np.array_equal(other.cg, computed.cg)


@pytest.mark.parametrize(
    "spoil",
    [
        lambda p, f: p.write_bytes(b"not an npz"),
        lambda p, f: p.write_bytes(p.read_bytes()[:1000]),  # cut short (a full disk)
        lambda p, f: np.savez(p, **{k: v for k, v in f.items() if k != "cg"}),
        lambda p, f: np.savez(p, **{**f, "cg": np.full_like(f["cg"], np.nan)}),
        lambda p, f: np.savez(p, **{**f, "cg": f["cg"][:, :, :1]}),
        lambda p, f: np.savez(p, **{**f, "r_grid": f["r_grid"] * 2.0}),  # another r_max's
    ],
    ids=["garbage", "truncated", "no-cg", "nan", "shape", "r-max"],
)
def test_a_spoilt_file_is_computed_again_and_replaced(cache, spoil):
    computed = fresh()
    (kept,) = cache.glob("sphere-*.npz")
    with np.load(kept) as f:
        spoil(kept, dict(f))
    again = fresh()
    assert np.array_equal(again.cg, computed.cg) and np.array_equal(again.r_grid, computed.r_grid)
    with np.load(kept) as f:  # replaced by good tables
        assert np.array_equal(f["cg"], computed.cg) and np.array_equal(f["r_grid"], computed.r_grid)
    assert list(cache.iterdir()) == [kept]  # no temporary file left


def test_a_cache_that_cannot_be_written_still_gives_the_tables(tmp_path, monkeypatch):
    blocked = tmp_path / "a-file"
    blocked.write_text("")
    monkeypatch.setenv(sphere.CACHE_DIR_ENV, str(blocked / "cache"))  # under a file
    sphere.sphere_tables.cache_clear()
    try:
        t = sphere.sphere_tables(0.7, R_MAX)
    finally:
        sphere.sphere_tables.cache_clear()
    assert np.array_equal(t.cg, sphere.compute_sphere_tables(0.7, R_MAX).cg)


def test_the_default_folder_is_the_users_cache(monkeypatch, tmp_path):
    monkeypatch.delenv(sphere.CACHE_DIR_ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert sphere.cache_dir() == tmp_path / "humantele"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert sphere.cache_dir() == tmp_path / "home" / ".cache" / "humantele"
