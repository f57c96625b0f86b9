"""The teleop server's self-signed TLS certificate, made on first use and kept for the next.

The certificate and its key live in the user's config folder
(``$XDG_CONFIG_HOME/astrobee-payload/``, default ``~/.config/astrobee-payload/``) as
``teleop-cert.pem`` and ``teleop-key.pem`` (the key readable by the user only). It names
``localhost``, the loopback addresses and the address the server binds (for a wildcard
bind, this machine's network addresses), so a headset
that trusts it once keeps trusting it. A new certificate is made when the bound address
is not among the names, or the certificate expires within a week.
"""

from __future__ import annotations

import datetime
import ipaddress
import os
import socket
import ssl
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from payload.errors import PayloadError

CERT_NAME = "teleop-cert.pem"
KEY_NAME = "teleop-key.pem"
VALID_DAYS = 825  # the longest lifetime browsers accept for a server certificate


class TlsError(PayloadError):
    """The certificate cannot be made, read or written."""


def config_dir() -> Path:
    """The user's config folder for the workbench."""
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "astrobee-payload"


def lan_addresses() -> list[str]:
    """This machine's addresses a headset on the same network would use (best effort)."""
    found = set()
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.connect(("192.0.2.1", 9))  # no packet is sent: this only picks the route
            found.add(s.getsockname()[0])
    except OSError:
        pass
    try:
        for info in socket.getaddrinfo(socket.gethostname(), None, socket.AF_INET):
            found.add(str(info[4][0]))
    except OSError:
        pass
    return sorted(a for a in found if not a.startswith("127."))


def _hosts(host: str) -> list[str]:
    """Names the certificate must carry for a bind to ``host``."""
    if host in ("0.0.0.0", "::", ""):
        return lan_addresses()
    return [host]


def _names(host: str) -> list[x509.GeneralName]:
    names: list[x509.GeneralName] = [x509.DNSName("localhost")]
    ips = {"127.0.0.1", "::1"}
    for h in _hosts(host):
        try:
            ipaddress.ip_address(h)
            ips.add(h)
        except ValueError:
            names.append(x509.DNSName(h))
    names += [x509.IPAddress(ipaddress.ip_address(a)) for a in sorted(ips)]
    return names


def _covers(cert: x509.Certificate, host: str) -> bool:
    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return False
    wanted = set(map(str, _names(host)))
    have = set(map(str, san))
    soon = datetime.datetime.now(datetime.timezone.utc) + datetime.timedelta(days=7)
    return wanted <= have and cert.not_valid_after_utc > soon


def make_certificate(host: str) -> tuple[bytes, bytes]:
    """A new self-signed certificate and key (PEM) naming ``host`` and the loopback names."""
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "astrobee-payload teleop")])
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=VALID_DAYS))
        .add_extension(x509.SubjectAlternativeName(_names(host)), critical=False)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.ExtendedKeyUsage([x509.oid.ExtendedKeyUsageOID.SERVER_AUTH]), critical=False
        )
        .sign(key, hashes.SHA256())
    )
    key_pem = key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )
    return cert.public_bytes(serialization.Encoding.PEM), key_pem


def ensure_certificate(host: str, folder: Path | None = None) -> tuple[Path, Path, bool]:
    """The certificate and key for ``host``, made (or remade) when needed.

    Returns:
        (certificate path, key path, whether a new certificate was made).

    Raises:
        TlsError: The folder or files cannot be written or read.
    """
    d = folder if folder is not None else config_dir()
    cert_path, key_path = d / CERT_NAME, d / KEY_NAME
    try:
        if cert_path.exists() and key_path.exists():
            cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
            if _covers(cert, host):
                return cert_path, key_path, False
        d.mkdir(parents=True, exist_ok=True)
        cert_pem, key_pem = make_certificate(host)
        fd = os.open(key_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "wb") as fh:
            fh.write(key_pem)
        cert_path.write_bytes(cert_pem)
    except (OSError, ValueError) as exc:
        raise TlsError(f"TLS certificate in {d}: {exc}") from exc
    return cert_path, key_path, True


def server_context(cert_path: Path, key_path: Path) -> ssl.SSLContext:
    """A TLS server context for the certificate."""
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        ctx.load_cert_chain(cert_path, key_path)
    except (OSError, ssl.SSLError) as exc:
        raise TlsError(f"TLS certificate {cert_path}: {exc}") from exc
    return ctx


def fingerprint(cert_path: Path) -> str:
    """SHA-256 fingerprint of the certificate, as browsers show it (AA:BB:...)."""
    cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
    return ":".join(f"{b:02X}" for b in cert.fingerprint(hashes.SHA256()))
