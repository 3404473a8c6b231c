"""The transport contract (uniros_async.testing.transport_contract) against every transport, in one process and
across real processes."""

from __future__ import annotations

import asyncio
import os

import pytest

from uniros_async.errors import ConfigError
from uniros_async.testing import transport_contract as contract
from uniros_async.testing import transport_contract_loans as loans
from uniros_async.testing.tls import TlsFiles, write_test_certs
from uniros_async.transports._shm_ring import PURE_PYTHON_ENV, compiled_ring_end
from uniros_async.transports.base import TransportOptions, connect

# "shm-python": shm:// with the pure-Python RingEnd on both ends (the fallback where the C one is not built)
URIS = {
    "memory": "memory://",
    "shm": "shm://",
    "shm-python": "shm://",
    "tcp": "tcp://127.0.0.1:0",
    "tls": "tls://127.0.0.1:0",
}
CROSS_PROCESS = ["shm", "shm-python", "tcp", "tls"]  # memory:// is in-process by definition
AUTH = ["shm", "tcp", "tls"]


@pytest.fixture(scope="session")
def tls_files(tmp_path_factory: pytest.TempPathFactory) -> TlsFiles:
    return write_test_certs(tmp_path_factory.mktemp("tls"))


@pytest.fixture(autouse=True)
def _ring_end_of(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch, tls_files: TlsFiles) -> None:
    """Which RingEnd shm:// uses in this test (spawned processes inherit the choice with the environment), and
    the certificates tls:// finds in UNIROS_TLS_* (the contract's checks build their own TransportOptions)."""
    kind = request.node.callspec.params.get("kind") if hasattr(request.node, "callspec") else None
    for var, value in tls_files.environ().items():
        monkeypatch.setenv(var, value)
    if kind == "shm-python":
        monkeypatch.setenv(PURE_PYTHON_ENV, "1")
    else:
        monkeypatch.delenv(PURE_PYTHON_ENV, raising=False)
        if kind == "shm":
            assert compiled_ring_end() is not None, "the compiled RingEnd is not built: pip install -e . needs gcc"


@pytest.mark.parametrize("check", contract.CHECKS, ids=lambda c: c.__name__.removeprefix("check_"))
@pytest.mark.parametrize("kind", list(URIS))
async def test_contract(kind: str, check) -> None:  # type: ignore[no-untyped-def]
    await check(URIS[kind])


@pytest.mark.parametrize("check", contract.AUTH_CHECKS, ids=lambda c: c.__name__.removeprefix("check_"))
@pytest.mark.parametrize("kind", AUTH)
async def test_auth_contract(kind: str, check) -> None:  # type: ignore[no-untyped-def]
    await check(URIS[kind])


@pytest.mark.slow
@pytest.mark.parametrize("kind", CROSS_PROCESS)
async def test_cross_process_echo(kind: str) -> None:
    """Frames small and large make the round trip through an echo server in another process."""
    with contract.EchoServer(URIS[kind]) as uri:
        async with asyncio.timeout(30):
            t = await connect(uri, TransportOptions())
            try:
                for payload in (b"x" * 277, os.urandom(64 * 1024), os.urandom(640 * 480 * 3), b""):
                    for _ in range(3):
                        await t.send(payload)
                        assert bytes(await t.receive()) == payload
                # several connections to the same server process
                t2 = await connect(uri, TransportOptions())
                await t2.send(b"second peer")
                assert bytes(await t2.receive()) == b"second peer"
                await t2.aclose()
                await t.send(b"first still works")
                assert bytes(await t.receive()) == b"first still works"
            finally:
                await t.aclose()


@pytest.mark.slow
@pytest.mark.parametrize("kind", AUTH)
async def test_cross_process_auth(kind: str) -> None:
    with contract.EchoServer(URIS[kind], auth_key=b"k3y") as uri:
        async with asyncio.timeout(30):
            t = await connect(uri, TransportOptions(auth_key=b"k3y"))
            await t.send(b"hello")
            assert bytes(await t.receive()) == b"hello"
            await t.aclose()


@pytest.mark.slow
@pytest.mark.parametrize("kind", list(URIS))
async def test_publisher_loan_contract(kind: str) -> None:
    """Publisher.loan over each transport, its reader in another process (testing/transport_contract_loans.py)."""
    await loans.check_publisher_loans(kind.removesuffix("-python"))


def test_in_place_loans_on_a_transport_that_copies_are_refused_naming_the_ones_that_lend() -> None:
    loans.require_lending("shm")
    for kind in ("memory", "tcp", "tls"):
        with pytest.raises(ConfigError, match=rf"transport '{kind}' does not lend memory.*\['shm'\]"):
            loans.require_lending(kind)
    with pytest.raises(ConfigError, match="unknown transport 'zmq'"):
        loans.require_lending("zmq")
