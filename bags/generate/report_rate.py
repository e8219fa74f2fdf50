"""Calibration of the reported joint-type probabilities against `inference.report_rate`, from
`bom eval --corpus ... --json` reports made at `report_rate: 1.0` (README, "Generalization",
stop 53).

With `coarsen: report` (dynamic mode) each part's reported log-probabilities are its joint types'
gaps below the fit's most probable type times `report_rate * n_eff / n`, so a report made at rate
1 gives the one at any rate `eta` by multiplying its log-probabilities by `eta` — exactly,
except that a gap clipped at the 300-nat floor at rate 1 becomes `300 x eta` nats here where
`bom` would report more (at rate 0.1 either way a probability below 1e-13). Prints, per rate, the Brier score (summed over
the three types, mean over parts), the expected calibration error of the top label, the wrong
calls at P >= 0.95, and the largest gap between mean predicted and observed frequency in a
reliability bin with at least 20 probabilities — per report and layout, and the Brier scores and
wrong calls summed over all of them. Standard library only.

    python3 bags/generate/report_rate.py tune_s0.json tune_s1.json [--rates 1,0.3,0.1]
"""
import argparse
import json
import math

TYPES = ["rigid", "prismatic", "revolute"]
RATES = [1.0, 0.5, 0.3, 0.2, 0.15, 0.12, 0.1, 0.08, 0.07, 0.05, 0.03]


def parts(report):
    """(layout, true type index, log-probabilities) of every scored part with a known type."""
    out = []
    for obj in report["objects"]:
        truth = {p["label"]: p.get("true_joint") for p in obj["metrics"]["per_part"]}
        for call in obj["calls"]:
            t = truth.get(call["label"])
            if t in TYPES:
                out.append((obj["layout"], TYPES.index(t), [math.log(max(p, 1e-300)) for p in call["type_probs"]]))
    return out


def tempered(logp, rate):
    top = max(logp)
    w = [math.exp(rate * (v - top)) for v in logp]
    s = sum(w)
    return [v / s for v in w]


def scores(rows, rate):
    brier, wrong, ece_bins, rel_bins = 0.0, 0, [[0, 0.0, 0] for _ in range(10)], [[0, 0.0, 0] for _ in range(10)]
    for _, t, logp in rows:
        p = tempered(logp, rate)
        brier += sum((p[k] - (k == t)) ** 2 for k in range(3))
        top = max(range(3), key=lambda k: p[k])
        wrong += top != t and p[top] >= 0.95
        b = ece_bins[min(int(p[top] * 10), 9)]
        b[0], b[1], b[2] = b[0] + 1, b[1] + p[top], b[2] + (top == t)
        for k in range(3):
            b = rel_bins[min(int(p[k] * 10), 9)]
            b[0], b[1], b[2] = b[0] + 1, b[1] + p[k], b[2] + (k == t)
    n = max(len(rows), 1)
    ece = sum(abs(b[1] - b[2]) for b in ece_bins) / n
    dev = max((abs(b[1] - b[2]) / b[0] for b in rel_bins if b[0] >= 20), default=0.0)
    return brier / n, wrong, ece, dev


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("reports", nargs="+")
    ap.add_argument("--rates", default=",".join(map(str, RATES)))
    a = ap.parse_args()
    rates = [float(r) for r in a.rates.split(",")]
    groups = []
    for f in a.reports:
        rows = parts(json.load(open(f)))
        for layout in sorted({r[0] for r in rows}):
            groups.append((f"{f} {layout}", [r for r in rows if r[0] == layout]))
    print(f"{'rate':>6}  {'Brier sum':>9}  {'wrong sum':>9}  " + "  ".join(g[0] for g in groups))
    for rate in rates:
        s = [scores(rows, rate) for _, rows in groups]
        cells = "  ".join(f"B {b:.3f} ECE {e:.3f} w {w} dev {d:.2f}" for b, w, e, d in s)
        print(f"{rate:>6}  {sum(x[0] for x in s):>9.3f}  {sum(x[1] for x in s):>9}  {cells}")


if __name__ == "__main__":
    main()
