"""The ROS-like bus: domains, nodes, topics, timers, services and parameters (see node.py and domain.py)."""

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
