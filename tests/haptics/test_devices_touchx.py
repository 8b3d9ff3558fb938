"""The touchx backend's libHD binding, against a fake libHD compiled for the test (no device)."""

import ctypes
import math
import shutil
import subprocess

import pytest

from humantele.haptics.devices import DeviceError, TouchX, TouchXConfig

FAKE_HD = r"""
typedef struct { unsigned int errorCode; int internalErrorCode; unsigned int hHD; } HDErrorInfo;
static double force[3]; static int frames, in_frame, enabled, started, err_after = -1;
static double T[16] = {0,1,0,0, -1,0,0,0, 0,0,1,0, 10,20,-30,1};  /* column-major, mm */
unsigned int hdInitDevice(const char *name) { return 0; }
HDErrorInfo hdGetError(void) {
    HDErrorInfo e = {0, 0, 0};
    if (err_after >= 0 && frames > err_after) e.errorCode = 0x0302;  /* HD_COMM_ERROR */
    return e;
}
void hdEnable(unsigned int cap) { if (cap == 0x4000) enabled = 1; }
void hdStartScheduler(void) { started = 1; }
void hdStopScheduler(void) { started = 0; }
void hdDisableDevice(unsigned int h) { enabled = 0; }
void hdBeginFrame(unsigned int h) { in_frame++; }
void hdEndFrame(unsigned int h) { in_frame--; frames++; }
void hdGetDoublev(unsigned int what, double *v) {
    if (what == 0x2052) for (int i = 0; i < 16; i++) v[i] = T[i];
}
void hdGetIntegerv(unsigned int what, int *v) { if (what == 0x2000) *v = 2; }
void hdSetDoublev(unsigned int what, const double *v) {
    if (what == 0x2700 && in_frame == 1) for (int i = 0; i < 3; i++) force[i] = v[i];
}
double fake_force(int i) { return force[i]; }
int fake_state(void) { return enabled * 100 + started * 10 + in_frame; }
void fake_fail_after(int n) { err_after = n; }
"""


@pytest.fixture
def fake_hd(tmp_path):
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler for the fake libHD")
    src, lib = tmp_path / "fakehd.c", tmp_path / "libHD.so"
    src.write_text(FAKE_HD)
    subprocess.run([cc, "-shared", "-fPIC", "-o", str(lib), str(src)], check=True)
    fake = ctypes.CDLL(str(lib))
    fake.fake_force.restype = ctypes.c_double
    return str(lib), fake


def test_reads_pose_in_metres_and_commands_force_in_one_frame(fake_hd):
    path, fake = fake_hd
    dev = TouchX(TouchXConfig(library=path))
    dev.open()
    assert fake.fake_state() == 110  # force output enabled, scheduler started
    s = dev.read()
    assert s.position == pytest.approx((0.010, 0.020, -0.030))
    # Rotation +90 deg about z (x axis -> y axis): quaternion (0, 0, sin 45, cos 45).
    assert s.quaternion == pytest.approx((0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)))
    assert s.buttons == 2
    assert fake.fake_state() % 10 == 1  # the frame stays open until the force is set
    dev.command_force((1.0, -2.0, 0.5))
    assert [fake.fake_force(i) for i in range(3)] == [1.0, -2.0, 0.5]
    assert fake.fake_state() % 10 == 0
    dev.read()
    dev.command_force((100.0, 0.0, math.nan))  # never NaN, never over the peak force
    assert [fake.fake_force(i) for i in range(3)] == [0.0, 0.0, 0.0]
    dev.read()
    dev.command_force((0.0, 100.0, 0.0))
    assert fake.fake_force(1) == pytest.approx(7.9)
    dev.close()
    assert fake.fake_force(1) == 0.0 and fake.fake_state() == 0  # zeroed, stopped, disabled


def test_hd_errors_become_device_errors(fake_hd):
    path, fake = fake_hd
    dev = TouchX(TouchXConfig(library=path))
    dev.open()
    fake.fake_fail_after(1)
    dev.read()
    dev.command_force((0.0, 0.0, 0.0))
    with pytest.raises(DeviceError, match="0x0302"):
        dev.read()
        dev.command_force((0.0, 0.0, 0.0))
    dev.close()
