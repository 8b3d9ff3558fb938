"""An Orthanc archive on loopback, for the tests and benchmarks (Debian package ``orthanc``,
``orthanc-dicomweb`` for STOW-RS): a temporary configuration and storage, free ports, no
remote access, stopped (SIGTERM) with this process. Readiness is its REST API answering.

Usage::

    with OrthancServer() as pacs:   # OrthancError if it cannot start
        cfg = ArchiveConfig(enabled=True, port=pacs.dicom_port, called_ae=pacs.aet)
        pacs.get("/patients")

``refuse_series`` makes it refuse any instance whose Series Description is that text: how a
test gets one object refused. Its Lua ``ReceivedInstanceFilter`` raises an error for it, which
Orthanc answers with status 0xA700; a filter that returns false instead makes Orthanc 1.10
drop the instance and still answer Success (0x0000): a sender cannot tell, so that is not
how an archive should refuse. :meth:`stop` then
:meth:`start` again is an outage: the same ports, the same storage.
"""

from __future__ import annotations

import ctypes
import json
import shutil
import signal
import socket
import subprocess
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

PLUGINS = Path("/usr/share/orthanc/plugins")
_PR_SET_PDEATHSIG = 1


class OrthancError(RuntimeError):
    """Orthanc is missing, exited, or did not answer in time (the message has its log)."""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _die_with_parent() -> None:  # (in the child, before exec)
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass


class OrthancServer:
    """One Orthanc process with a temporary configuration (see the module doc)."""

    def __init__(self, aet: str = "ORTHANC", refuse_series: str | None = None,
                 worklists_dir: Path | None = None) -> None:  # fmt: skip
        self.aet = aet
        self.refuse_series = refuse_series
        self.worklists_dir = worklists_dir
        self.tmp = Path(tempfile.mkdtemp(prefix="humantele-orthanc-"))
        self.http_port = free_port()
        self.dicom_port = free_port()
        self.proc: subprocess.Popen | None = None

    @staticmethod
    def available() -> bool:
        return shutil.which("Orthanc") is not None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.http_port}"

    @property
    def dicomweb_url(self) -> str:
        return f"{self.url}/dicom-web"

    def _config(self) -> dict[str, Any]:
        plugins = [str(p) for p in (PLUGINS / "libOrthancDicomWeb.so",) if p.exists()]
        cfg: dict[str, Any] = {
            "Name": "humantele-test",
            "StorageDirectory": str(self.tmp / "db"),
            "IndexDirectory": str(self.tmp / "db"),
            "HttpPort": self.http_port,
            "DicomPort": self.dicom_port,
            "DicomAet": self.aet,
            "DicomCheckCalledAet": True,
            "DicomAlwaysAllowStore": True,
            "DicomAlwaysAllowFind": True,
            "RemoteAccessAllowed": False,
            "AuthenticationEnabled": False,
            "HttpsCACertificates": "",
            "SslEnabled": False,
            "ConcurrentJobs": 1,
            "HttpThreadsCount": 4,
            "StorageCompression": False,
            "StableAge": 1,
            "Plugins": plugins,
            "DicomWeb": {"Enable": True, "Root": "/dicom-web/"},
        }
        if self.refuse_series is not None:
            script = self.tmp / "filter.lua"
            script.write_text(
                "function ReceivedInstanceFilter(dicom, origin, info)\n"
                f"  if dicom.SeriesDescription == {json.dumps(self.refuse_series)} then\n"
                "    error('refused by this test archive')\n  end\n  return true\nend\n"
            )
            cfg["LuaScripts"] = [str(script)]
        if self.worklists_dir is not None and (PLUGINS / "libModalityWorklists.so").exists():
            cfg["Plugins"].append(str(PLUGINS / "libModalityWorklists.so"))
            cfg["Worklists"] = {"Enable": True, "Database": str(self.worklists_dir)}
        return cfg

    def start(self, timeout_s: float = 60.0) -> None:
        if not self.available():
            raise OrthancError("Orthanc (Debian package orthanc) is not installed")
        path = self.tmp / "orthanc.json"
        path.write_text(json.dumps(self._config(), indent=1))
        log = open(self.tmp / "orthanc.log", "ab")  # noqa: SIM115
        self.proc = subprocess.Popen(
            ["Orthanc", "--logdir=" + str(self.tmp), str(path)], stdout=log,
            stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, preexec_fn=_die_with_parent,
        )  # fmt: skip
        log.close()
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise OrthancError(f"Orthanc exited ({self.proc.returncode}): {self.log()}")
            try:
                self.get("/system")
                return
            except (OSError, urllib.error.URLError):
                time.sleep(0.1)
        self.stop()
        raise OrthancError(f"Orthanc did not answer in {timeout_s:g} s: {self.log()}")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.proc = None

    def close(self) -> None:
        self.stop()
        shutil.rmtree(self.tmp, ignore_errors=True)

    def log(self) -> str:
        logs = sorted(self.tmp.glob("*.log"))
        text = "".join(p.read_text(errors="replace") for p in logs)
        return text[-2000:]

    def __enter__(self) -> OrthancServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- its REST API ------------------------------------------------------------------------

    def request(self, method: str, path: str, body: bytes | None = None) -> bytes:
        req = urllib.request.Request(self.url + path, data=body, method=method)
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.read()

    def get(self, path: str) -> Any:
        return json.loads(self.request("GET", path))

    def get_bytes(self, path: str) -> bytes:
        return self.request("GET", path)

    def delete(self, path: str) -> None:
        self.request("DELETE", path)

    def clear(self) -> None:
        """Every patient deleted (a test starts with an empty archive)."""
        for pid in self.get("/patients"):
            self.delete(f"/patients/{pid}")
