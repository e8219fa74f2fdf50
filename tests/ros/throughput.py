#!/usr/bin/env python3
"""Throughput of `bom node` (issue 5; a report, not a test): an rclpy node publishes a synthetic
4-part object at 30 Hz with 20,000 labelled points a frame (a cabinet body, a door on a vertical
hinge, a drawer, a static shelf), pushes the door then the drawer (WrenchStamped at 200 Hz at a
contact frame on /tf), and stops `bom node` with SIGINT at the end. The node's exit report gives
perception CPU per cloud and the latency from a window closing to its posterior being published.

Run like tests/ros/run_interop.sh (same environment):
    python tests/ros/throughput.py --bom target/release/bom
"""

import argparse
import math
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import rclpy
from rclpy.executors import MultiThreadedExecutor

from bom_msgs.msg import ObjectModel
from rosutil import contact_messages, qos, stamp
from geometry_msgs.msg import WrenchStamped
from sensor_msgs.msg import PointCloud2, PointField
from tf2_msgs.msg import TFMessage


def box_surface(rng, lo, hi, n):
    """n points on the surface of an axis-aligned box."""
    lo, hi = np.array(lo), np.array(hi)
    size = hi - lo
    areas = np.array([size[1] * size[2], size[0] * size[2], size[0] * size[1]]) * 2
    face = rng.choice(3, size=n, p=areas / areas.sum())
    pts = lo + rng.random((n, 3)) * size
    side = rng.random(n) < 0.5
    for a in range(3):
        m = face == a
        pts[m, a] = np.where(side[m], lo[a], hi[a])
    return pts


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--bom", default="target/release/bom")
    ap.add_argument("--seconds", type=float, default=14.0)
    ap.add_argument("--points", type=int, default=20000)
    ap.add_argument("--log", default="target/throughput-node.log")
    args = ap.parse_args()
    if os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") != "LOCALHOST":
        print("refusing to run: ROS_AUTOMATIC_DISCOVERY_RANGE must be LOCALHOST (loopback only)")
        return 2
    rng = np.random.default_rng(0)
    n = args.points // 4
    body = box_surface(rng, [0.0, -0.4, 0.0], [0.4, 0.4, 0.8], n)
    door = box_surface(rng, [0.42, -0.4, 0.02], [0.44, 0.0, 0.78], n)  # hinge at x=0.43, y=-0.4
    drawer = box_surface(rng, [0.05, 0.02, 0.1], [0.41, 0.38, 0.3], n)
    shelf = box_surface(rng, [0.0, -0.4, 0.85], [0.4, 0.4, 0.88], n)
    labels = np.repeat(np.arange(1, 5, dtype=np.uint32), n)
    hinge = np.array([0.43, -0.4, 0.0])

    def door_angle(t):  # pushed open 2-5 s
        return 0.6 * np.clip((t - 2.0) / 3.0, 0.0, 1.0)

    def drawer_out(t):  # pulled 8-10 s
        return 0.15 * np.clip((t - 8.0) / 2.0, 0.0, 1.0)

    def cloud_at(t):
        a = door_angle(t)
        c, s = math.cos(a), math.sin(a)
        d = door - hinge
        door_t = np.stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=1) + hinge
        drawer_t = drawer + np.array([drawer_out(t), 0.0, 0.0])
        xyz = np.concatenate([body, door_t, drawer_t, shelf]) + rng.normal(0, 0.001, (4 * n, 3))
        rec = np.zeros(4 * n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("label", "<u4")])
        rec["x"], rec["y"], rec["z"], rec["label"] = xyz[:, 0], xyz[:, 1], xyz[:, 2], labels
        fields = [PointField(name=nm, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, nm in enumerate("xyz")]
        fields.append(PointField(name="label", offset=12, datatype=PointField.UINT32, count=1))
        msg = PointCloud2(height=1, width=4 * n, fields=fields, is_bigendian=False, point_step=16, row_step=16 * 4 * n, is_dense=True)
        msg.data = rec.tobytes()
        msg.header.stamp = stamp(t)
        msg.header.frame_id = "world"
        return msg

    def contact_at(t):
        """(contact point, force) of the push at t."""
        if 2.0 <= t <= 5.0:
            a = door_angle(t)
            p = hinge + np.array([0.01, 0.35, 0.4])
            r = p - hinge
            p = hinge + np.array([math.cos(a) * r[0] - math.sin(a) * r[1], math.sin(a) * r[0] + math.cos(a) * r[1], r[2]])
            return p, np.array([math.cos(a), math.sin(a), 0.0]) * 3.0
        if 8.0 <= t <= 10.0:
            return np.array([0.41 + drawer_out(t), 0.2, 0.2]), np.array([4.0, 0.0, 0.0])
        return np.array([0.6, 0.0, 0.5]), np.zeros(3)

    log = open(args.log, "w")
    proc = subprocess.Popen([args.bom, "node"], stdout=log, stderr=subprocess.STDOUT)
    rclpy.init()
    node = rclpy.create_node("bom_throughput")
    pub_cloud = node.create_publisher(PointCloud2, "/segmented_points", qos(reliable=False, depth=10))
    pub_wrench = node.create_publisher(WrenchStamped, "/applied_wrench", qos(depth=100))
    pub_tf = node.create_publisher(TFMessage, "/tf", qos(depth=100))
    models = []
    node.create_subscription(ObjectModel, "/bom/object_model", models.append, qos(transient=True, depth=1))
    ex = MultiThreadedExecutor()
    ex.add_node(node)
    threading.Thread(target=ex.spin, daemon=True).start()
    deadline = time.time() + 30
    while time.time() < deadline and (pub_cloud.get_subscription_count() == 0 or pub_wrench.get_subscription_count() == 0):
        time.sleep(0.1)
    time.sleep(1.0)

    # Precompute clouds so that the publisher keeps 30 Hz.
    frames = [cloud_at(k / 30.0) for k in range(int(args.seconds * 30))]
    start = time.monotonic()
    k_cloud, k_wrench = 0, 0
    while k_cloud < len(frames):
        t_cloud, t_wrench = k_cloud / 30.0, k_wrench / 200.0
        if t_wrench <= t_cloud:
            tf, w = contact_messages(t_wrench, *contact_at(t_wrench))
            pub_tf.publish(tf)
            due, k_wrench = t_wrench, k_wrench + 1
            msg = w
            pub = pub_wrench
        else:
            due, msg, pub = t_cloud, frames[k_cloud], pub_cloud
            k_cloud += 1
        delay = start + due - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        pub.publish(msg)
    lag = time.monotonic() - start - args.seconds
    print(f"published {len(frames)} clouds of {4 * n} points and {k_wrench} wrenches (lag at the end {lag:.3f} s)")
    time.sleep(2.0)
    proc.send_signal(signal.SIGINT)
    code = proc.wait(timeout=120)
    log.close()
    ex.shutdown()
    rclpy.shutdown()
    print(open(args.log).read()[-1500:])
    print(f"node exit {code}; ObjectModel messages received: {len(models)}")
    return 0 if code == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
