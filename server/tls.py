"""HTTPS for ``crowdslam serve`` and ``crowdslam demo``: a certificate and key given as files, or a
self-signed pair made for a trial on a local network (phones give motion sensors only to pages served over
HTTPS; a phone accepts a self-signed certificate after a warning it must click through)."""

from __future__ import annotations

import datetime as dt
import ipaddress
import socket
import ssl
from dataclasses import dataclass
from pathlib import Path

SELF_SIGNED_DAYS = 30
"""A trial certificate lasts a month; a new one is made when it is older than half that."""


class TlsError(ValueError):
    """Certificate or key files that cannot serve HTTPS, said in one line."""


@dataclass(frozen=True)
class TlsFiles:
    cert: Path
    key: Path


def check(files: TlsFiles) -> TlsFiles:
    """The pair, once Python's ssl module has loaded it (a missing file, a key that does not match its
    certificate, or a file that is not PEM is refused before the server starts)."""
    for path in (files.cert, files.key):
        if not path.is_file():
            raise TlsError(f"no such file: {path}")
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    try:
        context.load_cert_chain(files.cert, files.key)
    except (ssl.SSLError, OSError) as error:
        raise TlsError(f"{files.cert} and {files.key} cannot serve HTTPS: {error}") from error
    return files


def lan_address() -> str | None:
    """This machine's address on its local network (the one its default route leaves by), or None offline.
    A UDP socket's connect sends nothing."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.connect(("192.0.2.1", 9))  # TEST-NET-1: never routed anywhere, only chooses the interface
            address = str(s.getsockname()[0])
        except OSError:
            return None
    return None if address.startswith("0.") else address


def self_signed(folder: Path, hosts: list[str]) -> TlsFiles:
    """A self-signed certificate for ``hosts`` (names or addresses; localhost and 127.0.0.1 always) in
    ``folder``, made anew when missing, older than half its life, or made for other hosts. The key file is
    readable by its owner only."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    names = sorted({"localhost", "127.0.0.1", *hosts} - {"0.0.0.0", "::", ""})
    files = TlsFiles(folder / "self-signed.crt", folder / "self-signed.key")
    now = dt.datetime.now(dt.UTC)
    if files.cert.is_file() and files.key.is_file():
        try:
            current = x509.load_pem_x509_certificate(files.cert.read_bytes())
            alternative = current.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
            covered = {str(v) for v in alternative.get_values_for_type(x509.DNSName)}
            covered |= {str(v) for v in alternative.get_values_for_type(x509.IPAddress)}
            fresh = current.not_valid_after_utc - now > dt.timedelta(days=SELF_SIGNED_DAYS / 2)
            if fresh and covered == set(names):
                return check(files)
        except (ValueError, x509.ExtensionNotFound, TlsError):
            pass  # unreadable or not ours: made anew
    alternative_names: list[x509.GeneralName] = []
    for name in names:
        try:
            alternative_names.append(x509.IPAddress(ipaddress.ip_address(name)))
        except ValueError:
            alternative_names.append(x509.DNSName(name))
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "crowdslam (self-signed)")])
    certificate = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=SELF_SIGNED_DAYS))
        .add_extension(x509.SubjectAlternativeName(alternative_names), critical=False)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .sign(key, hashes.SHA256())
    )
    folder.mkdir(parents=True, exist_ok=True)
    files.key.touch(mode=0o600, exist_ok=True)
    files.key.chmod(0o600)
    files.key.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )
    )
    files.cert.write_bytes(certificate.public_bytes(serialization.Encoding.PEM))
    return check(files)
