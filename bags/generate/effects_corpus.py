"""A corpus of objects with undeclared effects (issue 25), recorded with a tune/validation split.

    python bags/generate/effects_corpus.py --out effects --objects 96 --seed 0 [--jobs 2] [--only N,M]

Objects are those of `corpus.py` (drawn from seeds 50000 + index, so none is an object of the
structure corpus), each recorded as one continuous bag. Every other object (odd indices) gets an
effect that acts in the recording and is absent from `bom_ground_truth` (undeclared); the others
are effect-free, so that false alarms can be counted. Effects, cycled over the odd indices:

- `spring` on the first pushed joint: 0.1-20 N m/rad or 5-500 N/m, its rest position inside the
  travel (the part starts at rest there), or with probability 0.3 beyond the closed stop (a
  preloaded self-closing part: the stop is hit too, a second effect);
- `joint_limit`: the first pushed joint's range narrowed so that pushes reach it: one-sided (the
  side the first push heads for) or two-sided (later pushes head for the other); with probability
  0.25 the narrowed stop is never reached (the careful robot lets go first): a stop that does not
  act, scored as effect-free;
- `gravity`: gravity on (the structure corpus has none), the object tilted 3-20 degrees about the
  world x or y axis (with probability 0.3 untilted: then only horizontal hinges, lids and flaps,
  feel it); every movable part whose joint gravity loads gets the effect, and stops the parts
  then rest on are recorded as hit;
- `quadratic_damping` on the first pushed joint: `-c q' |q'|`, c 0.2-5 N m s^2/rad^2 or
  20-500 N s^2/m^2 (a MuJoCo passive-force callback);
- `two`: a spring together with a reached stop, or a spring with quadratic damping, on one joint;
- `extra_friction`: the first pushed joint's Coulomb friction multiplied by 2-4 while the ground
  truth declares the drawn value (the base model has Coulomb friction, so no effect should be
  added: bom's friction estimate absorbs it; scored apart).

The part with the effect is pushed at least twice (criticism holds one push out of a refit to the
others). Which stops were reached is measured in the recording (within 2% of the range), not
planned. The truth is an MCAP metadata record `bom_undeclared_effects` (key `json`):

    {"category": "spring", "effects": [{"part": 2, "kind": "spring", "joint": "door1_hinge",
      "primary": true, "pushes": 3, "q_start": -0.23, "stiffness": 4.1, "rest_position": -0.23}]}

Joint positions (`q_start`, `rest_position`, `lower`, `upper`) are MuJoCo's joint coordinate about
(along) the ground truth's `axis_direction` (rad or m); `q_start` is its value at the first
recorded frame. `bom eval --corpus` scores criticism against the manifest's copy of this record
(`criticism` in its JSON, per object and per layout).
Output: `DIR/continuous/<name>/all.mcap` and `DIR/manifest.json` (per object its category, split:
`tune` for every third index, as in `corpus.py`, and the truth).
"""

import json
import math
import os
import shutil
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parent))

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

import corpus  # noqa: E402
import record  # noqa: E402

# Ten entries: a cycle length prime to 3, so that the tune split (every third index) draws every
# kind (a cycle of 9 gave tune only three of them).
EFFECT_CYCLE = ["spring", "joint_limit", "gravity", "quadratic_damping", "two",
                "spring", "joint_limit", "gravity", "extra_friction", "quadratic_damping"]

# dof index -> quadratic damping coefficient, read by the passive-force callback (one object per
# process at a time)
_QUADRATIC = {}


def _passive(m, d):
    for dof, c in _QUADRATIC.items():
        v = d.qvel[dof]
        d.qfrc_passive[dof] -= c * v * abs(v)


def category(index):
    return "none" if index % 2 == 0 else EFFECT_CYCLE[(index // 2) % len(EFFECT_CYCLE)]


class EffectRecorder(record.Recorder):
    """The corpus recorder with one object's undeclared effects applied (see the module docs).
    `plan`: effect name -> parameters, for the joint `joint`; `free` joints may reach their stops
    (the careful robot does not let go before them, and calibration does not avoid them)."""

    def __init__(self, so, plan, joint, seed, gravity_parts):
        self.eplan, self.ejoint, self.gravity_parts = plan, joint, gravity_parts
        self.free = set(plan.get("free", []))
        super().__init__(so, plan.get("build_effects", {}), seed, 150)
        m, d = self.model, self.data
        j = self.joint_id(joint)
        if "spring" in plan:
            # the part starts at rest: at the spring's rest position, or on the stop it is pressed to
            lo, hi = m.jnt_range[j]
            rest = plan["spring"]["rest"]
            d.qpos[m.jnt_qposadr[j]] = min(max(rest, lo), hi)
            mujoco.mj_forward(m, d)
        self.q_start = {jn: float(d.qpos[m.jnt_qposadr[self.joint_id(jn)]]) for jn in so.handles}

    def apply_effects(self):
        super().apply_effects()
        m, plan = self.model, self.eplan
        j = self.joint_id(self.ejoint)
        dof = m.jnt_dofadr[j]
        lo, hi = m.jnt_range[j]
        if "extra_friction" in plan:
            m.dof_frictionloss[dof] *= plan["extra_friction"]
        if "spring" in plan:
            m.jnt_stiffness[j] = plan["spring"]["stiffness"]
            m.qpos_spring[m.jnt_qposadr[j]] = plan["spring"]["rest"]
        if "limit" in plan:
            m.jnt_range[j] = plan["limit"]
            m.jnt_limited[j] = 1
        _QUADRATIC.clear()
        if "quadratic_damping" in plan:
            _QUADRATIC[int(dof)] = plan["quadratic_damping"]

    def careful_stop(self, entry, sign, q_start):
        if entry[4] in self.free:
            return self.other_joint_near_stop(entry[4], q_start)
        return super().careful_stop(entry, sign, q_start)

    def other_joint_near_stop(self, pushed, q_start):
        return super().other_joint_near_stop(pushed, {j: q for j, q in q_start.items() if j not in self.free})

    def stop_counts(self, jname):
        """Stops of `free` joints are not hits in a dry push."""
        return jname not in self.free

    def calibrate(self, entry, sign, q_start):
        """A push on a joint whose stop is meant to be reached is scaled until it gets there."""
        if entry[4] not in self.free or "limit" not in self.eplan or entry[4] != self.ejoint:
            return super().calibrate(entry, sign, q_start)
        m, d = self.model, self.data
        j = self.joint_id(entry[4])
        lo, hi = m.jnt_range[j]
        q = d.qpos[m.jnt_qposadr[j]]
        want = 0.97 * ((hi - q) if sign > 0 else (q - lo))
        for _ in range(8):
            travel, _ = self.dry_push(entry, sign, q_start)
            if travel >= want:
                return
            entry[5] *= 1.7

    def ground_truth(self, declared):
        gt = super().ground_truth(False)
        if "extra_friction" in self.eplan:
            # the declared friction is the drawn one: the factor is the undeclared effect
            label = self.label_of(self.ejoint)
            for p in gt["parts"]:
                if p["label"] == label:
                    p["friction"] = p["friction"] / self.eplan["extra_friction"]
        return gt

    def label_of(self, jname):
        return int(self.body_part[self.model.jnt_bodyid[self.joint_id(jname)]])

    def truth(self, pushes):
        """The effects that acted, as the module docs describe them."""
        m = self.model
        out = []

        def entry(jname, kind, primary, **params):
            e = {"part": self.label_of(jname), "kind": kind, "joint": jname, "primary": primary,
                 "pushes": pushes.get(jname, 0), "q_start": self.q_start[jname]}
            e.update(params)
            out.append(e)

        ej, plan = self.ejoint, self.eplan
        if "spring" in plan:
            entry(ej, "spring", True, stiffness=plan["spring"]["stiffness"], rest_position=plan["spring"]["rest"])
        if "quadratic_damping" in plan:
            entry(ej, "quadratic_damping", True, coefficient=plan["quadratic_damping"])
        if "extra_friction" in plan:
            entry(ej, "extra_friction", True, factor=plan["extra_friction"])
        for jname in self.gravity_parts:
            entry(jname, "gravity", True, tilt_deg=plan["tilt_deg"],
                  mass=float(sum(m.body_mass[b] for b in range(m.nbody) if self.body_part[b] == self.label_of(jname))))
        for jname in self.spec_obj.handles:
            lo, hi = (float(v) for v in m.jnt_range[self.joint_id(jname)])
            lower = self.q_min[jname] < lo + 0.02 * (hi - lo)
            upper = self.q_max[jname] > hi - 0.02 * (hi - lo)
            if lower or upper:
                primary = "limit" in plan and jname == ej
                entry(jname, "joint_limit", primary, lower=lo if lower else None, upper=hi if upper else None, hit=True)
            elif "limit" in plan and jname == ej:
                entry(ej, "joint_limit", False, lower=None, upper=None, hit=False, range=[lo, hi])
        return out

    def final_metadata(self):
        pushes = {}
        for k in range(self.n_interactions):
            jn = self.order[k % len(self.order)]
            pushes[jn] = pushes.get(jn, 0) + 1
        self.effects_truth = self.truth(pushes)
        return {"bom_undeclared_effects": {"json": json.dumps({"category": self.eplan["category"], "effects": self.effects_truth})}}


def gravity_loaded(model, data, jname):
    """Whether gravity loads joint `jname`: a hinge axis more than 3 degrees off vertical, or a
    slide axis more than 3 degrees off horizontal."""
    j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, jname)
    mujoco.mj_forward(model, data)
    az = abs(float(data.xaxis[j][2]))
    s = math.sin(math.radians(3.0))
    return az > s if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_SLIDE else math.sqrt(max(0.0, 1 - az * az)) > s


def make_plan(cat, rng, so, joint, jtype, lo, hi, q0):
    """The effect parameters of category `cat` for `joint` (range [lo, hi], starting at q0)."""
    rev = jtype == "revolute"
    span = hi - lo
    closed = lo if abs(q0 - lo) <= abs(hi - q0) else hi  # the bound the part starts near
    inward = 1.0 if closed == lo else -1.0
    plan = {"category": cat}
    spring = lambda: {"stiffness": corpus.log_uniform(rng, 0.1, 20.0) if rev else corpus.log_uniform(rng, 5.0, 500.0),
                      "rest": closed + inward * span * float(rng.uniform(0.1, 0.5))}
    if cat in ("spring", "two"):
        plan["spring"] = spring()
        if cat == "spring" and rng.random() < 0.3:
            plan["spring"]["rest"] = closed - inward * span * float(rng.uniform(0.1, 0.5))
            plan["free"] = [joint]
    if cat == "joint_limit" or (cat == "two" and rng.random() < 0.5):
        q = plan.get("spring", {}).get("rest", q0)
        far = q + inward * span * float(rng.uniform(0.2, 0.4))
        near = q - inward * span * float(rng.uniform(0.05, 0.12)) if rng.random() < 0.5 else closed
        plan["limit"] = (min(near, far), max(near, far))
        if cat == "joint_limit" and rng.random() < 0.25:
            plan["limit"] = (min(closed, q + inward * 0.6 * span), max(closed, q + inward * 0.6 * span))
        else:
            plan["free"] = [joint]
    elif cat == "two":
        plan["quadratic_damping"] = corpus.log_uniform(rng, 0.2, 5.0) if rev else corpus.log_uniform(rng, 20.0, 500.0)
    if cat == "quadratic_damping":
        plan["quadratic_damping"] = corpus.log_uniform(rng, 0.2, 5.0) if rev else corpus.log_uniform(rng, 20.0, 500.0)
    if cat == "extra_friction":
        plan["extra_friction"] = float(rng.uniform(2.0, 4.0))
    return plan


def record_object(out, index, seed0):
    """Record object `index` with its category's effect; redraw from the next seed on a failed
    check (a stop reached that the plan did not free, parts touching)."""
    cat = category(index)
    for attempt in range(8):
        seed = seed0 + 50000 + index + 1000 * attempt
        rng = np.random.default_rng(seed + 104729)
        tilt_deg, tilt = 0.0, None
        if cat == "gravity":
            tilt_deg = float(rng.uniform(3.0, 20.0)) if rng.random() < 0.7 else 0.0
            about = int(rng.integers(0, 2))
            sign = 1.0 if rng.random() < 0.5 else -1.0
            tilt = [0.0, 0.0]
            tilt[about] = sign * math.radians(tilt_deg)
        so, family, desc, interactions = corpus.draw(seed, tilt=tilt)
        if cat == "gravity" and so.builder is not None and family != "procedural":
            continue  # robosuite's door: no tilt hook
        name = f"obj{index:03d}_{family}"
        order = so.push_order
        interactions = min(6, max(interactions, len(order) + 1))
        base = record.Recorder(so, {"gravity": tilt[1]} if tilt and family != "procedural" else {}, seed, 150)
        joint = order[0]
        j = base.joint_id(joint)
        lo, hi = (float(v) for v in base.model.jnt_range[j])
        q0 = float(base.data.qpos[base.model.jnt_qposadr[j]])
        jtype = "revolute" if base.model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE else "prismatic"
        plan = make_plan(cat, rng, so, joint, jtype, lo, hi, q0)
        gravity_parts = []
        if cat == "gravity":
            so.gravity_off = False
            plan["tilt_deg"] = tilt_deg
            if family != "procedural":
                plan["build_effects"] = {"gravity": tilt[1]}
            probe = record.build(so, plan.get("build_effects", {}))
            pd = mujoco.MjData(probe)
            gravity_parts = [jn for jn in so.handles if gravity_loaded(probe, pd, jn)]
            if not gravity_parts:
                print(f"{name} seed {seed}: no joint loaded by gravity; redrawn", flush=True)
                continue
            plan["free"] = list(so.handles)
            so.settle_s = max(so.settle_s, 2.0)
        for layout in ("continuous",):
            for old in (Path(out) / layout).glob(f"obj{index:03d}_*"):
                shutil.rmtree(old)
        cont = Path(out) / "continuous" / name / "all.mcap"
        cont.parent.mkdir(parents=True, exist_ok=True)
        try:
            rec = EffectRecorder(so, plan, joint, seed, gravity_parts)
            rec.order, rec.n_interactions = order, interactions
            mujoco.set_mjcb_passive(_passive if _QUADRATIC else None)
            rec.record(cont, interactions, declared=False)
        except Exception as e:  # a model the builder could not compile, a renderer failure
            print(f"{name} seed {seed}: {e}; redrawn", flush=True)
            continue
        finally:
            mujoco.set_mjcb_passive(None)
        bad = [j for j in rec.limits_reached if j not in rec.free] or rec.parts_touched
        if bad:
            print(f"{name} seed {seed}: recorder check failed ({bad}); redrawn", flush=True)
            continue
        primary = [e for e in rec.effects_truth if e["primary"]]
        # a stop planned out of reach acts on nothing: no primary effect expected
        unreached = "limit" in plan and joint not in rec.free
        if cat != "none" and not unreached and not any(e["pushes"] >= 2 for e in primary):
            print(f"{name} seed {seed}: no primary effect on a part pushed twice; redrawn", flush=True)
            continue
        return {"name": name, "index": index, "family": family, "seed_used": seed, "interactions": interactions,
                "split": "tune" if index % 3 == 0 else "validation", "category": cat, "description": desc,
                "continuous": [str(cont.relative_to(out))], "effects": rec.effects_truth}
    print(f"obj{index:03d}: no valid draw in 8 attempts; left out", flush=True)
    return None


def main(argv=None):
    objects, path = corpus.run(record_object, __doc__, 96, argv)
    cats = {}
    for o in objects:
        cats[o["category"]] = cats.get(o["category"], 0) + 1
    n_t = sum(o["split"] == "tune" for o in objects)
    print(f"wrote {path}: {len(objects)} objects ({n_t} tune, {len(objects) - n_t} validation); {cats}")


if __name__ == "__main__":
    main()
