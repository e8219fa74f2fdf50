"""Two `bom eval --corpus ... --json` reports of the same objects compared part by part: is B's
change from A more than the spread that the objects' own scatter gives?

    python3 bags/generate/compare_reports.py A.json B.json [--layout continuous] [--bootstrap 2000]

Per layout: joint types and parents right in one report only, with the exact two-sided McNemar
p-value (the discordant parts as a binomial of one half); the IdE (median relative error of damping
and friction, as `bom eval` reports it), the Brier score of the joint-type probabilities (per part the sum over the
three types of `(P - 1[true])^2`, averaged over parts, as `bom eval` reports it) and the wrong calls at P >= 0.95,
each for A and B with B - A and its 90% interval from a bootstrap over *objects* (an object's parts
share a recording, a camera and a registration, so they do not vary independently). An interval
that holds 0 says the reports differ by no more than a resampling of the objects would move one of
them. Parts are paired by object name and label; objects in only one report are left out and
counted. Standard library only.
"""
import argparse
import json
import math
import random
import statistics


def parts(report, layout):
    """{object: {label: part}} of one layout, each part holding its call, parent, probabilities
    and relative errors."""
    out = {}
    for row in report["objects"]:
        if row["layout"] != layout:
            continue
        calls = {c["label"]: c for c in row.get("calls", [])}
        obj = out.setdefault(row["name"], {})
        for p in row["metrics"]["per_part"]:
            c = calls.get(p["label"], {})
            obj[p["label"]] = {
                "joint": bool(p["joint_correct"]),
                "parent": bool(p["parent_correct"]),
                "probs": c.get("type_probs"),
                "true": p["true_joint"],
                "errors": [p[k] for k in ("damping_rel_error", "friction_rel_error") if p.get(k) is not None],
            }
    return out


TYPES = ("rigid", "prismatic", "revolute")


def brier_terms(part):
    probs = part["probs"]
    if not probs or part["true"] not in TYPES:
        return []
    return [(p - (1.0 if t == part["true"] else 0.0)) ** 2 for p, t in zip(probs, TYPES)]


def wrong_confident(part):
    probs = part["probs"]
    if not probs or part["true"] not in TYPES:
        return 0
    best = max(range(3), key=lambda k: probs[k])
    return int(TYPES[best] != part["true"] and probs[best] >= 0.95)


def metrics(objs):
    """IdE, Brier and wrong calls at P >= 0.95 over a list of objects (lists of parts)."""
    errors = [e for o in objs for p in o for e in p["errors"]]
    terms = [sum(t) for o in objs for p in o for t in [brier_terms(p)] if t]
    return {
        "ide": statistics.median(errors) if errors else float("nan"),
        "brier": sum(terms) / len(terms) if terms else float("nan"),
        "wrong95": sum(wrong_confident(p) for o in objs for p in o),
    }


def mcnemar(a_only, b_only):
    """Exact two-sided McNemar p-value: the discordant pairs as Binomial(n, 1/2)."""
    n, k = a_only + b_only, min(a_only, b_only)
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, i) for i in range(k + 1)) / 2.0**n
    return min(1.0, 2.0 * tail)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("--layout", choices=("continuous", "episodes"), action="append")
    ap.add_argument("--bootstrap", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    ra, rb = json.load(open(args.a)), json.load(open(args.b))
    rng = random.Random(args.seed)
    for layout in args.layout or ["continuous", "episodes"]:
        pa, pb = parts(ra, layout), parts(rb, layout)
        names = sorted(set(pa) & set(pb))
        left = len(set(pa) ^ set(pb))
        pairs = [[(pa[n][l], pb[n][l]) for l in sorted(set(pa[n]) & set(pb[n]))] for n in names]
        if not any(pairs):
            print(f"{layout}: no objects in both reports")
            continue
        flat = [x for o in pairs for x in o]
        print(f"{layout}: {len(names)} objects, {len(flat)} parts paired" + (f" ({left} objects in one report only, left out)" if left else ""))
        for key in ("joint", "parent"):
            a_only = sum(a[key] and not b[key] for a, b in flat)
            b_only = sum(b[key] and not a[key] for a, b in flat)
            ra_ = sum(a[key] for a, _ in flat) / len(flat)
            rb_ = sum(b[key] for _, b in flat) / len(flat)
            print(f"  {key:<7} accuracy A {ra_:.3f}  B {rb_:.3f}; right in A only {a_only}, in B only {b_only}; McNemar p = {mcnemar(a_only, b_only):.3f}")
        ma = metrics([[a for a, _ in o] for o in pairs])
        mb = metrics([[b for _, b in o] for o in pairs])
        boot = {k: [] for k in ma}
        for _ in range(args.bootstrap):
            sample = [pairs[rng.randrange(len(pairs))] for _ in pairs]
            sa = metrics([[a for a, _ in o] for o in sample])
            sb = metrics([[b for _, b in o] for o in sample])
            for k in boot:
                d = sb[k] - sa[k]
                if not math.isnan(d):
                    boot[k].append(d)
        for k, label in (("ide", "IdE"), ("brier", "Brier"), ("wrong95", "wrong P>=0.95")):
            d = sorted(boot[k])
            lo, hi = (d[int(0.05 * (len(d) - 1))], d[int(0.95 * (len(d) - 1))]) if d else (float("nan"),) * 2
            fmt = "{:.0f}" if k == "wrong95" else "{:.3f}"
            print(f"  {label:<13} A {fmt.format(ma[k])}  B {fmt.format(mb[k])}  B - A {mb[k] - ma[k]:+.3f}, 90% bootstrap interval [{lo:+.3f}, {hi:+.3f}]")


if __name__ == "__main__":
    main()
