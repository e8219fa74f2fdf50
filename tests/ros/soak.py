#!/usr/bin/env python3
"""Soak and overload of `bom node` (issue 27), run on demand, not in CI.

Phases, over loopback DDS from rclpy (a publisher process of its own, so that it can be killed):
1. `--minutes` (default 60) of a synthetic 4-part object (cabinet body, a door on a vertical hinge,
   a drawer, a static shelf) at 30 Hz with `--points` (20,000) labelled points a cloud and the
   wrench at 200 Hz at a contact frame on /tf; a push every 10 s (door open, drawer out, door
   closed, drawer in, and again), each a quasi-static push whose force is that of viscous plus
   Coulomb friction (door 1 N m s/rad + 0.5 N m, drawer 10 N s/m + 2 N);
2. `--overload-minutes` (5) at 3x the cloud rate;
3. a publisher killed (SIGKILL) in the middle of a push and restarted 3 s later, for
   `--restart-seconds` (60) more.
The stream's stamps are wall-clock seconds since the start, so the restarted publisher goes on
where the stream would be.

Recorded: the node's resident memory every 10 s (/proc), each posterior's latency from its
window closing (the node's log, time-stamped here), merges, forgotten windows, bad-input counts
and the node's exit report. Writes OUT/soak.json, OUT/node.log and, with matplotlib,
OUT/soak_memory.svg and OUT/soak_latency.svg. Prints the acceptance checks of issue 27:
memory growth after the first 5 minutes, every push accounted for (a posterior, a merge or a
forgotten window), latency against its first-5-minute median, the node alive after the restart.

Run in the environment of tests/ros/run_interop.sh:
    python tests/ros/soak.py --bom target/release/bom --out target/soak
"""

import argparse
import json
import math
import os
import re
import signal
import subprocess
import sys
import threading
import time

PUSH_PERIOD_S = 10.0
HINGE = (0.43, -0.4, 0.0)


def smooth(u):
    """0 -> 1 over u in [0, 1], zero speed at both ends."""
    u = min(max(u, 0.0), 1.0)
    return u * u * (3.0 - 2.0 * u)


def dsmooth(u):
    return 6.0 * u * (1.0 - u) if 0.0 < u < 1.0 else 0.0


def state(t):
    """(door angle rad, its rate, drawer travel m, its rate, pushed part or None) at stream time t.
    A 40 s cycle: door opened at 2-4.5 s, drawer out at 12-14 s, door closed at 22-24.5 s, drawer in
    at 32-34 s."""
    c = t % (4 * PUSH_PERIOD_S)
    door, ddoor, drawer, ddrawer, pushed = 0.0, 0.0, 0.0, 0.0, None
    if c < 22.0:
        door, ddoor = 0.6 * smooth((c - 2.0) / 2.5), 0.6 * dsmooth((c - 2.0) / 2.5) / 2.5
    else:
        door, ddoor = 0.6 * (1.0 - smooth((c - 22.0) / 2.5)), -0.6 * dsmooth((c - 22.0) / 2.5) / 2.5
    if c < 32.0:
        drawer, ddrawer = 0.15 * smooth((c - 12.0) / 2.0), 0.15 * dsmooth((c - 12.0) / 2.0) / 2.0
    else:
        drawer, ddrawer = 0.15 * (1.0 - smooth((c - 32.0) / 2.0)), -0.15 * dsmooth((c - 32.0) / 2.0) / 2.0
    if 2.0 <= c <= 4.5 or 22.0 <= c <= 24.5:
        pushed = 2
    elif 12.0 <= c <= 14.0 or 32.0 <= c <= 34.0:
        pushed = 3
    return door, ddoor, drawer, ddrawer, pushed


def contact(t):
    """(contact point, force) of the push at t (zero force between pushes)."""
    door, ddoor, drawer, ddrawer, pushed = state(t)
    if pushed == 2:
        r = (0.01, 0.35, 0.4)
        ca, sa = math.cos(door), math.sin(door)
        p = (HINGE[0] + ca * r[0] - sa * r[1], HINGE[1] + sa * r[0] + ca * r[1], r[2])
        torque = 1.0 * ddoor + 0.5 * (1.0 if ddoor >= 0 else -1.0)
        f = torque / 0.35  # along the door's normal, at 0.35 m from the hinge
        return p, (f * ca, f * sa, 0.0)
    if pushed == 3:
        f = 10.0 * ddrawer + 2.0 * (1.0 if ddrawer >= 0 else -1.0)
        return (0.41 + drawer, 0.2, 0.2), (f, 0.0, 0.0)
    return (0.6, 0.0, 0.5), (0.0, 0.0, 0.0)


def publish(args):
    """Publisher process: the object's clouds, wrench and /tf from stream time --from to --to."""
    import numpy as np
    import rclpy
    from geometry_msgs.msg import WrenchStamped
    from rosutil import contact_messages, qos, stamp
    from sensor_msgs.msg import PointCloud2, PointField
    from tf2_msgs.msg import TFMessage

    rng = np.random.default_rng(int(args.t0 * 1000) % 2**32)
    n = args.points // 4
    from throughput import box_surface

    body = box_surface(rng, [0.0, -0.4, 0.0], [0.4, 0.4, 0.8], n)
    door = box_surface(rng, [0.42, -0.4, 0.02], [0.44, 0.0, 0.78], n)
    drawer = box_surface(rng, [0.05, 0.02, 0.1], [0.41, 0.38, 0.3], n)
    shelf = box_surface(rng, [0.0, -0.4, 0.85], [0.4, 0.4, 0.88], n)
    labels = np.repeat(np.arange(1, 5, dtype=np.uint32), n)
    hinge = np.array(HINGE)
    rec = np.zeros(4 * n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("label", "<u4")])
    rec["label"] = labels
    fields = [PointField(name=nm, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, nm in enumerate("xyz")]
    fields.append(PointField(name="label", offset=12, datatype=PointField.UINT32, count=1))

    def cloud_at(t):
        a, _, x, _, _ = state(t)
        c, s = math.cos(a), math.sin(a)
        d = door - hinge
        door_t = np.stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=1) + hinge
        xyz = np.concatenate([body, door_t, drawer + np.array([x, 0.0, 0.0]), shelf]) + rng.normal(0, 0.001, (4 * n, 3))
        rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        msg = PointCloud2(height=1, width=4 * n, fields=fields, is_bigendian=False, point_step=16, row_step=16 * 4 * n, is_dense=True)
        msg.data = rec.tobytes()
        msg.header.stamp = stamp(t)
        msg.header.frame_id = "world"
        return msg

    rclpy.init()
    node = rclpy.create_node(f"bom_soak_publisher_{os.getpid()}")
    pub_cloud = node.create_publisher(PointCloud2, "/segmented_points", qos(reliable=False, depth=10))
    pub_wrench = node.create_publisher(WrenchStamped, "/applied_wrench", qos(depth=100))
    pub_tf = node.create_publisher(TFMessage, "/tf", qos(depth=100))
    deadline = time.time() + 30
    while time.time() < deadline and (pub_cloud.get_subscription_count() == 0 or pub_wrench.get_subscription_count() == 0):
        time.sleep(0.1)
    epoch = args.epoch
    now = lambda: time.time() - epoch  # noqa: E731
    t_cloud = math.ceil(max(now(), args.t0) * args.rate) / args.rate
    t_wrench = math.ceil(max(now(), args.t0) * 200.0) / 200.0
    clouds = 0
    while True:
        t_next = min(t_cloud, t_wrench)
        if t_next >= args.t1:
            break
        delay = t_next - now()
        if delay > 0:
            time.sleep(delay)
        if t_wrench <= t_cloud:
            tf, w = contact_messages(t_wrench, *contact(t_wrench))
            pub_tf.publish(tf)
            pub_wrench.publish(w)
            t_wrench += 1.0 / 200.0
        else:
            if now() - t_cloud < 1.0 / args.rate:  # late clouds are skipped, as a camera would
                pub_cloud.publish(cloud_at(t_cloud))
                clouds += 1
            t_cloud += 1.0 / args.rate
    print(f"publisher {os.getpid()}: {clouds} clouds at {args.rate} Hz, stream {args.t0:.1f}-{args.t1:.1f} s", flush=True)
    node.destroy_node()
    rclpy.shutdown()
    return 0


def rss_kb(pid):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    return 0


def median(v):
    v = sorted(v)
    return float("nan") if not v else (v[len(v) // 2] if len(v) % 2 else 0.5 * (v[len(v) // 2 - 1] + v[len(v) // 2]))


def run(args):
    if os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") != "LOCALHOST":
        print("refusing to run: ROS_AUTOMATIC_DISCOVERY_RANGE must be LOCALHOST (loopback only)")
        return 2
    os.makedirs(args.out, exist_ok=True)
    epoch = time.time()
    node = subprocess.Popen([args.bom, "node"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
    latencies, merges, lines = [], [], []
    log = open(os.path.join(args.out, "node.log"), "w")
    # First posteriors of a window only (a refit after an adopted effect logs "refitted posterior").
    pat = re.compile(r"INFO posterior after (\d+) window\(s\) published ([0-9.]+) s after")

    def reader():
        for line in node.stdout:
            t = time.time() - epoch
            log.write(f"{t:9.2f} {line}")
            lines.append(line)
            m = pat.search(line)
            if m:
                latencies.append((t, int(m.group(1)), float(m.group(2))))
            if "window merged" in line:
                merges.append(t)

    threading.Thread(target=reader, daemon=True).start()
    memory = []
    stop = threading.Event()

    def sampler():
        while not stop.is_set() and node.poll() is None:
            memory.append((time.time() - epoch, rss_kb(node.pid)))
            stop.wait(10.0)

    threading.Thread(target=sampler, daemon=True).start()
    me = [sys.executable, os.path.abspath(__file__), "--publish", "--epoch", str(epoch), "--points", str(args.points)]

    def publisher(t0, t1, rate):
        return subprocess.Popen(me + ["--from", str(t0), "--to", str(t1), "--rate", str(rate)])

    soak_end = 5.0 + args.minutes * 60.0
    over_end = soak_end + args.overload_minutes * 60.0
    phases = []
    p = publisher(5.0, soak_end, 30.0)
    p.wait()
    phases.append(("soak", 5.0, soak_end))
    p = publisher(soak_end, over_end, 90.0)
    p.wait()
    phases.append(("overload 3x", soak_end, over_end))
    # Kill a publisher in the middle of a push (a door push runs 2-4.5 s into a 40 s cycle).
    cycle = 4 * PUSH_PERIOD_S
    kill_at = (math.floor(over_end / cycle) + 1) * cycle + 3.2
    p = publisher(over_end, kill_at + 30.0, 30.0)
    while time.time() - epoch < kill_at:
        time.sleep(0.05)
    p.kill()
    p.wait()
    killed_at = time.time() - epoch
    time.sleep(3.0)
    restart = time.time() - epoch
    p = publisher(restart, restart + args.restart_seconds, 30.0)
    p.wait()
    phases.append(("killed and restarted", over_end, restart + args.restart_seconds))
    alive = node.poll() is None
    time.sleep(2.0)
    node.send_signal(signal.SIGINT)
    try:
        code = node.wait(timeout=300)
    except subprocess.TimeoutExpired:
        node.kill()
        code = None
    stop.set()
    time.sleep(0.5)
    log.close()
    text = "".join(lines)
    report = text[text.rfind("bom node:"):] if "bom node:" in text else ""
    m = re.search(r"(\d+) window\(s\) \((\d+) old ones forgotten\), (\d+) posterior update\(s\), (\d+) window\(s\) merged", report)
    windows, forgotten, updates, merged = (int(g) for g in m.groups()) if m else (0, 0, 0, 0)
    end = restart + args.restart_seconds
    # Pushes start 2 s into every 10 s and last at most 2.5 s; count those published whole.
    published = [(5.0, killed_at), (restart, end)]
    starts = [k * PUSH_PERIOD_S + 2.0 for k in range(int(end / PUSH_PERIOD_S) + 1)]
    pushes = sum(1 for s0 in starts if any(a <= s0 and s0 + 2.5 <= b - 2.0 for a, b in published))
    warnings = sum(1 for l in lines if " WARN " in f" {l}")
    out = {
        "phases": phases, "memory_kb": memory, "latency": latencies, "merges": merges, "node_exit": code,
        "pushes": pushes, "windows": windows, "forgotten": forgotten, "updates": updates, "merged": merged,
        "warnings": warnings, "killed_at_s": killed_at, "restarted_at_s": restart, "alive_after_restart": alive,
        "report": report,
    }
    with open(os.path.join(args.out, "soak.json"), "w") as f:
        json.dump(out, f, indent=1)
    return analyze(out, args.out)


def analyze(d, out_dir):
    """The acceptance checks of issue 27 on a run's record (soak.json), and the plots."""
    (_, _, soak_end), (_, _, over_end), _ = d["phases"]
    memory, latencies, restart = d["memory_kb"], d["latency"], d["restarted_at_s"]
    after5 = [kb for t, kb in memory if 300.0 <= t <= soak_end]
    first5 = [lat for t, _, lat in latencies if t <= 305.0]
    later = [lat for t, _, lat in latencies if 305.0 < t <= soak_end]
    after_restart = [lat for t, _, lat in latencies if t > restart]
    ok = True

    def check(c, what):
        nonlocal ok
        print(("ok    " if c else "FAIL  ") + what, flush=True)
        ok &= bool(c)

    if after5:
        growth = (max(after5) - after5[0]) / after5[0]
        check(growth <= 0.10, f"resident memory after the first 5 minutes: {after5[0] / 1024:.1f} -> max {max(after5) / 1024:.1f} MiB ({100 * growth:+.1f}%)")
    # Under overload the buffers fill to a new level within seconds; bounded means a plateau: the
    # last half of the phase no higher than 10% over its first minute.
    over = [(t, kb) for t, kb in memory if soak_end < t <= over_end]
    if over:
        t0 = over[0][0]
        first = [kb for t, kb in over if t <= t0 + 60.0]
        last = [kb for t, kb in over if t >= (t0 + over_end) / 2]
        check(max(last) <= 1.1 * max(first), f"memory under 3x overload levels off: first minute max {max(first) / 1024:.1f} MiB, last half max {max(last) / 1024:.1f} MiB (soak {max(after5) / 1024:.1f})")
    check(d["windows"] >= d["pushes"], f"every push closed a window: {d['pushes']} pushes, {d['windows']} windows")
    check(d["updates"] + d["merged"] >= d["windows"] - 1,
          f"every window gave a posterior or a counted merge: {d['windows']} windows, {d['updates']} updates, {d['merged']} merged, {d['forgotten']} forgotten")
    if first5 and later:
        check(median(later) <= 1.5 * median(first5), f"median latency window closed -> posterior: first 5 min {median(first5):.2f} s, later {median(later):.2f} s")
    check(d["alive_after_restart"] and len(after_restart) > 0,
          f"node alive after the publisher was killed at {d['killed_at_s']:.0f} s and restarted; {len(after_restart)} posterior(s) after the restart")
    check(d["node_exit"] == 0, f"node exit {d['node_exit']} on SIGINT")
    print(d["report"])
    try:
        import matplotlib

        matplotlib.use("svg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(8, 3))
        ax.plot([t / 60 for t, _ in memory], [kb / 1024 for _, kb in memory])
        for name, a, _ in d["phases"]:
            ax.axvline(a / 60, color="grey", lw=0.5)
            ax.text(a / 60, ax.get_ylim()[1], name, fontsize=7, va="top")
        ax.set_xlabel("time [min]")
        ax.set_ylabel("bom node resident memory [MiB]")
        fig.tight_layout()
        fig.savefig(os.path.join(out_dir, "soak_memory.svg"))
        fig, ax = plt.subplots(figsize=(8, 3))
        ax.plot([t / 60 for t, _, _ in latencies], [lat for _, _, lat in latencies], ".", ms=3)
        ax.set_xlabel("time [min]")
        ax.set_ylabel("window closed -> posterior [s]")
        fig.tight_layout()
        fig.savefig(os.path.join(out_dir, "soak_latency.svg"))
    except ImportError:
        print("note: matplotlib not installed: no plots")
    return 0 if ok else 1


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--bom", default="target/release/bom")
    ap.add_argument("--minutes", type=float, default=60.0)
    ap.add_argument("--overload-minutes", type=float, default=5.0)
    ap.add_argument("--restart-seconds", type=float, default=60.0)
    ap.add_argument("--points", type=int, default=20000)
    ap.add_argument("--out", default="target/soak")
    ap.add_argument("--analyze", metavar="SOAK_JSON", help="only check and plot a finished run's record")
    ap.add_argument("--publish", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--epoch", type=float, default=0.0, help=argparse.SUPPRESS)
    ap.add_argument("--from", dest="t0", type=float, default=0.0, help=argparse.SUPPRESS)
    ap.add_argument("--to", dest="t1", type=float, default=0.0, help=argparse.SUPPRESS)
    ap.add_argument("--rate", type=float, default=30.0, help=argparse.SUPPRESS)
    args = ap.parse_args()
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    if args.analyze:
        with open(args.analyze) as f:
            return analyze(json.load(f), os.path.dirname(os.path.abspath(args.analyze)))
    return publish(args) if args.publish else run(args)


if __name__ == "__main__":
    sys.exit(main())
