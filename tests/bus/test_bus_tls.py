"""A domain on tls://: its registry and its nodes' peer connections over mutual TLS, across real processes, with
throw-away certificates (``uniros_async.testing.tls``) on loopback."""

from __future__ import annotations

import asyncio
import dataclasses
from collections.abc import Iterator
from pathlib import Path

import pytest
from rig.bus_peers import BusPeer, check_talker

from uniros_async.bus import Domain, open_domain, open_node
from uniros_async.bus.messages import Data
from uniros_async.errors import AuthenticationError, ConfigError, DomainError
from uniros_async.testing.tls import TlsFiles, write_test_certs
from uniros_async.transports.base import TransportOptions, listen

T_S = 30.0


@pytest.fixture(scope="module")
def tls_files(tmp_path_factory: pytest.TempPathFactory) -> TlsFiles:
    return write_test_certs(tmp_path_factory.mktemp("tls"))


@pytest.fixture
def tls_environ(tls_files: TlsFiles, monkeypatch: pytest.MonkeyPatch) -> Iterator[TlsFiles]:
    """The certificates in ``$UNIROS_TLS_*``, where nodes without options (and spawned peers) find them."""
    for var, value in tls_files.environ().items():
        monkeypatch.setenv(var, value)
    yield tls_files


def endpoints(domain: Domain, node: str) -> dict[str, str]:
    """What ``node`` told the registry it listens on (the registry runs in this process)."""
    return dict(domain._nodes[node].info["endpoints"])


@pytest.mark.slow
@pytest.mark.parametrize("transport", ["tls", "auto"])
async def test_nodes_in_two_processes_exchange_a_topic_and_a_service(transport: str, tls_environ: TlsFiles) -> None:
    async with (
        asyncio.timeout(60),
        open_domain("tls://127.0.0.1:0") as domain,
        open_node("listener", domain=domain, transport=transport) as node,
        BusPeer(domain.uri, "talker", transport),
    ):
        assert domain.uri.startswith("tls://127.0.0.1:")
        # no node of a tls domain offers a clear tcp endpoint; "auto" adds shm (it never leaves the machine)
        for name in ("/listener", "/talker"):
            eps = endpoints(domain, name)
            assert eps["tls"].startswith("tls://127.0.0.1:"), eps
            assert set(eps) == ({"tls"} if transport == "tls" else {"tls", "shm"}), eps
        await check_talker(node)


async def test_a_node_whose_certificate_the_ca_did_not_sign_cannot_join(tls_files: TlsFiles, tmp_path: Path) -> None:
    stranger = write_test_certs(tmp_path / "stranger")
    fast = TransportOptions(connect_timeout_s=2.0)
    async with asyncio.timeout(T_S), open_domain("tls://127.0.0.1:0", options=tls_files.options()) as domain:
        # its own certificate, trusting the domain's CA: the domain hangs up on it, and the error says why
        mixed = TransportOptions(
            tls_cert_file=stranger.cert_file,
            tls_key_file=stranger.key_file,
            tls_ca_file=tls_files.ca_file,
            connect_timeout_s=2.0,
        )
        with pytest.raises(DomainError, match="certificate is not signed by the domain's CA"):
            async with open_node("intruder", domain=domain, options=mixed):
                pass
        # trusting only its own CA, it refuses the domain's certificate
        with pytest.raises(AuthenticationError, match="certificate verify failed"):
            async with open_node("intruder", domain=domain, options=stranger.options(fast)):
                pass
        async with open_node("member", domain=domain, options=tls_files.options()) as node:
            assert await node.list_nodes() == ["/member"], "the refused nodes left nothing behind"


async def test_a_tls_domain_needs_its_files_and_keeps_its_nodes_off_clear_tcp(
    tls_files: TlsFiles, monkeypatch: pytest.MonkeyPatch
) -> None:
    for var in tls_files.environ():
        monkeypatch.delenv(var, raising=False)
    with pytest.raises(ConfigError, match=r"tls_cert_file.*UNIROS_TLS_CERT, UNIROS_TLS_KEY, UNIROS_TLS_CA"):
        async with open_domain("tls://127.0.0.1:0"):
            pass
    opts = tls_files.options()
    async with asyncio.timeout(T_S), open_domain("tls://127.0.0.1:0", options=opts) as domain:
        with pytest.raises(ConfigError, match=r"tls_cert_file.*UNIROS_TLS_CERT"):
            async with open_node("bare", domain=domain):  # no files given and none in the environment
                pass
        with pytest.raises(ConfigError, match="transport='tcp' would carry this node's topics and services in clear"):
            async with open_node("clear", domain=domain, options=opts, transport="tcp"):
                pass
        async with (
            open_node("member", domain=domain, options=opts, transport="tls") as node,
            await listen("tcp://127.0.0.1:0", TransportOptions()) as clear,
        ):
            # a peer elsewhere that offered only a clear tcp endpoint is refused, not dialled
            peer = {"node": "/other", "host": "another-host", "token": "t", "endpoints": {"tcp": clear.uri}}
            with pytest.raises(ConfigError, match=r"offers \['tcp'\], not tls"):
                await node._connect_to(peer)
    async with open_domain("tcp://127.0.0.1:0") as plain:
        with pytest.raises(ConfigError, match="transport='tls' needs a domain served on tls://"):
            async with open_node("n", domain=plain, options=opts, transport="tls"):
                pass


async def test_a_peer_whose_certificate_does_not_name_its_address_is_refused_not_fatal(
    tls_files: TlsFiles, caplog: pytest.LogCaptureFixture
) -> None:
    opts = tls_files.options()
    misnamed = dataclasses.replace(opts, bind_host="127.0.0.2")  # loopback, but the certificate names 127.0.0.1
    async with (
        asyncio.timeout(T_S),
        open_domain("tls://127.0.0.1:0", options=opts) as domain,
        open_node("misnamed", domain=domain, options=misnamed, transport="tls") as bad,
        open_node("named", domain=domain, options=opts, transport="tls") as good,
        open_node("reader", domain=domain, options=opts, transport="tls") as reader,
    ):
        await bad.create_publisher(Data, "/x")
        pub = await good.create_publisher(Data, "/x")
        sub = await reader.create_subscription(Data, "/x")
        await sub.wait_for_publishers(1, timeout_s=10)
        while not any("IP address mismatch" in r.getMessage() for r in caplog.records):  # noqa: ASYNC110 - a log
            await asyncio.sleep(0.02)
        assert sub.publisher_count == 1, "the misnamed publisher is not connected"
        pub.publish(Data(value=[7.0]))
        assert list((await sub.receive()).value) == [7.0], "the reader's node kept working"
