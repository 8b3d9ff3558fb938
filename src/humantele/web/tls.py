"""A self-signed TLS certificate for a daemon's web page, made once and kept in its state dir.

A page that uses WebXR (the headset page) must come from a secure context, and a ``https``
page can only open ``wss://`` sockets, so the daemons serve their pages over TLS. There is no
certificate authority in a clinic: :func:`ensure_certificate` makes a self-signed certificate
on first run (ECDSA P-256, with the host names and addresses the page is served on as
subjectAltNames) and reuses it after, so a headset that accepted it once keeps working. The
user checks the SHA-256 fingerprint the daemon prints against the one the browser shows.

Host names are checked (:func:`check_host_name`, :data:`HostName` for configuration fields):
an IP address, or a DNS name of letters, digits and hyphens (labels of 1-63, 253 in all); a
space, a NUL, a wildcard or 300 characters is refused with the reason, never written into a
certificate.

Files in ``directory``: ``cert.pem`` and ``key.pem`` (the private key, mode 0600, never
printed). A certificate that is unreadable, expires within :data:`RENEW_BEFORE`, or lacks a
host now asked for is replaced (a new fingerprint; the reason is logged).
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import logging
import os
import re
import socket
import ssl
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID
from pydantic import AfterValidator

log = logging.getLogger(__name__)

CERT_FILE = "cert.pem"
KEY_FILE = "key.pem"
VALIDITY = dt.timedelta(days=825)
RENEW_BEFORE = dt.timedelta(days=7)
LOOPBACK_HOSTS = ("localhost", "127.0.0.1", "::1")
MAX_HOST_NAME = 253  # characters in a DNS name (RFC 1035), labels up to 63
_LABEL = re.compile(r"[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?")


def check_host_name(host: str) -> str:
    """``host`` if a certificate can name it (an IP address, or a DNS name of letters, digits
    and hyphens: labels of 1-63 characters that neither start nor end with a hyphen, 253
    characters in all); ValueError saying why not."""
    if not isinstance(host, str):
        raise ValueError(f"a host name is text, not {type(host).__name__}")
    try:
        return str(ipaddress.ip_address(host))
    except ValueError:
        pass
    shown = repr(host if len(host) <= 40 else host[:40] + "...")
    if not host:
        raise ValueError("empty host name")
    if len(host) > MAX_HOST_NAME:
        raise ValueError(f"host name {shown} has {len(host)} characters (at most {MAX_HOST_NAME})")
    bad = sorted({c for c in host if not (c.isascii() and (c.isalnum() or c in ".-"))})
    if bad:
        raise ValueError(
            f"host name {shown} has characters a certificate cannot name: "
            f"{', '.join(repr(c) for c in bad)} (letters, digits, '-' and '.' only; an IP "
            "address, or a DNS name in its ASCII form)"
        )
    for label in host.split("."):
        if not _LABEL.fullmatch(label):
            raise ValueError(
                f"host name {shown}: label {label[:63]!r} is empty, longer than 63 characters "
                "or starts or ends with '-'"
            )
    return host


HostName = Annotated[str, AfterValidator(check_host_name)]
"""A configuration field holding a name or address for the certificate."""


@dataclass(frozen=True)
class Certificate:
    """Where a certificate and its key are, its SHA-256 fingerprint (``AB:CD:...``, as browsers
    show it), the hosts it names, and whether it was made by this call."""

    cert_path: Path
    key_path: Path
    fingerprint_sha256: str
    hosts: tuple[str, ...]
    created: bool

    def ssl_context(self) -> ssl.SSLContext:
        """A server-side context for aiohttp (TLS 1.2 or newer)."""
        ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        ctx.minimum_version = ssl.TLSVersion.TLSv1_2
        ctx.load_cert_chain(self.cert_path, self.key_path)
        return ctx


def fingerprint(cert: x509.Certificate) -> str:
    """SHA-256 of the DER certificate as colon-separated upper-case hex pairs."""
    return cert.fingerprint(hashes.SHA256()).hex(":").upper()


def local_hosts(bind_host: str = "0.0.0.0", extra: tuple[str, ...] | list[str] = ()) -> list[str]:
    """The names and addresses a page bound to ``bind_host`` can be reached at: loopback, the
    host name, the addresses it resolves to, the address of the default route (found by
    connecting a UDP socket, which sends nothing), a specific ``bind_host``, and ``extra``
    (e.g. a DNS name the headset uses). Never blocks on an unreachable network for long."""
    hosts: list[str] = [*LOOPBACK_HOSTS]
    if bind_host not in ("", "0.0.0.0", "::"):
        hosts.append(bind_host)
    else:
        name = socket.gethostname()
        hosts.append(name)
        try:
            hosts += [str(info[4][0]) for info in socket.getaddrinfo(name, None)]
        except OSError:
            pass
        for family, probe in ((socket.AF_INET, "192.0.2.1"), (socket.AF_INET6, "2001:db8::1")):
            try:
                with socket.socket(family, socket.SOCK_DGRAM) as s:
                    s.connect((probe, 9))
                    hosts.append(str(s.getsockname()[0]))
            except OSError:
                pass
    found = len(hosts)
    hosts += list(extra)
    out: list[str] = []
    for i, h in enumerate(hosts):
        h = h.split("%", 1)[0]  # an IPv6 zone id is no part of a certificate's name
        try:
            h = check_host_name(h)
        except ValueError as exc:
            if i >= found:  # a name asked for: the caller says it is wrong
                raise
            log.warning("TLS: %s: left out of the certificate", exc)  # e.g. a host name "my_pc"
            continue
        if h not in out:
            out.append(h)
    return out


def _san(hosts: list[str]) -> x509.SubjectAlternativeName:
    names: list[x509.GeneralName] = []
    for h in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            names.append(x509.DNSName(h))
    return x509.SubjectAlternativeName(names)


def _names(cert: x509.Certificate) -> set[str]:
    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return set()
    ips = {str(ip) for ip in san.get_values_for_type(x509.IPAddress)}
    return ips | set(san.get_values_for_type(x509.DNSName))


def _write_private(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` readable by the user only (0600 from the start)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.unlink(missing_ok=True)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.replace(tmp, path)


def _reusable(
    cert_path: Path, key_path: Path, hosts: list[str]
) -> tuple[x509.Certificate | None, str]:
    """The kept certificate if it can be reused, else None and why not."""
    if not cert_path.exists() or not key_path.exists():
        return None, "none yet"
    try:
        cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
    except (OSError, ValueError, TypeError) as exc:
        return None, f"the kept one is unreadable ({exc.__class__.__name__})"
    if key.public_key().public_bytes(
        serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo
    ) != cert.public_key().public_bytes(
        serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo
    ):
        return None, "the kept key does not match the kept certificate"
    if cert.not_valid_after_utc - dt.datetime.now(dt.UTC) < RENEW_BEFORE:
        return None, "the kept one expires soon"
    missing = [h for h in hosts if _canonical(h) not in _names(cert)]
    if missing:
        return None, f"the kept one does not name {', '.join(missing)}"
    return cert, ""


def _canonical(host: str) -> str:
    try:
        return str(ipaddress.ip_address(host))
    except ValueError:
        return host


def ensure_certificate(
    directory: str | Path, hosts: list[str], common_name: str = "humantele"
) -> Certificate:
    """The certificate kept in ``directory`` (made there, with ``hosts`` as subjectAltNames,
    if there is none that can be reused). Raises OSError if the directory cannot be written,
    ValueError (saying which and why) for a host a certificate cannot name."""
    hosts = [check_host_name(h) for h in hosts]
    directory = Path(directory).expanduser()
    directory.mkdir(parents=True, exist_ok=True)
    cert_path, key_path = directory / CERT_FILE, directory / KEY_FILE
    cert, why = _reusable(cert_path, key_path, hosts)
    if cert is not None:
        os.chmod(key_path, 0o600)  # in case someone loosened it
        return Certificate(
            cert_path, key_path, fingerprint(cert), tuple(sorted(_names(cert))), False
        )
    key = ec.generate_private_key(ec.SECP256R1())
    now = dt.datetime.now(dt.UTC)
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + VALIDITY)
        .add_extension(_san(hosts), critical=False)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.ExtendedKeyUsage([x509.oid.ExtendedKeyUsageOID.SERVER_AUTH]), critical=False
        )
        .sign(key, hashes.SHA256())
    )
    _write_private(
        key_path,
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        ),
    )
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    fp = fingerprint(cert)
    level = logging.INFO if why == "none yet" else logging.WARNING  # a replaced one: re-accept
    log.log(level, "new TLS certificate in %s (%s); SHA-256 %s", directory, why, fp)
    return Certificate(cert_path, key_path, fp, tuple(sorted(_names(cert))), True)
