//! Dynamic mode: the kinodynamic parameters of a joint and the physics prior that ties its
//! coordinates to the measured wrench (paper §3.3: the physics engine Ψ evolves the object state
//! under the applied forces; §3.2: standard-normal priors on the kinodynamic parameters).
//!
//! **Parameters** of a movable joint, standardised `xi ~ N(0, I)` and mapped log-normally:
//! damping `b`, Coulomb friction `mu`, the mass `m` of the child part (its inertia is `m` times the
//! inertia per kilogram of its observed hull, [`crate::perception::PartGeometry`]), the deviation
//! scale `sigma_d` of the coordinates from the simulated trajectory, and, where the bag declares a
//! spring on the part, its stiffness `k` and rest position. Medians and log-sds are in
//! [`DynamicsConfig`].
//!
//! **Physics prior** (our form of eq. 2's trajectory model): in every interaction window `w` the
//! joint starts at rest at its coordinate `q_{w,0}` and Ψ simulates it under the measured wrench
//! with [`JointDynamics`] (the joint's subtree locked, its parent static during the window); the
//! coordinates at the window's grid frames deviate from the simulated trajectory as
//! `q_t ~ N(Psi_t, sigma_d^2)`. The paper adds noise to the observations only; the deviation term
//! keeps what the physics lacks (soft contact, the robot's compliance, an effect not modelled)
//! from bending the kinematic fit — the axis is still fitted to the observations through `q_t`,
//! and the physics to `q_t`; as `sigma_d -> 0` it is the paper's deterministic simulation.
//!
//! Gradients with respect to the kinodynamic parameters and `q_{w,0}` come from dual numbers
//! through the simulation; the joint's geometry enters the simulation as sampled constants (the
//! axis is pinned by the observations, whose likelihood carries its gradient).

use nalgebra::{Matrix3, Vector3};
use num_dual::DualSVec64;
use serde::{Deserialize, Serialize};

use super::likelihood::WindowEvidence;
use super::physics::{generalised_force, generalised_inertia, JointDynamics, JointKind};
use super::{c, JointParams, JointType, Real};

/// Priors and integration settings of dynamic mode (`model.dynamics` section of the config).
/// Medians per joint type are `[prismatic, revolute]`, in the joint's units (N·s/m or N·m·s/rad,
/// N or N·m, N/m or N·m/rad).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct DynamicsConfig {
    pub damping_median: [f64; 2],
    pub damping_log_sd: f64,
    pub friction_median: [f64; 2],
    pub friction_log_sd: f64,
    /// Mass of a part \[kg\].
    pub mass_median_kg: f64,
    pub mass_log_sd: f64,
    /// Deviation of the coordinates from the simulated trajectory [m of centre-of-mass path].
    pub deviation_median_m: f64,
    pub deviation_log_sd: f64,
    /// Declared springs: stiffness, and the prior sd of the rest position around the window's
    /// start [m of path].
    pub spring_median: [f64; 2],
    pub spring_log_sd: f64,
    pub spring_rest_sd_m: f64,
    /// Velocity scale of the smoothed Coulomb friction (m/s or rad/s).
    pub friction_velocity: f64,
    /// Integration step of the simulation \[s\].
    pub step_s: f64,
}

impl Default for DynamicsConfig {
    fn default() -> Self {
        DynamicsConfig {
            damping_median: [10.0, 1.0],
            damping_log_sd: 1.5,
            friction_median: [2.0, 1.0],
            friction_log_sd: 1.5,
            mass_median_kg: 1.0,
            mass_log_sd: 1.5,
            deviation_median_m: 0.005,
            deviation_log_sd: 1.0,
            spring_median: [10.0, 1.0],
            spring_log_sd: 1.5,
            spring_rest_sd_m: 0.3,
            friction_velocity: 0.01,
            step_s: 0.005,
        }
    }
}

/// Index of a movable joint type in the `[prismatic, revolute]` medians.
fn kind_index(joint: JointType) -> usize {
    if joint == JointType::Revolute { 1 } else { 0 }
}

/// Number of standardised kinodynamic parameters of a movable joint: damping, friction, mass,
/// deviation, and stiffness and rest with a declared spring.
pub fn num_params(spring: bool) -> usize {
    if spring { 6 } else { 4 }
}

/// Decoded kinodynamic parameters (joint units; `rest` in metres of path).
#[derive(Debug, Clone, Copy)]
pub struct KinoParams<T: Real> {
    pub damping: T,
    pub friction: T,
    pub mass: T,
    pub deviation: T,
    pub stiffness: T,
    pub rest: T,
}

/// Decode standardised `xi` (length [`num_params`]) for a movable `joint`.
pub fn decode<T: Real>(joint: JointType, xi: &[T], cfg: &DynamicsConfig) -> KinoParams<T> {
    let k = kind_index(joint);
    let ln = |x: T, median: f64, sd: f64| (x * sd).exp() * median;
    let (stiffness, rest) = if xi.len() >= 6 {
        (ln(xi[4], cfg.spring_median[k], cfg.spring_log_sd), xi[5] * cfg.spring_rest_sd_m)
    } else {
        (c(0.0), c(0.0))
    };
    KinoParams {
        damping: ln(xi[0], cfg.damping_median[k], cfg.damping_log_sd),
        friction: ln(xi[1], cfg.friction_median[k], cfg.friction_log_sd),
        mass: ln(xi[2], cfg.mass_median_kg, cfg.mass_log_sd),
        deviation: ln(xi[3], cfg.deviation_median_m, cfg.deviation_log_sd),
        stiffness,
        rest,
    }
}

/// Median, sd and 90% interval of a log-normal parameter `median * exp(sd_log * xi)` with
/// `xi ~ N(m, s^2)`.
pub fn log_normal_summary(median: f64, sd_log: f64, m: f64, s: f64) -> (f64, f64, f64, f64) {
    let (mu, sigma) = (median.ln() + sd_log * m, sd_log * s);
    let med = mu.exp();
    let sd = ((sigma * sigma).exp() - 1.0).max(0.0).sqrt() * (mu + sigma * sigma / 2.0).exp();
    (med, sd, (mu - 1.644_853_6 * sigma).exp(), (mu + 1.644_853_6 * sigma).exp())
}

/// Medians and log-sds of damping, friction, mass (in this order) for `joint`.
pub fn prior_scales(joint: JointType, cfg: &DynamicsConfig) -> [(f64, f64); 3] {
    let k = kind_index(joint);
    [
        (cfg.damping_median[k], cfg.damping_log_sd),
        (cfg.friction_median[k], cfg.friction_log_sd),
        (cfg.mass_median_kg, cfg.mass_log_sd),
    ]
}

/// A rigid body of a joint's (locked) subtree at the window's start: mass \[kg\], centre of mass
/// \[m\] and inertia per kilogram about it (m²), fixed frame.
#[derive(Debug, Clone, Copy)]
pub struct SubtreeBody {
    pub mass: f64,
    pub com: Vector3<f64>,
    pub unit_inertia: Matrix3<f64>,
}

/// One joint in one window, as the physics sees it (fixed frame, at the window's start).
#[derive(Debug, Clone)]
pub struct JointInWindow<'a> {
    /// The joint, its geometry moved by the parent's displacement at the window's start.
    pub joint: &'a JointParams<f64>,
    /// The child part at the window's start: centre of mass and inertia per kilogram.
    pub com: Vector3<f64>,
    pub unit_inertia: Matrix3<f64>,
    /// The other bodies of the joint's subtree (locked).
    pub subtree: Vec<SubtreeBody>,
    /// Whether the wrench of this window acts on the joint's subtree.
    pub pushed: bool,
}

/// Dual number for the physics prior: up to 6 kinodynamic parameters and `q_{w,0}`.
type D = DualSVec64<7>;
/// Dual slot of the window's starting coordinate.
const Q0_SLOT: usize = 6;

/// The physics prior of one joint in one window and its gradient: returns
/// `(sum_t log N(q_t; Psi_t, sigma_d^2), d/d xi_kd, d/d q_t)` over the window's frames after its
/// first, where `q[t]` are the joint's coordinates on the evidence grid [m of path] and `xi` its
/// standardised kinodynamic parameters. `d/d q_t` has one entry per frame of the window (the first
/// is the derivative with respect to `q_{w,0}` through the simulation).
pub fn window_prior(jw: &JointInWindow<'_>, win: &WindowEvidence, q: &[f64], xi: &[f64], cfg: &DynamicsConfig) -> (f64, Vec<f64>, Vec<f64>) {
    let p = jw.joint;
    let nk = xi.len();
    let xd: Vec<D> = xi.iter().enumerate().map(|(j, &x)| D::from_re(x).derivative(j)).collect();
    let kp = decode(p.joint, &xd, cfg);
    let frames = &win.frames;
    let q0 = D::from_re(q[frames[0]]).derivative(Q0_SLOT);
    // Joint coordinate of the physics: the angle for a revolute joint (path / radius), metres for
    // a prismatic one.
    let (kind, scale) = match p.joint {
        JointType::Revolute => (JointKind::Revolute, p.radius),
        _ => (JointKind::Prismatic, 1.0),
    };
    let last = win.frame_substep[frames.len() - 1];
    let simulated = jw.pushed || kp.stiffness.re > 0.0;
    let traj: Vec<D> = if simulated {
        let mut bodies = vec![(kp.mass, jw.com.map(D::from), jw.unit_inertia.map(D::from))];
        bodies.extend(jw.subtree.iter().map(|b| (D::from(b.mass), b.com.map(D::from), b.unit_inertia.map(D::from))));
        let inertia = generalised_inertia(kind, &p.direction.map(D::from), &p.point.map(D::from), &bodies);
        let tau: Vec<f64> = (0..last)
            .map(|n| if jw.pushed { generalised_force(kind, &p.direction, &p.point, &win.point[n], &win.force[n], &win.torque[n]) } else { 0.0 })
            .collect();
        let jd = JointDynamics { inertia, damping: kp.damping, friction: kp.friction, stiffness: kp.stiffness * (scale * scale), rest: kp.rest / scale };
        let mut traj = vec![q0 / scale];
        traj.extend(jd.simulate(q0 / scale, D::from(0.0), &tau, win.h, cfg.friction_velocity));
        traj
    } else {
        // No force on the subtree and no spring: the joint stays where it is.
        Vec::new()
    };
    let var = kp.deviation * kp.deviation;
    let norm = num_dual::DualNum::ln(&(var * (2.0 * std::f64::consts::PI))) * 0.5;
    let mut ll = D::from(0.0);
    let mut gq = vec![0.0; frames.len()];
    for (k, &t) in frames.iter().enumerate().skip(1) {
        let psi = if simulated { traj[win.frame_substep[k]] * scale } else { q0 };
        let d = D::from(q[t]) - psi;
        let term = -(d * d) / (var * 2.0) - norm;
        ll += term;
        // Direct derivative with respect to q_t (the dual part carries d/d q_{w,0} via psi).
        gq[k] = -d.re / var.re;
    }
    let eps = ll.eps.unwrap_generic(nalgebra::Const::<7>, nalgebra::U1);
    let gx: Vec<f64> = (0..nk).map(|j| eps[j]).collect();
    gq[0] += eps[Q0_SLOT];
    (ll.re, gx, gq)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::likelihood::WindowEvidence;

    /// A pushed door's coordinates: the prior prefers the damping and friction that produced
    /// them, and its dual-number gradient matches finite differences.
    #[test]
    fn physics_prior_finds_the_parameters_and_its_gradient_is_right() {
        let cfg = DynamicsConfig::default();
        let joint = JointParams {
            joint: JointType::Revolute,
            com: Vector3::new(0.3, 0.0, 0.9),
            noise: 0.005,
            rot_noise: 0.02,
            direction: Vector3::z(),
            point: Vector3::new(0.0, 0.0, 0.9),
            radius: 0.3,
        };
        let unit_inertia = Matrix3::from_diagonal(&Vector3::new(0.01, 0.01, 0.02));
        let jw = JointInWindow { joint: &joint, com: joint.com, unit_inertia, subtree: vec![], pushed: true };
        // 2 s at 30 Hz, evidence every 5th frame; a 6 N push at the door's edge for 0.8 s.
        let h = cfg.step_s;
        let n = (2.0 / h) as usize;
        let win = WindowEvidence {
            frames: (0..13).collect(),
            frame_substep: (0..13).map(|k| ((k as f64 * 5.0 / 30.0) / h).round() as usize).collect(),
            pushed: Some(0),
            h,
            force: (0..n).map(|i| if (i as f64) * h < 0.8 { Vector3::new(0.0, 6.0, 0.0) } else { Vector3::zeros() }).collect(),
            torque: vec![Vector3::zeros(); n],
            point: vec![Vector3::new(0.5, 0.0, 0.9); n],
        };
        // Coordinates simulated with b = 1.5, mu = 0.8, m = 0.5 (and no deviation).
        let truth = [(1.5f64 / 1.0).ln() / 1.5, (0.8f64 / 1.0).ln() / 1.5, (0.5f64).ln() / 1.5];
        let inertia = generalised_inertia(JointKind::Revolute, &joint.direction, &joint.point, &[(0.5, joint.com, unit_inertia)]);
        let tau: Vec<f64> = (0..n).map(|i| if (i as f64) * h < 0.8 { 6.0 * 0.5 } else { 0.0 }).collect();
        let jd = JointDynamics { inertia, damping: 1.5, friction: 0.8, stiffness: 0.0, rest: 0.0 };
        let mut sim = vec![0.0];
        sim.extend(jd.simulate(0.0, 0.0, &tau, h, cfg.friction_velocity));
        let q: Vec<f64> = win.frame_substep.iter().map(|&s| sim[s] * 0.3).collect();
        assert!(q[12] > 0.1, "the door turned: {q:?}");
        let at = |b: f64, mu: f64| window_prior(&jw, &win, &q, &[b, mu, truth[2], -1.0], &cfg).0;
        let best = at(truth[0], truth[1]);
        for (db, dm) in [(0.3, 0.0), (-0.3, 0.0), (0.0, 0.3), (0.0, -0.3)] {
            assert!(at(truth[0] + db, truth[1] + dm) < best - 1.0, "({db}, {dm})");
        }
        // Gradient against central finite differences, away from the optimum.
        let xi = [0.2, -0.3, 0.1, -0.5];
        let (_, gx, gq) = window_prior(&jw, &win, &q, &xi, &cfg);
        let e = 1e-6;
        for j in 0..4 {
            let (mut a, mut b) = (xi, xi);
            a[j] += e;
            b[j] -= e;
            let fd = (window_prior(&jw, &win, &q, &a, &cfg).0 - window_prior(&jw, &win, &q, &b, &cfg).0) / (2.0 * e);
            assert!((fd - gx[j]).abs() < 1e-4 * (1.0 + fd.abs()), "xi[{j}]: fd {fd} vs dual {}", gx[j]);
        }
        for t in [0, 4, 12] {
            let (mut a, mut b) = (q.clone(), q.clone());
            a[t] += e;
            b[t] -= e;
            let fd = (window_prior(&jw, &win, &a, &xi, &cfg).0 - window_prior(&jw, &win, &b, &xi, &cfg).0) / (2.0 * e);
            assert!((fd - gq[t]).abs() < 1e-4 * (1.0 + fd.abs()), "q[{t}]: fd {fd} vs dual {}", gq[t]);
        }
        let (m, sd, lo, hi) = log_normal_summary(2.0, 0.5, 0.0, 0.0);
        assert!((m - 2.0).abs() < 1e-12 && sd == 0.0 && lo == hi);
    }
}
