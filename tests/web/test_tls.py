"""The pages' self-signed certificate (made once, kept, replaced only when it must be) and the
message budget."""

import hashlib
import ssl
import stat

from cryptography import x509
from cryptography.hazmat.primitives import serialization

from humantele.web.guard import MessageBudget
from humantele.web.tls import ensure_certificate, local_hosts


def test_certificate_made_once_then_reused(tmp_path):
    hosts = ["localhost", "127.0.0.1", "::1", "headset-pc.clinic.example", "10.1.2.3"]
    first = ensure_certificate(tmp_path / "tls", hosts)
    assert first.created
    assert stat.S_IMODE(first.key_path.stat().st_mode) == 0o600  # the key: the user only
    cert = x509.load_pem_x509_certificate(first.cert_path.read_bytes())
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert set(san.get_values_for_type(x509.DNSName)) == {"localhost", "headset-pc.clinic.example"}
    assert {str(i) for i in san.get_values_for_type(x509.IPAddress)} == {
        "127.0.0.1", "::1", "10.1.2.3"}  # fmt: skip
    # The fingerprint is the SHA-256 of the DER certificate, as a browser shows it.
    der = cert.public_bytes(serialization.Encoding.DER)
    digest = hashlib.sha256(der).hexdigest().upper()
    assert first.fingerprint_sha256 == ":".join(digest[i : i + 2] for i in range(0, 64, 2))
    # A usable server context (the key matches the certificate).
    assert isinstance(first.ssl_context(), ssl.SSLContext)

    again = ensure_certificate(tmp_path / "tls", ["127.0.0.1", "10.1.2.3"])
    assert not again.created and again.fingerprint_sha256 == first.fingerprint_sha256


def test_certificate_replaced_when_it_must_be(tmp_path):
    d = tmp_path / "tls"
    first = ensure_certificate(d, ["127.0.0.1"])
    moved = ensure_certificate(d, ["127.0.0.1", "192.168.7.20"])  # a new address
    assert moved.created and moved.fingerprint_sha256 != first.fingerprint_sha256
    assert "192.168.7.20" in moved.hosts
    moved.key_path.write_text("not a key")  # damaged
    fixed = ensure_certificate(d, ["127.0.0.1"])
    assert fixed.created and stat.S_IMODE(fixed.key_path.stat().st_mode) == 0o600
    fixed.key_path.chmod(0o644)  # someone loosened it: reused, and tightened again
    reused = ensure_certificate(d, ["127.0.0.1"])
    assert not reused.created and stat.S_IMODE(reused.key_path.stat().st_mode) == 0o600


def test_local_hosts():
    hosts = local_hosts("0.0.0.0", ["scanner.clinic.example", "127.0.0.1"])
    assert hosts[:3] == ["localhost", "127.0.0.1", "::1"]
    assert "scanner.clinic.example" in hosts and len(hosts) == len(set(hosts))
    assert local_hosts("192.168.1.5") == ["localhost", "127.0.0.1", "::1", "192.168.1.5"]


def test_message_budget_refuses_beyond_rate_and_burst():
    now = [0.0]
    b = MessageBudget(10.0, 5, clock=lambda: now[0])
    assert [b.take() for _ in range(7)] == [True] * 5 + [False] * 2  # the burst, then no more
    now[0] += 0.1  # one more token after 1/rate
    assert b.take() and not b.take()
    now[0] += 100.0  # never more than the burst saved up
    assert sum(b.take() for _ in range(20)) == 5


def test_host_names_a_certificate_cannot_hold_are_refused_with_the_reason(tmp_path):
    import pytest

    from humantele.web.tls import check_host_name

    for good in ("scanner.clinic.example", "pc-1", "10.1.2.3", "fe80::1", "a" * 63 + ".lan"):
        check_host_name(good)
    cases = {
        "scanner pc": "characters a certificate cannot name: ' '",
        "a\x00b": r"characters a certificate cannot name: '\\x00'",
        "a" * 300: "has 300 characters",
        "a" * 64 + ".lan": "longer than 63",
        "*.clinic.example": "'\\*'",
        "-pc.lan": "starts or ends with '-'",
        "a..b": "empty",
        "": "empty host name",
        "scanner.clinic.example/x": "'/'",
    }
    for bad, why in cases.items():
        with pytest.raises(ValueError, match=why):
            check_host_name(bad)
        with pytest.raises(ValueError, match=why):  # never written into a certificate
            ensure_certificate(tmp_path / "tls", ["127.0.0.1", bad])
        with pytest.raises(ValueError, match=why):
            local_hosts("127.0.0.1", [bad])
    assert not (tmp_path / "tls" / "cert.pem").exists()
