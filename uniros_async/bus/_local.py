"""Per-process state of the bus: this process's identity and its in-process delivery tables."""

from __future__ import annotations

import collections
import inspect
import socket
import uuid
from collections.abc import Awaitable
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from uniros_async.bus.pubsub import Publisher, Subscription
    from uniros_async.bus.services import Service

PROCESS_TOKEN = uuid.uuid4().hex
"""Identifies this process to the registry (pids are reused; tokens are not)."""


def _host_id() -> str:
    try:
        boot = Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        boot = ""
    return f"{socket.gethostname()}:{boot}"


HOST_ID = _host_id()
TRANSPORT_CHOICES = ("auto", "memory", "shm", "tcp", "tls")
NETWORK_SCHEMES = ("tcp", "tls")
"""Schemes a domain serves other processes on; a node of the domain listens for its peers on the same one."""

# In-process delivery tables, keyed by (domain_id, topic). Only subscriptions that accept in-process delivery
# (their node's transport is "auto" or "memory") are listed.
_LOCAL_SUBS: dict[tuple[str, str], list[Subscription[Any]]] = collections.defaultdict(list)
_LOCAL_PUBS: dict[tuple[str, str], list[Publisher[Any]]] = collections.defaultdict(list)
_LOCAL_SERVICES: dict[tuple[str, str], Service[Any, Any]] = {}

_HELLO_TIMEOUT_S = 5.0


def _maybe_await(result: Any) -> Awaitable[Any] | None:
    return result if inspect.isawaitable(result) else None
