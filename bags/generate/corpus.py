"""A randomized corpus of articulated objects, recorded both ways, with a fixed tune/validation split.

    python bags/generate/corpus.py --out corpus --objects 120 --seed 0 [--jobs 2] [--only N,M]

Every object is drawn from its own seed (`--seed` + its index), so any object can be remade alone
and the corpus is deterministic. Families:

- `procedural`: boxes built with `MjSpec` — doors on vertical hinges (left or right), drawers
  (stacked and side by side), lids and flaps on horizontal hinges, sliding panels, and nested
  chains (a door with a sliding hatch or a turning latch in it, a drawer carrying a lidded box, a
  sliding panel carrying a flap): 1-4 movable parts, the whole object tilted by up to 15 degrees;
- `kitchen` (gymnasium-robotics: microwave, hinge cabinet, slide cabinet), `adroit` (its door
  with a latch), `metaworld` (drawer, window, laptop lid), `robosuite` (door with a latch): the
  shipped models, with randomized damping, friction, masses and camera.

Per object: viscous damping over two decades (0.5-50 N s/m, 0.05-5 N m s/rad), Coulomb friction
0-3 (N or N m, prismatic at least 0.2 N), masses 0.05-5 kg, camera azimuth, elevation and distance,
push point (the handle, +-2 cm), push direction off the motion by up to 30 degrees, ramp 0.1-0.3 s,
hold 0.3-1.0 s, 1-6 interactions cycling over the movable parts in a random order; each push is
scaled (dry runs) until its joint moves at least 8% of its range without reaching a stop.

Gravity is off (`opt.gravity = 0`): bom's base model has no gravity unless an effect declares it,
and the undeclared-effect corpus (issue 25) is a separate one; so lids and flaps behave like doors.

Output (`--out DIR`):
- `DIR/continuous/<name>/all.mcap`: one bag with every interaction;
- `DIR/episodes/<name>/ep<k>.mcap`: one bag per interaction, each from the object's initial state,
  stamps 300 s apart (separate episodes, as most interaction datasets are laid out);
- `DIR/manifest.json`: per object its name, family, seed, split (`tune` for every third object by
  index, `validation` otherwise: about a third to tune), bags of both layouts, parts and joints.
  With `--tune-only` every object is `tune`: a further corpus for choosing settings only (the
  `tune` split of one corpus is small; README, "A larger tune split"). Its seeds must not meet the
  main corpus's (object `i` uses `--seed + i`, a redraw `+ 1000` per attempt): e.g. `--seed 200000`.

Objects whose recording fails the recorder's checks (a stop reached, parts touching) are redrawn
from the next seed (`seed_used` in the manifest).
"""

import argparse
import json
import math
import os
import shutil
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parent))

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

import record  # noqa: E402
from record import ObjectSpec, kitchen_model, metaworld_model, _site_packages  # noqa: E402

BOX = mujoco.mjtGeom.mjGEOM_BOX
HINGE = mujoco.mjtJoint.mjJNT_HINGE
SLIDE = mujoco.mjtJoint.mjJNT_SLIDE


def log_uniform(rng, lo, hi):
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


# --------------------------------------------------------------------------------------------
# Procedural objects
# --------------------------------------------------------------------------------------------


class Builder:
    """Collects the parts of a procedural object: `add(...)` adds a movable part as a body under
    a parent body, with one joint, box geoms and a handle point. Geoms do not collide (stops are
    joint ranges), so the recorder's contact check never fires on a drawer sliding in its case."""

    def __init__(self, rng):
        self.rng = rng
        self.parts = {}  # part name -> [body]
        self.handles = {}  # joint name -> ("body", body, offset)
        self.damping = {}
        self.friction = {}
        self.desc = []  # one line per movable part

    def rgba(self):
        return [float(v) for v in self.rng.uniform(0.25, 0.95, 3)] + [1.0]

    def register(self, part, joint, offset, desc, kind=None):
        """A movable part `part` (its own body) on `joint`, pushed at `offset` in its body; with
        `kind` (`hinge` or `slide`), its joint's damping and friction are drawn here."""
        if kind is not None:
            self.joint_dynamics(joint, kind)
        self.parts[part] = [part]
        self.handles[joint] = ("body", part, offset)
        self.desc.append(desc)

    def joint_dynamics(self, name, kind):
        rng = self.rng
        if kind == "slide":
            self.damping[name] = log_uniform(rng, 0.5, 50.0)
            self.friction[name] = float(rng.uniform(0.2, 3.0))
        else:
            self.damping[name] = log_uniform(rng, 0.05, 5.0)
            self.friction[name] = float(rng.uniform(0.0, 1.5))


def box_geoms(body, boxes, rgba, mass):
    """Box geoms `(center, half sizes)` in `body`, `mass` spread by volume, no collisions."""
    vol = [8 * h[0] * h[1] * h[2] for _, h in boxes]
    for (c, h), v in zip(boxes, vol):
        body.add_geom(type=BOX, pos=list(c), size=list(h), rgba=rgba, mass=mass * v / sum(vol),
                      contype=0, conaffinity=0, group=1)


def procedural(seed, tilt_override=None):
    """A random box object (see the module docs): its `ObjectSpec` and a description. With
    `tilt_override` (rad about world x and y), that tilt instead of the drawn one (the draws that
    follow are the same either way)."""
    rng = np.random.default_rng(seed)
    W, D, H = rng.uniform(0.45, 0.9), rng.uniform(0.3, 0.5), rng.uniform(0.4, 0.9)
    t = 0.02  # wall thickness
    tilt = [0.0, 0.0, 0.0]
    if rng.random() < 0.35:
        tilt[int(rng.integers(0, 2))] = float(math.radians(rng.uniform(-15, 15)))
    if tilt_override is not None:
        tilt = [float(tilt_override[0]), float(tilt_override[1]), 0.0]
    yaw = float(math.radians(rng.uniform(-25, 25)))
    base_z = 0.3 + H / 2
    kinds = ["door", "drawer", "lid", "flap", "slider", "door_hatch", "door_latch", "drawer_box", "slider_flap"]
    weights = np.array([3, 3, 1.5, 1.2, 1, 1, 1, 0.8, 0.8])
    n_movable = int(rng.choice([1, 2, 3, 4], p=[0.25, 0.35, 0.25, 0.15]))
    b = Builder(rng)
    # Layout: the front face (y = -D/2) is split into columns and rows; each front element takes
    # a cell; a lid takes the top.
    elements = []
    budget = n_movable
    lid_used = False
    while budget > 0:
        k = str(rng.choice(kinds, p=weights / weights.sum()))
        need = 2 if k in ("door_hatch", "door_latch", "drawer_box", "slider_flap") else 1
        if need > budget or (k == "lid" and lid_used):
            continue
        lid_used |= k == "lid"
        elements.append(k)
        budget -= need
    front = [e for e in elements if e != "lid"]
    cols = 1 if len(front) <= 1 else int(rng.choice([1, 2])) if len(front) == 2 else 2
    rows = max(1, math.ceil(len(front) / cols))
    cell_w, cell_h = (W - 2 * t) / cols, (H - 2 * t) / rows
    spec_ops = []

    def carcass(spec):
        root = spec.worldbody.add_body(name="object_base", pos=[0, 0, base_z], euler=[tilt[0], tilt[1], yaw])
        case = root.add_body(name="case")
        boxes = [((0, D / 2 - t / 2, 0), (W / 2, t / 2, H / 2)),  # back
                 ((-W / 2 + t / 2, 0, 0), (t / 2, D / 2, H / 2)), ((W / 2 - t / 2, 0, 0), (t / 2, D / 2, H / 2)),
                 ((0, 0, -H / 2 + t / 2), (W / 2, D / 2, t / 2))]
        if not lid_used:
            boxes.append(((0, 0, H / 2 - t / 2), (W / 2, D / 2, t / 2)))
        # shelves between rows
        for r in range(1, rows):
            z = -H / 2 + t + r * cell_h
            boxes.append(((0, 0, z), (W / 2 - t, D / 2 - t, 0.006)))
        box_geoms(case, boxes, b.rgba(), float(rng.uniform(3.0, 8.0)))
        return case

    b.parts["case"] = ["case"]
    names = {}

    def fresh(kind):
        names[kind] = names.get(kind, 0) + 1
        return f"{kind}{names[kind]}"

    cells = [(c, r) for r in range(rows) for c in range(cols)]
    rng.shuffle(cells)
    for e in elements:
        if e == "lid":
            name = fresh("lid")
            mass = log_uniform(rng, 0.05, 2.0)
            rgba = b.rgba()
            jn = f"{name}_hinge"
            b.joint_dynamics(jn, "hinge")

            def op(spec, case, name=name, mass=mass, rgba=rgba, jn=jn):
                lid = case.add_body(name=name, pos=[0, D / 2, H / 2 + 0.011])
                lid.add_joint(name=jn, type=HINGE, axis=[-1, 0, 0], pos=[0, 0, 0], range=[0, 1.4])
                box_geoms(lid, [((0, -D / 2, 0), (W / 2, D / 2, 0.01)), ((0, -D + 0.02, 0.03), (0.06, 0.01, 0.02))], rgba, mass)
            spec_ops.append(op)
            b.register(name, jn, (0.0, -D + 0.02, 0.05), f"{name} (revolute, horizontal axis)")
            continue
        c, r = cells.pop()
        cx = -W / 2 + t + (c + 0.5) * cell_w
        cz = -H / 2 + t + (r + 0.5) * cell_h
        w, h = cell_w - 0.01, cell_h - 0.01
        if e in ("door", "door_hatch", "door_latch"):
            name = fresh("door")
            mass = log_uniform(rng, 0.2, 5.0)
            rgba = b.rgba()
            jn = f"{name}_hinge"
            b.joint_dynamics(jn, "hinge")
            left = bool(rng.random() < 0.5)
            hx = cx - w / 2 if left else cx + w / 2
            s = 1.0 if left else -1.0  # the door extends from its hinge along +s x
            hxh = s * (w - 0.05)
            sub = None
            if e == "door_hatch":
                sub = ("hatch", fresh("hatch"), log_uniform(rng, 0.05, 0.6), b.rgba())
            elif e == "door_latch":
                sub = ("latch", fresh("latch"), log_uniform(rng, 0.05, 0.4), b.rgba())

            def op(spec, case, name=name, mass=mass, rgba=rgba, jn=jn, hx=hx, s=s, w=w, h=h, cz=cz, sub=sub, hxh=hxh):
                door = case.add_body(name=name, pos=[hx, -D / 2 - 0.012, cz])
                # Opening swings the free edge out of the front (towards -y).
                door.add_joint(name=jn, type=HINGE, axis=[0, 0, s], pos=[0, 0, 0], range=[-1.57, 0.0])
                geoms = [((s * w / 2, 0, 0), (w / 2, 0.01, h / 2))]
                if sub is None:
                    geoms.append(((hxh, -0.03, 0), (0.01, 0.02, min(0.08, h / 4))))
                box_geoms(door, geoms, rgba, mass)
                if sub is not None and sub[0] == "hatch":
                    _, hn, hm, hrgba = sub
                    hatch = door.add_body(name=hn, pos=[s * w * 0.35, -0.022, 0])
                    hatch.add_joint(name=f"{hn}_slide", type=SLIDE, axis=[s, 0, 0], range=[0.0, w * 0.3])
                    box_geoms(hatch, [((0, 0, 0), (w * 0.18, 0.008, h * 0.2)), ((0, -0.02, 0), (0.01, 0.015, 0.03))], hrgba, hm)
                elif sub is not None:
                    _, ln, lm, lrgba = sub
                    latch = door.add_body(name=ln, pos=[hxh, -0.03, 0])
                    latch.add_joint(name=f"{ln}_hinge", type=HINGE, axis=[0, -1, 0], range=[-1.2, 1.2])
                    box_geoms(latch, [((0, -0.015, 0), (0.015, 0.015, 0.015)), ((-s * 0.06, -0.03, 0), (0.07, 0.012, 0.012))], lrgba, lm)
            spec_ops.append(op)
            b.register(name, jn, (hxh, -0.05, 0.0), f"{name} (revolute, {'left' if left else 'right'} hinge)")
            if sub is not None and sub[0] == "hatch":
                hn = sub[1]
                b.register(hn, f"{hn}_slide", (0.0, -0.035, 0.0), f"{hn} (prismatic on {name})", kind="slide")
            elif sub is not None:
                ln = sub[1]
                b.register(ln, f"{ln}_hinge", (-s * 0.12, -0.03, 0.0), f"{ln} (revolute on {name})", kind="hinge")
        elif e in ("drawer", "drawer_box"):
            name = fresh("drawer")
            mass = log_uniform(rng, 0.1, 4.0)
            rgba = b.rgba()
            jn = f"{name}_slide"
            b.joint_dynamics(jn, "slide")
            depth = D - 2 * t - 0.02
            box = None
            if e == "drawer_box":
                box = (fresh("box"), fresh("boxlid"), log_uniform(rng, 0.05, 0.5), b.rgba(), b.rgba())

            def op(spec, case, name=name, mass=mass, rgba=rgba, jn=jn, cx=cx, cz=cz, w=w, h=h, depth=depth, box=box):
                dr = case.add_body(name=name, pos=[cx, -D / 2 + depth / 2 - 0.01, cz])
                dr.add_joint(name=jn, type=SLIDE, axis=[0, -1, 0], range=[0.0, 0.8 * depth])
                hh = h / 2 - 0.01
                geoms = [((0, -depth / 2, 0), (w / 2, 0.01, h / 2)),  # front
                         ((0, 0, -hh + 0.005), (w / 2 - 0.01, depth / 2, 0.005)),  # bottom
                         ((0, -depth / 2 - 0.03, 0), (min(0.08, w / 4), 0.02, 0.012))]  # handle
                box_geoms(dr, geoms, rgba, mass)
                if box is not None:
                    bn, ln, bm, brgba, lrgba = box
                    bx = dr.add_body(name=bn, pos=[0, 0.0, -hh + 0.01 + 0.04])
                    box_geoms(bx, [((0, 0, 0), (w * 0.3, depth * 0.3, 0.04))], brgba, bm)
                    lid = bx.add_body(name=ln, pos=[0, depth * 0.3, 0.05])
                    lid.add_joint(name=f"{ln}_hinge", type=HINGE, axis=[-1, 0, 0], range=[0, 1.4])
                    box_geoms(lid, [((0, -depth * 0.3, 0), (w * 0.3, depth * 0.3, 0.008))], lrgba, bm * 0.3)
            spec_ops.append(op)
            b.register(name, jn, (0.0, -depth / 2 - 0.05, 0.0), f"{name} (prismatic)")
            if box is not None:
                bn, ln = box[0], box[1]
                # The box is fixed to the drawer: one part with it (same label).
                b.parts[name].append(bn)
                b.register(ln, f"{ln}_hinge", (0.0, -depth * 0.55, 0.01), f"{ln} (revolute on {name}, horizontal)", kind="hinge")
        elif e == "flap":
            name = fresh("flap")
            mass = log_uniform(rng, 0.1, 3.0)
            rgba = b.rgba()
            jn = f"{name}_hinge"
            b.joint_dynamics(jn, "hinge")

            def op(spec, case, name=name, mass=mass, rgba=rgba, jn=jn, cx=cx, cz=cz, w=w, h=h):
                fl = case.add_body(name=name, pos=[cx, -D / 2 - 0.012, cz - h / 2])
                fl.add_joint(name=jn, type=HINGE, axis=[1, 0, 0], range=[0.0, 1.4])
                box_geoms(fl, [((0, 0, h / 2), (w / 2, 0.01, h / 2)), ((0, -0.03, h - 0.04), (min(0.08, w / 4), 0.02, 0.012))], rgba, mass)
            spec_ops.append(op)
            b.register(name, jn, (0.0, -0.05, h - 0.04), f"{name} (revolute, horizontal axis at the bottom)")
        elif e in ("slider", "slider_flap"):
            name = fresh("slider")
            mass = log_uniform(rng, 0.1, 3.0)
            rgba = b.rgba()
            jn = f"{name}_slide"
            b.joint_dynamics(jn, "slide")
            fl = (fresh("flap"), log_uniform(rng, 0.05, 0.5), b.rgba()) if e == "slider_flap" else None
            sw = w * 0.6

            def op(spec, case, name=name, mass=mass, rgba=rgba, jn=jn, cx=cx, cz=cz, w=w, h=h, sw=sw, fl=fl):
                sl = case.add_body(name=name, pos=[cx - (w - sw) / 2, -D / 2 - 0.012, cz])
                sl.add_joint(name=jn, type=SLIDE, axis=[1, 0, 0], range=[0.0, w - sw])
                box_geoms(sl, [((0, 0, 0), (sw / 2, 0.01, h / 2)), ((-sw / 2 + 0.04, -0.03, 0), (0.012, 0.02, min(0.08, h / 4)))], rgba, mass)
                if fl is not None:
                    fn, fm, frgba = fl
                    f = sl.add_body(name=fn, pos=[0, -0.022, -h * 0.1])
                    f.add_joint(name=f"{fn}_hinge", type=HINGE, axis=[1, 0, 0], range=[0.0, 1.3])
                    box_geoms(f, [((0, 0, h * 0.17), (sw * 0.3, 0.008, h * 0.17)), ((0, -0.02, h * 0.3), (0.03, 0.012, 0.01))], frgba, fm)
            spec_ops.append(op)
            b.register(name, jn, (-sw / 2 + 0.04, -0.05, 0.0), f"{name} (prismatic, sideways)")
            if fl is not None:
                fn = fl[0]
                b.register(fn, f"{fn}_hinge", (0.0, -0.03, h * 0.3), f"{fn} (revolute on {name}, horizontal)", kind="hinge")

    def build_spec():
        spec = mujoco.MjSpec()
        spec.compiler.degree = False
        spec.worldbody.add_light(pos=[0, -1.5, 3], dir=[0, 0.5, -1])
        case = carcass(spec)
        for op in spec_ops:
            op(spec, case)
        return spec

    target = (0.0, 0.0, base_z)
    return b, build_spec, target, b.desc


# --------------------------------------------------------------------------------------------
# The corpus
# --------------------------------------------------------------------------------------------


def camera(rng, target, distance):
    az = math.radians(rng.uniform(-55, 55))
    el = math.radians(rng.uniform(12, 40))
    r = distance * rng.uniform(0.85, 1.3)
    pos = (target[0] + r * math.sin(az) * math.cos(el), target[1] - r * math.cos(az) * math.cos(el), target[2] + r * math.sin(el))
    return pos, target


def asset_object(seed):
    """A shipped model with randomized dynamics and camera (`ObjectSpec`, description)."""
    rng = np.random.default_rng(seed)
    family = str(rng.choice(["kitchen_microwave", "kitchen_hingecabinet", "kitchen_slidecabinet", "adroit_door",
                             "metaworld_drawer", "robosuite_door"]))
    if family.startswith("kitchen") or family in ("adroit_door", "metaworld_drawer"):
        base = {"kitchen_microwave": "microwave", "kitchen_hingecabinet": "hingecabinet", "kitchen_slidecabinet": "slidecabinet",
                "adroit_door": "adroit_door", "metaworld_drawer": "drawer"}[family]
        so = record.OBJECTS[base]()
    else:
        door = _site_packages("robosuite") / "models/assets/objects/door_lock.xml"

        def build_spec():
            # robosuite compiles its objects inside a world that sets angles in radians; loaded
            # alone (MuJoCo's default, degrees) the door's 0.4 rad range became 0.4 degrees and
            # its latch's 1.57 rad 1.57 degrees, so neither joint moved (stops 29-32 measured
            # that corpus). In radians the latch's tip sits in the frame's post (robosuite's
            # lock): the lock is an effect this corpus leaves out, so latch and frame do not
            # collide, and the hinge opens to 1.5 rad instead of robosuite's 0.4 (its range is
            # a task setting, not the door's: a wider one keeps pushes off the stop).
            spec = mujoco.MjSpec.from_file(str(door))
            spec.compiler.degree = False
            spec.joint("hinge").range = [0.0, 1.5]
            spec.add_exclude(bodyname1="frame", bodyname2="latch")
            # its latch ships with a return spring: an effect this corpus leaves out
            spec.joint("latch_joint").stiffness = [0.0, 0.0, 0.0]
            spec.worldbody.add_light(pos=[0, -1.5, 3], dir=[0, 0.5, -1])
            return spec
        so = ObjectSpec("robosuite_door", [], {"frame": ["frame"], "door": ["door"], "latch": ["latch"]},
                        {"hinge": ("site", "handle"), "latch_joint": ("site", "handle")},
                        camera_pos=(0.3, -1.4, 0.5), camera_target=(0.0, -0.1, 0.0), builder=build_spec)
    slide = {"slide_cabinet", "goal_slidey"}
    for j in so.handles:
        if j in slide:
            so.damping[j] = log_uniform(rng, 3.0, 50.0)
            so.friction[j] = float(rng.uniform(0.2, 3.0))
        elif j != "latch":
            so.damping[j] = log_uniform(rng, 0.1, 5.0)
            so.friction[j] = float(rng.uniform(0.0, 3.0))
    pos, target = camera(rng, so.camera_target, float(np.linalg.norm(np.array(so.camera_pos) - np.array(so.camera_target))))
    so.camera_pos, so.camera_target = pos, target
    return so, family


def draw(seed, tilt=None):
    """Object `seed`: an `ObjectSpec` ready to record, its family and a description; `tilt`
    overrides a procedural object's tilt (see `procedural`)."""
    rng = np.random.default_rng(seed + 7919)
    if rng.random() < 0.7:
        b, build_spec, target, desc = procedural(seed, tilt)
        so = ObjectSpec(f"procedural_{seed}", [], b.parts, b.handles, damping=b.damping, friction=b.friction,
                        builder=build_spec, gravity_off=True)
        so.camera_pos, so.camera_target = camera(rng, target, 1.7)
        family = "procedural"
    else:
        so, family = asset_object(seed)
        desc = [family]
        so.gravity_off = True
    so.perturb_deg = 30.0
    so.hold_range = (0.3, 1.0)
    so.ramp_s = float(rng.uniform(0.1, 0.3))
    so.force_range = (2.0, 12.0) if family == "procedural" else so.force_range
    order = list(so.handles)
    rng.shuffle(order)
    so.push_order = order
    so.min_travel_frac = 0.08
    n = int(rng.integers(1, 7))
    # at least one push per movable part, when the parts are few enough
    interactions = max(n, min(len(order), 6))
    return so, family, desc, interactions


def record_object(out, index, seed0):
    """Record object `index` both ways; redraw from the next seed on a failed check."""
    for attempt in range(6):
        seed = seed0 + index + 1000 * attempt
        so, family, desc, interactions = draw(seed)
        name = f"obj{index:03d}_{family}"
        if attempt > 0:
            # the failed draw's bags (its family may differ from this one's)
            for layout in ("continuous", "episodes"):
                for old in (Path(out) / layout).glob(f"obj{index:03d}_*"):
                    shutil.rmtree(old)
        cont = Path(out) / "continuous" / name / "all.mcap"
        cont.parent.mkdir(parents=True, exist_ok=True)
        try:
            rec = record.Recorder(so, {}, seed, 150)
            rec.record(cont, interactions, declared=True)
        except Exception as e:  # a model the builder could not compile, a renderer failure
            print(f"{name} seed {seed}: {e}; redrawn", flush=True)
            continue
        bad = rec.limits_reached or rec.parts_touched
        if bad:
            print(f"{name} seed {seed}: recorder check failed ({bad}); redrawn", flush=True)
            continue
        gt = rec.ground_truth(True)
        eps = []
        ok = True
        for k in range(interactions):
            p = Path(out) / "episodes" / name / f"ep{k + 1}.mcap"
            p.parent.mkdir(parents=True, exist_ok=True)
            r = record.Recorder(so, {}, seed, 150)
            r.record(p, interactions, declared=True, only=k, t0=1.0 + 300.0 * k)
            if r.limits_reached or r.parts_touched:
                ok = False
            eps.append(str(p.relative_to(out)))
        if not ok:
            print(f"{name} seed {seed}: an episode failed the recorder's checks; redrawn", flush=True)
            continue
        return {"name": name, "index": index, "family": family, "seed_used": seed, "interactions": interactions,
                "split": "tune" if index % 3 == 0 else "validation", "description": desc,
                "continuous": [str(cont.relative_to(out))], "episodes": eps,
                "parts": [{k: p[k] for k in ("label", "name", "parent", "joint")} for p in gt["parts"]]}
    print(f"obj{index:03d}: no valid draw in 6 attempts; left out", flush=True)
    return None


def run(record_one, doc, default_objects, argv=None):
    """The command line of a corpus script (`--out`, `--objects`, `--seed`, `--jobs`, `--only`,
    `--tune-only`): record every object with `record_one(out, index, seed)` (a manifest row, or
    None when left out) on `--jobs` processes, merge the rows into `OUT/manifest.json` (with
    `--only`, into the rows already there; with `--tune-only`, every row's split set to `tune`)
    and return (objects, manifest path)."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--objects", type=int, default=default_objects)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--only", help="comma-separated object indices (remake those alone)")
    ap.add_argument("--tune-only", action="store_true",
                    help="mark every object `tune`: a further corpus, drawn from other seeds, for choosing settings only")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    indices = [int(i) for i in args.only.split(",")] if args.only else list(range(args.objects))
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as ex:
        rows = list(ex.map(record_one, [out] * len(indices), indices, [args.seed] * len(indices)))
    manifest_path = out / "manifest.json"
    old = json.loads(manifest_path.read_text())["objects"] if manifest_path.exists() and args.only else []
    keep = {r["index"]: r for r in old}
    for r in rows:
        if r is not None:
            keep[r["index"]] = r
    objects = [keep[i] for i in sorted(keep)]
    if args.tune_only:
        for o in objects:
            o["split"] = "tune"
    manifest_path.write_text(json.dumps({"seed": args.seed, "objects": objects}, indent=1) + "\n")
    return objects, manifest_path


def main(argv=None):
    objects, path = run(record_object, __doc__, 120, argv)
    n_t = sum(o["split"] == "tune" for o in objects)
    print(f"wrote {path}: {len(objects)} objects ({n_t} tune, {len(objects) - n_t} validation)")


if __name__ == "__main__":
    main()
