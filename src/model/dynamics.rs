//! Dynamic mode: the kinodynamic parameters of a joint and the physics prior that ties its
//! coordinates to the measured wrench (paper §3.3: the physics engine Ψ evolves the object state
//! under the applied forces; §3.2: standard-normal priors on the kinodynamic parameters).
//!
//! **Parameters** of a movable joint, standardised `xi ~ N(0, I)` and mapped log-normally:
//! damping `b`, Coulomb friction `mu`, the mass `m` of the child part (its inertia is `m` times the
//! inertia per kilogram of its observed hull, [`crate::perception::PartGeometry`]), the deviation
//! scale `sigma_d` of the coordinates from the simulated trajectory, and then the parameters of the
//! joint's effects ([`crate::model::effects`]: declared by the bag or added by model criticism;
//! spring, joint stops, gravity, quadratic damping). Medians and log-sds are in
//! [`DynamicsConfig`].
//!
//! **Physics prior** (our form of eq. 2's trajectory model): in every interaction window `w` the
//! joint starts at rest at its coordinate `q_{w,0}` and Ψ simulates it under the measured wrench
//! with [`JointDynamics`] (the joint's subtree locked, its parent static during the window); the
//! coordinates at the window's grid frames deviate from the simulated trajectory as
//! `q_t ~ N(Psi_t, sigma_d^2)`, taken Student-t with `deviation_nu` degrees of freedom. The paper
//! adds noise to the observations only; the deviation term keeps what the physics lacks (soft
//! contact, the robot's compliance, an effect not modelled) from bending the kinematic fit — the
//! axis is still fitted to the observations through `q_t`, and the physics to `q_t`; as
//! `sigma_d -> 0` it is the paper's deterministic simulation. The heavy tails are for the same
//! misses: a frame the physics cannot explain, or a guide sample of the parameters that sends the
//! simulation far off (a mass much too small), costs a logarithm of its distance instead of its
//! square, so that it neither dominates the ELBO's gradient nor drags the coordinates after it.
//!
//! Gradients with respect to the kinodynamic parameters and `q_{w,0}` come from dual numbers
//! through the simulation; the joint's geometry enters the simulation as sampled constants (the
//! axis is pinned by the observations, whose likelihood carries its gradient).

use nalgebra::{Matrix3, Vector3};
use num_dual::DualSVec64;
use serde::{Deserialize, Serialize};

use super::likelihood::WindowEvidence;
use super::physics::{FrictionLaw, generalised_inertia, JointDynamics, JointKind, JointLimit};
use super::effects::{EffectSet, EffectsConfig};
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
    /// Student-t degrees of freedom of that deviation (0 or infinite: Gaussian). Heavy tails keep
    /// a few frames the physics cannot explain (a latch's contact, a sampled mass far too small)
    /// from dominating the fit and its gradient.
    pub deviation_nu: f64,
    /// Student-t degrees of freedom of a resting joint's deviation (rest frames before and after
    /// a window, and between the windows of one recording; 0: Gaussian, the default). With
    /// `deviation_nu` here, one frame in which a joint the model says rests moves anyway (a door
    /// falling shut under a gravity the base model lacks) costs logarithmically, as every other
    /// deviation does; Gaussian, it costs `d^2 / 2 sigma_d^2` without bound. Measured on `tune`
    /// and left off: README "Generalization", stop 86.
    pub rest_nu: f64,
    /// Model discrepancy of the reported damping, friction and mass: a log-sd added in quadrature
    /// to the posterior's (0: none). The physics engine is not the world — here MuJoCo's soft
    /// constraints against our regularised Coulomb law and locked subtrees — so the parameters
    /// the world acts with are taken as the fitted ones times `exp(delta)`, `delta ~ N(0, s^2)`,
    /// a discrepancy the data cannot identify (Kennedy & O'Hagan, JRSS B 63(3), 2001); its
    /// marginal widens each log-normal interval and moves no median. See [`log_normal_summary`].
    pub discrepancy_log_sd: f64,
    /// Prior probability that a window's physics does not hold for a joint (0: every window's
    /// does): the wrench was attributed to the wrong part (the nearest visible points belong to
    /// another part when the pushed one is hidden), the contact slipped, or the push acted through
    /// a joint the locked subtree does not have. Such a window's coordinates follow the kinematic
    /// random walk instead ([`robust_window_prior`]).
    pub window_outlier_prob: f64,
    /// Priors of the effects beyond damping and friction ([`EffectsConfig`]).
    pub effects: EffectsConfig,
    /// Regularisation of the Coulomb friction: a joint's velocity scale is
    /// `min(mu t_f / I, v_max)` ([`crate::model::physics`], module docs).
    pub friction_law: FrictionLaw,
    /// Integration step of the simulation \[s\].
    pub step_s: f64,
    /// Collapsed fits (observed coordinates, [`Observed`]): start each window's simulation at
    /// the coordinate that best explains all of the window's observed frames
    /// ([`fitted_window_start`]) instead of at its first frame's observation (false). A window's
    /// first observed coordinate is one noisy frame, and the whole simulated trajectory is
    /// offset by its error. Measured and left off: README "Generalization", stop 94 (it helps
    /// the reported kinodynamics on `tune` and `validation`, and turned a shipped bag's gravity
    /// finding into a spring).
    pub fit_window_start: bool,
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
            deviation_nu: 4.0,
            rest_nu: 0.0,
            discrepancy_log_sd: 0.1,
            window_outlier_prob: 0.1,
            effects: EffectsConfig::default(),
            friction_law: FrictionLaw::default(),
            step_s: 0.005,
            fit_window_start: false,
        }
    }
}

/// Index of a movable joint type in the `[prismatic, revolute]` medians.
fn kind_index(joint: JointType) -> usize {
    if joint == JointType::Revolute { 1 } else { 0 }
}

/// Number of standardised kinodynamic parameters of a movable joint: damping, friction, mass,
/// deviation, then those of its effects ([`EffectSet::num_params`]).
pub fn num_params(effects: &EffectSet) -> usize {
    4 + effects.num_params()
}

/// Decoded kinodynamic parameters (joint units; positions in metres of path).
#[derive(Debug, Clone, Copy)]
pub struct KinoParams<T: Real> {
    pub damping: T,
    pub friction: T,
    pub mass: T,
    pub deviation: T,
    /// Spring stiffness (N/m or N·m/rad; 0 without one) and rest position [m of path].
    pub stiffness: T,
    pub rest: T,
    /// Joint stops: lower and upper positions [m of path] where present, and the contact
    /// stiffness (N/m or N·m/rad).
    pub limit: Option<(Option<T>, Option<T>, T)>,
    /// Quadratic damping coefficient (N·s²/m² or N·m·s²/rad²; 0 without it).
    pub quadratic_damping: T,
}

/// Decode standardised `xi` (length [`num_params`]) for a movable `joint` with `effects`; the
/// layout is the base four, then each effect's in [`EffectKind`](crate::model::effects::EffectKind) order.
pub fn decode<T: Real>(joint: JointType, xi: &[T], effects: &EffectSet, cfg: &DynamicsConfig) -> KinoParams<T> {
    let k = kind_index(joint);
    let e = &cfg.effects;
    let ln = |x: T, median: f64, sd: f64| (x * sd).exp() * median;
    let mut at = 4;
    let mut next = || {
        at += 1;
        xi[at - 1]
    };
    let (stiffness, rest) = if effects.spring {
        let (a, b) = (next(), next());
        (ln(a, e.spring_median[k], e.spring_log_sd), b * e.spring_rest_sd_m)
    } else {
        (c(0.0), c(0.0))
    };
    let limit = effects.limit.map(|l| {
        let lower = l.lower.map(|anchor| next() * e.limit_position_sd_m + anchor);
        let upper = l.upper.map(|anchor| next() * e.limit_position_sd_m + anchor);
        (lower, upper, ln(next(), e.limit_stiffness_median[k], e.limit_stiffness_log_sd))
    });
    let quadratic_damping = if effects.quadratic_damping { ln(next(), e.quadratic_damping_median[k], e.quadratic_damping_log_sd) } else { c(0.0) };
    KinoParams {
        damping: ln(xi[0], cfg.damping_median[k], cfg.damping_log_sd),
        friction: ln(xi[1], cfg.friction_median[k], cfg.friction_log_sd),
        mass: ln(xi[2], cfg.mass_median_kg, cfg.mass_log_sd),
        deviation: ln(xi[3], cfg.deviation_median_m, cfg.deviation_log_sd),
        stiffness,
        rest,
        limit,
        quadratic_damping,
    }
}

/// Median, sd and 90% interval of a log-normal parameter `median * exp(sd_log * xi + delta)`
/// with `xi ~ N(m, s^2)` and an independent model discrepancy `delta ~ N(0, discrepancy^2)`
/// ([`DynamicsConfig::discrepancy_log_sd`]; 0 for none).
pub fn log_normal_summary(median: f64, sd_log: f64, m: f64, s: f64, discrepancy: f64) -> (f64, f64, f64, f64) {
    let (mu, sigma) = (median.ln() + sd_log * m, (sd_log * s).hypot(discrepancy));
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
    /// Where its weight acts \[m\] (the gravity effect's; see [`JointInWindow::weight_com`]).
    pub weight_com: Vector3<f64>,
}

/// One joint in one window, as the physics sees it (fixed frame, at the window's start).
#[derive(Debug, Clone)]
pub struct JointInWindow<'a> {
    /// The joint, its geometry moved by the parent's displacement at the window's start.
    pub joint: &'a JointParams<f64>,
    /// The child part at the window's start: centre of mass and inertia per kilogram.
    pub com: Vector3<f64>,
    pub unit_inertia: Matrix3<f64>,
    /// Where the child's weight acts \[m\], fixed frame, at the window's start: the centre of
    /// its seen surface ([`crate::model::likelihood::PartSeries::weight_offset`]), which the
    /// gravity effect's moment uses in place of `com` (a thin panel's hull centroid can lie
    /// decimetres off the panel; README, issue 25, stop 117).
    pub weight_com: Vector3<f64>,
    /// The other bodies of the joint's subtree (locked).
    pub subtree: Vec<SubtreeBody>,
    /// Whether the wrench of this window acts on the joint's subtree.
    pub pushed: bool,
    /// The effects on the joint beyond damping and friction.
    pub effects: EffectSet,
}

/// The physics prior of one joint in one window and its gradient: returns
/// `(sum_t log p(q_t; Psi_t, sigma_d), d/d xi_kd, d/d q_t)` over the window's frames after its
/// first, where `q[t]` are the joint's coordinates on the evidence grid [m of path] and `xi` its
/// standardised kinodynamic parameters (layout of [`decode`] for `jw.effects`). `d/d q_t` has one
/// entry per frame of the window (the first is the derivative with respect to `q_{w,0}` through
/// the simulation). `p` is Student-t with `cfg.deviation_nu` degrees of freedom and scale
/// `sigma_d` (Gaussian when `deviation_nu` is 0).
///
/// With `observed`, `q` are the *observed* coordinates and the result is their likelihood with
/// the latent coordinates integrated out: `q_t ~ N(Psi_t, sigma_d^2)` and `y_t ~ N(q_t, r_t^2)`
/// give `y_t ~ N(Psi_t, sigma_d^2 + r_t^2)`, taken Student-t with `observed.nu` degrees of freedom
/// as positions are (eq. 2, with the perception's bursts), over the frames with `r_t^2 > 0`.
pub fn window_prior(jw: &JointInWindow<'_>, win: &WindowEvidence, q: &[f64], observed: Option<&Observed>, xi: &[f64], cfg: &DynamicsConfig) -> (f64, Vec<f64>, Vec<f64>) {
    let (l, gx, gq, _) = window_prior_split(jw, win, q, observed, xi, cfg, None);
    (l, gx, gq)
}

/// [`window_prior`] and, fourth, its value over the frames not flagged in `skip` (see
/// [`robust_window_prior_collapsed`]).
pub fn window_prior_split(jw: &JointInWindow<'_>, win: &WindowEvidence, q: &[f64], observed: Option<&Observed>, xi: &[f64], cfg: &DynamicsConfig, skip: Option<&[bool]>) -> (f64, Vec<f64>, Vec<f64>, f64) {
    // Dual numbers as wide as the parameters plus `q_{w,0}`: the base model's 4 + 1 are the
    // common case and the cheapest; every extra slot costs a multiply in every operation.
    match xi.len() {
        0..=4 => window_prior_n::<5>(jw, win, q, observed, xi, cfg, skip),
        5..=6 => window_prior_n::<7>(jw, win, q, observed, xi, cfg, skip),
        // Criticism's candidates: a stop on both sides (7), with a second effect (8, 9).
        7 => window_prior_n::<8>(jw, win, q, observed, xi, cfg, skip),
        8 => window_prior_n::<9>(jw, win, q, observed, xi, cfg, skip),
        9 => window_prior_n::<10>(jw, win, q, observed, xi, cfg, skip),
        10 => window_prior_n::<11>(jw, win, q, observed, xi, cfg, skip),
        n => panic!("{n} kinodynamic parameters: at most 10 (4 base, 6 of effects)"),
    }
}

/// The physics prior of one window made robust at the window's scale: with probability
/// `1 - cfg.window_outlier_prob` the coordinates follow [`window_prior`], otherwise the physics
/// does not hold in this window and they follow a Gaussian random walk, increments
/// `q_k - q_{k-1} ~ N(0, (v dt_k)^2)` with `v = velocity_sd_mps` (kinematic mode's velocity scale,
/// [`crate::model::ModelConfig::velocity_sd_mps`]) plus, with `observed`, both frames'
/// observation variances. Returns the log of the mixture and its gradients (as
/// [`window_prior`]'s), and the posterior probability that the physics holds in the window.
///
/// Why: the Student-t deviations bound what one *frame* the physics cannot explain costs, but a
/// whole window it cannot explain — a lid pushed while hidden behind a drawer front, so that the
/// wrench went to the drawer — cost the true joint type a deviation in every frame of it, and a
/// moving drawer came out rigid with P = 1.00 where kinematic mode called it prismatic (corpus
/// objects 60 and 75 of the tune split). A window is the unit in which the physics' assumptions
/// fail together (one contact, one attribution), so it is the unit of the outlier model, as a
/// frame is for the positions' Student-t (a two-component mixture, e.g. Gelman et al., *Bayesian
/// Data Analysis*, 3rd ed., §17.2). Where the physics fits, it is more probable by about
/// `log(v dt / sigma_d)` per frame than the random walk, so its windows stay physics.
#[allow(clippy::too_many_arguments)]
pub fn robust_window_prior(
    jw: &JointInWindow<'_>,
    win: &WindowEvidence,
    q: &[f64],
    observed: Option<&Observed>,
    xi: &[f64],
    cfg: &DynamicsConfig,
    velocity_sd_mps: f64,
) -> (f64, Vec<f64>, Vec<f64>, f64) {
    let (l, gx, gq, r, _) = robust_window_prior_collapsed(jw, win, q, observed, xi, cfg, velocity_sd_mps, None);
    (l, gx, gq, r)
}

/// [`robust_window_prior`] and, as its fifth value, the same log density with the coordinates of
/// the window frames flagged in `skip` (one flag per grid frame; `None`: none) integrated out:
/// the physics holds in the window with the kept frames' Student-t terms, and the random walk
/// joins the kept frames with the skipped frames' increments summed (a sum of Gaussian increments
/// is Gaussian with their variances summed). Both are exact where a skipped frame is a leaf of the
/// physics prior's graph: the window's last frame only when the rest frames after it and a next
/// window that continues it are integrated out too (the caller's duty), and its first (every
/// other frame's simulation starts there) only with the whole window, which then contributes 0;
/// the first frame flagged alone is kept. The gradients are those of the full density.
///
/// Why: a frame in which the part (and every part it carries) is unseen informs its coordinate
/// only through this prior; the exact marginal over that coordinate is 1 under any joint type,
/// while a mean-field guide pays `KL(q(q_t) || p(q_t | rest))` for it — a cost that only movable
/// types carry and that grows with the unseen frames (README, "Generalization", stop 81).
#[allow(clippy::too_many_arguments)]
pub fn robust_window_prior_collapsed(
    jw: &JointInWindow<'_>,
    win: &WindowEvidence,
    q: &[f64],
    observed: Option<&Observed>,
    xi: &[f64],
    cfg: &DynamicsConfig,
    velocity_sd_mps: f64,
    skip: Option<&[bool]>,
) -> (f64, Vec<f64>, Vec<f64>, f64, f64) {
    let (lp, gxp, gqp, lp_kept) = window_prior_split(jw, win, q, observed, xi, cfg, skip);
    robust_mix(win, q, observed, cfg, velocity_sd_mps, skip, (lp, gxp, gqp, lp_kept))
}

/// The window-robust mixture of [`robust_window_prior_collapsed`] from the physics prior's
/// `(value, gradient in the parameters, gradient per window frame, value over the kept frames)`,
/// whatever parameters the gradient is over.
#[allow(clippy::too_many_arguments)]
pub fn robust_mix(
    win: &WindowEvidence,
    q: &[f64],
    observed: Option<&Observed>,
    cfg: &DynamicsConfig,
    velocity_sd_mps: f64,
    skip: Option<&[bool]>,
    physics: (f64, Vec<f64>, Vec<f64>, f64),
) -> (f64, Vec<f64>, Vec<f64>, f64, f64) {
    let (lp, gxp, gqp, lp_kept) = physics;
    let eps = cfg.window_outlier_prob;
    if eps <= 0.0 || win.frames.len() < 2 {
        return (lp, gxp, gqp, 1.0, lp_kept);
    }
    let (lw, gqw, lw_kept) = window_random_walk(win, q, observed, velocity_sd_mps, skip);
    let mix = |lp: f64, lw: f64| {
        let (a, b) = ((1.0 - eps).ln() + lp, eps.ln() + lw);
        let m = a.max(b);
        let l = m + ((a - m).exp() + (b - m).exp()).ln();
        (l, (a - l).exp())
    };
    let (l, r) = mix(lp, lw);
    let (l_kept, _) = mix(lp_kept, lw_kept);
    let gx = gxp.iter().map(|g| r * g).collect();
    let gq = gqp.iter().zip(&gqw).map(|(p, w)| r * p + (1.0 - r) * w).collect();
    (l, gx, gq, r, l_kept)
}

/// Whether grid frame `t` is flagged in `skip`. Only frames after a window's first carry terms of
/// its prior, so a flagged first frame changes nothing here (a whole window flagged has no term left).
fn skipped(skip: Option<&[bool]>, t: usize) -> bool {
    skip.is_some_and(|s| s.get(t).copied().unwrap_or(false))
}

/// Log density of a window's coordinates after its first under a Gaussian random walk of
/// velocity scale `v` \[m/s\] (see [`robust_window_prior`]) and its gradient per window frame;
/// third, the density of the frames not flagged in `skip` (the flagged frames' increments summed
/// into the next kept frame's: [`robust_window_prior_collapsed`]).
fn window_random_walk(win: &WindowEvidence, q: &[f64], observed: Option<&Observed>, v: f64, skip: Option<&[bool]>) -> (f64, Vec<f64>, f64) {
    let frames = &win.frames;
    let n = frames.len();
    let mut gq = vec![0.0; n];
    let mut l = 0.0;
    let (mut l_kept, mut last_kept, mut walk_var) = (0.0, 0usize, 0.0);
    let term = |d: f64, var: f64| -d * d / (2.0 * var) - 0.5 * (2.0 * std::f64::consts::PI * var).ln();
    for k in 1..n {
        let (a, b) = (frames[k - 1], frames[k]);
        let dt = ((win.frame_substep[k] as f64 - win.frame_substep[k - 1] as f64) * win.h).max(win.h);
        let r2 = observed.map_or(0.0, |o| o.var[a] + o.var[b]);
        let var = (v * dt).powi(2) + r2;
        let d = q[b] - q[a];
        l += term(d, var);
        gq[k] -= d / var;
        gq[k - 1] += d / var;
        walk_var += (v * dt).powi(2);
        if skip.is_some() && !skipped(skip, b) {
            let a = frames[last_kept];
            let r2 = observed.map_or(0.0, |o| o.var[a] + o.var[b]);
            l_kept += term(q[b] - q[a], walk_var + r2);
            (last_kept, walk_var) = (k, 0.0);
        }
    }
    // Nothing skipped: every increment kept as it is.
    (l, gq, if skip.is_some() { l_kept } else { l })
}

/// The simulated trajectory of one joint in one window, in metres of path at every integration
/// step (the first entry is `q0`), or `None` when nothing moves it (not pushed, no spring, no
/// gravity). `kp` are the decoded parameters (of any scalar type).
pub fn simulate_window<T: Real>(jw: &JointInWindow<'_>, win: &WindowEvidence, q0: T, kp: &KinoParams<T>, cfg: &DynamicsConfig) -> Option<Vec<T>> {
    simulate_joint(jw, win, q0, T::from(0.0), kp, cfg)
}

/// [`simulate_window`] from a moving start: the joint at `q0` \[m of path\] with velocity `v0`
/// \[m of path / s\] at the window's first step (the posterior predictive of
/// [`crate::prediction`] starts mid-push; the model's windows start at rest).
pub fn simulate_joint<T: Real>(jw: &JointInWindow<'_>, win: &WindowEvidence, q0: T, v0: T, kp: &KinoParams<T>, cfg: &DynamicsConfig) -> Option<Vec<T>> {
    let scale = if jw.joint.joint == JointType::Revolute { jw.joint.radius } else { 1.0 };
    simulate_scaled(jw, &WindowGeometry::lifted(jw), scale, win, q0, v0, kp, cfg, false)
}

/// The geometry of one joint in one window as the physics sees it (fixed frame, at the window's
/// start), in any scalar type: [`JointInWindow`]'s, or with the derivatives of the joint's own
/// kinematic parameters (dual numbers seeded on them, [`crate::model::density`]), so that one
/// simulation gives the physics prior's gradient in the axis and centre of mass too.
#[derive(Debug, Clone)]
pub struct WindowGeometry<T: Real> {
    /// Unit axis direction and a point on the axis \[m\].
    pub direction: Vector3<T>,
    pub point: Vector3<T>,
    /// A revolute joint's radius (path per radian) \[m\]; unused for a prismatic one.
    pub radius: T,
    /// The child's centre of mass \[m\] and inertia per kilogram \[m²\].
    pub com: Vector3<T>,
    pub unit_inertia: Matrix3<T>,
    /// The locked subtree's bodies.
    pub subtree: Vec<LiftedBody<T>>,
    /// Where the child's weight acts \[m\] (the gravity effect's; [`JointInWindow::weight_com`]).
    pub weight_com: Vector3<T>,
}

/// A locked subtree body of [`WindowGeometry`]: mass \[kg\], centre of mass \[m\], inertia per
/// kilogram \[m²\] and where its weight acts \[m\] ([`SubtreeBody`] in the scalar type).
pub type LiftedBody<T> = (T, Vector3<T>, Matrix3<T>, Vector3<T>);

impl<T: Real> WindowGeometry<T> {
    /// `jw`'s geometry as constants of the scalar type.
    pub fn lifted(jw: &JointInWindow<'_>) -> Self {
        let p = jw.joint;
        WindowGeometry {
            direction: p.direction.map(T::from),
            point: p.point.map(T::from),
            radius: T::from(p.radius),
            com: jw.com.map(T::from),
            unit_inertia: jw.unit_inertia.map(T::from),
            subtree: jw.subtree.iter().map(|b| (T::from(b.mass), b.com.map(T::from), b.unit_inertia.map(T::from), b.weight_com.map(T::from))).collect(),
            weight_com: jw.weight_com.map(T::from),
        }
    }
}

/// [`simulate_joint`] with the geometry `geom` in place of `jw`'s (whose joint type, push and
/// effects it still uses), the radius's derivatives carried.
pub fn simulate_joint_in<T: Real>(jw: &JointInWindow<'_>, geom: &WindowGeometry<T>, win: &WindowEvidence, q0: T, v0: T, kp: &KinoParams<T>, cfg: &DynamicsConfig) -> Option<Vec<T>> {
    if jw.joint.joint == JointType::Revolute {
        simulate_scaled(jw, geom, Radius(geom.radius), win, q0, v0, kp, cfg, true)
    } else {
        simulate_scaled(jw, geom, 1.0, win, q0, v0, kp, cfg, true)
    }
}

/// Metres of path per unit of the physics' joint coordinate: a revolute joint's radius (per
/// radian), 1 for a prismatic joint. A constant (`f64`) where it carries no derivatives, so that
/// the dual numbers of [`simulate_joint`] divide by a constant, as they always did (to the last bit).
trait PathScale<T: Real>: Copy {
    /// Path \[m\] to the joint coordinate.
    fn to_joint(self, x: T) -> T;
    /// The joint coordinate to path \[m\].
    fn to_path(self, x: T) -> T;
}

impl<T: Real> PathScale<T> for f64 {
    fn to_joint(self, x: T) -> T {
        x / self
    }
    fn to_path(self, x: T) -> T {
        x * self
    }
}

/// A radius of the scalar type (with derivatives).
#[derive(Clone, Copy)]
struct Radius<T>(T);

impl<T: Real> PathScale<T> for Radius<T> {
    fn to_joint(self, x: T) -> T {
        x / self.0
    }
    fn to_path(self, x: T) -> T {
        x * self.0
    }
}

/// [`simulate_joint`] and [`simulate_joint_in`]: `geom`'s joint, the path-to-coordinate `scale`;
/// `axis_derivatives` when the axis carries derivatives (the substep forces then by
/// [`super::physics::generalised_forces_of`], else by the per-substep form as always).
#[allow(clippy::too_many_arguments)]
fn simulate_scaled<T: Real>(
    jw: &JointInWindow<'_>,
    geom: &WindowGeometry<T>,
    scale: impl PathScale<T>,
    win: &WindowEvidence,
    q0: T,
    v0: T,
    kp: &KinoParams<T>,
    cfg: &DynamicsConfig,
    axis_derivatives: bool,
) -> Option<Vec<T>> {
    // Joint coordinate of the physics: the angle for a revolute joint (path / radius), metres for
    // a prismatic one.
    let kind = if jw.joint.joint == JointType::Revolute { JointKind::Revolute } else { JointKind::Prismatic };
    let last = win.frame_substep[win.frames.len() - 1];
    let simulated = jw.pushed || kp.stiffness.re() > 0.0 || jw.effects.gravity || v0.re() != 0.0;
    if !simulated {
        return None;
    }
    // `generalised_inertia` takes each body's inertia about its centre of mass in kg·m²; the
    // geometry holds it per kilogram (perception's hull model), so it scales with the body's mass
    // (unscaled, every revolute part had a floor of one kilogram's rotational inertia).
    let mut bodies = vec![(kp.mass, geom.com, geom.unit_inertia.map(|u| u * kp.mass))];
    bodies.extend(geom.subtree.iter().map(|&(m, com, unit, _)| (m, com, unit.map(|u| u * m))));
    let (d, point) = (&geom.direction, &geom.point);
    let inertia = generalised_inertia(kind, d, point, &bodies);
    let tau: Vec<T> = if !jw.pushed {
        vec![T::from(0.0); last]
    } else if axis_derivatives {
        super::physics::generalised_forces_of(kind, d, point, &win.point[..last], &win.force[..last], &win.torque[..last])
    } else {
        // A constant axis (SVI, prediction, criticism): the force as it always was, to the last
        // bit (SVI's fits amplify rounding: README, stop 110).
        (0..last).map(|n| super::physics::generalised_force_of(kind, d, point, &win.point[n], &win.force[n], &win.torque[n])).collect()
    };
    let mut jd = JointDynamics::new(inertia, kp.damping, kp.friction, kp.stiffness, scale.to_joint(kp.rest));
    if let Some((lower, upper, stiffness)) = kp.limit {
        let stop = |position: T, upper: bool| JointLimit { position: scale.to_joint(position), stiffness, upper, width: scale.to_joint(T::from(cfg.effects.limit_width_m)) };
        jd.limits = [lower.map(|p| stop(p, false)), upper.map(|p| stop(p, true))];
    }
    jd.quadratic_damping = kp.quadratic_damping;
    if jw.effects.gravity {
        let g = Vector3::from(cfg.effects.gravity).map(T::from);
        jd.gravity_at = scale.to_joint(q0);
        // The weight acts at each body's weight centre, not at the hull centroid the inertia uses.
        let weights = std::iter::once((kp.mass, &geom.weight_com)).chain(geom.subtree.iter().map(|b| (b.0, &b.3)));
        for (m, com) in weights {
            match kind {
                JointKind::Revolute => {
                    // The weight's moment turns with the joint: r(a) = R(d, a) r_perp + r_par.
                    let r = com - point;
                    let perp = r - d * r.dot(d);
                    jd.gravity[1] += m * d.dot(&perp.cross(&g));
                    jd.gravity[2] += m * d.dot(&d.cross(&perp).cross(&g));
                }
                _ => jd.gravity[0] += m * d.dot(&g),
            }
        }
    }
    let mut traj = vec![q0];
    traj.extend(jd.simulate(scale.to_joint(q0), scale.to_joint(v0), &tau, win.h, cfg.friction_law).into_iter().map(|x| scale.to_path(x)));
    Some(traj)
}

/// `Psi_k`, the simulation `traj` (`None`: nothing moves the joint) at frame `k` of `win`, started
/// at `q0`: `q0` at the window's first frame and wherever nothing moves the joint.
pub(crate) fn psi_at<T: Real>(traj: Option<&Vec<T>>, win: &WindowEvidence, k: usize, q0: T) -> T {
    if k == 0 {
        q0
    } else {
        traj.map_or(q0, |tr| tr[win.frame_substep[k]])
    }
}

/// `Psi_k` at every frame of `win` \[m of path\], simulated in `f64`
/// ([`crate::model::density::NonCentred`]'s forward differences).
pub fn window_psi(jw: &JointInWindow<'_>, win: &WindowEvidence, q0: f64, xi: &[f64], cfg: &DynamicsConfig) -> Vec<f64> {
    let kp = decode(jw.joint.joint, xi, &jw.effects, cfg);
    let traj = simulate_window(jw, win, q0, &kp, cfg);
    (0..win.frames.len()).map(|k| psi_at(traj.as_ref(), win, k, q0)).collect()
}

/// Observed joint coordinates' variances for [`window_prior`].
#[derive(Debug, Clone)]
pub struct Observed {
    /// Observation variance per grid frame \[m²\] (0: not observed; the latent coordinate is used).
    pub var: Vec<f64>,
    /// Student-t degrees of freedom (0 or infinite: Gaussian).
    pub nu: f64,
}

/// `d/dd log p(d)` of a one-dimensional Student-t with scale² `var` and `nu` degrees of freedom
/// (Gaussian when `nu` is 0 or infinite).
pub(crate) fn student_score(d: f64, var: f64, nu: f64) -> f64 {
    if nu.is_finite() && nu > 0.0 {
        -(nu + 1.0) * d / (nu * var + d * d)
    } else {
        -d / var
    }
}

#[allow(clippy::too_many_arguments)]
fn window_prior_n<const N: usize>(
    jw: &JointInWindow<'_>,
    win: &WindowEvidence,
    q: &[f64],
    observed: Option<&Observed>,
    xi: &[f64],
    cfg: &DynamicsConfig,
    skip: Option<&[bool]>,
) -> (f64, Vec<f64>, Vec<f64>, f64) {
    type D<const N: usize> = DualSVec64<N>;
    let nk = xi.len();
    let q0_slot = N - 1;
    let xd: Vec<D<N>> = xi.iter().enumerate().map(|(j, &x)| D::<N>::from_re(x).derivative(j)).collect();
    let kp = decode(jw.joint.joint, &xd, &jw.effects, cfg);
    let y0 = D::<N>::from_re(q[win.frames[0]]).derivative(q0_slot);
    let traj = simulate_window(jw, win, y0, &kp, cfg);
    let (traj, q0, start) = match fitted(observed, cfg) {
        Some(o) => {
            let re: Option<Vec<f64>> = traj.as_ref().map(|t| t.iter().map(|v| v.re).collect());
            let start = fitted_start(win, q, o, re.as_ref(), (kp.deviation * kp.deviation).re);
            (shifted(traj, y0, start), D::<N>::from_re(start), Some(start))
        }
        None => (traj, y0, None),
    };
    let (mut ll, mut gq, skipped_value) = window_terms(traj, win, q, observed, &kp, q0, cfg, skip);
    if let (Some(o), Some(start)) = (observed, start) {
        // The first frame's own observation; its derivative through the fitted start is 0 at the
        // optimum (envelope theorem), so the direct one is all.
        let (y0, r2) = first_observation(win, q, o);
        ll += first_frame_term(y0, r2, o.nu, q0);
        gq[0] += if r2 > 0.0 { student_score(y0 - start, r2, o.nu) } else { 0.0 };
    }
    let eps = ll.eps.unwrap_generic(nalgebra::Const::<N>, nalgebra::U1);
    let gx: Vec<f64> = (0..nk).map(|j| eps[j]).collect();
    gq[0] += eps[q0_slot];
    (ll.re, gx, gq, ll.re - skipped_value)
}

/// The value of [`window_prior`] alone, simulated in `f64`: what a finite difference of the
/// physics prior needs (the kinematic parameters' derivatives in [`crate::model::density`]), at
/// a fraction of the dual numbers' cost. Equal to `window_prior(..).0`.
pub fn window_prior_value(jw: &JointInWindow<'_>, win: &WindowEvidence, q: &[f64], observed: Option<&Observed>, xi: &[f64], cfg: &DynamicsConfig) -> f64 {
    let kp = decode::<f64>(jw.joint.joint, xi, &jw.effects, cfg);
    let y0 = q[win.frames[0]];
    let traj = simulate_window(jw, win, y0, &kp, cfg);
    match fitted(observed, cfg) {
        Some(o) => {
            let start = fitted_start(win, q, o, traj.as_ref(), kp.deviation * kp.deviation);
            let (y0_obs, r2) = first_observation(win, q, o);
            window_terms(shifted(traj, y0, start), win, q, observed, &kp, start, cfg, None).0 + first_frame_term(y0_obs, r2, o.nu, start)
        }
        None => window_terms(traj, win, q, observed, &kp, y0, cfg, None).0,
    }
}

/// The observed coordinates when the window's start is fitted to them
/// ([`DynamicsConfig::fit_window_start`]).
fn fitted<'o>(observed: Option<&'o Observed>, cfg: &DynamicsConfig) -> Option<&'o Observed> {
    observed.filter(|_| cfg.fit_window_start)
}

/// The trajectory simulated from `y0`, moved to start at `start`: the simulated displacement
/// `Psi_k - y0` applied from the fitted start.
fn shifted<T: Real>(traj: Option<Vec<T>>, y0: T, start: f64) -> Option<Vec<T>> {
    traj.map(|t| t.into_iter().map(|v| v - y0 + start).collect())
}

/// The first frame's own observation term once the start `q0` is fitted: its latent coordinate
/// is the start, observed with variance `r2` (`y_0 ~ t_nu(q0, r_0^2)`); 0 where it is not
/// observed (`r2` 0).
fn first_frame_term<T: Real>(y0: f64, r2: f64, nu: f64, q0: T) -> T {
    if r2 > 0.0 {
        let d = T::from(y0) - q0;
        super::likelihood::log_student(d * d / r2, T::from(0.5 * r2.ln()), 1, nu)
    } else {
        T::from(0.0)
    }
}

/// The window's first observed coordinate and its variance (0: not observed).
fn first_observation(win: &WindowEvidence, q: &[f64], observed: &Observed) -> (f64, f64) {
    let t0 = win.frames[0];
    (q[t0], observed.var.get(t0).copied().unwrap_or(0.0))
}

/// Where a window's simulation starts once fitted to its observed frames \[m of path\]:
/// [`fitted_start`] of the displacement simulated from the first frame's observation at
/// standardised parameters `xi`.
///
/// With [`DynamicsConfig::fit_window_start`] (off by default: README "Generalization", stop 94)
/// the collapsed physics prior of a window (observed coordinates `y`, [`Observed`]) is
/// `y_0 ~ t_nu(q0, r_0^2)` and `y_k ~ t_nu(q0 + delta_k, sigma_d^2 + r_k^2)` with the start `q0`
/// at its maximum, where
/// `delta_k = Psi_k - y_0` is the displacement simulated from the first observation. `delta` does
/// not depend on where the simulation starts for the base model (damping, friction and inertia act
/// on the velocity; the wrench's moment about a fixed axis does not turn with the joint); with a
/// spring, stop or gravity it is taken from the first observation, millimetres away. The start is
/// a maximiser of exactly this objective, so its gradient in the parameters needs no term for the
/// start (envelope theorem).
///
/// Why: started at the first frame's observation, a 2-5 mm error in that one frame offsets every
/// simulated frame of the window — for the corpus's pushes of 2-4 cm (scaled to 8% of a joint's
/// range) a tenth of the travel, which the collapsed fit of the reported kinodynamics absorbs into
/// damping and friction. Criticism's predictions take the median of the first three frames for
/// the same reason ([`crate::criticism`]). README "Generalization", stop 94.
pub fn fitted_window_start(jw: &JointInWindow<'_>, win: &WindowEvidence, q: &[f64], observed: &Observed, xi: &[f64], cfg: &DynamicsConfig) -> f64 {
    let y0 = q[win.frames[0]];
    let kp = decode::<f64>(jw.joint.joint, xi, &jw.effects, cfg);
    let traj = simulate_window(jw, win, y0, &kp, cfg);
    fitted_start(win, q, observed, traj.as_ref(), kp.deviation * kp.deviation)
}

/// The Student-t location `q0` of `y_0` (variance `r_0^2`) and of `y_k - delta_k` (variance
/// `dev2 + r_k^2`), `delta_k` the displacement of `traj` (simulated from `y_0`; `None`: nothing
/// moves the joint) at frame `k`, by iteratively reweighted least squares (Lange, Little & Taylor,
/// JASA 84, 1989), converged to 1e-13 m. Frames not observed (`r_k^2` 0) do not count; with none
/// observed, `y_0`.
fn fitted_start(win: &WindowEvidence, q: &[f64], observed: &Observed, traj: Option<&Vec<f64>>, dev2: f64) -> f64 {
    let y0 = q[win.frames[0]];
    let obs: Vec<(f64, f64)> = win
        .frames
        .iter()
        .enumerate()
        .filter_map(|(k, &t)| {
            let r2 = observed.var.get(t).copied().unwrap_or(0.0);
            if !(r2 > 0.0) || !q[t].is_finite() {
                return None;
            }
            let delta = psi_at(traj, win, k, y0) - y0;
            Some((q[t] - delta, if k == 0 { r2 } else { dev2 + r2 }))
        })
        .collect();
    if obs.is_empty() {
        return y0;
    }
    let nu = observed.nu;
    let mut q0 = y0;
    for _ in 0..200 {
        let (mut num, mut den) = (0.0, 0.0);
        for &(z, var) in &obs {
            let d = z - q0;
            let w = if nu.is_finite() && nu > 0.0 { (nu + 1.0) / (nu * var + d * d) } else { 1.0 / var };
            num += w * z;
            den += w;
        }
        let next = num / den;
        let done = (next - q0).abs() < 1e-13;
        q0 = next;
        if done {
            break;
        }
    }
    q0
}

/// The value of [`robust_window_prior`] alone (see [`window_prior_value`]).
pub fn robust_window_prior_value(jw: &JointInWindow<'_>, win: &WindowEvidence, q: &[f64], observed: Option<&Observed>, xi: &[f64], cfg: &DynamicsConfig, velocity_sd_mps: f64) -> f64 {
    let lp = window_prior_value(jw, win, q, observed, xi, cfg);
    robust_mix(win, q, observed, cfg, velocity_sd_mps, None, (lp, vec![], vec![], lp)).0
}

/// The terms of [`window_prior`] for the simulated trajectory `traj` (`None`: nothing moves the
/// joint) at decoded kinodynamics `kp` and start `q0`, in any scalar type (dual numbers for the
/// gradient, `f64` for the value alone): the log density, its direct derivative with respect to
/// each window frame's coordinate (the first left 0: it enters through the simulation, the dual
/// part), and the share of the value of the frames flagged in `skip`.
#[allow(clippy::too_many_arguments)]
pub(crate) fn window_terms<T: Real>(
    traj: Option<Vec<T>>,
    win: &WindowEvidence,
    q: &[f64],
    observed: Option<&Observed>,
    kp: &KinoParams<T>,
    q0: T,
    cfg: &DynamicsConfig,
    skip: Option<&[bool]>,
) -> (T, Vec<f64>, f64) {
    // No force on the subtree, no spring, no gravity (`traj` None): the joint stays where it is.
    let psi: Vec<T> = (0..win.frames.len()).map(|k| psi_at(traj.as_ref(), win, k, q0)).collect();
    window_terms_at(&psi, win, q, observed, kp, cfg, skip)
}

/// [`window_terms`] for `Psi` given at the window's frames (`psi[k]` at `win.frames[k]`; `psi[0]`,
/// the start, is not scored): what [`crate::model::density::NonCentred`] hands the density from
/// the simulation its map already ran.
pub(crate) fn window_terms_at<T: Real>(
    psi: &[T],
    win: &WindowEvidence,
    q: &[f64],
    observed: Option<&Observed>,
    kp: &KinoParams<T>,
    cfg: &DynamicsConfig,
    skip: Option<&[bool]>,
) -> (T, Vec<f64>, f64) {
    let frames = &win.frames;
    let dev2 = kp.deviation * kp.deviation;
    let half_log_dev2 = dev2.ln() * 0.5;
    let mut ll = T::from(0.0);
    let mut gq = vec![0.0; frames.len()];
    // The skipped frames' share of the value (their terms are leaves: each integrates to 1).
    let mut skipped_value = 0.0;
    for (k, &t) in frames.iter().enumerate().skip(1) {
        let d = T::from(q[t]) - psi[k];
        let term = match observed.map(|o| (o.var[t], o.nu)) {
            Some((r2, obs_nu)) if r2 > 0.0 => {
                let var = dev2 + r2;
                gq[k] = student_score(d.re(), var.re(), obs_nu);
                super::likelihood::log_student(d * d / var, var.ln() * 0.5, 1, obs_nu)
            }
            _ => {
                // Direct derivative with respect to q_t (the dual part carries d/d q_{w,0} via psi).
                gq[k] = student_score(d.re(), dev2.re(), cfg.deviation_nu);
                super::likelihood::log_student(d * d / dev2, half_log_dev2, 1, cfg.deviation_nu)
            }
        };
        if skipped(skip, t) {
            skipped_value += term.re();
        }
        ll += term;
    }
    (ll, gq, skipped_value)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::likelihood::WindowEvidence;

    /// A door of radius 0.3 m on `direction` through (0, 0, 0.9).
    fn door(direction: Vector3<f64>) -> JointParams<f64> {
        JointParams {
            joint: JointType::Revolute,
            com: Vector3::new(0.3, 0.0, 0.9),
            noise: 0.005,
            rot_noise: 0.02,
            direction,
            point: Vector3::new(0.0, 0.0, 0.9),
            radius: 0.3,
        }
    }

    /// 2 s at 30 Hz, evidence every 5th frame; a push of `force` N (along y) at the door's edge
    /// for 0.8 s.
    fn push_window(cfg: &DynamicsConfig, force: f64) -> WindowEvidence {
        let h = cfg.step_s;
        let n = (2.0 / h) as usize;
        WindowEvidence {
            frames: (0..13).collect(),
            rest: vec![],
            rest_before: vec![],
            frame_substep: (0..13).map(|k| ((k as f64 * 5.0 / 30.0) / h).round() as usize).collect(),
            pushed: Some(0),
            continues: false,
            hand_off: false,
            h,
            force: (0..n).map(|i| if (i as f64) * h < 0.8 { Vector3::new(0.0, force, 0.0) } else { Vector3::zeros() }).collect(),
            torque: vec![Vector3::zeros(); n],
            point: vec![Vector3::new(0.5, 0.0, 0.9); n],
        }
    }

    /// The physics prior's dual-number gradient against central finite differences, in every
    /// parameter and in the coordinates of the first, middle and last frame.
    fn check_gradients(jw: &JointInWindow<'_>, win: &WindowEvidence, q: &[f64], xi: &[f64], cfg: &DynamicsConfig) {
        // Latent coordinates, and observed ones with their variance (Student-t, latent ones
        // integrated out), a few millimetres of perception noise.
        let var: Vec<f64> = (0..q.len()).map(|t| (0.002 + 0.001 * (t % 3) as f64).powi(2)).collect();
        for deviation_nu in [4.0, 0.0] {
            check_gradients_with(jw, win, q, None, xi, &DynamicsConfig { deviation_nu, ..cfg.clone() });
        }
        for nu in [4.0, 0.0] {
            check_gradients_with(jw, win, q, Some(&Observed { var: var.clone(), nu }), xi, cfg);
        }
    }

    fn check_gradients_with(jw: &JointInWindow<'_>, win: &WindowEvidence, q: &[f64], observed: Option<&Observed>, xi: &[f64], cfg: &DynamicsConfig) {
        let (_, gx, gq) = window_prior(jw, win, q, observed, xi, cfg);
        let e = 1e-6;
        let fd = |a: &[f64], b: &[f64], qa: &[f64], qb: &[f64]| (window_prior(jw, win, qa, observed, a, cfg).0 - window_prior(jw, win, qb, observed, b, cfg).0) / (2.0 * e);
        for j in 0..xi.len() {
            let (mut a, mut b) = (xi.to_vec(), xi.to_vec());
            a[j] += e;
            b[j] -= e;
            let d = fd(&a, &b, q, q);
            assert!((d - gx[j]).abs() < 1e-4 * (1.0 + d.abs()), "xi[{j}]: fd {d} vs dual {}", gx[j]);
        }
        let n = win.frames.len();
        for k in [0, n / 2, n - 1] {
            let t = win.frames[k];
            let (mut a, mut b) = (q.to_vec(), q.to_vec());
            a[t] += e;
            b[t] -= e;
            let d = fd(xi, xi, &a, &b);
            assert!((d - gq[k]).abs() < 1e-4 * (1.0 + d.abs()), "q[{t}]: fd {d} vs dual {}", gq[k]);
        }
    }

    /// [`push_window`] with 6 N on `joint` (a door of [`door`]'s radius 0.3 m) of 0.5 kg, damping
    /// 1.5 and friction 0.8, simulated without deviation: the window, the coordinates at its
    /// frames \[m of path\] and the standardised truth (damping, friction, mass).
    fn simulated_push(cfg: &DynamicsConfig, joint: &JointParams<f64>, unit_inertia: Matrix3<f64>) -> (WindowEvidence, Vec<f64>, [f64; 3]) {
        let win = push_window(cfg, 6.0);
        let (h, n) = (cfg.step_s, win.force.len());
        let truth = [(1.5f64 / 1.0).ln() / 1.5, (0.8f64 / 1.0).ln() / 1.5, (0.5f64).ln() / 1.5];
        let inertia = generalised_inertia(JointKind::Revolute, &joint.direction, &joint.point, &[(0.5, joint.com, unit_inertia * 0.5)]);
        let tau: Vec<f64> = (0..n).map(|i| if (i as f64) * h < 0.8 { 6.0 * 0.5 } else { 0.0 }).collect();
        let mut sim = vec![0.0];
        sim.extend(JointDynamics::new(inertia, 1.5, 0.8, 0.0, 0.0).simulate(0.0, 0.0, &tau, h, cfg.friction_law));
        let q = win.frame_substep.iter().map(|&s| sim[s] * 0.3).collect();
        (win, q, truth)
    }

    /// A revolute part's rotational inertia scales with its mass (`m (|r_perp|^2 + d^T J d)`,
    /// `J` per kilogram): the physics prior of a 0.5 kg door's push is highest at 0.5 kg, not at
    /// a lighter or a heavier door. Before stop 104 the hull's `J` entered unscaled, a floor of one
    /// kilogram's rotational inertia, and the mass that reproduces this push was about 0.39 kg.
    #[test]
    fn a_revolute_parts_inertia_scales_with_its_mass() {
        let cfg = DynamicsConfig::default();
        let joint = door(Vector3::z());
        let unit_inertia = Matrix3::from_diagonal(&Vector3::new(0.01, 0.01, 0.02));
        let jw = JointInWindow { joint: &joint, com: joint.com, unit_inertia, weight_com: joint.com, subtree: vec![], pushed: true, effects: EffectSet::default() };
        let (win, q, truth) = simulated_push(&cfg, &joint, unit_inertia);
        let at = |dm: f64| window_prior(&jw, &win, &q, None, &[truth[0], truth[1], truth[2] + dm, -1.0], &cfg).0;
        let best = at(0.0);
        for dm in [0.15, -0.15] {
            println!("mass xi {dm:+}: {:.2} nats below the truth's", best - at(dm));
            assert!(at(dm) < best - 1.0, "mass xi {dm:+}: {} against {best} at the truth", at(dm));
        }
    }

    /// A pushed door's coordinates: the prior prefers the damping and friction that produced
    /// them, and its dual-number gradient matches finite differences.
    #[test]
    fn physics_prior_finds_the_parameters_and_its_gradient_is_right() {
        let cfg = DynamicsConfig::default();
        let joint = door(Vector3::z());
        let unit_inertia = Matrix3::from_diagonal(&Vector3::new(0.01, 0.01, 0.02));
        let jw = JointInWindow { joint: &joint, com: joint.com, unit_inertia, weight_com: joint.com, subtree: vec![], pushed: true, effects: EffectSet::default() };
        let (win, q, truth) = simulated_push(&cfg, &joint, unit_inertia);
        assert!(q[12] > 0.1, "the door turned: {q:?}");
        let at = |b: f64, mu: f64| window_prior(&jw, &win, &q, None, &[b, mu, truth[2], -1.0], &cfg).0;
        let best = at(truth[0], truth[1]);
        for (db, dm) in [(0.3, 0.0), (-0.3, 0.0), (0.0, 0.3), (0.0, -0.3)] {
            assert!(at(truth[0] + db, truth[1] + dm) < best - 1.0, "({db}, {dm})");
        }
        // Gradient against central finite differences, away from the optimum.
        check_gradients(&jw, &win, &q, &[0.2, -0.3, 0.1, -0.5], &cfg);
        let (m, sd, lo, hi) = log_normal_summary(2.0, 0.5, 0.0, 0.0, 0.0);
        assert!((m - 2.0).abs() < 1e-12 && sd == 0.0 && lo == hi);
        // The discrepancy adds in quadrature on the log scale and keeps the median.
        let (m, _, lo, hi) = log_normal_summary(2.0, 0.5, 0.1, 0.3, 0.2);
        let (m0, _, lo0, hi0) = log_normal_summary(2.0, 0.5, 0.1, 0.3, 0.0);
        assert_eq!(m, m0);
        let half = |l: f64, h: f64| (h.ln() - l.ln()) / (2.0 * 1.644_853_6);
        assert!((half(lo0, hi0) - 0.15).abs() < 1e-12 && (half(lo, hi) - 0.25).abs() < 1e-12, "{lo} {hi}");
    }

    /// With observed coordinates and `fit_window_start`, a first frame observed 4 mm off does not
    /// move the window's start (it lands within a millimetre of the truth, where the first frame
    /// alone put it 4 mm off), the prior still prefers the parameters that produced the push, and
    /// its gradient matches finite differences (the start is a maximiser: envelope theorem).
    #[test]
    fn a_fitted_window_start_is_not_offset_by_the_first_frame() {
        let cfg = DynamicsConfig { fit_window_start: true, ..DynamicsConfig::default() };
        let joint = door(Vector3::z());
        let unit_inertia = Matrix3::from_diagonal(&Vector3::new(0.01, 0.01, 0.02));
        let jw = JointInWindow { joint: &joint, com: joint.com, unit_inertia, weight_com: joint.com, subtree: vec![], pushed: true, effects: EffectSet::default() };
        let (win, mut q, truth) = simulated_push(&cfg, &joint, unit_inertia);
        q[0] += 0.004;
        let var: Vec<f64> = (0..q.len()).map(|t| (0.002 + 0.001 * (t % 3) as f64).powi(2)).collect();
        let xi = [truth[0], truth[1], truth[2], -1.0];
        for nu in [4.0, 0.0] {
            let observed = Observed { var: var.clone(), nu };
            let start = fitted_window_start(&jw, &win, &q, &observed, &xi, &cfg);
            assert!(start.abs() < 1e-3, "nu {nu}: start {start} (first frame {})", q[0]);
            let at = |b: f64, mu: f64| window_prior(&jw, &win, &q, Some(&observed), &[b, mu, truth[2], -1.0], &cfg).0;
            let best = at(truth[0], truth[1]);
            for (db, dm) in [(0.3, 0.0), (-0.3, 0.0), (0.0, 0.3), (0.0, -0.3)] {
                assert!(at(truth[0] + db, truth[1] + dm) < best - 1.0, "nu {nu}: ({db}, {dm})");
            }
            assert!((window_prior_value(&jw, &win, &q, Some(&observed), &xi, &cfg) - best).abs() < 1e-9);
            check_gradients_with(&jw, &win, &q, Some(&observed), &[0.2, -0.3, 0.1, -0.5], &cfg);
        }
    }

    /// With every effect on (spring, both stops, gravity on a tilted hinge, quadratic damping) the
    /// physics prior's dual-number gradient still matches finite differences, in every parameter
    /// and in the coordinates; and so with 6 to 9 parameters, each of which has dual numbers of
    /// its own width ([`window_prior_split`]).
    #[test]
    fn physics_prior_gradient_with_every_effect_matches_finite_differences() {
        let cfg = DynamicsConfig::default();
        let joint = door(Vector3::new(0.3, 0.0, 1.0).normalize());
        let stops = Some(crate::model::effects::LimitSpec { lower: Some(-0.05), upper: Some(0.12) });
        let every = EffectSet { spring: true, limit: stops, gravity: true, quadratic_damping: true };
        let sets = [
            (every, 10),
            (EffectSet { spring: true, ..Default::default() }, 6),
            (EffectSet { limit: stops, gravity: true, ..Default::default() }, 7),
            (EffectSet { limit: stops, quadratic_damping: true, ..Default::default() }, 8),
            (EffectSet { spring: true, limit: stops, ..Default::default() }, 9),
        ];
        for (effects, n) in sets {
            let unit_inertia = Matrix3::from_diagonal(&Vector3::new(0.01, 0.01, 0.02));
            let jw = JointInWindow { joint: &joint, com: joint.com, unit_inertia, weight_com: joint.com, subtree: vec![], pushed: true, effects };
            let win = push_window(&cfg, 8.0);
            let q: Vec<f64> = (0..13).map(|k| 0.01 * k as f64).collect();
            let xi: Vec<f64> = (0..num_params(&effects)).map(|j| 0.1 * ((j as f64) * 1.7).sin()).collect();
            assert_eq!(xi.len(), n);
            check_gradients(&jw, &win, &q, &xi, &cfg);
        }
    }

    /// The value-only path ([`window_prior_value`], [`robust_window_prior_value`], simulated in
    /// `f64`) gives the dual-number path's value, with every effect on, with and without observed
    /// coordinates: the finite differences of the density rest on the two agreeing.
    #[test]
    fn value_only_physics_prior_equals_the_dual_value() {
        let cfg = DynamicsConfig::default();
        let joint = door(Vector3::new(0.3, 0.0, 1.0).normalize());
        let unit_inertia = Matrix3::from_diagonal(&Vector3::new(0.01, 0.01, 0.02));
        for effects in [
            EffectSet::default(),
            EffectSet {
                spring: true,
                limit: Some(crate::model::effects::LimitSpec { lower: Some(-0.05), upper: Some(0.12) }),
                gravity: true,
                quadratic_damping: true,
            },
        ] {
            let jw = JointInWindow { joint: &joint, com: joint.com, unit_inertia, weight_com: joint.com, subtree: vec![], pushed: true, effects };
            let win = push_window(&cfg, 8.0);
            let q: Vec<f64> = (0..13).map(|k| 0.01 * k as f64 + 0.002 * ((k as f64) * 2.3).sin()).collect();
            let xi: Vec<f64> = (0..num_params(&effects)).map(|j| 0.1 * ((j as f64) * 1.7).sin()).collect();
            let observed = Observed { var: (0..13).map(|k| if k % 3 == 0 { 0.0 } else { 1e-6 }).collect(), nu: 4.0 };
            for obs in [None, Some(&observed)] {
                let dual = window_prior(&jw, &win, &q, obs, &xi, &cfg).0;
                let value = window_prior_value(&jw, &win, &q, obs, &xi, &cfg);
                assert!((dual - value).abs() <= 1e-12 * (1.0 + dual.abs()), "{dual} vs {value}");
                let dual = robust_window_prior(&jw, &win, &q, obs, &xi, &cfg, 0.2).0;
                let value = robust_window_prior_value(&jw, &win, &q, obs, &xi, &cfg, 0.2);
                assert!((dual - value).abs() <= 1e-12 * (1.0 + dual.abs()), "robust: {dual} vs {value}");
            }
        }
    }

    /// The window-robust prior: a window the physics explains stays physics (responsibility near
    /// 1, value within `log(1 - eps)` of the physics prior's), a door that turned the other way
    /// than the push is an outlier window (responsibility near 0, bounded cost), and the
    /// mixture's gradient matches finite differences in both regimes and in between.
    #[test]
    fn robust_window_prior_separates_windows_the_physics_cannot_explain() {
        let cfg = DynamicsConfig::default();
        let joint = door(Vector3::z());
        let unit_inertia = Matrix3::from_diagonal(&Vector3::new(0.01, 0.01, 0.02));
        let jw = JointInWindow { joint: &joint, com: joint.com, unit_inertia, weight_com: joint.com, subtree: vec![], pushed: true, effects: EffectSet::default() };
        let (win, q, truth) = simulated_push(&cfg, &joint, unit_inertia);
        let xi = [truth[0], truth[1], truth[2], -1.0];
        let v = crate::model::ModelConfig::default().velocity_sd_mps;
        let (l, _, _, r) = robust_window_prior(&jw, &win, &q, None, &xi, &cfg, v);
        let (lp, _, _) = window_prior(&jw, &win, &q, None, &xi, &cfg);
        assert!(r > 0.99, "physics explains the window: responsibility {r}");
        assert!((l - lp - (1.0 - cfg.window_outlier_prob).ln()).abs() < 0.05, "{l} vs {lp}");
        // The same motion against the push: the physics cannot explain it.
        let back: Vec<f64> = q.iter().map(|x| -x).collect();
        let (l, _, _, r) = robust_window_prior(&jw, &win, &back, None, &xi, &cfg, v);
        let (lp, _, _) = window_prior(&jw, &win, &back, None, &xi, &cfg);
        assert!(r < 0.01 && l > lp + 10.0, "an outlier window: responsibility {r}, {l} vs physics {lp}");
        // Off: the physics prior itself.
        let off = DynamicsConfig { window_outlier_prob: 0.0, ..cfg.clone() };
        assert_eq!(robust_window_prior(&jw, &win, &back, None, &xi, &off, v).0, lp);
        // Gradients: physics, outlier, and a window half way (the deviation scale chosen so).
        let e = 1e-6;
        for (qq, dev) in [(&q, -1.0), (&back, -1.0), (&back, 2.6)] {
            let x = [xi[0], xi[1], xi[2], dev];
            let (_, gx, gq, r) = robust_window_prior(&jw, &win, qq, None, &x, &cfg, v);
            let f = |a: &[f64], qa: &[f64]| robust_window_prior(&jw, &win, qa, None, a, &cfg, v).0;
            for j in 0..4 {
                let (mut a, mut b) = (x, x);
                a[j] += e;
                b[j] -= e;
                let d = (f(&a, qq) - f(&b, qq)) / (2.0 * e);
                assert!((d - gx[j]).abs() < 1e-4 * (1.0 + d.abs()), "r {r:.3} xi[{j}]: fd {d} vs {}", gx[j]);
            }
            for k in [0, 6, 12] {
                let (mut a, mut b) = (qq.clone(), qq.clone());
                a[k] += e;
                b[k] -= e;
                let d = (f(&x, &a) - f(&x, &b)) / (2.0 * e);
                assert!((d - gq[k]).abs() < 1e-4 * (1.0 + d.abs()), "r {r:.3} q[{k}]: fd {d} vs {}", gq[k]);
            }
        }
    }

    /// Frames integrated out of the window-robust prior: its collapsed value is the log of the
    /// full density integrated over the skipped coordinates (numerically, over a wide fine grid),
    /// for one frame through the physics-or-random-walk mixture in both regimes, and for two
    /// adjacent frames of the random walk alone (their increments merged); the window's first
    /// frame only with the whole window (which then integrates to 1).
    #[test]
    fn collapsed_window_prior_is_the_marginal_over_the_skipped_frames() {
        let cfg = DynamicsConfig::default();
        let joint = door(Vector3::z());
        let unit_inertia = Matrix3::from_diagonal(&Vector3::new(0.01, 0.01, 0.02));
        let jw = JointInWindow { joint: &joint, com: joint.com, unit_inertia, weight_com: joint.com, subtree: vec![], pushed: true, effects: EffectSet::default() };
        let (win, q, truth) = simulated_push(&cfg, &joint, unit_inertia);
        let v = crate::model::ModelConfig::default().velocity_sd_mps;
        // The deviation scale where both components matter (sd 6.7 cm against a walk's 8.3 cm).
        let xi = [truth[0], truth[1], truth[2], 2.6];
        let k = 6;
        let t = win.frames[k];
        let mut skip = vec![false; q.len()];
        skip[t] = true;
        let log_integral = |f: &dyn Fn(&[f64]) -> f64, at: &[f64], t: usize| {
            let (h, half) = (0.001, 1500);
            let vals: Vec<f64> = (-half..=half)
                .map(|j| {
                    let mut x = at.to_vec();
                    x[t] = at[t] + j as f64 * h;
                    f(&x)
                })
                .collect();
            let m = vals.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
            m + (vals.iter().map(|v| (v - m).exp()).sum::<f64>() * h).ln()
        };
        let back: Vec<f64> = q.iter().map(|x| -x).collect();
        for qq in [&q, &back] {
            let (l, _, _, r, kept) = robust_window_prior_collapsed(&jw, &win, qq, None, &xi, &cfg, v, Some(&skip));
            assert_eq!(l, robust_window_prior(&jw, &win, qq, None, &xi, &cfg, v).0);
            let full = |x: &[f64]| robust_window_prior(&jw, &win, x, None, &xi, &cfg, v).0;
            let marginal = log_integral(&full, qq, t);
            assert!((kept - marginal).abs() < 1e-3, "responsibility {r:.3}: collapsed {kept} vs integral {marginal}");
            assert!((kept - l).abs() > 0.1, "the skipped frame carried some of the value: {kept} vs {l}");
        }
        // The last frame (a leaf once nothing hangs from it) integrates out the same way.
        let last = *win.frames.last().unwrap();
        let mut end = vec![false; q.len()];
        end[last] = true;
        let (_, _, _, _, kept) = robust_window_prior_collapsed(&jw, &win, &q, None, &xi, &cfg, v, Some(&end));
        let full = |x: &[f64]| robust_window_prior(&jw, &win, x, None, &xi, &cfg, v).0;
        let marginal = log_integral(&full, &q, last);
        assert!((kept - marginal).abs() < 1e-3, "last frame: collapsed {kept} vs integral {marginal}");
        // The first frame alone is kept; the whole window flagged integrates to 1.
        let mut first = vec![false; q.len()];
        first[win.frames[0]] = true;
        let (l, _, _, _, kept) = robust_window_prior_collapsed(&jw, &win, &q, None, &xi, &cfg, v, Some(&first));
        assert_eq!(l, kept);
        let all = vec![true; q.len()];
        let (_, _, _, _, kept) = robust_window_prior_collapsed(&jw, &win, &q, None, &xi, &cfg, v, Some(&all));
        assert!(kept.abs() < 1e-12, "a window integrated out whole: {kept}");
        // Two adjacent frames of the random walk: merged increments against a 2-D integral.
        let mut two = vec![false; q.len()];
        let (ta, tb) = (win.frames[5], win.frames[6]);
        two[ta] = true;
        two[tb] = true;
        let (lw, _, kept) = window_random_walk(&win, &q, None, v, Some(&two));
        let (h, half) = (0.004, 150);
        let mut vals = Vec::new();
        for a in -half..=half {
            for b in -half..=half {
                let mut x = q.clone();
                x[ta] += a as f64 * h;
                x[tb] += b as f64 * h;
                vals.push(window_random_walk(&win, &x, None, v, None).0);
            }
        }
        let m = vals.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        let marginal = m + (vals.iter().map(|v| (v - m).exp()).sum::<f64>() * h * h).ln();
        assert!((kept - marginal).abs() < 1e-3, "walk: collapsed {kept} vs integral {marginal} (full {lw})");
    }
}
