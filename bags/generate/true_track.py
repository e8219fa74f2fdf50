"""The true position of one joint at every cloud of a corpus object's continuous bag: the recorder
re-run from the object's seed (deterministic), the joint's `qpos` read as each cloud is rendered.
Prints `stamp q` per line (header stamps as in the bag, seconds; radians or metres), to set
against perception's registered track (`BOM_LOG=info,bom::perception=trace bom replay BAG`).

    MUJOCO_GL=egl .venv-gen/bin/python bags/generate/true_track.py --corpus corpus obj060_procedural slider1_slide

Joint names are the recorder's (`door1_hinge`, `slider1_slide`, ...; `corpus.py` prints them).
"""
import argparse
import contextlib
import json
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import corpus  # noqa: E402
import record  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--corpus", required=True)
    ap.add_argument("object")
    ap.add_argument("joint")
    args = ap.parse_args(argv)
    entries = {e["name"]: e for e in json.loads((Path(args.corpus) / "manifest.json").read_text())["objects"]}
    if args.object not in entries:
        sys.exit(f"error: {args.object}: not in {args.corpus}/manifest.json")
    e = entries[args.object]
    so, _, _, interactions = corpus.draw(e["seed_used"])
    rec = record.Recorder(so, {}, e["seed_used"], 150)
    try:
        adr = rec.model.jnt_qposadr[rec.joint_id(args.joint)]
    except Exception:
        sys.exit(f"error: {args.joint}: no such joint in {args.object}")
    positions = []
    render = rec.cloud

    def cloud():
        # The simulation time of each cloud, from the first one (recorded at the bag's t0).
        positions.append((float(rec.data.time), float(rec.data.qpos[adr])))
        return render()

    rec.cloud = cloud
    # The recorder's own report goes to stderr; the bag it writes is thrown away.
    with contextlib.redirect_stdout(sys.stderr):
        rec.record(os.devnull, interactions, declared=True, t0=1.0)
    for t, q in positions:
        print(f"{1.0 + t - positions[0][0]:.3f} {q:.6f}")


if __name__ == "__main__":
    main()
