//! Differentiable articulated-body physics Ψ (paper §3.3, "Differentiable physics engine"): a tree
//! of rigid parts joined by rigid, prismatic and revolute joints on screw axes, with viscous
//! damping, smoothed Coulomb friction, joint springs, gravity and a measured external wrench,
//! integrated semi-implicitly with substeps.
//!
//! Formulation: spatial vectors in absolute (world) coordinates, `[angular; linear]` with the
//! linear part the velocity of the body point at the world origin (Featherstone, *Rigid Body
//! Dynamics Algorithms*, 2008, ch. 2 and 5). Joint screws are given in the reference
//! configuration and carried by the parent's displacement (product of exponentials). Inverse
//! dynamics is the recursive Newton-Euler algorithm; forward dynamics solves the joint-space
//! equation `M(q) q'' = tau - c(q, q')`, with `M` assembled column by column from inverse dynamics
//! (the trees here have a handful of joints, so this beats the articulated-body algorithm's
//! bookkeeping). Everything is generic over [`Real`], so gradients of a whole simulated
//! trajectory come from dual numbers.
//!
//! Joint coordinates: radians (revolute) and metres (prismatic), as URDF; damping in N·m·s/rad or
//! N·s/m, friction in N·m or N.
//!
//! **Integration**: semi-implicit Euler — the velocity first, then the position with the new
//! velocity — with the joint forces (damping, friction, springs) evaluated *implicitly* at the
//! new velocity and position:
//! `M (v+ - v) = h (tau_ext - c - b v+ - mu tanh(v+ / v_s) - k (q + h v+ - rest))`, solved by
//! Newton's method (the friction term is monotone in `v+`, so the root is unique). A light door
//! with strong Coulomb friction has a friction time constant `I v_s / mu` of a fraction of a
//! millisecond; an explicit velocity update would need steps that short to stay stable, and a
//! linearised one chatters across zero velocity; this one is stable for any step.
//!
//! [`JointDynamics`] is the same physics for one joint whose parent does not move and whose
//! subtree is locked (its generalised inertia is then constant): what the model uses per joint
//! and window, tested against [`Articulation`]. It also carries the effects of
//! [`crate::model::effects`]: joint stops ([`JointLimit`], implicit, linearised per step), gravity
//! (explicit) and quadratic damping (implicit, with the friction), each tested against a closed
//! form.
//!
//! **Coulomb friction** is regularised as `-mu * tanh(q' / v_s)` so that it has a gradient, with
//! the velocity scale set by a relaxation time `t_f` ([`FrictionLaw`]): `v_s = mu t_f / I`, `I`
//! the joint's generalised inertia. At rest the friction is then viscous with slope `I / t_f` —
//! it stops the joint within about `t_f` — and a load `F` below the breakaway force `mu` makes the
//! joint creep at about `F t_f / I` instead of sticking. This is the law of a soft friction
//! constraint: MuJoCo's `frictionloss` solves the same balance (Todorov, *Convex and
//! analytically-invertible dynamics with contacts and constraints*, ICRA 2014: steady creep
//! `F (1 - d) / (d b I)`, so with its default `solref` 0.02 s and `solimp` 0.9/0.95,
//! `t_f = (1 - d) / (d b) = 1.06 ms`), and it stands for the pre-sliding compliance of real joints
//! (the bristles of the Dahl and LuGre models). A fixed `v_s` for every joint would not do: at
//! their true friction and inertia the bundled objects' joints have `v_s` from 0.0006 to 0.27
//! (m/s or rad/s). `v_s` is capped at `v_max` (0.07 by default): the inertia is a latent
//! variable, poorly identified for a small, partly seen part (a latch), and without the cap an
//! underestimate turns its friction into a weak damper. The law equals the hard one,
//! `-mu * sign(q')`, up to `mu * (1 - tanh(|q'| / v_s))`, below 2% of `mu` once `|q'| > 2.3 v_s`,
//! and converges pointwise to it as `t_f -> 0`.

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use super::{c, rotation, tanh, Displacement, Real};

/// Integration parameters, in one explicit struct (rapier style).
#[derive(Debug, Clone, PartialEq)]
pub struct IntegrationParameters {
    /// Time step of the output trajectory \[s\].
    pub dt: f64,
    /// Semi-implicit Euler substeps per time step.
    pub substeps: usize,
    /// Regularisation of the Coulomb friction (module docs); joint `i`'s inertia is `M_ii`.
    pub friction: FrictionLaw,
    /// Gravity in the fixed frame (m/s²).
    pub gravity: [f64; 3],
}

impl Default for IntegrationParameters {
    fn default() -> Self {
        IntegrationParameters { dt: 1.0 / 30.0, substeps: 20, friction: FrictionLaw::default(), gravity: [0.0, 0.0, -9.81] }
    }
}

/// MuJoCo's soft friction relaxation time with its default `solref` (0.02 s, 1) and `solimp`
/// (0.9, 0.95): `(1 - d) / (d b)` with `d = 0.9`, `b = 2 / (0.95 * 0.02 s)`, 1.0556 ms, to four
/// digits \[s\] (module docs).
pub const FRICTION_RELAXATION_S: f64 = 1.056e-3;

/// The regularisation of Coulomb friction (module docs): velocity scale
/// `v_s = min(mu t_f / I, v_max)` of a joint with friction `mu` and generalised inertia `I`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FrictionLaw {
    /// Relaxation time `t_f` \[s\].
    pub relaxation_s: f64,
    /// Largest velocity scale `v_max` (m/s or rad/s).
    pub velocity_max: f64,
}

impl Default for FrictionLaw {
    fn default() -> Self {
        FrictionLaw { relaxation_s: FRICTION_RELAXATION_S, velocity_max: 0.07 }
    }
}

impl FrictionLaw {
    /// Whether `v_max` bounds the velocity scale of a joint with friction `mu` and inertia `inertia`.
    fn capped(&self, mu: f64, inertia: f64) -> bool {
        mu > 0.0 && mu * self.relaxation_s / inertia > self.velocity_max
    }

    /// The slope at rest, `mu / v_s` (N·s/m or N·m·s/rad), of a joint with friction `mu` and
    /// generalised inertia `inertia`.
    fn slope<T: Real>(&self, mu: T, inertia: T) -> T {
        if self.capped(mu.re(), inertia.re()) { mu / self.velocity_max } else { inertia / self.relaxation_s }
    }
}

/// Regularised Coulomb friction of a joint at velocity `w`: `mu tanh(w s / mu)`, `s = mu / v_s`
/// its slope at rest ([`FrictionLaw`]); 0 without friction.
fn coulomb<T: Real>(mu: T, slope: T, w: T) -> T {
    if mu.re() > 0.0 { mu * tanh(w * slope / mu) } else { c(0.0) }
}

/// Derivative of [`coulomb`] in `w`.
fn coulomb_slope<T: Real>(mu: T, slope: T, w: T) -> T {
    if mu.re() > 0.0 {
        let th = tanh(w * slope / mu);
        slope * (c::<T>(1.0) - th * th)
    } else {
        c(0.0)
    }
}

/// Kind of the joint that attaches a body to its parent.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum JointKind {
    Rigid,
    Prismatic,
    Revolute,
}

/// One rigid part and the joint attaching it to its parent, in the reference configuration
/// (all coordinates 0), fixed frame.
#[derive(Debug, Clone)]
pub struct Body<T: Real> {
    /// Parent body index (must be smaller than this body's), or None for the fixed frame.
    pub parent: Option<usize>,
    pub joint: JointKind,
    /// Unit joint axis.
    pub axis: Vector3<T>,
    /// A point on a revolute axis \[m\].
    pub point: Vector3<T>,
    /// Mass \[kg\].
    pub mass: T,
    /// Centre of mass \[m\].
    pub com: Vector3<T>,
    /// Rotational inertia about the centre of mass, fixed-frame axes (kg·m²).
    pub inertia: Matrix3<T>,
    /// Viscous damping (N·s/m or N·m·s/rad).
    pub damping: T,
    /// Coulomb friction (N or N·m).
    pub friction: T,
    /// Joint spring `-stiffness (q - rest)` (N/m or N·m/rad; m or rad).
    pub stiffness: T,
    pub rest: T,
}

/// A wrench applied to a body: force \[N\] at `point` \[m\] plus a pure torque \[N·m\], fixed frame.
#[derive(Debug, Clone, Copy)]
pub struct Wrench<T: Real> {
    pub body: usize,
    pub point: Vector3<T>,
    pub force: Vector3<T>,
    pub torque: Vector3<T>,
}

/// A spatial vector `[angular; linear]` in world coordinates.
#[derive(Debug, Clone, Copy)]
struct Sv<T: Real> {
    w: Vector3<T>,
    v: Vector3<T>,
}

impl<T: Real> Sv<T> {
    fn zero() -> Self {
        Sv { w: Vector3::zeros(), v: Vector3::zeros() }
    }
    fn add(&self, o: &Sv<T>) -> Sv<T> {
        Sv { w: self.w + o.w, v: self.v + o.v }
    }
    fn scale(&self, s: T) -> Sv<T> {
        Sv { w: self.w * s, v: self.v * s }
    }
    /// Motion cross product `self x m`.
    fn cross_motion(&self, m: &Sv<T>) -> Sv<T> {
        Sv { w: self.w.cross(&m.w), v: self.v.cross(&m.w) + self.w.cross(&m.v) }
    }
    /// Force cross product `self x* f`.
    fn cross_force(&self, f: &Sv<T>) -> Sv<T> {
        Sv { w: self.w.cross(&f.w) + self.v.cross(&f.v), v: self.w.cross(&f.v) }
    }
    /// Pairing of a motion (self) with a force.
    fn dot(&self, f: &Sv<T>) -> T {
        self.w.dot(&f.w) + self.v.dot(&f.v)
    }
}

/// A body's pose-dependent quantities at a configuration.
struct Placed<T: Real> {
    /// Displacement from the reference configuration.
    disp: Displacement<T>,
    /// Joint screw in world coordinates (zero for rigid joints).
    screw: Sv<T>,
    com: Vector3<T>,
    inertia: Matrix3<T>,
}

/// Spatial inertia applied to a velocity: the momentum `[I_c w + c x p; p]`, `p = m (v + w x c)`.
fn momentum<T: Real>(b: &Placed<T>, mass: T, vel: &Sv<T>) -> Sv<T> {
    let p = (vel.v + vel.w.cross(&b.com)) * mass;
    Sv { w: b.inertia * vel.w + b.com.cross(&p), v: p }
}

/// An articulated object: bodies in topological order.
#[derive(Debug, Clone)]
pub struct Articulation<T: Real> {
    pub bodies: Vec<Body<T>>,
}

impl<T: Real> Articulation<T> {
    /// Poses, world screws and inertias at coordinates `q` (one per body; ignored for rigid).
    fn place(&self, q: &[T]) -> Vec<Placed<T>> {
        let mut out: Vec<Placed<T>> = Vec::with_capacity(self.bodies.len());
        for (i, b) in self.bodies.iter().enumerate() {
            let pre = b.parent.map(|p| out[p].disp).unwrap_or_else(Displacement::identity);
            let (own, screw_ref) = match b.joint {
                JointKind::Rigid => (Displacement::identity(), Sv::zero()),
                JointKind::Prismatic => {
                    (Displacement { r: Matrix3::identity(), t: b.axis * q[i] }, Sv { w: Vector3::zeros(), v: b.axis })
                }
                JointKind::Revolute => {
                    let r = rotation(&b.axis, q[i]);
                    (Displacement { r, t: b.point - r * b.point }, Sv { w: b.axis, v: b.point.cross(&b.axis) })
                }
            };
            // Adjoint of the parent's displacement carries the reference screw along.
            let w = pre.r * screw_ref.w;
            let screw = Sv { w, v: pre.r * screw_ref.v + pre.t.cross(&w) };
            let disp = pre.compose(&own);
            let com = disp.apply(&b.com);
            let inertia = disp.r * b.inertia * disp.r.transpose();
            out.push(Placed { disp, screw, com, inertia });
        }
        out
    }

    /// Recursive Newton-Euler inverse dynamics: the joint forces that produce accelerations `qdd`
    /// at `(q, qd)` under gravity `g` and the external wrenches.
    fn inverse_dynamics(&self, placed: &[Placed<T>], qd: &[T], qdd: &[T], g: &Vector3<T>, ext: &[Wrench<T>]) -> Vec<T> {
        let n = self.bodies.len();
        let (mut vel, mut acc) = (vec![Sv::zero(); n], vec![Sv::zero(); n]);
        let mut force = vec![Sv::zero(); n];
        // Gravity as a fictitious upward acceleration of the fixed frame.
        let base = Sv { w: Vector3::zeros(), v: -*g };
        for i in 0..n {
            let (vp, ap) = match self.bodies[i].parent {
                Some(p) => (vel[p], acc[p]),
                None => (Sv::zero(), base),
            };
            let s = placed[i].screw;
            vel[i] = vp.add(&s.scale(qd[i]));
            acc[i] = ap.add(&s.scale(qdd[i])).add(&vp.cross_motion(&vel[i]));
            let h = momentum(&placed[i], self.bodies[i].mass, &vel[i]);
            force[i] = momentum(&placed[i], self.bodies[i].mass, &acc[i]).add(&vel[i].cross_force(&h));
        }
        for e in ext {
            let f = Sv { w: e.torque + e.point.cross(&e.force), v: e.force };
            force[e.body] = force[e.body].add(&f.scale(c(-1.0)));
        }
        let mut tau = vec![c(0.0); n];
        for i in (0..n).rev() {
            tau[i] = placed[i].screw.dot(&force[i]);
            if let Some(p) = self.bodies[i].parent {
                force[p] = force[p].add(&force[i]);
            }
        }
        tau
    }

    /// Joint-space terms at `(q, qd)`: the degrees of freedom (non-rigid joints), the inertia
    /// matrix `M(q)` over them and the generalised force `f = tau_joint - c(q, qd)`, with the
    /// joints' damping, smoothed friction and springs in `tau_joint`.
    fn joint_space(&self, q: &[T], qd: &[T], params: &IntegrationParameters, ext: &[Wrench<T>]) -> (Vec<usize>, Vec<Vec<T>>, Vec<T>) {
        let n = self.bodies.len();
        let placed = self.place(q);
        let g = Vector3::new(c(params.gravity[0]), c(params.gravity[1]), c(params.gravity[2]));
        let zero = vec![c::<T>(0.0); n];
        let bias = self.inverse_dynamics(&placed, qd, &zero, &g, ext);
        let dofs: Vec<usize> = (0..n).filter(|&i| self.bodies[i].joint != JointKind::Rigid).collect();
        let k = dofs.len();
        // Joint-space inertia, one column per degree of freedom.
        let mut m = vec![vec![c::<T>(0.0); k]; k];
        for (col, &j) in dofs.iter().enumerate() {
            let mut e = zero.clone();
            e[j] = c(1.0);
            let column = self.inverse_dynamics(&placed, &zero, &e, &Vector3::zeros(), &[]);
            for (row, &i) in dofs.iter().enumerate() {
                m[row][col] = column[i];
            }
        }
        let f = dofs
            .iter()
            .enumerate()
            .map(|(row, &i)| {
                let b = &self.bodies[i];
                let friction = coulomb(b.friction, params.friction.slope(b.friction, m[row][row]), qd[i]);
                -(b.damping * qd[i]) - friction - b.stiffness * (q[i] - b.rest) - bias[i]
            })
            .collect();
        (dofs, m, f)
    }

    /// Joint accelerations at `(q, qd)`: `M(q) qdd = tau_joint - c(q, qd)`, with the joints'
    /// damping, smoothed friction and springs in `tau_joint`. Rigid joints get 0.
    pub fn forward_dynamics(&self, q: &[T], qd: &[T], params: &IntegrationParameters, ext: &[Wrench<T>]) -> Vec<T> {
        let (dofs, mut m, mut rhs) = self.joint_space(q, qd, params, ext);
        solve(&mut m, &mut rhs);
        let mut qdd = vec![c::<T>(0.0); self.bodies.len()];
        for (row, &i) in dofs.iter().enumerate() {
            qdd[i] = rhs[row];
        }
        qdd
    }

    /// Simulate `steps` time steps from `(q, qd)`; `wrench(t)` gives the external wrenches at time
    /// `t` \[s\]. Returns the coordinates after each step (`steps` entries). Semi-implicit Euler
    /// with linearly implicit dissipation and springs (module docs).
    pub fn simulate(
        &self,
        q0: &[T],
        qd0: &[T],
        steps: usize,
        params: &IntegrationParameters,
        wrench: impl Fn(f64) -> Vec<Wrench<T>>,
    ) -> Vec<Vec<T>> {
        let (mut q, mut qd) = (q0.to_vec(), qd0.to_vec());
        let h = params.dt / params.substeps.max(1) as f64;
        let mut out = Vec::with_capacity(steps);
        for s in 0..steps {
            for k in 0..params.substeps.max(1) {
                let t = s as f64 * params.dt + k as f64 * h;
                let (dofs, m, f) = self.joint_space(&q, &qd, params, &wrench(t));
                // f holds the joint forces at the old velocity; re-evaluate them at the new one.
                let joints: Vec<JointForce<T>> = dofs
                    .iter()
                    .enumerate()
                    .map(|(row, &i)| {
                        let b = &self.bodies[i];
                        let slope = params.friction.slope(b.friction, m[row][row]);
                        JointForce { damping: b.damping, friction: b.friction, slope, stiffness: b.stiffness, q: q[i] - b.rest }
                    })
                    .collect();
                let base: Vec<T> = dofs.iter().enumerate().map(|(row, &i)| f[row] - joints[row].force(qd[i], h) - joints[row].stiffness * qd[i] * h).collect();
                let v: Vec<T> = dofs.iter().map(|&i| qd[i]).collect();
                let w = implicit_velocity(&m, &v, &base, &joints, h);
                let dv: Vec<T> = w.iter().zip(&v).map(|(a, b)| *a - *b).collect();
                for (row, &i) in dofs.iter().enumerate() {
                    qd[i] += dv[row];
                    q[i] += qd[i] * h;
                }
            }
            out.push(q.clone());
        }
        out
    }

    /// Centre of mass of every body at coordinates `q` \[m\].
    pub fn centres_of_mass(&self, q: &[T]) -> Vec<Vector3<T>> {
        self.place(q).iter().map(|p| p.com).collect()
    }

    /// Kinetic plus gravitational potential energy \[J\] (zero potential at the fixed frame's origin).
    pub fn energy(&self, q: &[T], qd: &[T], params: &IntegrationParameters) -> T {
        let placed = self.place(q);
        let g = Vector3::new(c::<T>(params.gravity[0]), c(params.gravity[1]), c(params.gravity[2]));
        let mut e = c::<T>(0.0);
        let mut vel: Vec<Sv<T>> = Vec::with_capacity(q.len());
        for (i, b) in self.bodies.iter().enumerate() {
            let vp = b.parent.map(|p| vel[p]).unwrap_or_else(Sv::zero);
            let v = vp.add(&placed[i].screw.scale(qd[i]));
            e += v.dot(&momentum(&placed[i], b.mass, &v)) * 0.5 - b.mass * g.dot(&placed[i].com);
            vel.push(v);
        }
        e
    }
}

/// Solve `a x = b` in place (`b` becomes `x`) by Gaussian elimination with partial pivoting on
/// the real parts; `a` is small and symmetric positive definite here.
fn solve<T: Real>(a: &mut [Vec<T>], b: &mut [T]) {
    let n = b.len();
    for col in 0..n {
        let piv = (col..n).max_by(|&x, &y| a[x][col].re().abs().total_cmp(&a[y][col].re().abs())).unwrap_or(col);
        a.swap(col, piv);
        b.swap(col, piv);
        for row in col + 1..n {
            let f = a[row][col] / a[col][col];
            for k in col..n {
                let v = a[col][k];
                a[row][k] -= f * v;
            }
            let v = b[col];
            b[row] -= f * v;
        }
    }
    for col in (0..n).rev() {
        let mut s = b[col];
        for k in col + 1..n {
            s -= a[col][k] * b[k];
        }
        b[col] = s / a[col][col];
    }
}

/// One joint whose parent does not move and whose subtree is locked:
/// `I qdd = tau(t) - b qd - mu tanh(qd / v_s) + f(q)` in the joint's coordinate (rad or m), with
/// the subtree's constant generalised inertia `I` (kg·m² or kg) and the position-dependent forces
/// `f(q)` of the effects ([`crate::model::effects`]): the spring `-k (q - rest)`, a joint limit
/// ([`JointLimit`]) and gravity ([`JointDynamics::gravity`]). Integrated like
/// [`Articulation::simulate`]: the spring and the limit implicitly (the limit linearised at the
/// step's start, so a stiff stop stays stable), gravity explicitly (it may push away from an
/// equilibrium, which would break the monotone implicit solve).
#[derive(Debug, Clone, Copy)]
pub struct JointDynamics<T: Real> {
    pub inertia: T,
    pub damping: T,
    pub friction: T,
    pub stiffness: T,
    pub rest: T,
    /// Joint stops, lower and upper, where the model has them.
    pub limits: [Option<JointLimit<T>>; 2],
    /// Generalised gravity force `g0 + g1 cos(q - q_g) + g2 sin(q - q_g)` (N or N·m): constant
    /// along a prismatic axis; for a revolute one the moment of the weights turning with the joint
    /// (`q_g` is the coordinate at which `g1`, `g2` were computed). Zeros: no gravity.
    pub gravity: [T; 3],
    pub gravity_at: T,
    /// Quadratic damping `-c q' |q'|` (N·s²/m² or N·m·s²/rad²): the drag of a fluid or a
    /// soft-close damper, which grows with speed faster than the viscous term. Monotone in the
    /// velocity, so the implicit solve keeps a unique root.
    pub quadratic_damping: T,
}

/// A one-sided joint stop: a soft contact `f = -k w softplus((q - position) / w)` beyond an upper
/// limit (mirrored for a lower one), `w` the contact width (m or rad). As `w -> 0` it is the
/// penalty contact `-k max(q - position, 0)`; its derivative in `q` is never positive, so the
/// implicit velocity solve stays monotone.
#[derive(Debug, Clone, Copy)]
pub struct JointLimit<T: Real> {
    pub position: T,
    /// Contact stiffness (N/m or N·m/rad).
    pub stiffness: T,
    /// Whether the stop is above (`true`) or below the free range.
    pub upper: bool,
    /// The contact width (m or rad): of the scalar type, as it scales with a revolute joint's radius.
    pub width: T,
}

impl<T: Real> JointLimit<T> {
    /// The stop's force at `q` and its derivative `df/dq` (<= 0).
    pub fn force(&self, q: T) -> (T, T) {
        let s = if self.upper { 1.0 } else { -1.0 };
        // `s / width`, written so that `width` may carry derivatives (the same value: s is +-1).
        let x = (q - self.position) * (self.width.recip() * s);
        // softplus and the logistic function, overflow-safe in both directions.
        let (sp, sig) = if x.re() > 0.0 {
            let e = (-x).exp();
            (x + (e + 1.0).ln(), (e + 1.0).recip())
        } else {
            let e = x.exp();
            ((e + 1.0).ln(), e / (e + 1.0))
        };
        (-(self.stiffness * sp) * (self.width * s), -(self.stiffness * sig))
    }
}

impl<T: Real> JointDynamics<T> {
    /// Damping, friction and a spring only: no limit, no gravity.
    pub fn new(inertia: T, damping: T, friction: T, stiffness: T, rest: T) -> Self {
        JointDynamics { inertia, damping, friction, stiffness, rest, limits: [None, None], gravity: [c(0.0); 3], gravity_at: c(0.0), quadratic_damping: c(0.0) }
    }

    /// The position-dependent forces at `q`: `(f, K)` with `f` the spring, limit and gravity force
    /// and `K >= 0` the stiffness the implicit step uses (spring plus the limit's slope).
    fn position_force(&self, q: T) -> (T, T) {
        let mut f = -(self.stiffness * (q - self.rest));
        let mut k = self.stiffness;
        for l in self.limits.iter().flatten() {
            let (fl, dl) = l.force(q);
            f += fl;
            k -= dl;
        }
        let [g0, g1, g2] = self.gravity;
        if g0.re() != 0.0 || g1.re() != 0.0 || g2.re() != 0.0 {
            let a = q - self.gravity_at;
            f += g0 + g1 * a.cos() + g2 * a.sin();
        }
        (f, k)
    }
}

/// Generalised inertia of rigid bodies `(mass [kg], centre of mass [m], inertia about the centre
/// of mass [kg·m²])` about a revolute axis (unit `axis` through `point`:
/// `sum (m |r_perp|^2 + axis^T I_c axis)`, the parallel-axis theorem) or along a prismatic one
/// (`sum m`). An inertia per kilogram (perception's hull model) is multiplied by the mass first.
pub fn generalised_inertia<T: Real>(joint: JointKind, axis: &Vector3<T>, point: &Vector3<T>, bodies: &[(T, Vector3<T>, Matrix3<T>)]) -> T {
    bodies.iter().fold(c::<T>(0.0), |acc, (m, com, inertia)| match joint {
        JointKind::Rigid => acc,
        JointKind::Prismatic => acc + *m,
        JointKind::Revolute => {
            let r = com - point;
            let perp = r - axis * r.dot(axis);
            acc + *m * perp.dot(&perp) + axis.dot(&(inertia * axis))
        }
    })
}

/// Generalised force of a wrench (force \[N\] at `at` \[m\] plus a pure torque \[N·m\]) on a joint:
/// the moment about a revolute axis (unit `axis` through `point`), or the force along a prismatic
/// one.
pub fn generalised_force(joint: JointKind, axis: &Vector3<f64>, point: &Vector3<f64>, at: &Vector3<f64>, force: &Vector3<f64>, torque: &Vector3<f64>) -> f64 {
    generalised_force_of(joint, axis, point, at, force, torque)
}

/// [`generalised_force`] with the axis of any scalar type (its derivatives carried); the same
/// value to the last bit for `f64`.
pub fn generalised_force_of<T: Real>(joint: JointKind, axis: &Vector3<T>, point: &Vector3<T>, at: &Vector3<f64>, force: &Vector3<f64>, torque: &Vector3<f64>) -> T {
    match joint {
        JointKind::Rigid => c(0.0),
        JointKind::Prismatic => axis.dot(&force.map(c::<T>)),
        JointKind::Revolute => axis.dot(&((at.map(c::<T>) - point).cross(&force.map(c::<T>)) + torque.map(c::<T>))),
    }
}

/// [`generalised_force_of`] at every substep of a push (`at[n]`, `force[n]`, `torque[n]`, the
/// same units), for an axis that carries derivatives (BOM-NUTS's density,
/// [`crate::model::dynamics::simulate_joint_in`]). The revolute moment
/// `a . ((p_n - c) x f_n + t_n)` is computed as `a . (p_n x f_n + t_n) - (a x c) . f_n` (the scalar
/// triple product `a . (c x f) = (a x c) . f`): `a x c` is formed once, so each substep costs two
/// dot products of a `T` vector with an `f64` one, not a cross product in `T` (on `microwave` the
/// substep forces were a sixth of a NUTS gradient's time; README, stop 110). Equal to
/// [`generalised_force_of`] up to rounding.
pub fn generalised_forces_of<T: Real>(joint: JointKind, axis: &Vector3<T>, point: &Vector3<T>, at: &[Vector3<f64>], force: &[Vector3<f64>], torque: &[Vector3<f64>]) -> Vec<T> {
    let dot = |v: &Vector3<T>, w: &Vector3<f64>| v[0] * w[0] + v[1] * w[1] + v[2] * w[2];
    match joint {
        JointKind::Rigid => vec![c(0.0); at.len().min(force.len())],
        JointKind::Prismatic => force.iter().take(at.len()).map(|f| dot(axis, f)).collect(),
        JointKind::Revolute => {
            let n = axis.cross(point);
            at.iter().zip(force).zip(torque).map(|((p, f), t)| dot(axis, &(p.cross(f) + t)) - dot(&n, f)).collect()
        }
    }
}

/// A joint's own forces at velocity `w`: damping, regularised friction (`slope` its slope at rest,
/// [`coulomb`]) and the spring at the position reached with `w` after a step `h` (`q` is the
/// position relative to the spring's rest).
#[derive(Debug, Clone, Copy)]
struct JointForce<T: Real> {
    damping: T,
    friction: T,
    slope: T,
    stiffness: T,
    q: T,
}

impl<T: Real> JointForce<T> {
    fn force(&self, w: T, h: f64) -> T {
        -(self.damping * w) - coulomb(self.friction, self.slope, w) - self.stiffness * (self.q + w * h)
    }

    /// Derivative of `-force` with respect to `w`.
    fn stiffness_in_w(&self, w: T, h: f64) -> T {
        self.damping + coulomb_slope(self.friction, self.slope, w) + self.stiffness * h
    }

    fn re(&self) -> JointForce<f64> {
        JointForce { damping: self.damping.re(), friction: self.friction.re(), slope: self.slope.re(), stiffness: self.stiffness.re(), q: self.q.re() }
    }
}

/// The implicit velocity update: `w` with `M (w - v) = h (base + force(w))`. The left side minus
/// the right is the gradient of a strictly convex function of `w` (`M` is positive definite, the
/// joint forces decrease monotonically in `w`), so its root is unique: it is found on the real
/// parts by Newton's method with backtracking, then one Newton step in the scalar type carries the
/// derivatives (implicit function theorem).
fn implicit_velocity<T: Real>(m: &[Vec<T>], v: &[T], base: &[T], joints: &[JointForce<T>], h: f64) -> Vec<T> {
    let k = v.len();
    let residual = |m: &[Vec<f64>], v: &[f64], base: &[f64], jf: &[JointForce<f64>], w: &[f64]| -> Vec<f64> {
        (0..k).map(|r| (0..k).map(|c| m[r][c] * (w[c] - v[c])).sum::<f64>() - (base[r] + jf[r].force(w[r], h)) * h).collect()
    };
    let (mr, vr, br): (Vec<Vec<f64>>, Vec<f64>, Vec<f64>) =
        (m.iter().map(|row| row.iter().map(|x| x.re()).collect()).collect(), v.iter().map(|x| x.re()).collect(), base.iter().map(|x| x.re()).collect());
    let jr: Vec<JointForce<f64>> = joints.iter().map(|j| j.re()).collect();
    let norm = |r: &[f64]| r.iter().map(|x| x * x).sum::<f64>();
    let mut w = vr.clone();
    let mut res = residual(&mr, &vr, &br, &jr, &w);
    for _ in 0..60 {
        let mut jac = mr.clone();
        for r in 0..k {
            jac[r][r] += jr[r].stiffness_in_w(w[r], h) * h;
        }
        let mut step: Vec<f64> = res.iter().map(|x| -x).collect();
        solve(&mut jac, &mut step);
        let mut alpha = 1.0;
        let before = norm(&res);
        loop {
            let trial: Vec<f64> = (0..k).map(|r| w[r] + alpha * step[r]).collect();
            let tr = residual(&mr, &vr, &br, &jr, &trial);
            if norm(&tr) < before || alpha < 1e-6 {
                w = trial;
                res = tr;
                break;
            }
            alpha *= 0.5;
        }
        if norm(&step).sqrt() * alpha < 1e-13 * (1.0 + norm(&w).sqrt()) {
            break;
        }
    }
    // One Newton step in T from the real root.
    let wt: Vec<T> = w.iter().map(|x| c::<T>(*x)).collect();
    let mut jac = m.to_vec();
    let mut step: Vec<T> = (0..k)
        .map(|r| {
            jac[r][r] += joints[r].stiffness_in_w(wt[r], h) * h;
            let mw = (0..k).fold(c::<T>(0.0), |acc, col| acc + m[r][col] * (wt[col] - v[col]));
            -(mw - (base[r] + joints[r].force(wt[r], h)) * h)
        })
        .collect();
    solve(&mut jac, &mut step);
    wt.iter().zip(&step).map(|(a, b)| *a + *b).collect()
}

/// [`tanh`] in `f64`, returning ±1 without computing it where that is already its value
/// (`|x| > 19.1`): a joint moving faster than 19 friction velocity scales, common during a push.
#[inline]
fn smooth_sign(x: f64) -> f64 {
    if x.abs() > 19.1 { x.signum() } else { tanh(x) }
}

impl<T: Real> JointDynamics<T> {
    /// Integrate from `(q0, v0)`, the generalised force being `tau[n]` during substep `n` of
    /// length `h` \[s\]; returns the coordinate after every substep. `friction` sets the
    /// regularisation of the Coulomb friction (module docs).
    /// `tau` is of the scalar type: its derivatives (with respect to the axis that the force is
    /// projected on) carry through the step like the parameters'.
    pub fn simulate(&self, q0: T, v0: T, tau: &[T], h: f64, friction: FrictionLaw) -> Vec<T> {
        let (mut q, mut v) = (q0, v0);
        let (ir, br, fr) = (self.inertia.re(), self.damping.re(), self.friction.re());
        // Friction's velocity scale `v_s = min(mu t_f / I, v_max)` (module docs); with no
        // friction any positive scale will do, the friction term being 0.
        let tf = friction;
        let capped = tf.capped(fr, ir);
        let vs = if capped { tf.velocity_max } else if fr > 0.0 { fr * tf.relaxation_s / ir } else { 1.0 };
        // `1 / v_s` in the scalar type: `I / (mu t_f)`.
        let inv_vs = if capped {
            c::<T>(1.0 / tf.velocity_max)
        } else if fr > 0.0 {
            self.inertia / (self.friction * tf.relaxation_s)
        } else {
            c::<T>(0.0)
        };
        tau.iter()
            .map(|&tau_t| {
                let t = tau_t.re();
                // The scalar case of `implicit_velocity`, without its allocations: Newton on the
                // real parts from the previous velocity, safeguarded by bisection on the bracket
                // that a monotone residual always has, then one Newton step in T.
                // Position forces linearised at the step's start: f(q + w h) ~ f0 - K w h.
                let (f0, k) = self.position_force(q);
                let (vr, f0r, kr) = (v.re(), f0.re(), k.re());
                let cr = self.quadratic_damping.re();
                // Friction and quadratic damping, and their derivative in the velocity.
                // `th = tanh(w / vs)`, computed once per Newton iterate for both.
                let fric = |w: f64, th: f64| fr * th + cr * w * w.abs();
                let dfric = |w: f64, th: f64| fr * (1.0 - th * th) / vs + 2.0 * cr * w.abs();
                let g = |w: f64, th: f64| ir * (w - vr) - (t + f0r - br * w - fric(w, th) - kr * w * h) * h;
                let dg = |w: f64, th: f64| ir + (br + dfric(w, th) + kr * h) * h;
                // Bracket: g is increasing; the friction term is bounded by fr, and the quadratic
                // damping only pulls the root towards zero.
                let lin = ir + (br + kr * h) * h;
                let centre = (ir * vr + (t + f0r) * h) / lin;
                let span = fr * h / lin + 1e-12;
                let (mut lo, mut hi) = ((centre - span).min(0.0) - 1e-9, (centre + span).max(0.0) + 1e-9);
                if !(lo <= hi) {
                    // Non-finite parameters: no motion to compute (the caller sees NaN).
                    v = c::<T>(f64::NAN);
                    q = c::<T>(f64::NAN);
                    return q;
                }
                let mut w = vr.clamp(lo, hi);
                let mut th = smooth_sign(w / vs);
                for _ in 0..60 {
                    let gw = g(w, th);
                    if gw.abs() < 1e-14 * (1.0 + ir * w.abs()) {
                        break;
                    }
                    if gw > 0.0 { hi = w } else { lo = w }
                    let next = w - gw / dg(w, th);
                    w = if next > lo && next < hi { next } else { 0.5 * (lo + hi) };
                    th = smooth_sign(w / vs);
                }
                // `w` is a constant of the scalar type (its derivatives come from the Newton step
                // below, which needs first derivatives only); `v_s` depends on the parameters, so
                // `tanh(w / v_s)` is the real one just computed plus its first-order change.
                let wt = c::<T>(w);
                let th_t = c::<T>(th) + (inv_vs * w - w / vs) * (1.0 - th * th);
                let (mut fr_t, mut dfr_t) = (self.friction * th_t, inv_vs * self.friction * (1.0 - th * th));
                if cr != 0.0 {
                    let aw = if w >= 0.0 { wt } else { -wt };
                    fr_t += self.quadratic_damping * wt * aw;
                    dfr_t += self.quadratic_damping * aw * 2.0;
                }
                let force = -(self.damping * wt) - fr_t + f0 - k * wt * h;
                let res = self.inertia * (wt - v) - (force + tau_t) * h;
                let slope = self.inertia + (self.damping + dfr_t + k * h) * h;
                v = wt - res / slope;
                q += v * h;
                q
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use num_dual::DualSVec64;

    fn box_inertia(m: f64, x: f64, y: f64, z: f64) -> Matrix3<f64> {
        Matrix3::from_diagonal(&Vector3::new(y * y + z * z, x * x + z * z, x * x + y * y)) * (m / 12.0)
    }

    fn slider(mass: f64, damping: f64) -> Articulation<f64> {
        Articulation {
            bodies: vec![Body {
                parent: None,
                joint: JointKind::Prismatic,
                axis: Vector3::new(1.0, 0.0, 0.0),
                point: Vector3::zeros(),
                mass,
                com: Vector3::new(0.2, 0.1, 0.5),
                inertia: box_inertia(mass, 0.3, 0.2, 0.1),
                damping,
                friction: 0.0,
                stiffness: 0.0,
                rest: 0.0,
            }],
        }
    }

    /// A door 0.8 m wide hinged on a vertical axis through (0, 0, z), under a pure torque.
    fn door(mass: f64, damping: f64, friction: f64) -> Articulation<f64> {
        Articulation {
            bodies: vec![
                Body {
                    parent: None,
                    joint: JointKind::Rigid,
                    axis: Vector3::z(),
                    point: Vector3::zeros(),
                    mass: 10.0,
                    com: Vector3::new(0.4, 0.3, 0.5),
                    inertia: box_inertia(10.0, 0.8, 0.6, 1.0),
                    damping: 0.0,
                    friction: 0.0,
                    stiffness: 0.0,
                    rest: 0.0,
                },
                Body {
                    parent: Some(0),
                    joint: JointKind::Revolute,
                    axis: Vector3::z(),
                    point: Vector3::new(0.0, 0.0, 0.5),
                    mass,
                    com: Vector3::new(0.4, 0.0, 0.5),
                    inertia: box_inertia(mass, 0.8, 0.02, 1.0),
                    damping,
                    friction,
                    stiffness: 0.0,
                    rest: 0.0,
                },
            ],
        }
    }

    #[test]
    fn damped_slider_under_constant_force_matches_closed_form() {
        let (m, b, f) = (2.0, 3.0, 5.0);
        let a = slider(m, b);
        let p = IntegrationParameters { dt: 0.01, substeps: 20, ..Default::default() };
        let push = |_t: f64| vec![Wrench { body: 0, point: Vector3::new(0.2, 0.1, 0.5), force: Vector3::new(f, 0.0, 0.0), torque: Vector3::zeros() }];
        let traj = a.simulate(&[0.0], &[0.0], 150, &p, push);
        for (k, q) in traj.iter().enumerate().step_by(30) {
            let t = (k + 1) as f64 * p.dt;
            let exact = f / b * (t - m / b * (1.0 - (-b * t / m).exp()));
            assert!((q[0] - exact).abs() < 2e-3 * exact.max(0.01), "t={t}: {} vs {exact}", q[0]);
        }
    }

    #[test]
    fn door_under_constant_torque_matches_closed_form() {
        let (m, b, tau) = (4.0, 0.8, 1.5);
        let a = door(m, b, 0.0);
        let inertia = m * (0.8f64.powi(2) + 0.02f64.powi(2)) / 12.0 + m * 0.4 * 0.4;
        let p = IntegrationParameters { dt: 0.01, substeps: 20, ..Default::default() };
        let torque = |_t: f64| vec![Wrench { body: 1, point: Vector3::new(0.4, 0.0, 0.5), force: Vector3::zeros(), torque: Vector3::new(0.0, 0.0, tau) }];
        let traj = a.simulate(&[0.0, 0.0], &[0.0, 0.0], 200, &p, torque);
        for (k, q) in traj.iter().enumerate().step_by(40) {
            let t = (k + 1) as f64 * p.dt;
            let exact = tau / b * (t - inertia / b * (1.0 - (-b * t / inertia).exp()));
            assert!((q[1] - exact).abs() < 2e-3 * exact.max(0.01), "t={t}: {} vs {exact}", q[1]);
            assert_eq!(q[0], 0.0);
        }
        // Regularised Coulomb friction above the torque holds the door: it only creeps, at the
        // steady speed where `mu tanh(v / v_s) = tau - b v`, `v_s = mu t_f / I` (module docs).
        let mu = 2.0 * tau;
        let stuck = door(m, b, mu).simulate(&[0.0, 0.0], &[0.0, 0.0], 100, &p, torque);
        assert!(stuck[99][1].abs() < 0.02, "{}", stuck[99][1]);
        let vs = mu * p.friction.relaxation_s / inertia;
        let creep = bisect(|v| mu * (v / vs).tanh() + b * v - tau, 0.0, 1.0);
        let speed = (stuck[99][1] - stuck[49][1]) / (50.0 * p.dt);
        assert!((speed - creep).abs() < 1e-3 * creep, "creeps at {speed} rad/s, want {creep}");
        assert!((creep - tau * p.friction.relaxation_s / inertia).abs() < 0.2 * creep, "about tau t_f / I");
    }

    /// The root of an increasing `f` on `[lo, hi]`.
    fn bisect(f: impl Fn(f64) -> f64, mut lo: f64, mut hi: f64) -> f64 {
        for _ in 0..200 {
            let mid = 0.5 * (lo + hi);
            if f(mid) > 0.0 { hi = mid } else { lo = mid }
        }
        0.5 * (lo + hi)
    }

    /// One joint on its own agrees with the articulated body it is part of (the parent static),
    /// springs and strong friction included; and a spring alone oscillates at sqrt(k / I).
    #[test]
    fn joint_dynamics_match_the_articulation() {
        let (m, b, mu, k) = (0.3, 2.0, 1.5, 1.2);
        let mut a = door(m, b, mu);
        a.bodies[1].stiffness = k;
        a.bodies[1].rest = 0.2;
        let p = IntegrationParameters { dt: 1.0 / 30.0, substeps: 10, ..Default::default() };
        let push = |t: f64| {
            let f = if t < 1.0 { 6.0 } else { 0.0 };
            vec![Wrench { body: 1, point: Vector3::new(0.7, -0.01, 0.5), force: Vector3::new(0.0, f, 0.0), torque: Vector3::zeros() }]
        };
        let traj = a.simulate(&[0.0, 0.0], &[0.0, 0.0], 60, &p, push);
        let body = &a.bodies[1];
        let inertia = generalised_inertia(JointKind::Revolute, &body.axis, &body.point, &[(body.mass, body.com, body.inertia)]);
        let h = p.dt / p.substeps as f64;
        // The contact point turns with the door; its moment arm about the hinge stays 0.7 m.
        let tau: Vec<f64> = (0..60 * p.substeps).map(|n| if (n as f64) * h < 1.0 { 6.0 * 0.7 } else { 0.0 }).collect();
        let jd = JointDynamics::new(inertia, b, mu, k, 0.2);
        let q = jd.simulate(0.0, 0.0, &tau, h, p.friction);
        for s in (0..60).step_by(5) {
            let qa = traj[s][1];
            let qj = q[(s + 1) * p.substeps - 1];
            assert!((qa - qj).abs() < 0.02 * qa.abs().max(0.05), "step {s}: articulation {qa} vs joint {qj}");
        }
        assert!(traj.iter().any(|q| q[1] > 0.5), "it moves: {:?}", traj[59]);
        // A stiff friction (time constant << the step) stays stable: no oscillation at rest.
        let stiff = JointDynamics::new(0.01, 0.1, 5.0, 0.0, 0.0);
        let q: Vec<f64> = stiff.simulate(0.0, 1.0, &vec![0.0; 300], 0.005, FrictionLaw::default());
        assert!(q.windows(2).skip(100).all(|w| (w[1] - w[0]).abs() < 1e-6), "settled: {:?}", &q[290..]);
        // Undamped spring: period 2 pi sqrt(I / k).
        let spring = JointDynamics::new(0.5, 0.0, 0.0, 2.0, 0.0);
        let h = 0.0005;
        let q: Vec<f64> = spring.simulate(0.1, 0.0, &vec![0.0; 8000], h, FrictionLaw::default());
        let half = q.windows(2).position(|w| w[0] < 0.0 && w[1] >= 0.0).expect("crosses back") as f64 * h;
        let period = 2.0 * std::f64::consts::PI * (0.5f64 / 2.0).sqrt();
        assert!((half - 0.75 * period).abs() < 0.01 * period, "{half} vs {}", 0.75 * period);
    }

    /// The substep forces of [`generalised_forces_of`] (scalar triple product, `a x c` once) are
    /// [`generalised_force_of`]'s (cross product per substep), value and derivatives in the axis
    /// and hinge point, for every joint kind, to rounding.
    #[test]
    fn substep_forces_match_the_per_substep_form() {
        let at: Vec<Vector3<f64>> = (0..7).map(|n| Vector3::new(0.4 + 0.01 * n as f64, -0.3, 0.9 - 0.02 * n as f64)).collect();
        let force: Vec<Vector3<f64>> = (0..7).map(|n| Vector3::new(-3.0 + n as f64, 1.5, 0.25 * n as f64)).collect();
        let torque: Vec<Vector3<f64>> = (0..7).map(|n| Vector3::new(0.1, -0.05 * n as f64, 0.3)).collect();
        let seed = |v: [f64; 3], first: usize| Vector3::from_fn(|k, _| DualSVec64::<6>::from_re(v[k]).derivative(first + k));
        let axis = seed([0.36, -0.48, 0.8], 0);
        let point = seed([0.05, 0.7, -0.2], 3);
        for kind in [JointKind::Rigid, JointKind::Prismatic, JointKind::Revolute] {
            let all = generalised_forces_of(kind, &axis, &point, &at, &force, &torque);
            assert_eq!(all.len(), at.len());
            for n in 0..at.len() {
                let one = generalised_force_of(kind, &axis, &point, &at[n], &force[n], &torque[n]);
                assert!((all[n].re - one.re).abs() <= 1e-12 * (1.0 + one.re.abs()), "{kind:?} {n}: {} vs {}", all[n].re, one.re);
                let (da, db) = (all[n].eps.unwrap_generic(nalgebra::Const::<6>, nalgebra::Const::<1>), one.eps.unwrap_generic(nalgebra::Const::<6>, nalgebra::Const::<1>));
                assert!((da - db).amax() <= 1e-12 * (1.0 + db.amax()), "{kind:?} {n}: {da} vs {db}");
            }
        }
    }

    #[test]
    fn free_swing_conserves_energy() {
        // A pendulum: the door's hinge turned horizontal (axis x), swinging under gravity.
        let mut a = door(3.0, 0.0, 0.0);
        a.bodies[1].axis = Vector3::x();
        a.bodies[1].com = Vector3::new(0.0, 0.3, 0.5);
        a.bodies[1].inertia = box_inertia(3.0, 0.8, 0.6, 0.02);
        let p = IntegrationParameters { dt: 0.01, substeps: 20, ..Default::default() };
        let (q0, qd0) = ([0.0, 0.3], [0.0, 0.0]);
        let e0 = a.energy(&q0, &qd0, &p);
        let mut q = q0.to_vec();
        let mut qd = qd0.to_vec();
        let h = p.dt / p.substeps as f64;
        let mut worst: f64 = 0.0;
        let mut swing: f64 = 0.0;
        for _ in 0..(200 * p.substeps) {
            let qdd = a.forward_dynamics(&q, &qd, &p, &[]);
            qd[1] += qdd[1] * h;
            q[1] += qd[1] * h;
            worst = worst.max((a.energy(&q, &qd, &p) - e0).abs());
            swing = swing.max((q[1] - 0.3).abs());
        }
        assert!(swing > 1.0, "it swings: {swing}");
        let ke_scale = 3.0 * 9.81 * 0.3;
        assert!(worst < 2e-3 * ke_scale, "energy drift {worst} J");
    }

    #[test]
    fn gradients_of_a_trajectory_match_finite_differences() {
        type D = DualSVec64<3>;
        // d(final angle)/d(damping, friction, mass) of a pushed door, by dual numbers.
        let run = |b: D, mu: D, m: D| -> D {
            let a: Articulation<D> = Articulation {
                bodies: vec![Body {
                    parent: None,
                    joint: JointKind::Revolute,
                    axis: Vector3::<f64>::z().map(D::from),
                    point: Vector3::new(0.0, 0.0, 0.5).map(D::from),
                    mass: m,
                    com: Vector3::new(0.4, 0.0, 0.5).map(D::from),
                    inertia: box_inertia(1.0, 0.8, 0.02, 1.0).map(D::from) * m,
                    damping: b,
                    friction: mu,
                    stiffness: D::from(0.0),
                    rest: D::from(0.0),
                }],
            };
            let p = IntegrationParameters { dt: 0.02, substeps: 10, ..Default::default() };
            let push = |_t: f64| {
                vec![Wrench { body: 0, point: Vector3::new(0.8, 0.0, 0.5).map(D::from), force: Vector3::new(0.0, 4.0, 0.0).map(D::from), torque: Vector3::zeros() }]
            };
            a.simulate(&[D::from(0.0)], &[D::from(0.0)], 40, &p, push)[39][0]
        };
        let x = [0.7, 0.5, 2.0];
        let out = run(D::from_re(x[0]).derivative(0), D::from_re(x[1]).derivative(1), D::from_re(x[2]).derivative(2));
        let grad = out.eps.unwrap_generic(nalgebra::Const::<3>, nalgebra::U1);
        let f = |v: [f64; 3]| run(D::from(v[0]), D::from(v[1]), D::from(v[2])).re;
        for k in 0..3 {
            let (mut a, mut b) = (x, x);
            a[k] += 1e-6;
            b[k] -= 1e-6;
            let fd = (f(a) - f(b)) / 2e-6;
            assert!((fd - grad[k]).abs() < 1e-5 * (1.0 + fd.abs()), "parameter {k}: fd {fd} vs dual {}", grad[k]);
        }
    }

    /// The effects' forces: a slider pushed into a stop rests where the contact force balances
    /// the push (penetration `F / k_c`, plus the softplus offset `w ln 2` of the smoothing); a
    /// frictionless slider on a slope accelerates at `g sin(theta)`; a hinge whose weight hangs
    /// off a horizontal axis swings like the compound pendulum `T = 2 pi sqrt(I / (m g r))`;
    /// quadratic damping gives the terminal speed `sqrt(F / c)`.
    #[test]
    fn joint_limit_gravity_and_quadratic_damping_match_closed_forms() {
        let h = 0.001;
        // Stop at 0.1 m, contact stiffness 5000 N/m, push 20 N, damping 20 N s/m.
        let mut jd = JointDynamics::<f64>::new(2.0, 20.0, 0.0, 0.0, 0.0);
        jd.limits = [None, Some(JointLimit { position: 0.1, stiffness: 5000.0, upper: true, width: 0.001 })];
        let q = jd.simulate(0.0, 0.0, &vec![20.0; 4000], h, FrictionLaw::default());
        let want = 0.1 + 20.0 / 5000.0;
        assert!((q[3999] - want).abs() < 0.0015, "rests at {} (want about {want})", q[3999]);
        // The same push away from a lower stop: nothing holds it back before 0.1 m.
        let mut free = jd;
        free.limits = [Some(JointLimit { position: -0.1, stiffness: 5000.0, upper: false, width: 0.001 }), None];
        let qf = free.simulate(0.0, 0.0, &vec![20.0; 2000], h, FrictionLaw::default());
        assert!(qf[1999] > 0.5, "{}", qf[1999]);
        // A slope of 0.35 rad: g sin(theta) along the slide.
        let theta: f64 = 0.35;
        let m = 1.5;
        let mut slope = JointDynamics::<f64>::new(m, 0.0, 0.0, 0.0, 0.0);
        slope.gravity = [m * 9.81 * theta.sin(), 0.0, 0.0];
        let q = slope.simulate(0.0, 0.0, &vec![0.0; 1000], h, FrictionLaw::default());
        let want = 0.5 * 9.81 * theta.sin() * 1.0f64.powi(2);
        assert!((q[999] - want).abs() < 0.01 * want, "{} vs {want}", q[999]);
        // Pendulum: mass 1 kg at r = 0.3 m below a horizontal hinge, inertia m r^2 (point mass);
        // torque about the axis -m g r sin(q): cos/sin coefficients (0, -m g r) about q = 0.
        let r = 0.3;
        let mut pend = JointDynamics::<f64>::new(r * r, 0.0, 0.0, 0.0, 0.0);
        pend.gravity = [0.0, 0.0, -9.81 * r];
        let h = 0.0005;
        let q = pend.simulate(0.05, 0.0, &vec![0.0; 4000], h, FrictionLaw::default());
        let half = q.windows(2).position(|w| w[0] < 0.0 && w[1] >= 0.0).expect("swings back") as f64 * h;
        let period = 2.0 * std::f64::consts::PI * (r / 9.81f64).sqrt();
        assert!((half - 0.75 * period).abs() < 0.01 * period, "{half} vs {}", 0.75 * period);
        // Quadratic damping 8 N s^2/m^2 under 2 N: terminal speed 0.5 m/s.
        let mut drag = JointDynamics::<f64>::new(1.0, 0.0, 0.0, 0.0, 0.0);
        drag.quadratic_damping = 8.0;
        let q = drag.simulate(0.0, 0.0, &vec![2.0; 4000], 0.001, FrictionLaw::default());
        let speed = (q[3999] - q[2999]) / 1.0;
        assert!((speed - 0.5).abs() < 0.005, "terminal speed {speed}");
    }
}
