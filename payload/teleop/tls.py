"""The teleop server's TLS certificate: a leaf signed by a one-off local CA, kept for reuse.

Two certificates live in the user's config folder (``$XDG_CONFIG_HOME/astrobee-payload/``,
default ``~/.config/astrobee-payload/``):

- ``teleop-ca.pem``: a CA certificate (``CA:TRUE``, path length 0, key usage: sign
  certificates only) that the headset is told to trust once;
- ``teleop-cert.pem`` and ``teleop-key.pem``: the server's leaf certificate (``CA:FALSE``,
  server authentication only, valid :data:`VALID_DAYS` days) naming ``localhost``, the
  loopback addresses and the bind address (for a wildcard bind, this machine's network
  addresses), and its key (readable by the user only, unencrypted: the server starts
  unattended).

The CA's private key is never written anywhere: it signs the leaf and is discarded, so
nothing else can ever be signed by the CA a headset trusts. The price: a new leaf (a new
bind address, or the leaf within a week of expiry) comes with a new CA to trust again.
A user-supplied certificate and key (e.g. from an organisation's CA) can be used instead
(``payload teleop serve --cert FILE --key FILE``).
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
CA_NAME = "teleop-ca.pem"
VALID_DAYS = 365  # the leaf: about a year (browsers accept at most 398 days)
CA_VALID_DAYS = 366  # the CA outlives its one leaf


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


def make_certificate(host: str) -> tuple[bytes, bytes, bytes]:
    """A new one-off CA and the leaf it signs for ``host`` and the loopback names.

    Returns:
        (leaf certificate, leaf key, CA certificate), PEM; the CA's key is discarded.
    """
    now = datetime.datetime.now(datetime.timezone.utc)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "astrobee-payload teleop CA")])
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=CA_VALID_DAYS))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(_usage(cert_sign=True), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), False)
        .sign(ca_key, hashes.SHA256())
    )
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "astrobee-payload teleop")])
    ski = ca.extensions.get_extension_for_class(x509.SubjectKeyIdentifier).value
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(ca_name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=VALID_DAYS))
        .add_extension(x509.SubjectAlternativeName(_names(host)), critical=False)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(_usage(cert_sign=False), critical=True)
        .add_extension(
            x509.ExtendedKeyUsage([x509.oid.ExtendedKeyUsageOID.SERVER_AUTH]), critical=False
        )
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_subject_key_identifier(ski), critical=False
        )
        .sign(ca_key, hashes.SHA256())
    )
    key_pem = key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )
    pem = serialization.Encoding.PEM
    return cert.public_bytes(pem), key_pem, ca.public_bytes(pem)


def _usage(cert_sign: bool) -> x509.KeyUsage:
    """Key usage: a CA signs certificates only; the leaf signs TLS handshakes only."""
    return x509.KeyUsage(
        digital_signature=not cert_sign,
        content_commitment=False,
        key_encipherment=False,
        data_encipherment=False,
        key_agreement=False,
        key_cert_sign=cert_sign,
        crl_sign=False,
        encipher_only=False,
        decipher_only=False,
    )


def _is_ca(cert: x509.Certificate) -> bool:
    try:
        return bool(cert.extensions.get_extension_for_class(x509.BasicConstraints).value.ca)
    except x509.ExtensionNotFound:
        return False


def ensure_certificate(host: str, folder: Path | None = None) -> tuple[Path, Path, bool]:
    """The certificate and key for ``host``, made (or remade) when needed.

    Returns:
        (certificate path, key path, whether a new certificate was made).

    Raises:
        TlsError: The folder or files cannot be written or read.
    """
    d = folder if folder is not None else config_dir()
    cert_path, key_path, ca_path = d / CERT_NAME, d / KEY_NAME, d / CA_NAME
    try:
        if cert_path.exists() and key_path.exists() and ca_path.exists():
            cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
            if _covers(cert, host) and not _is_ca(cert):  # an old self-signed CA is remade
                return cert_path, key_path, False
        d.mkdir(parents=True, exist_ok=True)
        cert_pem, key_pem, ca_pem = make_certificate(host)
        fd = os.open(key_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "wb") as fh:
            fh.write(key_pem)
        cert_path.write_bytes(cert_pem)
        ca_path.write_bytes(ca_pem)
    except (OSError, ValueError) as exc:
        raise TlsError(f"TLS certificate in {d}: {exc}") from exc
    return cert_path, key_path, True


def _not_pem(cert_path: Path, key_path: Path) -> str | None:
    """Which of the two files holds no PEM block of its kind (OpenSSL says only "PEM
    lib"), or None."""
    for path, block in ((cert_path, "CERTIFICATE"), (key_path, "PRIVATE KEY")):
        try:
            text = path.read_bytes()
        except OSError:
            continue  # said by the OSError branch's reading
        if b"-----BEGIN " not in text or block.encode() not in text:
            return f"{path} holds no PEM {block.lower()} (-----BEGIN ... {block}-----)"
    return None


def server_context(cert_path: Path, key_path: Path) -> ssl.SSLContext:
    """A TLS server context for the certificate."""
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        ctx.load_cert_chain(cert_path, key_path)
    except ssl.SSLError as exc:  # not a certificate and its key
        why = (
            f"the key {key_path} is not this certificate's"
            if exc.reason == "KEY_VALUES_MISMATCH"
            else _not_pem(cert_path, key_path) or exc.reason or str(exc)
        )
        raise TlsError(f"TLS certificate {cert_path}: {why}") from exc
    except OSError as exc:  # unreadable ("[Errno 13] ..." said as the system's reason)
        raise TlsError(f"TLS certificate {cert_path}: {exc.strerror or exc}") from exc
    return ctx


def fingerprint(cert_path: Path) -> str:
    """SHA-256 fingerprint of the certificate, as browsers show it (AA:BB:...)."""
    cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
    return ":".join(f"{b:02X}" for b in cert.fingerprint(hashes.SHA256()))
