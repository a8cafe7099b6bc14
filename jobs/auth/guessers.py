"""Who a guess at a key is counted against: the client's address, or for IPv6 its /64.

One IPv6 host is given a whole /64 network, and picks a new address in it at will: counted
per address, its guesses would never add up to a lock-out.
"""

from __future__ import annotations

import ipaddress

IPV6_PREFIX = 64  # what one host (a home, a server's interface) is given


def guesser_of(address: str) -> str:
    """`address` as its guesses are counted: an IPv4 address itself, an IPv6 one as its /64
    (`2001:db8:1:2::/64`), an IPv4-mapped IPv6 one as the IPv4 address; anything that is no
    IP address (a test client's name) as it is."""
    try:
        ip = ipaddress.ip_address(address.split("%", 1)[0])  # without a link-local zone
    except ValueError:
        return address
    if isinstance(ip, ipaddress.IPv6Address):
        if ip.ipv4_mapped is not None:
            return str(ip.ipv4_mapped)
        return str(ipaddress.IPv6Network((ip, IPV6_PREFIX), strict=False))
    return str(ip)
