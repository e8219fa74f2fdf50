"""How well perception tracks nested parts: for every movable part on a movable parent of a
corpus split, its registered rotation relative to its parent against the joint's true turn, at
every cloud of the object's continuous bag that shows both (a slide's true relative rotation is
none). A small part on a door that is misregistered while the door swings, or when it comes back
into view, shows here as clouds off by more than 0.1 rad.

    MUJOCO_GL=egl .venv-gen/bin/python bags/generate/nested_tracks.py --corpus corpus --split tune \\
        --bom target/release/bom [--config FILE] [--only obj045_procedural,...]

Prints one line per nested part: clouds compared, clouds off by more than 0.1 rad, the largest
and the median error. With `--timeline N`, also every N-th cloud compared and every cloud off by
more than 0.1 rad: its stamp, the parent's registered rotation, the error and the axis of the
part's rotation relative to its parent (in the parent's reference frame; a nested part lagging
its door's swing turns about the door's hinge). The true turn comes from the recorder re-run
(`true_track.joint_tracks`); the registered poses from `BOM_LOG=info,bom::perception=trace bom
replay`.
"""
import argparse
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import true_track  # noqa: E402

TRACE = re.compile(r"part (\d+) at ([\d.]+) s: rotation ([\d.]+) rad about \[([-\d.]+), ([-\d.]+), ([-\d.]+)\]")


def rotation(axis, angle):
    """Rodrigues: the rotation matrix of `angle` rad about the unit `axis`."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def angle(r):
    return float(np.arccos(np.clip((np.trace(r) - 1) / 2, -1.0, 1.0)))


def registered(bom, bag, config):
    """Every part's registered rotation per stamp, {label: {stamp: 3x3}}, from a replay's trace."""
    cmd = [bom, "replay", bag] + (["--config", config] if config else [])
    err = subprocess.run(cmd, env={**os.environ, "BOM_LOG": "info,bom::perception=trace"}, capture_output=True, text=True).stderr
    out = {}
    for line in err.splitlines():
        m = TRACE.search(line)
        if m:
            axis = np.array([float(m.group(i)) for i in (4, 5, 6)])
            out.setdefault(int(m.group(1)), {})[round(float(m.group(2)), 3)] = rotation(axis, float(m.group(3)))
    return out


def true_turn(entry, part):
    """The part's joint position per stamp, {stamp: q}, from the recorder re-run: its joint is
    `<part>_hinge` in procedural objects, `<part>` or `<part>_joint` in the shipped models. None
    when no such joint exists."""
    for name in (part["name"] + "_hinge", part["name"], part["name"] + "_joint"):
        try:
            (track,), _ = true_track.joint_tracks(entry, [name])
        except KeyError:
            continue
        return {round(t, 3): q for t, q in track}
    return None


def axis_of(r):
    """The unit axis of rotation matrix `r` (any unit vector for the identity)."""
    w = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    n = np.linalg.norm(w)
    return w / n if n > 1e-12 else np.array([1.0, 0.0, 0.0])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--corpus", required=True)
    ap.add_argument("--split", default="tune")
    ap.add_argument("--bom", required=True)
    ap.add_argument("--config")
    ap.add_argument("--only", help="comma-separated object names")
    ap.add_argument("--timeline", type=int, default=0, metavar="N", help="also print every N-th cloud compared (0: none)")
    args = ap.parse_args(argv)
    only = set(args.only.split(",")) if args.only else None
    manifest = json.loads((Path(args.corpus) / "manifest.json").read_text())
    for o in manifest["objects"]:
        if o["split"] != args.split or (only and o["name"] not in only):
            continue
        parts = {p["label"]: p for p in o["parts"]}
        nested = [p for p in o["parts"] if p["joint"] != "rigid" and p["parent"] in parts and parts[p["parent"]]["joint"] != "rigid"]
        if not nested:
            continue
        reg = registered(args.bom, str(Path(args.corpus) / o["continuous"][0]), args.config)
        for p in nested:
            truth = None
            if p["joint"] == "revolute":
                truth = true_turn(o, p)
                if truth is None:
                    print(f"{o['name']} part {p['label']}: no joint found for {p['name']}")
                    continue
            parent, child = reg.get(p["parent"], {}), reg.get(p["label"], {})
            stamps = [t for t in sorted(set(parent) & set(child)) if truth is None or t in truth]
            if not stamps:
                print(f"{o['name']} part {p['label']}: no cloud shows both it and its parent")
                continue
            # Relative rotations from the first cloud that shows both (the references may differ).
            r0 = (parent[stamps[0]].T @ child[stamps[0]]).T
            q0 = truth[stamps[0]] if truth else 0.0
            rel = [r0 @ parent[t].T @ child[t] for t in stamps]
            errs = np.array([abs(angle(r) - (abs(truth[t] - q0) if truth else 0.0)) for r, t in zip(rel, stamps)])
            if args.timeline > 0:
                for k, t in enumerate(stamps):
                    if k % args.timeline == 0 or errs[k] > 0.1:
                        a = axis_of(rel[k])
                        print(f"  {t:8.3f} s  parent turned {angle(parent[t]):.3f} rad  error {errs[k]:.3f} rad  "
                              f"relative axis [{a[0]:+.2f}, {a[1]:+.2f}, {a[2]:+.2f}]")
            off = int((errs > 0.1).sum())
            print(f"{o['name']:28s} part {p['label']} {p['name']:8s} {p['joint']:9s} on {p['parent']}: {len(stamps)} clouds, "
                  f"{off} off by > 0.1 rad ({off / len(stamps):.0%}), largest {errs.max():.2f} rad, median {np.median(errs):.3f}", flush=True)


if __name__ == "__main__":
    main()
