"""Which part each push of a corpus's continuous bags pushes, by two rules, against the recorder's
push order: the contract's nearest part at one instant (the cloud nearest the push's first sample
above 1 N) and bom's rule since stop 71 (`perception::ContactVotes`: over every cloud from that
sample until the force falls to 0.5 N or below, each part's nearest point's distance to the
contact point of the last wrench sample at or before the cloud; the part with the smallest
statistic over the clouds it is seen in; ties to the part seen in more clouds, then the lower
label).

The truth is the recorder's plan: push k of an object is on joint `push_order[k % n]` of the
object redrawn from its seed (`corpus.draw`, deterministic), mapped to a label by the ground
truth's part names (procedural parts: `door1` for `door1_hinge`; objects whose joints are not named
after their parts, and bags whose count of pushes differs from the plan's, are skipped). A pick
counts as right when it is that part, and as in its subtree when it is that part or a descendant
(the hand on a latch pushes the latch's door too).

    MUJOCO_GL=egl .venv-gen/bin/python bags/generate/pushed_parts.py --corpus DIR [--effects]

`--effects` for a corpus of `effects_corpus.py` (its objects push each part more often). Prints
per split: pushes scored, right and in the subtree for each rule.
"""
import argparse
import bisect
import contextlib
import io
import json
import math
import sys
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from mcap_ros2.reader import read_ros2_messages

sys.path.insert(0, str(Path(__file__).resolve().parent))
import corpus  # noqa: E402
import mujoco  # noqa: E402  (after corpus, which sets up MuJoCo's environment)

OPEN_N, CLOSE_N = 1.0, 0.5  # bom's windows.force_open_n and force_close_n


def quat_mat(x, y, z, w):
    """Rotation matrix of a ROS quaternion (MuJoCo's `mju_quat2Mat`, which takes w first)."""
    m = np.zeros(9)
    mujoco.mju_quat2Mat(m, np.array([w, x, y, z]))
    return m.reshape(3, 3)


def read(bag):
    """Clouds in the fixed frame (stamp, points, labels), wrench samples (stamp, |force|) and the
    contact point at a stamp (the `/tf` contact frame nearest in time). The recorder's own formats
    only: clouds of FLOAT32 x, y, z and UINT32 label with one static transform to the fixed frame,
    the contact frame a child of the fixed frame."""
    static, clouds, wrenches, contact = None, [], [], []
    for m in read_ros2_messages(bag, topics=["/tf_static", "/tf", "/segmented_points", "/applied_wrench"]):
        topic, msg = m.channel.topic, m.ros_msg
        if topic == "/tf_static":
            tr = msg.transforms[0].transform
            static = (quat_mat(tr.rotation.x, tr.rotation.y, tr.rotation.z, tr.rotation.w),
                      np.array([tr.translation.x, tr.translation.y, tr.translation.z]))
        elif topic == "/tf":
            for tr in msg.transforms:
                if tr.child_frame_id == "contact":
                    t = tr.header.stamp
                    v = tr.transform.translation
                    contact.append((t.sec + t.nanosec * 1e-9, np.array([v.x, v.y, v.z])))
        elif topic == "/segmented_points":
            a = np.frombuffer(bytes(msg.data), dtype=np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("l", "<u4")]))
            t = msg.header.stamp
            clouds.append((t.sec + t.nanosec * 1e-9, np.stack([a["x"], a["y"], a["z"]], 1).astype(float), a["l"].copy()))
        else:
            f, t = msg.wrench.force, msg.header.stamp
            wrenches.append((t.sec + t.nanosec * 1e-9, math.sqrt(f.x ** 2 + f.y ** 2 + f.z ** 2)))
    rot, trans = static
    clouds = sorted(((t, (rot @ p.T).T + trans, l) for t, p, l in clouds), key=lambda c: c[0])
    contact.sort(key=lambda c: c[0])
    wrenches.sort()
    stamps = [c[0] for c in contact]

    def contact_at(t):
        i = bisect.bisect_left(stamps, t)
        j = min((j for j in (i - 1, i) if 0 <= j < len(stamps)), key=lambda j: abs(stamps[j] - t))
        return contact[j][1]
    return clouds, wrenches, contact_at


def pushes(bag):
    """Per push (force above OPEN_N until it falls to CLOSE_N): the instant rule's pick and, per
    label, the distances \\[m\\] over the push's clouds."""
    clouds, wrenches, contact_at = read(bag)
    ws = [w[0] for w in wrenches]
    out, k = [], 0
    while k < len(wrenches):
        if wrenches[k][1] > OPEN_N:
            start, e = wrenches[k][0], k
            while e < len(wrenches) and wrenches[e][1] > CLOSE_N:
                e += 1
            end = wrenches[e][0] if e < len(wrenches) else wrenches[-1][0]
            per = {}
            for t, p, l in clouds:
                if start <= t <= end:
                    c = contact_at(wrenches[bisect.bisect_right(ws, t) - 1][0])
                    d = np.linalg.norm(p - c, axis=1)
                    for lab in np.unique(l):
                        if lab:
                            per.setdefault(int(lab), []).append(float(d[l == lab].min()))
            i = min(range(len(clouds)), key=lambda i: abs(clouds[i][0] - start))
            d = np.linalg.norm(clouds[i][1] - contact_at(start), axis=1)
            out.append({"instant": int(clouds[i][2][int(np.argmin(d))]), "per": per})
            k = e
        k += 1
    return out


RULES = {
    "median": lambda v: float(np.median(v)),
    "q25": lambda v: float(np.percentile(v, 25)),
    "mean": lambda v: float(np.mean(v)),
    "min": lambda v: float(np.min(v)),
}


def pick(push, rule):
    if rule == "instant" or not push["per"]:
        return push["instant"]
    key = {lab: (RULES[rule](v), -len(v), lab) for lab, v in push["per"].items()}
    return min(key, key=key.get)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--corpus", required=True)
    ap.add_argument("--effects", action="store_true", help="a corpus of effects_corpus.py")
    args = ap.parse_args(argv)
    root = Path(args.corpus)
    rules = ["instant", *RULES]
    score = {}
    for o in json.load(open(root / "manifest.json"))["objects"]:
        bag = root / o["continuous"][0]
        truth = {}
        for md in make_reader(open(bag, "rb")).iter_metadata():
            if md.name == "bom_ground_truth":
                truth = {p["label"]: p for p in json.loads(md.metadata["json"])["parts"]}
        with contextlib.redirect_stdout(io.StringIO()):
            so, _, _, _ = corpus.draw(o["seed_used"])
        order = list(so.push_order or so.handles)
        n = min(6, max(o["interactions"], len(order) + 1)) if args.effects else o["interactions"]
        labels = [next((lab for lab, p in truth.items() if j.startswith(p["name"] + "_")), None) for j in (order[k % len(order)] for k in range(n))]
        found = pushes(str(bag))
        if None in labels or len(found) != len(labels):
            score.setdefault(o["split"], {}).setdefault("skipped", 0)
            score[o["split"]]["skipped"] += 1
            continue
        s = score.setdefault(o["split"], {})
        for push, want in zip(found, labels):
            s["pushes"] = s.get("pushes", 0) + 1
            for r in rules:
                got = pick(push, r)
                right, sub = s.setdefault(r, [0, 0])
                x = got
                while x and x != want:
                    x = truth.get(x, {}).get("parent", 0)
                s[r] = [right + (got == want), sub + (x == want)]
    for split, s in sorted(score.items()):
        cells = " | ".join(f"{r} {s[r][0]} / {s[r][1]}" for r in rules if r in s)
        print(f"{split}: {s.get('pushes', 0)} pushes scored ({s.get('skipped', 0)} objects skipped); right / in the subtree: {cells}")


if __name__ == "__main__":
    main()
