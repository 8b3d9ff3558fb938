"""Fixtures for the real-device paths: a fake OpenHaptics libHD built with the system C compiler."""

import ctypes
import shutil
import subprocess
from pathlib import Path

import pytest

HERE = Path(__file__).parent
NO_CC = "no C compiler to build the fake OpenHaptics libHD (system package g++)"


def _build_fake_hd(out: Path, extra: list[str] | None = None) -> None:
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip(NO_CC)
    subprocess.run(
        [cc, "-shared", "-fPIC", "-O1", "-o", str(out), str(HERE / "fake_libhd.c"),
         *(extra or []), "-lpthread", "-lm"],
        check=True,
    )  # fmt: skip


@pytest.fixture(scope="session")
def fake_hd_path(tmp_path_factory) -> str:
    """Path of the fake libHD.so (tests/devices/fake_libhd.c), compiled once per session."""
    out = tmp_path_factory.mktemp("fakehd") / "libHD.so"
    _build_fake_hd(out)
    return str(out)


@pytest.fixture(scope="session")
def fake_hd_missing_phantomio(tmp_path_factory) -> str:
    """A fake libHD.so linked, as the real one, against the Touch driver's libPhantomIOLib42.so,
    which is then removed: loading it fails on the missing dependency, not on libHD itself."""
    d = tmp_path_factory.mktemp("fakehd_dep")
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip(NO_CC)
    stub_c = d / "phantomio.c"
    stub_c.write_text("int phantom_io_stub(void) { return 0; }\n")
    stub = d / "libPhantomIOLib42.so"
    subprocess.run([cc, "-shared", "-fPIC", "-o", str(stub), str(stub_c)], check=True)
    out = d / "libHD.so"
    _build_fake_hd(out, ["-Wl,--no-as-needed", f"-L{d}", "-lPhantomIOLib42"])
    stub.unlink()
    return str(out)


@pytest.fixture
def fake_hd(fake_hd_path, tmp_path, monkeypatch):
    """(path, handle) of the fake libHD, reset; manual scheduler (ticks run by ``fake_tick``).
    GTDD_HOME points at a configured Touch driver directory, as on a set-up machine."""
    (tmp_path / "3DSystems" / "config").mkdir(parents=True)
    monkeypatch.setenv("GTDD_HOME", str(tmp_path / "3DSystems"))
    fake = ctypes.CDLL(fake_hd_path)
    for fn in ("fake_force", "fake_max_force_seen", "fake_temperature", "fake_offset",
               "fake_timing"):  # fmt: skip
        getattr(fake, fn).restype = ctypes.c_double
    fake.fake_timing.argtypes = [ctypes.c_int, ctypes.c_double]
    fake.fake_timing_over.argtypes = [ctypes.c_int, ctypes.c_double]
    fake.fake_timing_over.restype = ctypes.c_long
    fake.fake_counter.restype = ctypes.c_long
    fake.fake_thread_policy.restype = ctypes.c_long
    fake.fake_set_nominal_max_force.argtypes = [ctypes.c_double]
    fake.fake_set_nominal_continuous_force.argtypes = [ctypes.c_double]
    fake.fake_set_thermal.argtypes = [ctypes.c_double, ctypes.c_double]
    fake.fake_set_velocity.argtypes = [ctypes.c_double] * 3
    fake.fake_fail_at_tick.argtypes = [ctypes.c_long, ctypes.c_uint]
    fake.fake_set_calibration_delay.argtypes = [ctypes.c_long]
    fake.fake_set_watchdog_us.argtypes = [ctypes.c_long]
    fake.fake_set_transform.argtypes = [ctypes.POINTER(ctypes.c_double)]
    fake.fake_reset(1)
    # The watchdog (a tick over 1 ms faults, as the real scheduler's) is off in the fake until
    # a test sets it, so that a busy test machine's stall is not taken for a defect; the tests
    # of the watchdog turn it on. fake_reset leaves it as set.
    fake.fake_set_watchdog_us(0)
    yield fake_hd_path, fake
    fake.fake_reset(1)
