#!/usr/bin/env python3
"""Mutation test of `bom replay` (issue 27), run on demand, not in CI.

Makes N randomly damaged copies of the shipped bags' first 600 kB (flipped bits, a truncation, a
zeroed span, a duplicated span: one kind per copy, as in the run that found the bags of
../shared/data/damaged-bags/), replays each with a time limit, and counts the outcomes. Pass: every
run exits 0 or 3, none panics (101), aborts (134) or hangs past the limit, and every exit 3 prints
exactly one `error:` line. Each failing copy is kept under OUT for a regression test.

Usage: tests/mutate.py [--bom target/release/bom] [--copies 400] [--seed 0] [--timeout 60]
                       [--jobs 2] [--out target/mutate]
"""

import argparse
import collections
import glob
import os
import random
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor


def mutate(data, rng):
    b = bytearray(data)
    kind = rng.randrange(4)
    if kind == 0:
        for _ in range(rng.randint(1, 16)):
            i = rng.randrange(len(b))
            b[i] ^= 1 << rng.randrange(8)
        return "bitflip", bytes(b)
    if kind == 1:
        return "truncate", bytes(b[: rng.randrange(len(b))])
    i = rng.randrange(len(b))
    n = min(rng.randint(1, 4096), len(b) - i)
    if kind == 2:
        b[i : i + n] = bytes(n)
        return "zero", bytes(b)
    span = bytes(b[i : i + n])
    at = rng.randrange(len(b))
    return "duplicate", bytes(b[:at]) + span + bytes(b[at:])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--bom", default="target/release/bom")
    ap.add_argument("--copies", type=int, default=400)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--timeout", type=float, default=60.0)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--out", default="target/mutate")
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    sources = sorted(glob.glob("bags/mujoco/*.mcap") + glob.glob("bags/sturm/*.mcap"))
    originals = [open(p, "rb").read()[:600_000] for p in sources]
    rng = random.Random(args.seed)
    jobs = []
    for k in range(args.copies):
        idx = rng.randrange(len(sources))
        kind, data = mutate(originals[idx], rng)
        path = os.path.join(args.out, f"damaged_{k:03d}.mcap")
        with open(path, "wb") as f:
            f.write(data)
        jobs.append((k, os.path.basename(sources[idx]), kind, path))

    def run(job):
        k, src, kind, path = job
        t0 = time.monotonic()
        try:
            p = subprocess.run([args.bom, "replay", path], capture_output=True, text=True, timeout=args.timeout,
                               env=dict(os.environ, RUST_BACKTRACE="0"))
            code, err = p.returncode, p.stderr
        except subprocess.TimeoutExpired:
            code, err = "hang", ""
        dt = time.monotonic() - t0
        errors = [l for l in err.splitlines() if l.startswith("error:")]
        ok = code in (0, 3) and "panicked" not in err and (code == 0 or len(errors) == 1)
        return k, src, kind, code, dt, ok, (errors[-1] if errors else err.strip().splitlines()[-1:] or [""])[0] if not ok else ""

    results = []
    with ThreadPoolExecutor(args.jobs) as ex:
        for r in ex.map(run, jobs):
            results.append(r)
            if not r[5]:
                print(f"FAIL  copy {r[0]} ({r[1]}, {r[2]}): exit {r[3]} after {r[4]:.1f} s: {r[6]}", flush=True)
    codes = collections.Counter(str(r[3]) for r in results)
    kinds = collections.Counter(r[2] for r in results)
    failed = [r for r in results if not r[5]]
    for r in results:
        if r[5]:
            os.remove(os.path.join(args.out, f"damaged_{r[0]:03d}.mcap"))
    longest = max(results, key=lambda r: r[4])
    print(f"copies {len(results)} (seed {args.seed}; {dict(kinds)}); exit codes {dict(codes)}; "
          f"longest run {longest[4]:.1f} s (copy {longest[0]}); failures kept in {args.out}")
    print(f"{len(results) - len(failed)} passed, {len(failed)} failed")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
