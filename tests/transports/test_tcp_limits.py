"""tcp:// and tls:// limits and defaults: connection and handshake caps, memory per connection, non-loopback
listeners without authentication, and mutual TLS refusing strangers."""

from __future__ import annotations

import asyncio
import contextlib
import gc
import os
import resource
from collections.abc import AsyncIterator, Callable
from pathlib import Path

import pytest

from uniros_async.errors import AuthenticationError, ConfigError, TransportBrokenError
from uniros_async.testing.tls import TlsFiles, write_test_certs
from uniros_async.transports import tcp
from uniros_async.transports.base import Listener, TransportOptions, connect, listen

T_S = 10.0


@pytest.fixture(scope="module")
def tls_files(tmp_path_factory: pytest.TempPathFactory) -> TlsFiles:
    return write_test_certs(tmp_path_factory.mktemp("tls"))


@contextlib.asynccontextmanager
async def _listening(uri: str, options: TransportOptions) -> AsyncIterator[tcp.TcpListener]:
    lst = await listen(uri, options)
    assert isinstance(lst, tcp.TcpListener)
    try:
        yield lst
    finally:
        await lst.aclose()


async def _until(pred: Callable[[], bool]) -> None:
    """Wait (with a deadline) for a listener's counter: counters have no event to wait on."""
    async with asyncio.timeout(T_S):
        while not pred():  # noqa: ASYNC110
            await asyncio.sleep(0.005)


async def _round_trip(lst: Listener, options: TransportOptions) -> None:
    acc = asyncio.ensure_future(lst.accept())
    client = await connect(lst.uri, options)
    server = await acc
    try:
        await client.send(b"ping")
        assert bytes(await server.receive()) == b"ping"
    finally:
        await client.aclose()
        await server.aclose()


def _rss_kib() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    raise AssertionError("no VmRSS in /proc/self/status")


@pytest.mark.parametrize("host", ["0.0.0.0", "::"])
async def test_non_loopback_listener_without_key_refuses_to_start(host: str) -> None:
    uri = f"tcp://[{host}]:0" if ":" in host else f"tcp://{host}:0"
    with pytest.raises(ConfigError, match=r"refusing to listen on .*auth_key.*--insecure"):
        await listen(uri, TransportOptions())


async def test_non_loopback_listener_starts_with_a_key_or_when_insecure() -> None:
    # Bound to every interface for an instant; nothing connects but this test, over loopback.
    for opts in (TransportOptions(auth_key=b"k"), TransportOptions(insecure=True)):
        async with _listening("tcp://0.0.0.0:0", opts) as lst:
            assert lst.address[0] == "0.0.0.0"
            await _round_trip(lst, opts)


async def test_loopback_needs_no_key() -> None:
    for uri in ("tcp://127.0.0.1:0", "tcp://localhost:0", "tcp://[::1]:0"):
        async with _listening(uri, TransportOptions()) as lst:
            assert tcp.is_loopback(lst.address[0])


async def test_connections_over_the_cap_are_closed_at_once() -> None:
    opts = TransportOptions(max_connections=3)
    async with asyncio.timeout(T_S), _listening("tcp://127.0.0.1:0", opts) as lst:
        held = [await connect(lst.uri, opts) for _ in range(3)]
        accepted = [await lst.accept() for _ in range(3)]
        assert lst.open_connections == 3
        reader, writer = await asyncio.open_connection(*lst.address)
        assert await reader.read() == b""  # closed before a hello was sent
        writer.close()
        assert lst.rejected == 1
        for t in held + accepted:
            await t.aclose()
        await _until(lambda: lst.open_connections == 0)
        await _round_trip(lst, opts)  # room again


async def test_unfinished_handshakes_over_the_cap_are_refused_then_evicted() -> None:
    opts = TransportOptions(max_handshakes=4)
    async with asyncio.timeout(T_S), _listening("tcp://127.0.0.1:0", opts) as lst:
        silent = [await asyncio.open_connection(*lst.address) for _ in range(10)]
        await _until(lambda: lst.rejected >= 6)
        assert lst.handshaking <= 4
        await _round_trip(lst, opts)  # a real peer still gets in while strangers hold connections
        for _, w in silent:
            w.close()


async def test_idle_connection_holds_little_memory() -> None:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
    opts = TransportOptions()
    n = 200
    async with asyncio.timeout(T_S * 3), _listening("tcp://127.0.0.1:0", opts) as lst:
        gc.collect()
        before = _rss_kib()
        pairs = []
        for _ in range(n):
            c = await connect(lst.uri, opts)
            s = await lst.accept()
            await c.send(b"x" * 300)
            await s.receive()
            pairs += [c, s]
        gc.collect()
        per_end_kib = (_rss_kib() - before) / (2 * n)
        for t in pairs:
            await t.aclose()
    assert per_end_kib < 32, f"an idle connection end holds {per_end_kib:.1f} KiB (the stream buffer is 256 KiB)"


async def test_tls_round_trip_and_encrypted_wire(tls_files: TlsFiles) -> None:
    opts = tls_files.options()
    async with asyncio.timeout(T_S), _listening("tls://127.0.0.1:0", opts) as lst:
        assert lst.uri.startswith("tls://127.0.0.1:")
        acc = asyncio.ensure_future(lst.accept())
        client = await connect(lst.uri, opts)
        server = await acc
        assert isinstance(client, tcp.TcpTransport)
        assert client.peer.startswith("tls://") and client.fileno() == -1
        await client.send(b"secret joint state" * 10)
        assert bytes(await server.receive()) == b"secret joint state" * 10
        await client.aclose()
        await server.aclose()


async def test_tls_listener_refuses_a_client_without_a_certificate(tls_files: TlsFiles) -> None:
    async with asyncio.timeout(T_S), _listening("tls://127.0.0.1:0", tls_files.options()) as lst:
        import ssl

        ctx = ssl.create_default_context(cafile=tls_files.ca_file)  # verifies the listener, presents nothing
        reader, writer = await asyncio.open_connection(*lst.address, ssl=ctx, server_hostname="127.0.0.1")
        with contextlib.suppress(ssl.SSLError, ConnectionResetError):
            assert await reader.read() == b""  # TLS 1.3: the refusal comes as an alert after the client's finish
        writer.close()
        await _round_trip(lst, tls_files.options())


async def test_tls_refuses_a_certificate_from_another_ca(tls_files: TlsFiles, tmp_path: Path) -> None:
    stranger = write_test_certs(tmp_path / "other")
    async with asyncio.timeout(T_S), _listening("tls://127.0.0.1:0", tls_files.options()) as lst:
        with pytest.raises(AuthenticationError, match="TLS handshake"):
            await connect(lst.uri, stranger.options(TransportOptions(connect_timeout_s=2.0)))
        with pytest.raises((TransportBrokenError, AuthenticationError)):
            # the stranger trusts our CA but presents its own certificate: the listener refuses it
            mixed = TransportOptions(
                tls_cert_file=stranger.cert_file,
                tls_key_file=stranger.key_file,
                tls_ca_file=tls_files.ca_file,
                connect_timeout_s=2.0,
            )
            t = await connect(lst.uri, mixed)
            await t.send(b"x")
            await t.receive()
        await _round_trip(lst, tls_files.options())


async def test_tls_without_files_names_what_is_missing(monkeypatch: pytest.MonkeyPatch) -> None:
    for var in ("UNIROS_TLS_CERT", "UNIROS_TLS_KEY", "UNIROS_TLS_CA"):
        monkeypatch.delenv(var, raising=False)
    with pytest.raises(ConfigError, match="tls_cert_file"):
        await listen("tls://127.0.0.1:0", TransportOptions())


async def test_domain_and_ros1_node_refuse_the_network_without_authentication() -> None:
    from uniros_async.adapters.ros1 import open_ros1_node
    from uniros_async.bus import open_domain

    with pytest.raises(ConfigError, match="refusing to listen on tcp://0.0.0.0"):
        async with open_domain("tcp://0.0.0.0:0"):
            pass
    with pytest.raises(ConfigError, match="ROS 1 cannot authenticate"):
        async with open_ros1_node("/hostile_check", host="0.0.0.0"):
            pass


def test_robot_serve_refuses_a_network_host_without_a_key() -> None:
    import subprocess
    import sys

    proc = subprocess.run(
        [sys.executable, "-m", "uniros_async.cli", "robot", "serve", "rx200", "--host", "0.0.0.0"],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "UNIROS_AUTH_KEY": ""},
    )
    assert proc.returncode != 0
    assert "refusing to listen on tcp://0.0.0.0" in proc.stderr and "--insecure" in proc.stderr


async def test_domains_and_nodes_take_the_key_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    from uniros_async.bus import open_domain, open_node

    monkeypatch.setenv("UNIROS_AUTH_KEY", "from-the-environment")
    async with asyncio.timeout(T_S), open_domain("tcp://127.0.0.1:0") as dom:
        async with open_node("keyed", domain=dom.uri) as node:
            await node.set_parameter("/k", 1)
        with pytest.raises(AuthenticationError, match="auth_key"):
            async with open_node("keyless", domain=dom.uri, options=TransportOptions(connect_timeout_s=2.0)):
                pass


async def test_failed_tls_handshakes_free_their_connection_slots(tls_files: TlsFiles) -> None:
    import ssl

    opts = tls_files.options(TransportOptions(max_connections=3, handshake_timeout_s=0.5))
    async with asyncio.timeout(T_S), _listening("tls://127.0.0.1:0", opts) as lst:
        ctx = ssl.create_default_context(cafile=tls_files.ca_file)  # no client certificate: the listener refuses
        for _ in range(5):
            reader, writer = await asyncio.open_connection(*lst.address, ssl=ctx, server_hostname="127.0.0.1")
            with contextlib.suppress(ssl.SSLError, ConnectionResetError):
                await reader.read()
            writer.close()
        await _until(lambda: lst.open_connections == 0)
        await _round_trip(lst, opts)


async def test_a_burst_of_peers_beyond_max_handshakes_all_get_in() -> None:
    opts = TransportOptions(max_handshakes=4, connect_timeout_s=T_S)
    n = 120
    async with asyncio.timeout(T_S * 2), _listening("tcp://127.0.0.1:0", opts) as lst:
        clients = await asyncio.gather(*(connect(lst.uri, opts) for _ in range(n)))
        servers = [await lst.accept() for _ in range(n)]
        for c in clients:
            await c.send(b"in")
        assert all([bytes(await s.receive()) == b"in" for s in servers])
        for t in (*clients, *servers):
            await t.aclose()


async def test_connect_to_a_full_listener_waits_for_a_free_slot() -> None:
    opts = TransportOptions(max_connections=2, connect_timeout_s=0.5)
    async with asyncio.timeout(T_S), _listening("tcp://127.0.0.1:0", opts) as lst:
        held = [await connect(lst.uri, opts) for _ in range(2)]
        accepted = [await lst.accept() for _ in range(2)]
        with pytest.raises(TimeoutError, match="could not connect"):
            await connect(lst.uri, opts)
        late = asyncio.ensure_future(connect(lst.uri, TransportOptions(connect_timeout_s=T_S)))
        await held[0].aclose()
        await accepted[0].aclose()
        client = await late  # retried until the slot was free
        server = await lst.accept()
        await client.send(b"x")
        assert bytes(await server.receive()) == b"x"
        for t in (client, server, held[1], accepted[1]):
            await t.aclose()


@pytest.mark.parametrize("scheme", ["tcp", "tls"])
async def test_unsent_bytes_counts_a_backlog_until_the_peer_reads_it(scheme: str, tls_files: TlsFiles) -> None:
    """``unsent_bytes`` is what was sent and has not left this host: it grows while the peer reads nothing and
    the buffers between fill, falls to 0 once the peer has read everything, and is 0 once the connection ends."""
    opts = tls_files.options() if scheme == "tls" else TransportOptions()
    async with _listening(f"{scheme}://127.0.0.1:0", opts) as lst:
        client = await connect(lst.uri, opts)
        server = await asyncio.wait_for(lst.accept(), T_S)
        try:
            assert client.unsent_bytes() == 0
            frame = bytes(1 << 20)
            sent = 0
            async with asyncio.timeout(T_S):
                while client.unsent_bytes() == 0:  # the peer reads nothing: its window, then ours, fills
                    await client.send(frame)
                    sent += 1
            assert client.unsent_bytes() > 0
            async with asyncio.timeout(T_S):
                for _ in range(sent):
                    assert len(await server.receive()) == len(frame)
                while client.unsent_bytes():  # noqa: ASYNC110 - no event says the kernel sent it; polled
                    await asyncio.sleep(0.01)
        finally:
            await client.aclose()
            await server.aclose()
        assert client.unsent_bytes() == 0
