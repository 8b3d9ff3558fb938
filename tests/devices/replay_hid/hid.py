"""A stand-in for hidapi's ``hid`` module in another process: a recorded force board (a .hex
recording, ``HUMANTELE_HID_REPLAY``) replayed at the board's rate (``HUMANTELE_HID_RATE_HZ``,
default 100; ``HUMANTELE_HID_LOOP=1``: again and again) from the moment it is opened, so the
follower's real HID reader (open by USB id,
drain, parse, CRC) reads it as it reads the board. Put this folder first on ``PYTHONPATH``.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

VENDOR_ID, PRODUCT_ID = 0x1209, 0x4854  # the board's (HidForceConfig's defaults)
PATH = b"/dev/hidraw-replay"


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

    def open_path(self, path: bytes) -> None:
        if path != PATH:
            raise OSError("open failed")
        self._reports, self._t0 = _reports(), time.monotonic()

    def set_nonblocking(self, flag: bool) -> None:
        pass

    def read(self, size: int, timeout_ms: int = 0) -> list[int]:
        """The next report once the board has sent it (waiting up to ``timeout_ms``)."""
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

    def close(self) -> None:
        self._reports = []
