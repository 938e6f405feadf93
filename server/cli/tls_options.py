"""``--tls-cert``, ``--tls-key`` and ``--tls-self-signed``: HTTPS for ``crowdslam serve`` and
``crowdslam demo`` (phones give the phone page their motion sensors only over HTTPS)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from server.settings import Settings
    from server.tls import TlsFiles

LOOPBACK = {"127.0.0.1", "localhost", "::1"}
ANY = {"0.0.0.0", "::", ""}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("HTTPS")
    group.add_argument(
        "--tls-cert", type=Path, metavar="PEM", help="certificate chain (default: CROWDSLAM_TLS_CERT)"
    )
    group.add_argument(
        "--tls-key", type=Path, metavar="PEM", help="its private key (default: CROWDSLAM_TLS_KEY)"
    )
    group.add_argument(
        "--tls-self-signed",
        action="store_true",
        help="a self-signed certificate for this machine (its LAN address with --host 0.0.0.0), made under "
        "the data directory: a trial with phones on a local network, not production",
    )


def tls_files(args: argparse.Namespace, settings: Settings, command: str) -> TlsFiles | None:
    """The certificate and key to serve with, checked, or None for plain HTTP; SystemExit with one line
    when they cannot serve."""
    from server.tls import TlsError, TlsFiles, check, lan_address, self_signed

    cert = args.tls_cert or settings.tls_cert
    key = args.tls_key or settings.tls_key
    try:
        if args.tls_self_signed:
            if args.tls_cert or args.tls_key:
                raise TlsError(
                    "--tls-self-signed makes its own certificate: leave out --tls-cert and --tls-key"
                )
            hosts = [args.host]
            if args.host in ANY and (lan := lan_address()) is not None:
                hosts.append(lan)
            return self_signed(settings.data_dir / "tls", hosts)
        if cert is None and key is None:
            return None
        if cert is None or key is None:
            raise TlsError("HTTPS needs both a certificate (--tls-cert) and its key (--tls-key)")
        return check(TlsFiles(cert, key))
    except TlsError as error:
        raise SystemExit(f"crowdslam {command}: {error}") from None


def public_base(host: str, port: int, tls: TlsFiles | None) -> str:
    """The address a phone on the network opens: the LAN address when serving on every interface."""
    from server.tls import lan_address

    scheme = "https" if tls is not None else "http"
    name = (lan_address() or "127.0.0.1") if host in ANY else host
    if ":" in name:
        name = f"[{name}]"
    return f"{scheme}://{name}:{port}"
