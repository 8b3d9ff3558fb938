"""A stand-in for hidapi's ``hid`` module in another process: a recorded force board (a .hex
recording, ``HUMANTELE_HID_REPLAY``) replayed at the board's rate (``HUMANTELE_HID_RATE_HZ``,
default 100; ``HUMANTELE_HID_LOOP=1``: again and again) from the moment it is opened, so the
follower's real HID reader (open by USB id,
drain, parse, CRC) reads it as it reads the board. Put this folder first on ``PYTHONPATH``.

``HUMANTELE_HID_EPOCH`` (a ``time.monotonic`` value, which every process of a machine shares):
the board runs on from it whether or not it is read, as a real one does and as the hl2ss
replay with the same ``--epoch`` does (report ``n`` is sent at ``epoch + n / rate``), so the
two replays of one clinic stay together however late each process starts or reads. Unread
reports wait in the kernel's hidraw buffer (HIDRAW_BUFFER_SIZE, 64 reports); once it is full
the newer ones are dropped (linux drivers/hid/hidraw.c, ``hidraw_report_event``), counted in
``dropped_full``. ``HUMANTELE_HID_START_FILE``: the epoch is the board's opening, shared
through that file with the other replays of the clinic (the hl2ss replay's ``--start-file``):
the first read of either starts both. Looped from an epoch, the board's clock and counter run
on across the turn's end (each round's times are its reports' plus the rounds before it, at
the recording's own spacing, as the hl2ss replay's timestamps): a board's clock never goes
back.
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

VENDOR_ID, PRODUCT_ID = 0x1209, 0x4854  # the board's (HidForceConfig's defaults)
PATH = b"/dev/hidraw-replay"
HIDRAW_BUFFER_SIZE = 64  # linux include/linux/hidraw.h


def _reports() -> list[bytes]:
    lines = Path(os.environ["HUMANTELE_HID_REPLAY"]).read_text().splitlines()
    return [bytes.fromhex(x.split("#", 1)[0].strip()) for x in lines if x.split("#", 1)[0].strip()]


def enumerate(vendor_id: int = 0, product_id: int = 0) -> list[dict]:  # noqa: A001 (hidapi's)
    if (vendor_id and vendor_id != VENDOR_ID) or (product_id and product_id != PRODUCT_ID):
        return []
    return [{"vendor_id": VENDOR_ID, "product_id": PRODUCT_ID, "path": PATH,
             "serial_number": "REPLAY", "product_string": "force board (replay)"}]  # fmt: skip


class device:  # noqa: N801 (hidapi's name)
    def __init__(self) -> None:
        self._reports: list[bytes] = []
        self._t0 = 0.0
        self._next = 0
        self._rate = float(os.environ.get("HUMANTELE_HID_RATE_HZ", "100"))
        self._loop = os.environ.get("HUMANTELE_HID_LOOP") == "1"  # again at the end
        epoch = os.environ.get("HUMANTELE_HID_EPOCH")
        self._epoch = float(epoch) if epoch else None
        self._start_file = os.environ.get("HUMANTELE_HID_START_FILE")  # the epoch, shared
        self._buffer: list[int] = []  # with an epoch: the reports the kernel holds (indices)
        self._arrived = -1  # the last report index the board has sent
        self.dropped_full = 0

    def open_path(self, path: bytes) -> None:
        if path != PATH:
            raise OSError("open failed")
        self._reports, self._t0 = _reports(), time.monotonic()
        if self._epoch is None and self._start_file:
            from humantele.runtime.shared_start import shared_start

            self._epoch = shared_start(self._start_file, self._t0)
        if self._epoch is not None:  # what the board sent before it was opened is not kept
            self._arrived = max(-1, self._sent_by(time.monotonic()))

    def set_nonblocking(self, flag: bool) -> None:
        pass

    def read(self, size: int, timeout_ms: int = 0) -> list[int]:
        """The next report once the board has sent it (waiting up to ``timeout_ms``)."""
        if self._epoch is not None:
            return self._read_from_epoch(size, timeout_ms)
        if not self._reports or (self._next >= len(self._reports) and not self._loop):
            return []
        due = self._t0 + self._next / self._rate
        wait = due - time.monotonic()
        if wait > timeout_ms / 1000.0:
            time.sleep(timeout_ms / 1000.0)
            return []
        if wait > 0:
            time.sleep(wait)
        self._next += 1
        return list(self._reports[(self._next - 1) % len(self._reports)][:size])

    def _sent_by(self, now: float) -> int:
        """The index of the last report the board has sent by ``now`` (on its time: sent)."""
        return math.floor((now - self._epoch) * self._rate + 1e-6)

    def _arrive(self, now: float) -> None:
        """The reports the board has sent by ``now`` into the kernel's buffer (full: dropped)."""
        n_now = self._sent_by(now)
        if not self._loop:
            n_now = min(n_now, len(self._reports) - 1)
        for n in range(self._arrived + 1, n_now + 1):
            if len(self._buffer) < HIDRAW_BUFFER_SIZE:
                self._buffer.append(n)
            else:
                self.dropped_full += 1
        self._arrived = max(self._arrived, n_now)

    def _read_from_epoch(self, size: int, timeout_ms: int) -> list[int]:
        if not self._reports:
            return []
        self._arrive(time.monotonic())
        if not self._buffer:
            due = self._epoch + (self._arrived + 1) / self._rate
            wait = due - time.monotonic()
            if (not self._loop and self._arrived >= len(self._reports) - 1) or (
                wait > timeout_ms / 1000.0
            ):
                time.sleep(timeout_ms / 1000.0)
                return []
            time.sleep(max(0.0, wait))
            self._arrive(time.monotonic())
            if not self._buffer:
                return []
        n = self._buffer.pop(0)
        return list(self._running_on(n)[:size])

    def _running_on(self, n: int) -> bytes:
        """Report ``n`` of the looped turn, its counter and time moved on by its round (made
        again by the board's own codec, CRC and all); one the codec refuses goes as recorded."""
        from humantele.forcesense.hid import ReportError, encode_report, parse_report

        count = len(self._reports)
        report, rounds = self._reports[n % count], n // count
        if rounds == 0 or count < 2:
            return report
        try:
            reading, flags = parse_report(report)
            first, last = (parse_report(self._reports[i])[0].t for i in (0, -1))
        except ReportError:
            return report
        lap_s = (last - first) * count / (count - 1)  # a turn at the recording's spacing
        t_us = round((reading.t + rounds * lap_s) * 1e6)
        seq = reading.seq + rounds * count
        return encode_report(seq, t_us, reading.a, reading.b, reading.temperature_c, flags)

    def close(self) -> None:
        self._reports = []
