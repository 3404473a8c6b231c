"""Encrypted network transport: the tcp transport's frames over mutual TLS, ``tls://HOST:PORT``.

Everything ``tcp://`` does (framing, caps, the uniros handshake with its optional ``auth_key``) runs inside a TLS
connection from the standard library's ``ssl`` module, TLS 1.2 or newer. Both ends present a certificate
(``tls_cert_file`` and ``tls_key_file``, or the environment variables ``UNIROS_TLS_CERT`` and ``UNIROS_TLS_KEY``) and
verify the other's against ``tls_ca_file`` (or ``UNIROS_TLS_CA``): mutual TLS. The listener refuses a client
without a certificate signed by that CA; the client refuses a listener whose certificate is not, or does not name
the host it dialled (a DNS name or an IP address in the certificate's subjectAltName).

```python
opts = TransportOptions(tls_cert_file="me.pem", tls_key_file="me.key", tls_ca_file="ca.pem")
listener = await listen("tls://0.0.0.0:7000", opts)  # client certificates authenticate: no auth_key needed
transport = await connect("tls://robot-pc:7000", opts)
```

What TLS costs: the receive side never reads the socket itself (the bytes there are ciphertext), so the tcp
transport's answer polling does not apply, and every frame is encrypted and authenticated (AES-GCM or ChaCha20).
``uniros bench transport`` measures the round trip beside plain tcp. ``uniros_async.testing.tls`` writes a
throw-away CA and certificates for tests.
"""

from __future__ import annotations

import os
import ssl

from uniros_async.errors import ConfigError
from uniros_async.transports.base import TransportOptions
from uniros_async.transports.tcp import TcpListener, TcpTransport, open_connection, open_listener

__all__ = ["CA_ENV", "CERT_ENV", "KEY_ENV", "TlsTransport", "client_context", "connect", "listen", "server_context"]

CERT_ENV = "UNIROS_TLS_CERT"
"""Where ``tls_cert_file`` comes from when the options leave it None (so CLI commands take ``tls://`` URIs too)."""
KEY_ENV = "UNIROS_TLS_KEY"
CA_ENV = "UNIROS_TLS_CA"


class TlsTransport(TcpTransport):
    """One end of a mutual-TLS connection carrying the tcp transport's frames."""

    scheme = "tls"
    _encrypted = True


def _files(options: TransportOptions) -> tuple[str, str | None, str]:
    cert = options.tls_cert_file or os.environ.get(CERT_ENV)
    key = options.tls_key_file or os.environ.get(KEY_ENV)
    ca = options.tls_ca_file or os.environ.get(CA_ENV)
    if not cert or not ca:
        raise ConfigError(
            "tls:// needs this end's certificate and the CA that signed its peers' certificates: set "
            "TransportOptions(tls_cert_file=..., tls_key_file=..., tls_ca_file=...) or the environment variables "
            f"{CERT_ENV}, {KEY_ENV}, {CA_ENV} (PEM files; got certificate {cert!r}, CA {ca!r})"
        )
    return cert, key, ca


def _load(ctx: ssl.SSLContext, options: TransportOptions) -> ssl.SSLContext:
    cert, key, ca = _files(options)
    try:
        ctx.load_cert_chain(cert, key)
        ctx.load_verify_locations(cafile=ca)
    except (OSError, ssl.SSLError) as exc:
        raise ConfigError(
            f"cannot load the TLS files (tls_cert_file={cert!r}, tls_key_file={key!r}, tls_ca_file={ca!r}): {exc}"
        ) from exc
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    return ctx


def server_context(options: TransportOptions) -> ssl.SSLContext:
    """The listener's context: our certificate, and a client certificate required and verified against the CA.

    Raises:
        ConfigError: a file is missing or unreadable.
    """
    ctx = _load(ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER), options)
    ctx.verify_mode = ssl.CERT_REQUIRED
    return ctx


def client_context(options: TransportOptions) -> ssl.SSLContext:
    """The client's context: our certificate, and the listener's verified against the CA and the host dialled.

    Raises:
        ConfigError: a file is missing or unreadable.
    """
    ctx = _load(ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT), options)  # CERT_REQUIRED and check_hostname by default
    return ctx


async def listen(uri: str, options: TransportOptions) -> TcpListener[TlsTransport]:
    """Listen at ``tls://HOST:PORT`` (port 0: a free one). Client certificates authenticate, so a non-loopback
    HOST needs no ``auth_key``; one may still be set (then peers prove both).

    Raises:
        ConfigError: the URI is malformed, or a TLS file is missing or unreadable.
        OSError: the address cannot be bound.
    """
    return await open_listener(uri, options, TlsTransport, server_context(options))


async def connect(uri: str, options: TransportOptions) -> TcpTransport:
    """Connect to ``tls://HOST:PORT``, verify the listener's certificate, and complete the uniros handshake.

    Raises:
        ConfigError: the URI has no host or port, or a TLS file is missing or unreadable.
        AuthenticationError: the listener's certificate failed verification (or the auth_key settings differ).
        TransportBrokenError: the listener refused our certificate (it closes the connection during the handshake).
        TimeoutError: nobody accepted and completed both handshakes within ``connect_timeout_s``.
    """
    return await open_connection(uri, options, TlsTransport, client_context(options))
