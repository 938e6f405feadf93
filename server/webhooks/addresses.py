"""Which addresses a webhook may reach. A webhook is a URL any operator key may set, and the server then
POSTs to it from inside its network: without a rule it is a way in (cloud metadata at 169.254.169.254, the
database, an admin page on localhost). So a host that resolves to an address that is not public (loopback,
link-local, private, shared, multicast, reserved, unspecified) is refused, checked on the resolved address
when the webhook is stored and again at every delivery (a name may resolve elsewhere later), unless the
operator of the server lists it in ``CROWDSLAM_WEBHOOK_ALLOWED_HOSTS``. A delivery connects to the address
that was checked, not to the name again."""

from __future__ import annotations

import ipaddress
import socket
from dataclasses import dataclass

Address = ipaddress.IPv4Address | ipaddress.IPv6Address


class RefusedAddressError(ValueError):
    """The webhook's host is not one the server may POST to."""


@dataclass(frozen=True)
class AllowedHosts:
    names: frozenset[str]
    networks: tuple[ipaddress.IPv4Network | ipaddress.IPv6Network, ...]

    @classmethod
    def parse(cls, text: str) -> AllowedHosts:
        """``receiver.internal,10.0.5.0/24,127.0.0.1``: host names (matched exactly, without case) and
        addresses or networks; ValueError naming an entry that is neither."""
        names, networks = set(), []
        for entry in (e.strip() for e in text.split(",")):
            if not entry:
                continue
            try:
                networks.append(ipaddress.ip_network(entry, strict=False))
                continue
            except ValueError:
                pass
            if not all(part and part.replace("-", "").isalnum() for part in entry.split(".")):
                raise ValueError(
                    f"CROWDSLAM_WEBHOOK_ALLOWED_HOSTS: {entry!r} is neither a host name nor a CIDR"
                )
            names.add(entry.lower())
        return cls(frozenset(names), tuple(networks))

    def allows(self, host: str, address: Address) -> bool:
        return host.lower() in self.names or any(address in n for n in self.networks)


def is_public(address: Address) -> bool:
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        return is_public(address.ipv4_mapped)
    return address.is_global and not address.is_multicast


def resolve(host: str, port: int, allowed: AllowedHosts) -> Address:
    """The address to connect to for ``host``: every address the name resolves to must be public or
    allowed (one that is not refuses them all: a name with a private address among its public ones is
    aimed inward). Blocking (a DNS lookup): call it off the event loop."""
    try:
        literal: Address | None = ipaddress.ip_address(host.strip("[]"))
    except ValueError:
        literal = None
    if literal is not None:
        found = [literal]
    else:
        try:
            infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
        except OSError as exc:
            raise RefusedAddressError(f"{host!r} does not resolve: {exc}") from None
        found = list(dict.fromkeys(ipaddress.ip_address(info[4][0]) for info in infos))
    if not found:
        raise RefusedAddressError(f"{host!r} does not resolve")
    for address in found:
        if not is_public(address) and not allowed.allows(host, address):
            raise RefusedAddressError(
                f"{host!r} resolves to {address}, which is not a public address: a webhook may not reach the "
                "server's own network unless CROWDSLAM_WEBHOOK_ALLOWED_HOSTS lists it"
            )
    return found[0]
