"""A stand-in for the ``hid`` module (hidapi) that replays byte reports, so the HID backends run
their real open/read paths: ``enumerate`` lists one device, ``device().read`` hands out the
queued reports one by one (then empty reads), and ``unplug()`` makes reads fail as a pulled
cable does, as cython-hidapi's ``hid.pyx`` does: ``read`` on the lost handle raises
``OSError("read error")`` (hid_read returned -1) for good, ``open_path`` of a path that is not
there raises ``OSError("open failed")``, and a closed handle raises ``ValueError("not open")``;
``replug()`` brings the board back under a new path (the kernel gives the next hidraw node),
so only a new ``enumerate`` + ``open_path`` reads it again. ``flood``: the board never stops
sending (every read gets a report)."""

from __future__ import annotations

from pathlib import Path


def load_recording(path: Path) -> list[bytes]:
    """Reports of a .hex recording (one per line, '#' comments)."""
    out = []
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            out.append(bytes.fromhex(line))
    return out


class FakeHid:
    """Install with ``monkeypatch.setitem(sys.modules, "hid", FakeHid(...))``."""

    def __init__(self, vendor_id: int, product_id: int, reports: list[bytes], serial: str = "1"):
        self.info = {"vendor_id": vendor_id, "product_id": product_id, "path": b"/dev/hidraw7",
                     "serial_number": serial, "product_string": "fake"}  # fmt: skip
        self.reports = list(reports)
        self.opened = 0
        self.unplugged = False
        self.plug = 0  # how many times it was plugged in again
        self.flood: bytes | None = None
        self.reads = 0
        self.read_error: type[Exception] = OSError  # another binding: RuntimeError

    def enumerate(self, vendor_id: int = 0, product_id: int = 0) -> list[dict]:
        i = self.info
        if (vendor_id and vendor_id != i["vendor_id"]) or (
            product_id and product_id != i["product_id"]
        ):
            return []
        return [] if self.unplugged else [dict(i)]

    def unplug(self) -> None:
        self.unplugged = True

    def replug(self) -> None:
        self.unplugged = False
        self.plug += 1
        self.info["path"] = f"/dev/hidraw{7 + self.plug}".encode()

    def device(self) -> _FakeDevice:
        return _FakeDevice(self)


class _FakeDevice:
    def __init__(self, hub: FakeHid) -> None:
        self.hub = hub
        self.closed = False
        self.plug = hub.plug  # a handle is of one plugging-in

    def open_path(self, path: bytes) -> None:
        if self.hub.unplugged or path != self.hub.info["path"]:
            raise OSError("open failed")
        self.plug = self.hub.plug
        self.hub.opened += 1

    def set_nonblocking(self, flag: bool) -> None:
        pass

    def read(self, size: int, timeout_ms: int = 0) -> list[int]:
        if self.closed:
            raise ValueError("not open")
        if self.hub.unplugged or self.plug != self.hub.plug:
            raise self.hub.read_error("read error")
        self.hub.reads += 1
        if self.hub.flood is not None:
            return list(self.hub.flood[:size])
        if not self.hub.reports:
            return []
        return list(self.hub.reports.pop(0)[:size])

    def close(self) -> None:
        self.closed = True
