"""Secure by default: a listener beyond loopback needs authentication, or an explicit ``insecure``.

Every listener that accepts network connections calls ``check_exposure`` before binding: tcp:// (the domain, nodes,
served arms), and the ROS 1 adapter's XML-RPC and TCPROS servers (which cannot authenticate at all, so beyond
loopback they always need ``insecure``). A tls:// listener (a tls domain, its nodes, an arm served with ``--tls``)
skips the check: its client certificates authenticate every peer.
"""

from __future__ import annotations

import ipaddress

from uniros_async.errors import ConfigError

__all__ = ["check_exposure", "is_loopback"]


def is_loopback(host: str) -> bool:
    """Whether ``host`` names this machine only (127.0.0.0/8, ::1, ``localhost``); "" and wildcards do not."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False  # a host name other than localhost may resolve to any interface


def check_exposure(where: str, host: str, *, authenticated: bool, insecure: bool, how: str) -> None:
    """Refuse to listen beyond loopback without authentication unless ``insecure`` says so.

    Args:
        where: the address as the user gave it (for the message).
        host: the host part to bind.
        authenticated: peers must prove a key or a certificate before anything else is read.
        insecure: the caller explicitly accepts an unauthenticated listener on the network.
        how: how to authenticate this listener, for the message ("set an auth_key", ...).

    Raises:
        ConfigError: a non-loopback, unauthenticated listener without ``insecure``.
    """
    if authenticated or insecure or is_loopback(host):
        return
    raise ConfigError(
        f"refusing to listen on {where}: {host or 'every interface'} is reachable from other machines and peers "
        f"would not be authenticated. {how}; or listen on 127.0.0.1; or, to accept unauthenticated peers from the "
        f"network, pass --insecure (insecure=True)"
    )
