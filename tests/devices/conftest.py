"""Fixtures for the real-device paths: a fake OpenHaptics libHD built with the system C compiler."""

import ctypes
import shutil
import subprocess
from pathlib import Path

import pytest

HERE = Path(__file__).parent


@pytest.fixture(scope="session")
def fake_hd_path(tmp_path_factory) -> str:
    """Path of the fake libHD.so (tests/devices/fake_libhd.c), compiled once per session."""
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler (cc/gcc) to build the fake OpenHaptics libHD")
    out = tmp_path_factory.mktemp("fakehd") / "libHD.so"
    subprocess.run(
        [cc, "-shared", "-fPIC", "-O1", "-o", str(out), str(HERE / "fake_libhd.c"), "-lpthread"],
        check=True,
    )
    return str(out)


@pytest.fixture
def fake_hd(fake_hd_path):
    """(path, handle) of the fake libHD, reset; manual scheduler (ticks run by ``fake_tick``)."""
    fake = ctypes.CDLL(fake_hd_path)
    fake.fake_force.restype = ctypes.c_double
    fake.fake_max_force_seen.restype = ctypes.c_double
    fake.fake_counter.restype = ctypes.c_long
    fake.fake_set_nominal_max_force.argtypes = [ctypes.c_double]
    fake.fake_set_velocity.argtypes = [ctypes.c_double] * 3
    fake.fake_fail_at_tick.argtypes = [ctypes.c_long, ctypes.c_uint]
    fake.fake_set_transform.argtypes = [ctypes.POINTER(ctypes.c_double)]
    fake.fake_reset(1)
    yield fake_hd_path, fake
    fake.fake_reset(1)
