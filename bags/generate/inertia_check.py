"""The planner's kinodynamics against the truth: for each corpus object with >= 2 interactions
whose first pushed part bom types right, the generalised inertia, damping and friction that
`task_success.py`'s bom planner builds from bom's JSON summary (median, and whether the 90% range of
its posterior draws holds the truth) against the true ones (MuJoCo's joint-space mass matrix and
the joint's damping and frictionloss).

    MUJOCO_GL=egl .venv-gen/bin/python bags/generate/inertia_check.py --corpus corpus --models DIR --split tune

`DIR` holds the summaries `task_success.py --models DIR` wrote (`<object>.json`); objects without
one are skipped. One line per object, then the counts of true values inside the 90% ranges.
"""
import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import task_success as ts  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--corpus", required=True)
    ap.add_argument("--models", required=True)
    ap.add_argument("--split", default="tune")
    ap.add_argument("--draws", type=int, default=400)
    args = ap.parse_args(argv)
    entries = json.loads((Path(args.corpus) / "manifest.json").read_text())["objects"]
    inside = {"inertia": 0, "damping": 0, "friction": 0}
    ratios, n = [], 0
    for e in entries:
        summary = Path(args.models) / f"{e['name']}.json"
        if e["split"] != args.split or e["interactions"] < 2 or not summary.exists():
            continue
        scene = ts.Scene(e["seed_used"])
        task = scene.task()
        truth = scene.true_model(task)
        model, called = ts.bom_model(json.loads(summary.read_text()), task, args.draws, e["seed_used"])
        if model is None or called != task["kind"]:
            continue
        n += 1
        cells = []
        for k in ("inertia", "damping", "friction"):
            draws, t = model[k], float(truth[k][0])
            lo, hi = np.quantile(draws, [0.05, 0.95])
            ok = bool(lo <= t <= hi)
            inside[k] += ok
            cells.append(f"{k} {draws[0]:.4g} (true {t:.4g}, 90% [{lo:.3g}, {hi:.3g}]{'' if ok else ' MISS'})")
        ratios.append(abs(math.log(model["inertia"][0] / float(truth["inertia"][0]))))
        print(f"{e['name']:<28} {task['kind']:<9} " + "; ".join(cells), flush=True)
    if n:
        print(f"{n} parts; truth inside the 90% range: inertia {inside['inertia']}, damping {inside['damping']}, "
              f"friction {inside['friction']}; median |log(inertia / true)| {np.median(ratios):.3f}")


if __name__ == "__main__":
    main()
