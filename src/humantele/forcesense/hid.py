"""The force sensor board over USB HID (hidapi): report parsing and the device backend.

Report layout (64 bytes, little-endian; docs/force_sensor_hid.md is the reference):

====== ==== ===================================================================
offset size field
====== ==== ===================================================================
0      1    report id, 0x01
1      1    layout version, 1
2      2    sequence number (uint16, wraps)
4      4    board time, microseconds (uint32, wraps)
8      1    number of pairs P (3..6)
9      1    flags: bit 0 over-range, bit 1 sensor fault
10     2    board temperature (int16, 0.01 deg C)
12     24   6 pairs x (a, b) int16, 0.005 mT per count (unused pairs 0)
36     26   reserved, 0
62     2    CRC-16/CCITT-FALSE of bytes 0..61 (uint16)
====== ==== ===================================================================

A report that is short, has a wrong id/version/pair count, a bad CRC or a fault flag is
dropped and counted by reason; nothing raises into the caller's loop.

An unplugged board (issue 30 §2): hidapi's read raises (``OSError("read error")``; a
``ValueError`` once closed; other bindings a ``RuntimeError``): counted in ``dropped["io"]``,
the handle closed, and the board looked for again (``hid.enumerate``, ``open_path``: it may
come back on another path) on later reads, after ``reopen_s``, doubled per failed try up to
``reopen_max_s`` (0.25 s, 0.5 s, 1 s: back within about a second of the replug). One
``read`` drains at most ``max_reports`` reports and ``max_read_ms`` (a board that never
stops sending cannot hold it: 20,000 reports, 10.8 s, before the bound).
"""

from __future__ import annotations

import binascii
import struct
import time
from collections.abc import Callable
from typing import Literal

import numpy as np
from pydantic import Field

from humantele.config import ConfigModel
from humantele.forcesense.base import ForceSensor, ForceSensorUnavailable
from humantele.forcesense.readings import ForceReading

REPORT_ID = 0x01
VERSION = 1
REPORT_SIZE = 64
MAX_PAIRS = 6
MT_PER_COUNT = 0.005
FLAG_OVER_RANGE = 0x01
FLAG_FAULT = 0x02
_HEAD = struct.Struct("<BBHIBBh")  # 12 bytes
_PAIRS = struct.Struct(f"<{2 * MAX_PAIRS}h")  # 24 bytes


class ReportError(ValueError):
    """A report that cannot be used; ``reason`` is a short key for counting."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason = reason


def crc16_ccitt(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no xor-out): the
    standard library's ``binascii.crc_hqx`` (in C; the bitwise loop in Python took about
    1 ms a report on a busy machine, a tenth of a core at the board's 100 Hz)."""
    return binascii.crc_hqx(bytes(data), crc)


def encode_report(
    seq: int, t_us: int, a_mt, b_mt, temperature_c: float = 25.0, flags: int = 0
) -> bytes:
    """The 64-byte report the board sends (used by tests and the board's firmware docs)."""
    a = np.asarray(a_mt, dtype=float)
    b = np.asarray(b_mt, dtype=float)
    p = len(a)
    vals = np.zeros(2 * MAX_PAIRS)
    vals[0 : 2 * p : 2] = a
    vals[1 : 2 * p : 2] = b
    counts = np.clip(np.rint(vals / MT_PER_COUNT), -32768, 32767).astype(int)
    head = _HEAD.pack(
        REPORT_ID,
        VERSION,
        seq & 0xFFFF,
        t_us & 0xFFFFFFFF,
        p,
        flags,
        int(round(temperature_c * 100)),
    )
    body = head + _PAIRS.pack(*counts.tolist()) + bytes(26)
    return body + struct.pack("<H", crc16_ccitt(body))


def parse_report(data: bytes | bytearray | list[int]) -> tuple[ForceReading, int]:
    """(reading with t = board time in s, flags) from one report; ReportError if unusable."""
    raw = bytes(data)
    if len(raw) < REPORT_SIZE:
        raise ReportError("short", f"{len(raw)} bytes, need {REPORT_SIZE}")
    raw = raw[:REPORT_SIZE]
    rid, ver, seq, t_us, p, flags, temp = _HEAD.unpack_from(raw, 0)
    if rid != REPORT_ID:
        raise ReportError("report_id", f"0x{rid:02x}")
    if ver != VERSION:
        raise ReportError("version", str(ver))
    (crc,) = struct.unpack_from("<H", raw, 62)
    if crc != crc16_ccitt(raw[:62]):
        raise ReportError("crc", "checksum mismatch")
    if not 3 <= p <= MAX_PAIRS:
        raise ReportError("pairs", f"{p} pairs")
    if flags & FLAG_FAULT:
        raise ReportError("fault", "sensor fault flag set")
    counts = np.array(_PAIRS.unpack_from(raw, 12), dtype=float) * MT_PER_COUNT
    reading = ForceReading(
        t_us * 1e-6, counts[0 : 2 * p : 2], counts[1 : 2 * p : 2], temp / 100.0, seq
    )
    return reading, flags


class HidForceConfig(ConfigModel):
    """The sensor board's USB ids (and serial, to pick one of several)."""

    backend: Literal["hid"] = "hid"
    vendor_id: int = Field(0x1209, ge=0, le=0xFFFF, description="pid.codes test VID")
    product_id: int = Field(0x4854, ge=0, le=0xFFFF)
    serial: str | None = None
    read_timeout_ms: int = Field(20, ge=0, le=1000, description="wait for the first report")
    max_reports: int = Field(64, ge=1, le=10_000, description="reports one read drains at most")
    max_read_ms: float = Field(30.0, gt=0, le=1000, description="ms one read drains at most")
    reopen_s: float = Field(0.25, ge=0, le=60, description="first wait to look for a lost board")
    reopen_max_s: float = Field(1.0, ge=0, le=60, description="the wait's cap (s)")


class HidForceSensor(ForceSensor):
    """Reads reports from the board; ``read`` returns the newest good reading or None.

    ``device``: an already open hidapi-like device (``read(n, timeout_ms)``, ``close()``), for
    tests; None: ``open()`` finds the board by its USB ids. ``on_report``: called with every
    report as read (the bytes, before parsing) and its receive time (s, ``time.monotonic``),
    for ``humantele devices record``; a failing callback is counted in ``dropped["hook"]``
    and does not stop the reading. A lost board is looked for again (module docstring):
    ``connected`` says whether it is open, ``unplugs`` and ``reopens`` count. ``clock``: what
    the reopening is timed on (s).
    """

    name = "hid force sensor"

    def __init__(
        self, config: HidForceConfig | None = None, device=None, clock=time.monotonic
    ) -> None:
        self.config = config or HidForceConfig()
        self.dropped: dict[str, int] = {}
        self.received = 0
        self._dev = device
        self.on_report: Callable[[bytes, float], None] | None = None
        self.clock = clock
        self.unplugs = 0
        self.reopens = 0
        self._lost = False
        self._next_open = 0.0
        self._wait_s = self.config.reopen_s

    @property
    def connected(self) -> bool:
        return self._dev is not None

    def open(self) -> None:
        """Open the board; ForceSensorUnavailable saying which USB id was looked for."""
        if self._dev is None:
            self._dev = self._open(self.config)

    @staticmethod
    def _open(c: HidForceConfig):
        want = f"{c.vendor_id:04x}:{c.product_id:04x}"
        try:
            import hid
        except ImportError as exc:  # pragma: no cover - hidapi is a dependency
            raise ForceSensorUnavailable(f"hidapi is not installed: {exc}") from exc
        found = hid.enumerate(c.vendor_id, c.product_id)
        if c.serial is not None:
            found = [d for d in found if d.get("serial_number") == c.serial]
        if not found:
            raise ForceSensorUnavailable(
                f"no force sensor board with USB id {want}"
                + (f" and serial {c.serial!r}" if c.serial else "")
                + " found; is it plugged in, and may this user open it (udev rule)? "
                "Use the 'sim' force sensor backend to run without hardware."
            )
        dev = hid.device()
        try:
            dev.open_path(found[0]["path"])
        except (OSError, ValueError, RuntimeError) as exc:
            raise ForceSensorUnavailable(f"cannot open force sensor {want}: {exc}") from exc
        return dev

    def feed(self, data) -> ForceReading | None:
        """Parse one report; None (counted in ``dropped``) if unusable."""
        try:
            reading, _flags = parse_report(data)
        except ReportError as exc:
            self.dropped[exc.reason] = self.dropped.get(exc.reason, 0) + 1
            return None
        self.received += 1
        return reading

    def read(self, t: float | None = None) -> ForceReading | None:
        """Drain waiting reports (at most ``max_reports``, ``max_read_ms``); the newest good
        one (time-stamped ``t`` if given). A lost board: None, looked for when due."""
        if self._dev is None:
            if not self._lost:
                raise ForceSensorUnavailable(
                    "the force sensor board is not open; call open() first"
                )
            if not self._reopen():
                return None
        c = self.config
        newest = None
        timeout = c.read_timeout_ms
        end = time.monotonic() + (c.read_timeout_ms + c.max_read_ms) / 1000.0
        for _ in range(c.max_reports):
            try:
                data = self._dev.read(REPORT_SIZE, timeout)
            except (OSError, ValueError, RuntimeError):  # unplugged (hidapi: "read error")
                self.dropped["io"] = self.dropped.get("io", 0) + 1
                self._unplugged()
                break
            if not data:
                break
            if self.on_report is not None:
                try:
                    self.on_report(bytes(data), time.monotonic())
                except Exception:  # noqa: BLE001 - the recorder's fault must not stop reading
                    self.dropped["hook"] = self.dropped.get("hook", 0) + 1
            r = self.feed(data)
            newest = r or newest
            timeout = 0
            if time.monotonic() >= end:
                break
        if newest is not None and t is not None:
            newest = ForceReading(t, newest.a, newest.b, newest.temperature_c, newest.seq)
        return newest

    def _unplugged(self) -> None:
        """The board is gone: close its handle, look for it again after ``reopen_s``."""
        self.unplugs += 1
        self.close()
        self._lost = True
        self._wait_s = self.config.reopen_s
        self._next_open = self.clock() + self._wait_s

    def _reopen(self) -> bool:
        """Look for the lost board when due; True if it is open again."""
        now = self.clock()
        if now < self._next_open:
            return False
        try:
            self._dev = self._open(self.config)
        except (ForceSensorUnavailable, OSError, ValueError, RuntimeError):
            self.dropped["reopen_failed"] = self.dropped.get("reopen_failed", 0) + 1
            self._wait_s = min(max(self.config.reopen_max_s, self.config.reopen_s),
                               self._wait_s * 2.0)  # fmt: skip
            self._next_open = now + self._wait_s
            return False
        self._lost = False
        self.reopens += 1
        return True

    def stats(self) -> dict:
        return {"received": self.received, "dropped": dict(self.dropped),
                "connected": self.connected, "unplugs": self.unplugs,
                "reopens": self.reopens}  # fmt: skip

    def close(self) -> None:
        self._lost = False  # closed by its owner: not looked for again
        dev, self._dev = self._dev, None
        if dev is None:
            return
        try:
            dev.close()
        except Exception:  # noqa: BLE001 - closing a vanished device must not raise
            pass
