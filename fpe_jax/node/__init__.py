"""The live prediction node (`fpe node`): the NumPy runner behind ROS 1 or ROS 2 topics.

JAX-free: the car may have no JAX. The middleware-neutral core (`Node`) talks to a `Transport`
(ROS 1 through rospy, ROS 2 through DDS) with messages as nested dicts, one type store per
flavour (`typestore`).
"""

from fpe_jax.node._core import OUTPUTS, Node, NodeOptions, Transport
from fpe_jax.node._types import FLAVOURS, full_definition, typestore

__all__ = [
    "FLAVOURS",
    "OUTPUTS",
    "Node",
    "NodeOptions",
    "Transport",
    "full_definition",
    "typestore",
]
