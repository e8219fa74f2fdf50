"""How well a hinge's coordinate is read off its observed centre of mass and off its observed turn,
against the recorder's joint positions, for the procedural objects of a corpus split (README,
"Stop 72").

    MUJOCO_GL=egl .venv-gen/bin/python bags/generate/hinge_readings.py --corpus corpus --split tune \
        --readings target/release/examples/hinge_readings

`--readings` is `cargo build --release --example hinge_readings` (`examples/hinge_readings.rs`): it
replays an object's continuous bag and prints, per grid frame, each revolute part's coordinate (m
of path, 0 at its first observation) read off the centre of mass and as bom reads it
(`bom::model::observed_coordinate`). The truth is the recorder re-run from the object's seed with
the hinges' `qpos` taken as each cloud is rendered (`true_track.joint_tracks`), moved to the same
origin, times the fitted radius, its sign the one that agrees with bom's axis. Scored: hinges
that bom calls revolute and that hang on a part that does not move (a latch on a door turns with
the door, which one joint's reading does not hold). Printed per hinge: frames, RMS error of each
reading [mm of path]; then the medians and how often bom's reading is the nearer. Standard
library, MuJoCo and the recorder only.
"""
import argparse
import json
import math
import statistics
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import true_track  # noqa: E402
from mcap.reader import make_reader  # noqa: E402


def ground_truth(bag):
    with open(bag, "rb") as f:
        for md in make_reader(f).iter_metadata():
            if md.name == "bom_ground_truth":
                return json.loads(md.metadata["json"])
    return None


def score(rows, truth):
    """RMS errors [mm] of (centre of mass, bom's reading) against the truth for one hinge."""
    tr = dict(truth)
    stamps = sorted(tr)
    q0 = tr[stamps[0]]
    pairs = []
    for stamp, q_com, q_read, radius in rows:
        k = min(stamps, key=lambda s: abs(s - stamp))
        if abs(k - stamp) <= 0.02:
            pairs.append(((tr[k] - q0) * radius, q_com, q_read))
    if len(pairs) < 2:
        return None
    sign = 1.0 if sum(t * r for t, _, r in pairs) >= 0.0 else -1.0
    rms = lambda k: 1000.0 * math.sqrt(sum((p[k] - sign * p[0]) ** 2 for p in pairs) / len(pairs))
    return len(pairs), rms(1), rms(2)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--corpus", required=True)
    ap.add_argument("--split", default="tune")
    ap.add_argument("--readings", required=True, help="the hinge_readings example's binary")
    args = ap.parse_args(argv)
    root = Path(args.corpus)
    entries = [e for e in json.loads((root / "manifest.json").read_text())["objects"] if e["split"] == args.split and e["family"] == "procedural"]
    com, read = [], []
    for e in entries:
        bag = root / e["continuous"][0]
        gt = ground_truth(bag)
        if gt is None:
            print(f"{e['name']}: no ground truth, skipped")
            continue
        parts = {p["label"]: p for p in gt["parts"]}
        out = subprocess.run([args.readings, str(bag)], capture_output=True, text=True)
        if out.returncode != 0:
            print(f"{e['name']}: readings failed ({out.stderr.strip().splitlines()[-1:]}), skipped")
            continue
        rows = {}
        for line in out.stdout.splitlines():
            if line.startswith("#"):
                continue
            f = line.split()
            rows.setdefault(int(f[0]), []).append(tuple(float(x) for x in f[1:]))
        keep = [l for l in rows if parts.get(l, {}).get("joint") == "revolute" and parts.get(parts[l]["parent"], {}).get("joint", "rigid") == "rigid"]
        if not keep:
            continue
        try:
            tracks, _ = true_track.joint_tracks(e, [parts[l]["name"] + "_hinge" for l in keep])
        except KeyError as err:
            print(f"{e['name']}: no joint {err}, skipped")
            continue
        for l, track in zip(keep, tracks):
            s = score(rows[l], track)
            if not s:
                continue
            n, e_com, e_read = s
            com.append(e_com)
            read.append(e_read)
            print(f"{e['name']} part {l} ({parts[l]['name']}): {n} frames, RMS error {e_com:.2f} mm off the centre of mass, {e_read:.2f} mm as read", flush=True)
    if com:
        nearer = sum(r < c for c, r in zip(com, read))
        print(f"{len(com)} hinges: median RMS error {statistics.median(com):.2f} mm off the centre of mass, "
              f"{statistics.median(read):.2f} mm as read; read nearer on {nearer}")


if __name__ == "__main__":
    main()
