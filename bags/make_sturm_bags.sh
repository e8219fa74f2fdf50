#!/usr/bin/env bash
# Rebuild bags/sturm/*.mcap from the real tracks in ../shared/data/sturm-articulation
# (one bag per track, 30 Hz, 4x4-point patches, 4x4x4 cubes for bare points, joint type from the data README).
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${DATA:-../shared/data/sturm-articulation}
BOM=${BOM:-target/release/bom}
mkdir -p bags/sturm
imp() { "$BOM" import-tracks "$1" --out "bags/sturm/$2.mcap" --joint "$3"; }
for f in "$DATA"/cabinet_one/*.log; do imp "$f" "cabinet_one_$(basename "$f" .log)" revolute; done
for d in left_door right_door dishwasher; do
  for f in "$DATA"/second_set/$d/*.log; do imp "$f" "${d}_$(basename "$f" .log)" revolute; done
done
for d in drawer sliding_cabinet; do
  for f in "$DATA"/second_set/$d/*.log; do imp "$f" "${d}_$(basename "$f" .log)" prismatic; done
done
imp "$DATA"/tracked_planes/door.txt planes_door revolute
imp "$DATA"/tracked_planes/drawer.txt planes_drawer prismatic
