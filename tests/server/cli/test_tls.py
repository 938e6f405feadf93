"""HTTPS for the phone page: a self-signed pair for a trial, a given pair checked before the server starts,
and ``crowdslam serve`` speaking HTTPS with either."""

from __future__ import annotations

import os
import ssl
import stat
import subprocess
from pathlib import Path

import httpx
import pytest
from cryptography import x509

from server.cli.background_server import CLI, free_port, wait_until_ready
from server.tls import TlsError, TlsFiles, check, self_signed


def _names(cert: Path) -> set[str]:
    loaded = x509.load_pem_x509_certificate(cert.read_bytes())
    alternative = loaded.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    names = {str(v) for v in alternative.get_values_for_type(x509.DNSName)}
    return names | {str(v) for v in alternative.get_values_for_type(x509.IPAddress)}


def test_a_self_signed_pair_names_its_hosts_and_is_made_again_only_when_they_change(tmp_path: Path) -> None:
    files = self_signed(tmp_path / "tls", ["192.168.1.20"])
    assert _names(files.cert) == {"localhost", "127.0.0.1", "192.168.1.20"}
    assert stat.S_IMODE(files.key.stat().st_mode) == 0o600  # the key is its owner's alone
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.load_cert_chain(files.cert, files.key)  # a pair that serves
    first = files.cert.read_bytes()
    assert self_signed(tmp_path / "tls", ["192.168.1.20"]).cert.read_bytes() == first  # kept
    moved = self_signed(tmp_path / "tls", ["10.0.0.7", "0.0.0.0"])  # the machine moved to another network
    assert _names(moved.cert) == {"localhost", "127.0.0.1", "10.0.0.7"}
    files.cert.write_text("not a certificate")
    assert _names(self_signed(tmp_path / "tls", ["10.0.0.7"]).cert) == {"localhost", "127.0.0.1", "10.0.0.7"}


def test_a_pair_that_cannot_serve_is_refused_saying_why(tmp_path: Path) -> None:
    one = self_signed(tmp_path / "one", [])
    other = self_signed(tmp_path / "other", ["10.1.1.1"])
    with pytest.raises(TlsError, match="no such file"):
        check(TlsFiles(tmp_path / "missing.crt", one.key))
    with pytest.raises(TlsError, match="cannot serve HTTPS"):
        check(TlsFiles(one.cert, other.key))  # a key that is not the certificate's


def test_serve_refuses_half_a_pair_before_it_starts(tmp_path: Path) -> None:
    env = {**os.environ, "CROWDSLAM_DATA_DIR": str(tmp_path / "data")}
    env.pop("CROWDSLAM_DATABASE_URL", None)
    cert = self_signed(tmp_path / "tls", []).cert
    done = subprocess.run(
        [*CLI, "serve", "--tls-cert", str(cert)], env=env, capture_output=True, text=True, timeout=120
    )
    assert done.returncode != 0
    assert "needs both a certificate (--tls-cert) and its key (--tls-key)" in done.stderr


def test_serve_speaks_https_with_a_self_signed_certificate(tmp_path: Path) -> None:
    env = {**os.environ, "CROWDSLAM_DATA_DIR": str(tmp_path / "data")}
    env.pop("CROWDSLAM_DATABASE_URL", None)
    subprocess.run([*CLI, "migrate"], env=env, check=True, capture_output=True)
    port = free_port()
    log = tmp_path / "serve.log"
    cert = tmp_path / "data" / "tls" / "self-signed.crt"
    with log.open("ab") as sink:
        process = subprocess.Popen(
            [*CLI, "serve", "--port", str(port), "--tls-self-signed", "--log-level", "warning"],
            env=env,
            stdout=sink,
            stderr=subprocess.STDOUT,
        )

    def trusting() -> ssl.SSLContext:
        return ssl.create_default_context(cafile=str(cert))

    def answers() -> bool:
        try:
            return httpx.get(f"https://127.0.0.1:{port}/healthz", verify=trusting(), timeout=1.0).is_success
        except (httpx.TransportError, ssl.SSLError, OSError):
            return False  # not listening yet, or its certificate not written yet

    try:
        wait_until_ready(process, "crowdslam serve --tls-self-signed", log, answers, 120.0, poll_s=0.2)
        phone = httpx.get(f"https://127.0.0.1:{port}/phone/", verify=trusting())
        assert phone.status_code == 200
        assert "accelerometer=(self)" in phone.headers["permissions-policy"]
        with pytest.raises(httpx.TransportError):
            httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=2.0)  # no plain HTTP beside it
        assert f"phones open https://127.0.0.1:{port}/phone/" in log.read_text()
    finally:
        process.terminate()
        process.wait(timeout=60)
