//! Differentiable articulated-body physics Ψ (paper §3.3, "Differentiable physics engine"): a tree
//! of rigid parts joined by rigid, prismatic and revolute joints on screw axes, with viscous
//! damping, smoothed Coulomb friction, gravity and a measured external wrench, integrated
//! semi-implicitly with substeps.
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
//! **Coulomb friction** is smoothed as `-mu * tanh(q' / v_s)` so that it has a gradient: it
//! equals the hard law `-mu * sign(q')` up to `mu * (1 - tanh(|q'| / v_s))`, which vanishes as
//! `|q'| / v_s` grows (below 2% of `mu` once `|q'| > 2.3 v_s`), and converges pointwise to it as
//! `v_s -> 0`. Below `v_s` the joint creeps instead of sticking — MuJoCo's soft friction does the
//! same.

use nalgebra::{Matrix3, Vector3};

use super::{c, rotation, Displacement, Real};

/// Integration parameters, in one explicit struct (rapier style).
#[derive(Debug, Clone, PartialEq)]
pub struct IntegrationParameters {
    /// Time step of the output trajectory \[s\].
    pub dt: f64,
    /// Semi-implicit Euler substeps per time step.
    pub substeps: usize,
    /// Velocity scale of the smoothed Coulomb friction, `v_s` above (m/s or rad/s).
    pub friction_velocity: f64,
    /// Gravity in the fixed frame (m/s²).
    pub gravity: [f64; 3],
}

impl Default for IntegrationParameters {
    fn default() -> Self {
        IntegrationParameters { dt: 1.0 / 30.0, substeps: 20, friction_velocity: 0.01, gravity: [0.0, 0.0, -9.81] }
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

    /// Joint accelerations at `(q, qd)`: `M(q) qdd = tau_joint - c(q, qd)`, with the joints'
    /// damping and smoothed friction in `tau_joint`. Rigid joints get 0.
    pub fn forward_dynamics(&self, q: &[T], qd: &[T], params: &IntegrationParameters, ext: &[Wrench<T>]) -> Vec<T> {
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
        let mut rhs: Vec<T> = dofs
            .iter()
            .map(|&i| {
                let b = &self.bodies[i];
                let friction = b.friction * (qd[i] / params.friction_velocity).tanh();
                -(b.damping * qd[i]) - friction - bias[i]
            })
            .collect();
        solve(&mut m, &mut rhs);
        let mut qdd = zero;
        for (row, &i) in dofs.iter().enumerate() {
            qdd[i] = rhs[row];
        }
        qdd
    }

    /// Simulate `steps` time steps from `(q, qd)`; `wrench(t)` gives the external wrenches at time
    /// `t` \[s\]. Returns the coordinates after each step (`steps` entries).
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
                let qdd = self.forward_dynamics(&q, &qd, params, &wrench(t));
                // Semi-implicit (symplectic) Euler: velocity first, then position.
                for i in 0..q.len() {
                    qd[i] += qdd[i] * h;
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
        // Smoothed Coulomb friction above the torque holds the door (it only creeps).
        let stuck = door(m, b, 2.0 * tau).simulate(&[0.0, 0.0], &[0.0, 0.0], 100, &p, torque);
        assert!(stuck[99][1].abs() < 0.02, "{}", stuck[99][1]);
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
}
