"""Helpers shared by the rclpy scripts of tests/ros (interop.py, throughput.py)."""

from builtin_interfaces.msg import Time
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy


def qos(reliable=True, transient=False, depth=10):
    """A keep-last QoS profile: reliable or best effort, volatile or transient local."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if transient else DurabilityPolicy.VOLATILE,
    )


def stamp(t):
    """builtin_interfaces/Time of `t` seconds (t >= 0)."""
    return Time(sec=int(t), nanosec=int(round((t - int(t)) * 1e9)) % 1_000_000_000)
