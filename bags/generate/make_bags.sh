#!/usr/bin/env bash
# Rebuild bags/mujoco/*.mcap (see bags/README.md). Needs the recorder's venv:
#   python3 -m venv .venv-gen && .venv-gen/bin/pip install -r bags/generate/requirements.txt \
#     && .venv-gen/bin/pip install --no-deps -r bags/generate/requirements-nodeps.txt
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=${PY:-.venv-gen/bin/python}
R="$PY bags/generate/record.py --interactions 4"
mkdir -p bags/mujoco
$R --object microwave       --seed 1 --out bags/mujoco/microwave.mcap
$R --object hingecabinet    --seed 2 --out bags/mujoco/hingecabinet.mcap
$R --object slidecabinet    --seed 3 --out bags/mujoco/slidecabinet.mcap
$R --object drawer          --seed 4 --out bags/mujoco/drawer.mcap
$R --object adroit_door     --seed 5 --out bags/mujoco/adroit_door.mcap
$R --object slide_microwave --seed 6 --out bags/mujoco/slide_microwave.mcap
# declared effects
$R --object microwave       --seed 7 --effect spring=1.5 --out bags/mujoco/microwave_spring.mcap
$R --object slidecabinet    --seed 8 --effect friction=2.0 --out bags/mujoco/slidecabinet_friction.mcap
# undeclared effects (model criticism must find them)
# Six interactions, three per door: criticism refits each door on all but one of its pushes.
$PY bags/generate/record.py --interactions 6 --object hingecabinet --seed 9 --effect spring=0.8 --undeclared --out bags/mujoco/hingecabinet_spring_undeclared.mcap
$R --object drawer          --seed 10 --effect limit=0.75 --undeclared --out bags/mujoco/drawer_limit_undeclared.mcap
$R --object slidecabinet    --seed 11 --effect gravity=0.35 --undeclared --out bags/mujoco/slidecabinet_gravity_undeclared.mcap
