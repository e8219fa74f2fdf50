"""The true position of one joint at every cloud of a corpus object's continuous bag: the recorder
re-run from the object's seed (deterministic), the joint's `qpos` read as each cloud is rendered.
Prints `stamp q` per line (header stamps as in the bag, seconds; radians or metres), to set
against perception's registered track (`BOM_LOG=info,bom::perception=trace bom replay BAG`).

    MUJOCO_GL=egl .venv-gen/bin/python bags/generate/true_track.py --corpus corpus obj060_procedural slider1_slide

Joint names are the recorder's (`door1_hinge`, `slider1_slide`, ...; `corpus.py` prints them).

With `--trace LOG --label L` (LOG: the stderr of `BOM_LOG=info,bom::perception=trace bom replay
BAG`, L: the part's label) it prints instead how far perception's registered track of part L is
from the joint's true motion since the first cloud: for a hinge the registered rotation angle
against the true turn, for a slide the anchor's displacement along its largest displacement
against the true travel (RMS and largest error over the clouds in both, and the last cloud's
values). `--series` adds one line per cloud before the summary: stamp, true motion, registered
motion, their difference, and the registered rotation angle (for a slide, a rotation the joint
does not have).
"""
import argparse
import contextlib
import json
import math
import os
import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import corpus  # noqa: E402
import record  # noqa: E402
import mujoco  # noqa: E402  (after record, which sets up MuJoCo's environment)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--corpus", required=True)
    ap.add_argument("object")
    ap.add_argument("joint")
    ap.add_argument("--trace", help="stderr of `BOM_LOG=info,bom::perception=trace bom replay BAG`")
    ap.add_argument("--label", type=int, help="the part whose registered track --trace compares")
    ap.add_argument("--series", action="store_true", help="with --trace: also print every cloud's values")
    args = ap.parse_args(argv)
    if (args.trace is None) != (args.label is None):
        sys.exit("error: --trace and --label go together")
    entries = {e["name"]: e for e in json.loads((Path(args.corpus) / "manifest.json").read_text())["objects"]}
    if args.object not in entries:
        sys.exit(f"error: {args.object}: not in {args.corpus}/manifest.json")
    try:
        (track,), hinge = joint_tracks(entries[args.object], [args.joint])
    except KeyError:
        sys.exit(f"error: {args.joint}: no such joint in {args.object}")
    if args.trace is None:
        for t, q in track:
            print(f"{t:.3f} {q:.6f}")
        return
    compare(track, registered(args.trace, args.label), hinge[0], args.series)


def joint_tracks(entry, joints):
    """The recorder re-run from a manifest `entry`'s seed (deterministic): for each name in
    `joints`, its `qpos` at every cloud as `[(stamp, q)]` (stamps as in the continuous bag, the
    first cloud at 1.0 s), and whether each is a hinge. KeyError for a joint the object lacks."""
    so, _, _, interactions = corpus.draw(entry["seed_used"])
    rec = record.Recorder(so, {}, entry["seed_used"], 150)
    ids = [rec.joint_id(name) for name in joints]
    for name, j in zip(joints, ids):
        if j < 0:  # mj_name2id's answer for a name the model lacks
            raise KeyError(name)
    adrs = [rec.model.jnt_qposadr[j] for j in ids]
    samples = []
    render = rec.cloud

    def cloud():
        # The simulation time of each cloud, from the first one (recorded at the bag's t0).
        samples.append((float(rec.data.time), [float(rec.data.qpos[a]) for a in adrs]))
        return render()

    rec.cloud = cloud
    # The recorder's own report goes to stderr; the bag it writes is thrown away.
    with contextlib.redirect_stdout(sys.stderr):
        rec.record(os.devnull, interactions, declared=True, t0=1.0)
    t_first = samples[0][0]
    tracks = [[(round(1.0 + t - t_first, 3), q[k]) for t, q in samples] for k in range(len(ids))]
    return tracks, [rec.model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE for j in ids]


def registered(path, label):
    """The last registered pose logged per stamp for part `label`: {stamp: (angle, shift xyz)}."""
    line = re.compile(rf"part {label} at ([\d.]+) s: rotation ([\d.]+) rad about \[[^\]]+\], anchor moved \[([^\]]+)\]")
    out = {}
    with open(path) as f:
        for text in f:
            m = line.search(text)
            if m:
                out[round(float(m.group(1)), 3)] = (float(m.group(2)), [float(v) for v in m.group(3).split(",")])
    if not out:
        sys.exit(f"error: {path}: no registered pose of part {label} (was BOM_LOG=...,bom::perception=trace set?)")
    return out


def compare(track, reg, hinge, series=False):
    truth = dict(track)
    stamps = [t for t in sorted(reg) if t in truth]
    if not stamps:
        sys.exit("error: the trace's stamps and the recording's do not meet")
    q0 = truth[stamps[0]]
    if hinge:
        pairs = [(reg[t][0], abs(truth[t] - q0)) for t in stamps]
        unit = "rad"
    else:
        far = max((reg[t][1] for t in stamps), key=lambda v: math.hypot(*v))
        n = math.hypot(*far) or 1.0
        along = [sum(a * b / n for a, b in zip(reg[t][1], far)) for t in stamps]
        pairs = [(a, abs(truth[t] - q0)) for a, t in zip(along, stamps)]
        unit = "m"
    err = [a - b for a, b in pairs]
    if series:
        print(f"# stamp [s], true, registered, registered - true [{unit}], registered rotation [rad]")
        for t, (a, b), e in zip(stamps, pairs, err):
            print(f"{t:.3f} {b:+.4f} {a:+.4f} {e:+.4f} {reg[t][0]:.3f}")
    rms = math.sqrt(sum(e * e for e in err) / len(err))
    print(f"{len(err)} clouds: registered - true RMS {rms:.4f} {unit}, largest {max(map(abs, err)):.4f} {unit}; "
          f"last cloud registered {pairs[-1][0]:.4f}, true {pairs[-1][1]:.4f} {unit}")


if __name__ == "__main__":
    main()
