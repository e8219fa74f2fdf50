"""IdE by kind of part: the relative errors of damping and friction in a `bom eval --corpus ... --json`
report, grouped by what each part is in the corpus manifest (procedural parts by their name without
the number: door, drawer, lid, flap, slider, hatch, latch, boxlid; asset parts by family), with the
median, the count above 0.3 and the median of log(estimate / truth) (its sign says whether a
kind's error is a bias).

    python3 bags/generate/ide_by_kind.py REPORT.json --manifest corpus/manifest.json [--layout continuous]

Standard library only. Prints one row per kind and the overall median (the report's IdE).
"""
import argparse
import json
import math
import statistics


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("report")
    ap.add_argument("--manifest", required=True)
    ap.add_argument("--layout", default="continuous", choices=("continuous", "episodes"))
    args = ap.parse_args(argv)
    manifest = {e["name"]: e for e in json.load(open(args.manifest))["objects"]}
    report = json.load(open(args.report))
    groups = {}
    for row in report["objects"]:
        if row["layout"] != args.layout or row["name"] not in manifest:
            continue
        names = {p["label"]: p["name"] for p in manifest[row["name"]]["parts"]}
        for p in row["metrics"]["per_part"]:
            kind = "".join(c for c in names.get(p["label"], "?") if not c.isdigit())
            if row.get("family") != "procedural":
                kind = row.get("family") or kind
            for k in ("damping", "friction"):
                e, m, t = p.get(f"{k}_rel_error"), p.get(f"{k}_median"), p.get(f"{k}_true")
                if e is None:
                    continue
                log_ratio = math.log(m / t) if m and t and m > 0 and t > 0 else None
                groups.setdefault(kind, []).append((e, log_ratio))
    every = []
    print(f"{'kind':<22} {'values':>6} {'median':>7} {'>0.3':>5} {'med log(est/true)':>18}")
    for kind, v in sorted(groups.items()):
        errors = [e for e, _ in v]
        logs = [x for _, x in v if x is not None]
        every += errors
        bias = f"{statistics.median(logs):+.3f}" if logs else "-"
        print(f"{kind:<22} {len(v):>6} {statistics.median(errors):>7.3f} {sum(e > 0.3 for e in errors):>5} {bias:>18}")
    if every:
        print(f"{'all':<22} {len(every):>6} {statistics.median(every):>7.3f}")


if __name__ == "__main__":
    main()
