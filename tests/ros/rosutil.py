"""Helpers shared by the rclpy scripts of tests/ros (interop.py, throughput.py)."""

from builtin_interfaces.msg import Time
from geometry_msgs.msg import TransformStamped, WrenchStamped
from tf2_msgs.msg import TFMessage
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
    """builtin_interfaces/Time of `t` seconds (t >= 0), rounded to the nanosecond (5.9999999999 s is
    6 s, not 5 s plus a nanosecond field rounded to 0)."""
    ns = int(round(t * 1e9))
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def contact_messages(t, point, force):
    """The /tf message placing frame `contact` at `point` (m, in `world`) and the WrenchStamped of
    `force` (N) applied there, both stamped `t` (contract section 1: the wrench frame's origin is
    the point of application)."""
    tf = TransformStamped()
    tf.header.stamp = stamp(t)
    tf.header.frame_id = "world"
    tf.child_frame_id = "contact"
    tf.transform.translation.x, tf.transform.translation.y, tf.transform.translation.z = map(float, point)
    tf.transform.rotation.w = 1.0
    w = WrenchStamped()
    w.header.stamp = stamp(t)
    w.header.frame_id = "contact"
    w.wrench.force.x, w.wrench.force.y, w.wrench.force.z = map(float, force)
    return TFMessage(transforms=[tf]), w
