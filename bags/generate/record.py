"""Record interaction bags from MuJoCo on furniture models shipped in PyPI wheels (not bom's physics).

A simulated robot pushes or pulls a handle of an articulated object with a force that ramps up,
holds and releases; a fixed depth camera with per-pixel segmentation watches. The bag follows
../shared/spec/interface.md: segmented PointCloud2 on /segmented_points (camera optical frame,
pose on /tf_static), WrenchStamped on /applied_wrench at 200 Hz in the frame `contact` whose
origin (on /tf) is the point of application, and a `bom_ground_truth` metadata record.

    python bags/generate/record.py --object microwave --interactions 4 --seed 1 --out bags/mujoco/microwave.mcap
    python bags/generate/record.py --object hingecabinet --effect spring=3.0 --undeclared --out ...

The recorder is deterministic for a given seed (same machine, same MuJoCo).
"""

import argparse
import json
import math
import os
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from mcap_ros2.writer import Writer  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
DEFS = REPO / "src" / "msgs" / "defs"


def _site_packages(module):
    """Folder of an installed package, found without importing it (only its files are used)."""
    import importlib.util

    spec = importlib.util.find_spec(module)
    if spec is None or not spec.submodule_search_locations:
        sys.exit(f"error: package {module} not installed (pip install --no-deps -r bags/generate/requirements-nodeps.txt)")
    return Path(list(spec.submodule_search_locations)[0])


def kitchen_dir():
    return _site_packages("gymnasium_robotics") / "envs/assets/kitchen_franka/kitchen_assets"


def metaworld_dir():
    return _site_packages("metaworld") / "assets/objects"


# --------------------------------------------------------------------------------------------
# Objects: which shipped model, which bodies make each part, where the handles are.
# --------------------------------------------------------------------------------------------


@dataclass
class ObjectSpec:
    name: str
    # (asset xml, chain xml, meshdir, texturedir) of each model composed into the scene, or
    # ("adroit", path) for the Adroit door, loaded whole with the hand removed
    models: list
    # part name -> bodies (the part is the union of these bodies' geoms)
    parts: dict
    # joint name -> the handle pushed to move it: ("site", name), ("geom", name) or
    # ("body", name, (x, y, z)) a point fixed in a body; an optional last entry (lo, hi) [N]
    # overrides force_range for that joint
    handles: dict
    # where the object's root sits in the world (the gravity effect tilts it about the world y axis)
    pos: tuple = (0.0, 0.0, 0.8)
    # nested attachment: (child model index, parent body, position in the parent body)
    attach: tuple = None
    camera_pos: tuple = (0.35, -1.6, 1.45)
    camera_target: tuple = (0.0, 0.0, 0.95)
    force_range: tuple = (8.0, 14.0)
    # joint name -> viscous damping replacing the shipped value (N s/m or N m s/rad): the shipped
    # sliders have so little damping that any push that moves them also slams them into a stop
    damping: dict = field(default_factory=dict)
    # seconds simulated (and not recorded) before the recording starts, so that a model whose
    # initial pose is not at rest (contacts resolving) is at rest when the camera starts
    settle_s: float = 0.0
    # --- corpus objects (bags/generate/corpus.py); the defaults keep the shipped bags' recorder ---
    # a function returning the whole scene as an MjSpec (procedural objects), instead of `models`
    builder: object = None
    # joint name -> Coulomb friction (frictionloss) replacing the shipped value (N or N m)
    friction: dict = field(default_factory=dict)
    # body name -> mass (kg) replacing the shipped value (inertia scaled with it)
    masses: dict = field(default_factory=dict)
    # the push direction leaves the motion's direction by up to this angle (deg, uniform in angle
    # and in azimuth about it); None: the shipped bags' N(0, 0.1^2) per axis added to it
    perturb_deg: float = None
    # seconds the force holds, and ramps up and down
    hold_range: tuple = (0.4, 0.7)
    ramp_s: float = 0.2
    # joints pushed, in order (cycled); None: the order of `handles`
    push_order: list = None
    # scale each push's force (dry runs from the state at the push) until the pushed joint moves
    # at least this fraction of its range; 0: no calibration
    min_travel_frac: float = 0.0
    # no gravity: the base model has none unless an effect declares it (corpus objects are about
    # structure and kinodynamics; gravity is an effect of its own)
    gravity_off: bool = False


def kitchen_model(item):
    k = kitchen_dir()
    return (k / f"item_assets/{item}_asset.xml", k / f"item_assets/{item}_chain.xml", k / "item_assets", k / "textures")


def metaworld_model(item):
    m = metaworld_dir()
    return (m / f"assets/{item}_dependencies.xml", m / f"assets/{item}.xml", m, m)


OBJECTS = {
    "microwave": lambda: ObjectSpec(
        "microwave", [kitchen_model("microwave")],
        {"microwave": ["microroot"], "door": ["microdoorroot"]},
        {"microwave": ("site", "microhandle_site")},
        force_range=(6.0, 10.0)),
    "hingecabinet": lambda: ObjectSpec(
        "hingecabinet", [kitchen_model("hingecabinet")],
        {"cabinet": ["hingecab"], "left_door": ["hingeleftdoor"], "right_door": ["hingerightdoor"]},
        {"left_hinge_cabinet": ("site", "hinge_site1"), "right_hinge_cabinet": ("site", "hinge_site2")},
        force_range=(10.0, 14.0)),
    "slidecabinet": lambda: ObjectSpec(
        "slidecabinet", [kitchen_model("slidecabinet")],
        {"cabinet": ["slide"], "door": ["slidelink"]},
        {"slide_cabinet": ("site", "slide_site")},
        force_range=(4.5, 7.0), damping={"slide_cabinet": 10.0}),
    "drawer": lambda: ObjectSpec(
        "drawer", [metaworld_model("drawer")],
        {"case": ["drawercase_link"], "drawer": ["drawer_link"]},
        {"goal_slidey": ("geom", "objGeom")},
        pos=(0.0, 0.0, 0.75), camera_pos=(0.25, -0.9, 1.25), camera_target=(0.0, 0.0, 0.85),
        force_range=(2.5, 4.0), damping={"goal_slidey": 10.0}),
    # A door with a latch on it (a nested chain shipped as one model): frame, door, latch.
    "adroit_door": lambda: ObjectSpec(
        "adroit_door", [("adroit", _site_packages("gymnasium_robotics") / "envs/assets/adroit_hand/adroit_door.xml")],
        {"frame": ["frame"], "door": ["door"], "latch": ["latch"]},
        {"door_hinge": ("body", "door", (-0.1, -0.05, 0.15)), "latch": ("site", "S_handle", (34.5, 37.0))},
        camera_pos=(0.45, -1.5, 0.95), camera_target=(0.25, 0.0, 0.4),
        # The shipped latch has damping 0.05 against friction 5 N m: a push that overcomes the
        # friction spins it into its stop at 16 rad/s; damping 1 N m s/rad and a push just above
        # the friction turn it at under 1 rad/s.
        force_range=(9.0, 14.0), damping={"latch": 1.0}, settle_s=1.0),
    # A nested chain: a microwave standing on the sliding door of the slide cabinet, so the
    # microwave's door hinges on a part that itself slides (composed with MjSpec.attach_body).
    "slide_microwave": lambda: ObjectSpec(
        "slide_microwave", [kitchen_model("slidecabinet"), kitchen_model("microwave")],
        {"cabinet": ["slide"], "slider": ["slidelink"], "microwave": ["mw_microroot"], "microwave_door": ["mw_microdoorroot"]},
        {"slide_cabinet": ("site", "slide_site", (12.0, 18.0)), "mw_microwave": ("site", "mw_microhandle_site")},
        attach=(1, "slidelink", (0.0, 0.05, 0.2)), damping={"slide_cabinet": 40.0},
        camera_pos=(0.4, -2.0, 1.9), camera_target=(0.0, 0.0, 1.15),
        force_range=(6.0, 10.0)),
}


# --------------------------------------------------------------------------------------------
# Scene composition
# --------------------------------------------------------------------------------------------


def model_spec(model, pos, euler):
    asset, chain, meshdir, texdir = model
    xml = f"""<mujoco>
  <compiler angle="radian" meshdir="{meshdir}" texturedir="{texdir}"/>
  <option timestep="0.001"/>
  <visual><global offwidth="320" offheight="240"/></visual>
  <include file="{asset}"/>
  <worldbody>
    <light pos="0 -1.5 3" dir="0 0.5 -1" directional="true"/>
    <body name="object_base" pos="{pos[0]} {pos[1]} {pos[2]}" euler="{euler[0]} {euler[1]} {euler[2]}">
      <include file="{chain}"/>
    </body>
  </worldbody>
</mujoco>"""
    # MuJoCo resolves <include> relative to the main file: write it next to nothing, use absolutes.
    with tempfile.NamedTemporaryFile("w", suffix=".xml", delete=False) as f:
        f.write(xml)
        path = f.name
    try:
        return mujoco.MjSpec.from_file(path)
    finally:
        os.unlink(path)


def look_at(eye, target):
    """MuJoCo camera quaternion (camera looks along -z, y up) looking from eye to target."""
    eye, target = np.array(eye, float), np.array(target, float)
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross([0.0, 0.0, 1.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    rot = np.stack([right, up, back], axis=1)
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, rot.flatten())
    return q, rot


def adroit_spec(path, tilt):
    """The Adroit door scene without the hand, its table, actuators and sensors."""
    spec = mujoco.MjSpec.from_file(str(path))
    for name in ("forearm", "vive_tracker", "table"):
        body = spec.body(name)
        if body is not None:
            spec.delete(body)
    for group in (spec.actuators, spec.sensors, spec.tendons, spec.equalities):
        for element in list(group):
            spec.delete(element)
    frame = spec.body("frame")
    if any(tilt):
        frame.alt.euler = list(tilt)
    spec.visual.global_.offwidth, spec.visual.global_.offheight = 320, 240
    spec.option.timestep = 0.001
    return spec


def build(spec_obj, effects):
    if spec_obj.builder is not None:
        spec = spec_obj.builder()
        spec.visual.global_.offwidth, spec.visual.global_.offheight = 320, 240
        spec.option.timestep = 0.001
        if spec_obj.gravity_off:
            spec.option.gravity = [0.0, 0.0, 0.0]
        q, _ = look_at(spec_obj.camera_pos, spec_obj.camera_target)
        spec.worldbody.add_camera(name="depth", pos=list(spec_obj.camera_pos), quat=list(q), fovy=58.0)
        return spec.compile()
    tilt = (0.0, effects.get("gravity", 0.0), 0.0)
    first = spec_obj.models[0]
    spec = adroit_spec(first[1], tilt) if first[0] == "adroit" else model_spec(first, spec_obj.pos, tilt)
    if spec_obj.attach:
        child_index, parent_body, at = spec_obj.attach
        child = model_spec(spec_obj.models[child_index], (0, 0, 0), (0, 0, 0))
        root = child.worldbody.first_body().first_body()  # object_base -> the model's root body
        frame = spec.body(parent_body).add_frame(pos=list(at))
        frame.attach_body(root, "mw_", "")
    q, _ = look_at(spec_obj.camera_pos, spec_obj.camera_target)
    spec.worldbody.add_camera(name="depth", pos=list(spec_obj.camera_pos), quat=list(q), fovy=58.0)
    if spec_obj.gravity_off:
        spec.option.gravity = [0.0, 0.0, 0.0]
    model = spec.compile()
    return model


# --------------------------------------------------------------------------------------------
# ROS message helpers (dicts for mcap_ros2), schemas from the .msg files bom embeds
# --------------------------------------------------------------------------------------------

PRIMITIVES = {"bool", "byte", "char", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64",
              "uint64", "float32", "float64", "string", "wstring"}


def msg_text(name):
    pkg, typ = name.replace("/msg/", "/").split("/")
    if name.endswith("TFMessage"):
        return "geometry_msgs/TransformStamped[] transforms\n"
    return (DEFS / pkg / f"{typ}.msg").read_text()


def schema_text(name):
    root = name.replace("/msg/", "/")
    out, seen, queue = msg_text(root), {root}, []

    def deps(pkg, text):
        for line in text.splitlines():
            line = line.split("#")[0].strip()
            if not line or ("=" in line and line.split()[0] in PRIMITIVES):
                continue
            base = line.split()[0].split("[")[0].split("<=")[0]
            if base in PRIMITIVES:
                continue
            yield base.replace("/msg/", "/") if "/" in base else f"{pkg}/{base}"

    queue.extend(deps(root.split("/")[0], msg_text(root)))
    while queue:
        dep = queue.pop(0)
        if dep in seen:
            continue
        seen.add(dep)
        body = msg_text(dep)
        out += "\n" + "=" * 80 + f"\nMSG: {dep}\n" + body
        queue.extend(deps(dep.split("/")[0], body))
    return out


def stamp(t):
    ns = int(round(t * 1e9))
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}


def quat_xyzw(rot):
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.asarray(rot, float).flatten())
    return {"x": float(q[1]), "y": float(q[2]), "z": float(q[3]), "w": float(q[0])}


def transform(parent, child, t, pos, rot):
    return {"header": {"stamp": stamp(t), "frame_id": parent}, "child_frame_id": child,
            "transform": {"translation": {"x": float(pos[0]), "y": float(pos[1]), "z": float(pos[2])},
                          "rotation": quat_xyzw(rot)}}


def cloud_msg(t, frame, pts, labels):
    pts = np.asarray(pts, dtype="<f4").reshape(-1, 3)
    rec = np.zeros(len(pts), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("label", "<u4")])
    rec["x"], rec["y"], rec["z"], rec["label"] = pts[:, 0], pts[:, 1], pts[:, 2], labels
    fields = [{"name": n, "offset": 4 * i, "datatype": 7 if n != "label" else 6, "count": 1}
              for i, n in enumerate(["x", "y", "z", "label"])]
    return {"header": {"stamp": stamp(t), "frame_id": frame}, "height": 1, "width": len(pts),
            "fields": fields, "is_bigendian": False, "point_step": 16, "row_step": 16 * len(pts),
            "data": rec.tobytes(), "is_dense": True}


# --------------------------------------------------------------------------------------------
# The recorder
# --------------------------------------------------------------------------------------------


class Recorder:
    WIDTH, HEIGHT = 240, 180
    CLOUD_HZ, WRENCH_HZ = 30.0, 200.0

    def __init__(self, spec_obj, effects, seed, max_points):
        self.spec_obj, self.effects, self.max_points = spec_obj, effects, max_points
        self.rng = np.random.default_rng(seed)
        self.model = build(spec_obj, effects)
        self.data = mujoco.MjData(self.model)
        m = self.model
        self.apply_effects()
        # Start every pushed joint slightly open (15% into its range from the bound nearer 0), so
        # that the recording starts away from the stops.
        for jname in spec_obj.handles:
            j = self.joint_id(jname)
            lo, hi = m.jnt_range[j]
            self.data.qpos[m.jnt_qposadr[j]] = lo + 0.15 * (hi - lo) if abs(lo) <= abs(hi) else hi - 0.15 * (hi - lo)
        mujoco.mj_forward(m, self.data)
        for _ in range(int(round(spec_obj.settle_s / m.opt.timestep))):
            mujoco.mj_step(m, self.data)
        self.data.time = 0.0
        # Part label of every body: its own or its nearest listed ancestor's (0 = no part).
        self.part_names = list(spec_obj.parts)
        body_label = {}
        for label, name in enumerate(self.part_names, start=1):
            for body in spec_obj.parts[name]:
                body_label[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, body)] = label
        self.body_part = np.zeros(m.nbody, dtype=int)
        for b in range(m.nbody):
            a = b
            while a > 0 and a not in body_label:
                a = m.body_parentid[a]
            self.body_part[b] = body_label.get(a, 0)
        self.geom_part = self.body_part[m.geom_bodyid]
        # Visual groups 0-2 only: collision geometry (group 4) duplicates the visuals.
        self.geom_part[m.geom_group > 2] = 0
        self.renderer = mujoco.Renderer(m, self.HEIGHT, self.WIDTH)
        self.cam = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_CAMERA, "depth")
        fovy = math.radians(m.cam_fovy[self.cam])
        self.f = 0.5 * self.HEIGHT / math.tan(0.5 * fovy)

    def joint_id(self, name):
        return mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, name)

    def apply_effects(self):
        m, e = self.model, self.effects
        for jname, c in self.spec_obj.damping.items():
            m.dof_damping[m.jnt_dofadr[self.joint_id(jname)]] = c
        for jname, c in self.spec_obj.friction.items():
            m.dof_frictionloss[m.jnt_dofadr[self.joint_id(jname)]] = c
        for bname, mass in self.spec_obj.masses.items():
            b = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, bname)
            scale = mass / m.body_mass[b]
            m.body_mass[b] = mass
            m.body_inertia[b] *= scale
        for jname in self.spec_obj.handles:
            j = self.joint_id(jname)
            dof = m.jnt_dofadr[j]
            if "friction" in e:
                m.dof_frictionloss[dof] *= e["friction"]
            if "spring" in e:
                m.jnt_stiffness[j] = e["spring"]
                lo, hi = m.jnt_range[j]
                m.qpos_spring[m.jnt_qposadr[j]] = 0.0 if lo <= 0.0 <= hi else lo
            if "limit" in e:
                lo, hi = m.jnt_range[j]
                frac = e["limit"]
                m.jnt_range[j] = (lo, lo + frac * (hi - lo)) if abs(lo) < abs(hi) else (hi - frac * (hi - lo), hi)
                m.jnt_limited[j] = 1

    # -- sensing ---------------------------------------------------------------------------

    def camera_pose(self):
        d = self.data
        pos = d.cam_xpos[self.cam].copy()
        rot = d.cam_xmat[self.cam].reshape(3, 3).copy()
        # ROS optical frame: z forward, y down = MuJoCo camera frame rotated pi about x.
        return pos, rot @ np.diag([1.0, -1.0, -1.0])

    def cloud(self):
        r, d, m = self.renderer, self.data, self.model
        r.update_scene(d, camera=self.cam)
        r.enable_depth_rendering()
        depth = r.render().copy()
        r.disable_depth_rendering()
        r.enable_segmentation_rendering()
        seg = r.render().copy()
        r.disable_segmentation_rendering()
        geom = seg[:, :, 0]
        is_geom = seg[:, :, 1] == int(mujoco.mjtObj.mjOBJ_GEOM)
        label = np.where(is_geom & (geom >= 0), self.geom_part[np.clip(geom, 0, m.ngeom - 1)], 0)
        # Label noise at part boundaries: a pixel next to another part takes its label at 30%.
        noisy = label.copy()
        for dv, du in ((0, 1), (1, 0), (0, -1), (-1, 0)):
            nb = np.roll(np.roll(label, dv, axis=0), du, axis=1)
            swap = (nb != label) & (nb > 0) & (label > 0) & (self.rng.random(label.shape) < 0.3)
            noisy[swap] = nb[swap]
        label = noisy
        valid = (label > 0) & (depth > 0.05) & (depth < 5.0)
        valid &= self.rng.random(depth.shape) > 0.03  # dropped pixels
        v, u = np.nonzero(valid)
        z = depth[v, u]
        z = z + self.rng.normal(0.0, 1.0, z.shape) * (0.001 + 0.0025 * z * z)  # depth-dependent noise
        x = (u + 0.5 - 0.5 * self.WIDTH) / self.f * z
        y = (v + 0.5 - 0.5 * self.HEIGHT) / self.f * z
        pts, lab = np.stack([x, y, z], axis=1), label[v, u]
        keep = []
        for l in np.unique(lab):
            idx = np.nonzero(lab == l)[0]
            if len(idx) > self.max_points:
                idx = np.sort(self.rng.choice(idx, self.max_points, replace=False))
            keep.append(idx)
        keep = np.concatenate(keep) if keep else np.zeros(0, dtype=int)
        return pts[keep], lab[keep].astype(np.uint32)

    def handle_point(self, jname):
        kind, name = self.spec_obj.handles[jname][:2]
        if kind == "body":
            b = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, name)
            offset = np.array(self.spec_obj.handles[jname][2], float)
            return self.data.xpos[b] + self.data.xmat[b].reshape(3, 3) @ offset
        if kind == "site":
            return self.data.site_xpos[mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, name)].copy()
        return self.data.geom_xpos[mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, name)].copy()

    def other_joint_near_stop(self, pushed, q_start):
        """Whether a joint other than the pushed one has moved by more than 2% of its range since
        the push began (a spring's slow creep does not count) and is now within 30% of its range of
        the stop it moves towards."""
        m, d = self.model, self.data
        for jname, q0 in q_start.items():
            if jname == pushed:
                continue
            j = self.joint_id(jname)
            lo, hi = m.jnt_range[j]
            qv = d.qpos[m.jnt_qposadr[j]]
            margin = 0.3 * (hi - lo)
            moved = 0.02 * (hi - lo)
            if (qv > q0 + moved and qv > hi - margin) or (qv < q0 - moved and qv < lo + margin):
                return True
        return False

    def part_contacts(self):
        """Pairs of different parts (labels, smaller first) whose collision geometry is in contact."""
        m, d = self.model, self.data
        pairs = set()
        for i in range(d.ncon):
            c = d.contact[i]
            a = self.body_part[m.geom_bodyid[c.geom1]]
            b = self.body_part[m.geom_bodyid[c.geom2]]
            if a > 0 and b > 0 and a != b and c.dist < 0.0:
                pairs.add((min(a, b), max(a, b)))
        return sorted(pairs)

    def push_direction(self, jname, sign, perturb):
        m, d = self.model, self.data
        j = self.joint_id(jname)
        axis, anchor = d.xaxis[j].copy(), d.xanchor[j].copy()
        if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE:
            direction = np.cross(axis, self.handle_point(jname) - anchor)
        else:
            direction = axis.copy()
        direction = sign * direction / np.linalg.norm(direction)
        if isinstance(perturb, tuple):
            # (angle off the motion, azimuth about it)
            angle, azimuth = perturb
            ref = np.array([0.0, 0.0, 1.0]) if abs(direction[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
            u = np.cross(direction, ref)
            u /= np.linalg.norm(u)
            v = np.cross(direction, u)
            side = math.cos(azimuth) * u + math.sin(azimuth) * v
            return math.cos(angle) * direction + math.sin(angle) * side
        direction = direction + perturb
        return direction / np.linalg.norm(direction)

    # -- ground truth ----------------------------------------------------------------------

    def ground_truth(self, declared):
        m, d = self.model, self.data
        mujoco.mj_forward(m, d)
        parts = []
        for label, name in enumerate(self.part_names, start=1):
            body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, self.spec_obj.parts[name][0])
            parent_body = m.body_parentid[body]
            parent = int(self.body_part[parent_body])
            entry = {"label": label, "name": name, "parent": parent, "joint": "rigid",
                     "mass": float(sum(m.body_mass[b] for b in range(m.nbody) if self.body_part[b] == label))}
            if m.body_jntnum[body] == 1:
                j = m.body_jntadr[body]
                dof = m.jnt_dofadr[j]
                kind = "revolute" if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE else "prismatic"
                entry.update({"joint": kind, "axis_direction": [float(v) for v in d.xaxis[j]],
                              "damping": float(m.dof_damping[dof]), "friction": float(m.dof_frictionloss[dof])})
                if kind == "revolute":
                    entry["axis_point"] = [float(v) for v in d.xanchor[j]]
            parts.append(entry)
        effects = []
        if declared:
            for jname in self.spec_obj.handles:
                j = self.joint_id(jname)
                part = int(self.body_part[m.jnt_bodyid[j]])
                if "spring" in self.effects:
                    effects.append({"part": part, "kind": "spring", "stiffness": float(m.jnt_stiffness[j]),
                                    "rest_position": float(m.qpos_spring[m.jnt_qposadr[j]])})
                if "limit" in self.effects:
                    effects.append({"part": part, "kind": "joint_limit", "range": [float(v) for v in m.jnt_range[j]]})
                if "friction" in self.effects:
                    effects.append({"part": part, "kind": "extra_friction", "factor": float(self.effects["friction"])})
                if "gravity" in self.effects:
                    effects.append({"part": part, "kind": "gravity", "tilt_about_y_rad": float(self.effects["gravity"])})
        return {"fixed_frame": "world", "parts": parts, "effects": effects}

    def final_metadata(self):
        """MCAP metadata records (name -> string map) written after the recording, when its checks
        are known; none here."""
        return {}

    # -- the recording -----------------------------------------------------------------------

    def plan(self, interactions):
        """The schedule: rest, then per interaction ramp, hold, release, rest 1.5 s. Entries
        `[start, full, release, end, joint, magnitude, (perturbation, contact offset)]`."""
        rng, so = self.rng, self.spec_obj
        joints = list(so.push_order or so.handles)
        plan = []
        t = 0.5
        for k in range(interactions):
            jname = joints[k % len(joints)]
            hold = rng.uniform(*so.hold_range)
            handle = so.handles[jname]
            forces = handle[-1] if len(handle) > 2 and len(handle[-1]) == 2 else so.force_range
            mag = rng.uniform(*forces)
            if so.perturb_deg is None:
                perturb = rng.normal(0.0, 0.1, 3)
            else:
                perturb = (math.radians(rng.uniform(0.0, so.perturb_deg)), rng.uniform(0.0, 2.0 * math.pi))
            offset = rng.uniform(-0.02, 0.02, 3)  # contact point varies by up to 2 cm per axis
            r = so.ramp_s
            plan.append([t, t + r, t + r + hold, t + 2 * r + hold, jname, mag, (perturb, offset)])
            t += 2 * r + hold + 1.5
        return plan, t

    def push_force(self, now, entry, sign):
        """Force and contact point of a push at time `now` (the pushed joint's current state)."""
        m, d = self.model, self.data
        start, full, release, end, jname, mag, (perturb, offset) = entry
        jid = self.joint_id(jname)
        r = self.spec_obj.ramp_s
        scale = min(1.0, (now - start) / r) if now < full else (1.0 if now < release else max(0.0, (end - now) / r))
        body = m.jnt_bodyid[jid]
        # The offset is fixed in the pushed body, so the contact point moves with it.
        contact = self.handle_point(jname) + d.xmat[body].reshape(3, 3) @ offset
        direction = self.push_direction(jname, sign, perturb)
        return mag * scale * direction, contact, body

    def careful_stop(self, entry, sign, q_start):
        """Whether the careful robot lets go now: the pushed joint within 30% of its range of the
        stop it heads for, or another joint the push moves near its stop."""
        m, d = self.model, self.data
        jid = self.joint_id(entry[4])
        lo, hi = m.jnt_range[jid]
        qv = d.qpos[m.jnt_qposadr[jid]]
        margin = 0.3 * (hi - lo)
        return (sign > 0 and qv > hi - margin) or (sign < 0 and qv < lo + margin) or self.other_joint_near_stop(entry[4], q_start)

    def stop_counts(self, jname):
        """Whether joint `jname` reaching a stop in a dry push counts as a hit (all do here)."""
        return True

    def dry_push(self, entry, sign, q_start):
        """Simulate one push from the current state, without recording, on a copy of the data:
        the pushed joint's largest excursion, and whether any joint came within 2% of its range
        of a stop (the recorder's test) up to 1.5 s after the push."""
        import copy
        m = self.model
        saved = self.data
        self.data = copy.copy(saved)
        try:
            d = self.data
            jid = self.joint_id(entry[4])
            q0 = d.qpos[m.jnt_qposadr[jid]]
            travel, hit, stopped = 0.0, False, False
            now = entry[0]
            while now < entry[3] + 1.5:
                d.qfrc_applied[:] = 0.0
                if now < entry[3] and not stopped:
                    if self.careful_stop(entry, sign, q_start):
                        stopped = True
                    else:
                        force, contact, body = self.push_force(now, entry, sign)
                        mujoco.mj_applyFT(m, d, force, np.zeros(3), contact, body, d.qfrc_applied)
                mujoco.mj_step(m, d)
                now += m.opt.timestep
                travel = max(travel, abs(d.qpos[m.jnt_qposadr[jid]] - q0))
                for jname in self.spec_obj.handles:
                    if not self.stop_counts(jname):
                        continue
                    j = self.joint_id(jname)
                    lo, hi = m.jnt_range[j]
                    qv = d.qpos[m.jnt_qposadr[j]]
                    # a margin over the recorder's 2%: the recording must pass its check
                    hit |= qv < lo + 0.03 * (hi - lo) or qv > hi - 0.03 * (hi - lo)
            return travel, hit
        finally:
            self.data = saved

    def calibrate(self, entry, sign, q_start):
        """Scale the push's magnitude (dry runs) until the pushed joint moves at least
        `min_travel_frac` of its range without any joint reaching a stop."""
        m = self.model
        lo, hi = m.jnt_range[self.joint_id(entry[4])]
        want = self.spec_obj.min_travel_frac * (hi - lo)
        for _ in range(8):
            travel, hit = self.dry_push(entry, sign, q_start)
            if hit:
                entry[5] *= 0.6
            elif travel < want:
                entry[5] *= 1.7
            else:
                return

    def record(self, out, interactions, declared, only=None, t0=1.0):
        """Record `interactions` pushes into `out`; with `only`, just that one interaction of the
        schedule (an episode from the object's initial state), started 0.5 s in. Stamps start at
        `t0` seconds."""
        m, d = self.model, self.data
        w = Writer(str(out), chunk_size=256 * 1024)
        schemas = {t: w.register_msgdef(t, schema_text(t)) for t in (
            "sensor_msgs/msg/PointCloud2", "geometry_msgs/msg/WrenchStamped", "tf2_msgs/msg/TFMessage")}
        w.add_metadata("bom_ground_truth", {"json": json.dumps(self.ground_truth(declared))})
        cam_pos, cam_rot = self.camera_pose()
        w.write_message("/tf_static", schemas["tf2_msgs/msg/TFMessage"],
                        {"transforms": [transform("world", "camera_optical", t0 - 1.0, cam_pos, cam_rot)]},
                        int((t0 - 1.0) * 1e9), int((t0 - 1.0) * 1e9))
        plan, duration = self.plan(interactions)
        if only is not None:
            entry = plan[only]
            shift = entry[0] - 0.5
            plan = [[v - shift for v in entry[:4]] + entry[4:]]
            duration = plan[0][3] + 1.5
        joints = list(self.spec_obj.handles)
        steps = int(round(duration / m.opt.timestep))
        next_cloud, next_wrench = 0.0, 0.0
        seq = 0
        sign = {j: None for j in joints}
        contact = np.zeros(3)
        # A careful robot lets go before a joint reaches its stop (within 30% of the range), unless
        # the recording is about a joint limit being reached. It watches every joint of the object,
        # not only the pushed one: a push on a latch can swing the door it sits on.
        stopped = set()
        q_start = {}
        q_min = {j: math.inf for j in joints}
        q_max = {j: -math.inf for j in joints}
        touches = {}  # (part, part) -> first time two different parts touched
        for step in range(steps + 1):
            now = step * m.opt.timestep
            force = np.zeros(3)
            for k, entry in enumerate(plan):
                start, end, jname = entry[0], entry[3], entry[4]
                if start <= now < end and k not in stopped:
                    jid = self.joint_id(jname)
                    lo, hi = m.jnt_range[jid]
                    qv = d.qpos[m.jnt_qposadr[jid]]
                    if now - start < m.opt.timestep:
                        # Each push heads for the farther stop.
                        sign[jname] = 1.0 if (hi - qv) >= (qv - lo) else -1.0
                        q_start = {j: d.qpos[m.jnt_qposadr[self.joint_id(j)]] for j in joints}
                        if self.spec_obj.min_travel_frac > 0.0:
                            self.calibrate(entry, sign[jname], q_start)
                    if "limit" not in self.effects and self.careful_stop(entry, sign[jname], q_start):
                        stopped.add(k)
                        continue
                    force, contact, body = self.push_force(now, entry, sign[jname])
                    d.qfrc_applied[:] = 0.0
                    mujoco.mj_applyFT(m, d, force, np.zeros(3), contact, body, d.qfrc_applied)
                    break
            else:
                d.qfrc_applied[:] = 0.0
            if now >= next_wrench - 1e-9:
                ts = t0 + now
                w.write_message("/tf", schemas["tf2_msgs/msg/TFMessage"],
                                {"transforms": [transform("world", "contact", ts, contact, np.eye(3))]},
                                int(ts * 1e9), int(ts * 1e9), seq)
                w.write_message("/applied_wrench", schemas["geometry_msgs/msg/WrenchStamped"],
                                {"header": {"stamp": stamp(ts), "frame_id": "contact"},
                                 "wrench": {"force": dict(zip("xyz", map(float, force))),
                                            "torque": {"x": 0.0, "y": 0.0, "z": 0.0}}},
                                int(ts * 1e9), int(ts * 1e9), seq)
                next_wrench += 1.0 / self.WRENCH_HZ
                seq += 1
            if now >= next_cloud - 1e-9:
                ts = t0 + now
                pts, lab = self.cloud()
                w.write_message("/segmented_points", schemas["sensor_msgs/msg/PointCloud2"],
                                cloud_msg(ts, "camera_optical", pts, lab), int(ts * 1e9), int(ts * 1e9), seq)
                next_cloud += 1.0 / self.CLOUD_HZ
                seq += 1
            mujoco.mj_step(m, d)
            for a, b in self.part_contacts():
                touches.setdefault((a, b), now)
            for jname in joints:
                qv = d.qpos[m.jnt_qposadr[self.joint_id(jname)]]
                q_min[jname], q_max[jname] = min(q_min[jname], qv), max(q_max[jname], qv)
        self.travel = {j: q_max[j] - q_min[j] for j in joints}
        self.q_min, self.q_max = q_min, q_max
        self.limits_reached = []
        for jname in joints:
            lo, hi = m.jnt_range[self.joint_id(jname)]
            # Within 2% of the range of a stop counts as reaching it (a soft limit lets the joint
            # sit a little inside).
            if q_min[jname] < lo + 0.02 * (hi - lo) or q_max[jname] > hi - 0.02 * (hi - lo):
                self.limits_reached.append(jname)
            print(f"  {jname}: q in [{q_min[jname]:.3f}, {q_max[jname]:.3f}] of range [{lo:.3f}, {hi:.3f}]")
        # Two parts touching is a stop too (a latch against its frame), though no joint range says so.
        self.parts_touched = [(self.part_names[a - 1], self.part_names[b - 1], t) for (a, b), t in touches.items()]
        for a, b, t in self.parts_touched:
            print(f"  contact: {a} touches {b} at {t:.3f} s")
        # Metadata known only once the recording is done (a subclass's record of what acted).
        for name, data in self.final_metadata().items():
            w.add_metadata(name, data)
        w.finish()
        return duration


def parse_effects(items):
    effects = {}
    for item in items or []:
        name, _, value = item.partition("=")
        defaults = {"spring": 3.0, "limit": 0.3, "gravity": 0.35, "friction": 3.0}
        if name not in defaults:
            sys.exit(f"error: --effect {name}: unknown (spring, limit, gravity, friction)")
        effects[name] = float(value) if value else defaults[name]
    return effects


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--object", required=True, choices=sorted(OBJECTS))
    ap.add_argument("--interactions", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--effect", action="append", help="spring[=N*m/rad or N/m]: spring return to the closed position; "
                    "limit[=fraction of range]: the pushed joint's range narrowed so the push reaches the stop; "
                    "gravity[=tilt rad]: the object tilted about y, so gravity acts along its joints; "
                    "friction[=factor]: Coulomb friction multiplied")
    ap.add_argument("--undeclared", action="store_true", help="leave the effects out of bom_ground_truth")
    ap.add_argument("--max-points", type=int, default=150, help="points kept per part and frame")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    effects = parse_effects(args.effect)
    rec = Recorder(OBJECTS[args.object](), effects, args.seed, args.max_points)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    duration = rec.record(args.out, args.interactions, declared=not args.undeclared)
    print(f"wrote {args.out}: {args.object}, {args.interactions} interactions, {duration:.1f} s, effects {effects}"
          f"{' (undeclared)' if args.undeclared and effects else ''}")
    if rec.limits_reached and "limit" not in effects:
        sys.exit(f"error: joint limit reached without the limit effect: {rec.limits_reached}")
    if rec.parts_touched and "limit" not in effects:
        sys.exit(f"error: parts touched without the limit effect (an undeclared stop): {rec.parts_touched}")


if __name__ == "__main__":
    main()
