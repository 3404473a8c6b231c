"""The ROS-like bus: domains, nodes, topics, timers, services and parameters (see node.py and domain.py).

Names are imported lazily, so a process that needs only the bus's codec or messages (an env worker of a
gymnasium env) does not load the domain and node machinery.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from uniros_async._lazy import lazy_exports

if TYPE_CHECKING:
    from uniros_async.bus.domain import Domain, open_domain
    from uniros_async.bus.node import Node, Publisher, Service, ServiceClient, Subscription, Timer, open_node
    from uniros_async.bus.qos import QoS, latest, reliable

__all__ = [
    "Domain",
    "Node",
    "Publisher",
    "QoS",
    "Service",
    "ServiceClient",
    "Subscription",
    "Timer",
    "latest",
    "open_domain",
    "open_node",
    "reliable",
]

_WHERE = {
    "Domain": "domain",
    "Node": "node",
    "Publisher": "node",
    "QoS": "qos",
    "Service": "node",
    "ServiceClient": "node",
    "Subscription": "node",
    "Timer": "node",
    "latest": "qos",
    "open_domain": "domain",
    "open_node": "node",
    "reliable": "qos",
}

__getattr__, __dir__ = lazy_exports(__name__, _WHERE)
