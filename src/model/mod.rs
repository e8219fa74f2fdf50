//! Model stage: the generative model of a Bayesian object model (paper, section 3), kinematic
//! variant.
//!
//! The latent variables are the tree `G` over the fixed frame (node 0) and the parts ([`tree`]),
//! a joint type per part ([`JointType`], paper §3.2), standardised continuous parameters per part
//! and joint type with `N(0, I)` priors (paper §3.2: reference centre of mass, noise level, screw
//! axis; [`rigid`], [`prismatic`], [`revolute`], one joint kind per file), and per-frame joint
//! coordinates with a random-walk smoothness prior ([`likelihood::coordinate_prior`]). The
//! physics engine Ψ of the paper is replaced by kinematics — a chain of screw displacements —
//! since no forces are known in kinematic mode; observations are part centres of mass with the
//! Gaussian likelihood of eq. 2 ([`likelihood`]).
//!
//! Every function that inference differentiates is generic over the scalar [`Real`], so the same
//! code runs on `f64` and on `num-dual` dual numbers (tests check the gradients against finite
//! differences).

pub mod density;
pub mod dynamics;
pub mod effects;
pub mod likelihood;
pub mod physics;
pub mod prismatic;
pub mod revolute;
pub mod rigid;
pub mod tree;

use nalgebra::{Matrix3, Vector3};
use num_dual::DualNum;
use serde::{Deserialize, Serialize};

/// The scalar of model code: `f64` or a dual number over `f64`.
pub trait Real: DualNum<Primitive = f64> + nalgebra::Scalar + Copy {}
impl<T: DualNum<Primitive = f64> + nalgebra::Scalar + Copy> Real for T {}

/// Lift an `f64` into the scalar type.
#[inline]
pub fn c<T: Real>(x: f64) -> T {
    T::from(x)
}

/// Joint types of the paper (URDF `fixed` = `rigid`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum JointType {
    Rigid,
    Prismatic,
    Revolute,
}

impl JointType {
    pub const ALL: [JointType; 3] = [JointType::Rigid, JointType::Prismatic, JointType::Revolute];

    pub fn index(self) -> usize {
        self as usize
    }

    pub fn name(self) -> &'static str {
        match self {
            JointType::Rigid => "rigid",
            JointType::Prismatic => "prismatic",
            JointType::Revolute => "revolute",
        }
    }

    /// Parse a contract or URDF name (`fixed` maps to `rigid`).
    pub fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "rigid" | "fixed" => JointType::Rigid,
            "prismatic" => JointType::Prismatic,
            "revolute" | "continuous" => JointType::Revolute,
            _ => return None,
        })
    }

    /// Number of standardised global parameters of this joint type (the layout is documented in
    /// each joint's file; the first five are always the reference centre of mass and the noises).
    pub fn num_params(self) -> usize {
        match self {
            JointType::Rigid => rigid::NUM_PARAMS,
            JointType::Prismatic => prismatic::NUM_PARAMS,
            JointType::Revolute => revolute::NUM_PARAMS,
        }
    }

    /// Whether the joint has a per-frame coordinate.
    pub fn movable(self) -> bool {
        self != JointType::Rigid
    }
}

/// Prior scales of the kinematic model (`model` section of the config). Standardised parameters
/// are `N(0, 1)`; these scales map them to physical units.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct ModelConfig {
    /// Prior sd of the reference centre of mass around its perceived value \[m\].
    pub com_sd_m: f64,
    /// Median of the log-normal prior on the observation noise sigma \[m\].
    pub noise_median_m: f64,
    /// Log-sd of that prior.
    pub noise_log_sd: f64,
    /// Degrees of freedom of the Student-t observation noise (0: Gaussian, the paper's eq. 2).
    pub student_nu: f64,
    /// Dynamic mode: the sd \[m\] of the robot's contact point as an observation of the material
    /// point of the pushed part that it touches ([`likelihood::ContactObs`]; 0: not observed).
    /// Default 0.005, the noise prior's median (not tuned). On since stop 98, when each push's
    /// material point came to be placed by perception's poses while the part is still at rest
    /// (their median; [`likelihood::ContactObs`]): on the corpus's `tune` split it then gains
    /// joint types, parents and the layouts' agreement over the three seeds at a cost in IdE
    /// (README "Generalization", stop 98); with stop 95's one-frame anchor it lost calls there.
    pub contact_sd_m: f64,
    /// Dynamic mode: whether the contact point is Gaussian along the push and Student-t across it
    /// ([`likelihood::log_likelihood_contact`]); false: Student-t in every direction, like a
    /// centre of mass. Why: a hand may slip along the surface it pushes, but it cannot move
    /// into that surface unless the surface moves with it, so its displacement along the force
    /// is no outlier. Perception, in contrast, can miss a part's motion along directions its
    /// visible surface leaves loose (a drawer's sides and bottom slide along themselves).
    pub contact_firm: bool,
    /// Median and log-sd of the log-normal prior on the rotation noise \[rad\].
    pub rotation_noise_median_rad: f64,
    pub rotation_noise_log_sd: f64,
    /// Prior sd of a revolute axis point around the part's reference centre of mass \[m\].
    pub axis_point_sd_m: f64,
    /// Model discrepancy of a reported axis direction \[deg\]: the sd, per direction across the
    /// axis, of an isotropic tilt added to the posterior's spread (0: none). Perception is not the
    /// world — a panel's registered track bends by millimetres, its errors come in bursts — so a
    /// direction fitted to more frames does not converge on the true one; the discrepancy is
    /// what more data cannot remove (Kennedy & O'Hagan, JRSS B 63(3), 2001; as
    /// `dynamics.discrepancy_log_sd` for the kinodynamics). It widens `direction_sd_deg` and the
    /// 90% cone in quadrature ([`crate::inference::AxisSummary::with_discrepancy`]) and moves no
    /// estimate or joint type. 1.6, chosen on the corpus's `tune` objects (README
    /// "Generalization", stop 77).
    pub axis_discrepancy_deg: f64,
    /// Model discrepancy of a reported revolute axis point \[m\]: the sd, per direction across
    /// the axis, of an isotropic displacement added to the posterior's spread of the point (0:
    /// none). The hinge line fitted to a panel's registered track misses the true one by 1-5 cm
    /// where the posterior allows millimetres, and by no less after a turn of 1.2 rad than of
    /// 0.3 (a panel's registration can slide in its own plane, which only its outline pins), so
    /// the term is a length, not a position error divided by the turn. It widens `point_sd_m` in
    /// quadrature ([`crate::inference::AxisSummary::with_discrepancy`]) and moves no estimate or
    /// joint type. 0.0225, chosen on the corpus's `tune` objects (README "Generalization", stop
    /// 78).
    pub axis_point_discrepancy_m: f64,
    /// Median and log-sd of the log-normal prior on the velocity scale of the random-walk prior
    /// on joint coordinates (kinematic mode) [m/s of centre-of-mass path].
    pub velocity_sd_mps: f64,
    pub velocity_log_sd: f64,
    /// Prior sd of the joint coordinate at a window start that no continuity ties to an earlier
    /// frame (the first frame, a new episode; kinematic mode: every window) when the joint may be
    /// anywhere \[m\] (the broad component of [`likelihood::window_start_prior`]).
    pub window_start_sd_m: f64,
    /// Prior probability that the joint is at its reference configuration at such a start: the
    /// object was reset between episodes, or the start is the first frame (0 is the part's first
    /// observation by construction). 0: the broad component alone.
    pub window_reset_prob: f64,
    /// Spread of the joint coordinate around the reference configuration at a reset start \[m\].
    pub window_reset_sd_m: f64,
    /// Minimum effective radius of a revolute joint, so `angle = path / radius` stays finite \[m\].
    pub min_radius_m: f64,
    /// How far beyond the part's own extent a revolute axis may pass before its prior falls, and
    /// the scale of that fall \[m\] ([`revolute::reach_prior`]); 0: off.
    pub hinge_reach_m: f64,
    /// Prior probabilities of rigid, prismatic, revolute.
    pub type_prior: [f64; 3],
    /// Contact prior on trees ([`tree`]): the contact area the fixed frame counts as, and the
    /// least weight of a part \[m²\].
    pub contact_world_m2: f64,
    pub contact_min_m2: f64,
    /// Dynamic mode (wrenches recorded): kinodynamic priors and integration.
    pub dynamics: dynamics::DynamicsConfig,
}

impl Default for ModelConfig {
    fn default() -> Self {
        ModelConfig {
            com_sd_m: 0.02,
            noise_median_m: 0.005,
            noise_log_sd: 1.0,
            student_nu: 4.0,
            contact_sd_m: 0.005,
            contact_firm: false,
            rotation_noise_median_rad: 0.02,
            rotation_noise_log_sd: 1.0,
            axis_point_sd_m: 0.2,
            axis_discrepancy_deg: 1.6,
            axis_point_discrepancy_m: 0.0225,
            velocity_sd_mps: 0.5,
            velocity_log_sd: 1.5,
            window_start_sd_m: 1.0,
            window_reset_prob: 0.0,
            window_reset_sd_m: 0.01,
            min_radius_m: 0.02,
            hinge_reach_m: 0.05,
            type_prior: [1.0 / 3.0; 3],
            contact_world_m2: 0.0002,
            contact_min_m2: 1e-5,
            dynamics: dynamics::DynamicsConfig::default(),
        }
    }
}

/// A rigid displacement `x -> R x + t` of the scalar type, in the fixed frame.
#[derive(Debug, Clone, Copy)]
pub struct Displacement<T: Real> {
    pub r: Matrix3<T>,
    pub t: Vector3<T>,
}

impl<T: Real> Displacement<T> {
    pub fn identity() -> Self {
        Displacement { r: Matrix3::identity(), t: Vector3::zeros() }
    }

    /// Apply to a point.
    #[inline]
    pub fn apply(&self, x: &Vector3<T>) -> Vector3<T> {
        mat_vec(&self.r, x) + self.t
    }

    /// `self ∘ other`: first `other`, then `self`.
    #[inline]
    pub fn compose(&self, other: &Displacement<T>) -> Displacement<T> {
        Displacement { r: mat_mul(&self.r, &other.r), t: mat_vec(&self.r, &other.t) + self.t }
    }

    /// Apply to a constant point: [`Self::apply`] of `x.map(c)`, the same value to the last bit.
    #[inline]
    pub fn apply_const(&self, x: &Vector3<f64>) -> Vector3<T> {
        mat_vec(&self.r, x) + self.t
    }
}

impl Displacement<f64> {
    /// Lift an `f64` displacement into another scalar type (as constants).
    pub fn lift<T: Real>(&self) -> Displacement<T> {
        Displacement { r: self.r.map(c), t: self.t.map(c) }
    }

    /// The inverse displacement applied to `y`: `R^T (y - t)`.
    #[inline]
    pub fn inverse_apply(&self, y: &Vector3<f64>) -> Vector3<f64> {
        self.r.transpose() * (y - self.t)
    }

    /// `self.lift().compose(other)`, the same value to the last bit, without the derivative
    /// arithmetic of constants (the likelihood's inner loop, [`crate::inference`]).
    #[inline]
    pub fn compose_lifted<T: Real>(&self, other: &Displacement<T>) -> Displacement<T> {
        let r = Matrix3::from_fn(|i, j| other.r[(0, j)] * self.r[(i, 0)] + other.r[(1, j)] * self.r[(i, 1)] + other.r[(2, j)] * self.r[(i, 2)]);
        let t = Vector3::from_fn(|i, _| other.t[0] * self.r[(i, 0)] + other.t[1] * self.r[(i, 1)] + other.t[2] * self.r[(i, 2)] + self.t[i]);
        Displacement { r, t }
    }
}

/// `a b`: nalgebra's `a * b` to the last bit (its generic product sums over `k` in order for
/// entry `(i, j)`, multiplying every term by 1 first; dual numbers pay for that multiplication,
/// and the likelihood's inner loop is mostly 3x3 products of dual numbers). `b` may be constant
/// (`f64`): then `a * b.map(c)` to the last bit, without the derivative arithmetic of constants.
#[inline]
pub fn mat_mul<T, U: Copy>(a: &Matrix3<T>, b: &Matrix3<U>) -> Matrix3<T>
where
    T: Real + std::ops::Mul<U, Output = T>,
{
    Matrix3::from_fn(|i, j| a[(i, 0)] * b[(0, j)] + a[(i, 1)] * b[(1, j)] + a[(i, 2)] * b[(2, j)])
}

/// `a x`: nalgebra's `a * x` to the last bit, `x` of the scalar type or constant (see [`mat_mul`]).
#[inline]
pub fn mat_vec<T, U: Copy>(a: &Matrix3<T>, x: &Vector3<U>) -> Vector3<T>
where
    T: Real + std::ops::Mul<U, Output = T>,
{
    Vector3::from_fn(|i, _| a[(i, 0)] * x[0] + a[(i, 1)] * x[1] + a[(i, 2)] * x[2])
}

/// Decoded physical parameters of one joint (any type), in the fixed frame.
#[derive(Debug, Clone, Copy)]
pub struct JointParams<T: Real> {
    pub joint: JointType,
    /// Reference centre of mass of the child part \[m\].
    pub com: Vector3<T>,
    /// Position noise sd \[m\].
    pub noise: T,
    /// Rotation noise sd \[rad\].
    pub rot_noise: T,
    /// Unit axis direction (prismatic, revolute).
    pub direction: Vector3<T>,
    /// A point on the axis \[m\] (revolute).
    pub point: Vector3<T>,
    /// Effective radius of the centre of mass around the axis \[m\] (revolute).
    pub radius: T,
}

/// Decode the standardised parameters `xi` (length [`JointType::num_params`]) of `joint`;
/// `com0` is the perceived reference centre of mass \[m\].
pub fn decode<T: Real>(joint: JointType, xi: &[T], com0: &Vector3<f64>, cfg: &ModelConfig) -> JointParams<T> {
    let com = Vector3::new(
        c::<T>(com0.x) + xi[0] * cfg.com_sd_m,
        c::<T>(com0.y) + xi[1] * cfg.com_sd_m,
        c::<T>(com0.z) + xi[2] * cfg.com_sd_m,
    );
    let noise = (xi[3] * cfg.noise_log_sd).exp() * cfg.noise_median_m;
    let rot_noise = (xi[4] * cfg.rotation_noise_log_sd).exp() * cfg.rotation_noise_median_rad;
    let base = JointParams { joint, com, noise, rot_noise, direction: Vector3::zeros(), point: com, radius: c(0.0) };
    match joint {
        JointType::Rigid => base,
        JointType::Prismatic => prismatic::decode(base, &xi[rigid::NUM_PARAMS..]),
        JointType::Revolute => revolute::decode(base, &xi[rigid::NUM_PARAMS..], com0, cfg),
    }
}

/// The screw displacement of a joint at coordinate `q` (path length of the child's centre of
/// mass \[m\]), relative to the reference configuration.
pub fn displacement<T: Real>(p: &JointParams<T>, q: T) -> Displacement<T> {
    match p.joint {
        JointType::Rigid => Displacement::identity(),
        JointType::Prismatic => prismatic::displacement(p, q),
        JointType::Revolute => revolute::displacement(p, q),
    }
}

/// `tanh(x)` that stays finite for any argument: num-dual computes `sinh / cosh`, which is
/// `inf / inf` beyond |x| ≈ 710 (a fast joint against a 0.01 rad/s friction scale gets there).
#[inline]
pub fn tanh<T: Real>(x: T) -> T {
    if x.re() >= 0.0 {
        let e = (x * -2.0).exp();
        (c::<T>(1.0) - e) / (c::<T>(1.0) + e)
    } else {
        let e = (x * 2.0).exp();
        (e - 1.0) / (e + 1.0)
    }
}

/// Unit vector of `v` (zero stays zero).
pub fn normalize<T: Real>(v: &Vector3<T>) -> Vector3<T> {
    let n = (v.dot(v) + 1e-300).sqrt();
    v.map(|x| x / n)
}

/// Rotation matrix about unit axis `k` by `angle` (Rodrigues' formula).
pub fn rotation<T: Real>(k: &Vector3<T>, angle: T) -> Matrix3<T> {
    let (s, co) = (angle.sin(), angle.cos());
    let kx = Matrix3::new(c(0.0), -k.z, k.y, k.z, c(0.0), -k.x, -k.y, k.x, c(0.0));
    Matrix3::identity() + kx * s + mat_mul(&kx, &kx) * (c::<T>(1.0) - co)
}

/// The joint coordinate that best explains an observed centre of mass `y` \[m\] (fixed frame,
/// already expressed relative to the parent's displacement): the projection onto a prismatic
/// axis, or the angle about a revolute axis times the radius. Used for tracking predicted poses.
pub fn track_coordinate(p: &JointParams<f64>, y: &Vector3<f64>) -> f64 {
    match p.joint {
        JointType::Rigid => 0.0,
        JointType::Prismatic => (y - p.com).dot(&p.direction),
        JointType::Revolute => {
            let d = p.direction;
            let (a, b) = (p.com - p.point, y - p.point);
            let (a, b) = (a - d * a.dot(&d), b - d * b.dot(&d));
            let angle = d.dot(&a.cross(&b)).atan2(a.dot(&b));
            angle * p.radius
        }
    }
}

/// The joint coordinate \[m of path\] that one frame's observations give, `pre` the parent's
/// displacement at that frame (fixed frame): for a revolute joint whose turn the part's shape
/// makes observable — its axis, carried by `pre`, closer to the span of the observation's
/// rotation axes than to their complement — the angle that best explains the observed rotation
/// times the radius ([`revolute::rotation_coordinate`]); otherwise [`track_coordinate`] of the
/// observed centre of mass `y` \[m\] (fixed frame).
///
/// Why the rotation alone: a hinged panel's turn is read off its whole surface, its centre of
/// mass partly off its outline, which slides in the panel's own plane as the visible part changes
/// (README, "Stop 72"). Against the recorder's joint positions, on the 27 hinges of the structure
/// corpus's `tune` split that hang on a part that does not move, the rotation's reading errs by a
/// median 1.55 mm of path (RMS over a recording) and the centre of mass's by 3.06 mm; the rotation
/// is nearer on 23 of them (`bags/generate/hinge_readings.py`). Weighed by the observations' stated
/// variances the centre would still dominate (the rotation's carry perception's 0.02 rad floor,
/// several times its scatter); and stop 59's rule, the two averaged only where they agree, took a
/// slide of the centre whole, since there they disagree.
pub fn observed_coordinate(p: &JointParams<f64>, pre: &Displacement<f64>, y: &Vector3<f64>, rot: Option<&likelihood::RotationObs>) -> f64 {
    let from_com = track_coordinate(p, &pre.inverse_apply(y));
    let Some(o) = rot.filter(|_| p.joint == JointType::Revolute) else { return from_com };
    let axis = pre.r * p.direction;
    if o.axes.iter().map(|(a, _)| a.dot(&axis).powi(2)).sum::<f64>() <= 0.5 {
        return from_com;
    }
    revolute::rotation_coordinate(p, pre, o, from_com).map_or(from_com, |(q, _)| q)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tracking_inverts_the_displacement() {
        let cfg = ModelConfig::default();
        let com0 = Vector3::new(0.3, -0.2, 0.9);
        let xi = [0.1, -0.2, 0.3, 0.0, 0.0, 0.4, 2.0, 1.0, 2.0, -1.5, 0.2];
        for joint in [JointType::Prismatic, JointType::Revolute] {
            let p = decode::<f64>(joint, &xi[..joint.num_params()], &com0, &cfg);
            // A path of 0.17 m, or half a radian of a revolute (angles wrap at pi).
            let q = if joint == JointType::Revolute { 0.5 * p.radius } else { 0.17 };
            let x = displacement(&p, q).apply(&p.com);
            assert!((track_coordinate(&p, &x) - q).abs() < 1e-9, "{joint:?}");
            // The centre of mass moves by about the path length for small q.
            let x = displacement(&p, 1e-4).apply(&p.com);
            assert!(((x - p.com).norm() - 1e-4).abs() < 1e-6, "{joint:?}");
        }
    }

    /// A hinge's coordinate comes from its observed turn when the shape shows the turn about the
    /// axis — a centre of mass slid 2 cm in the panel's plane does not move it — and from the
    /// centre of mass when it does not (no rotation observed, or only about other axes); a
    /// parent's displacement is taken out of both. A slider's comes from its centre of mass.
    #[test]
    fn a_hinge_is_read_off_its_turn_where_the_shape_shows_it() {
        use likelihood::RotationObs;
        let cfg = ModelConfig::default();
        let com0 = Vector3::new(0.3, -0.2, 0.9);
        let xi = [0.1, -0.2, 0.3, 0.0, 0.0, 0.4, 2.0, 1.0, 2.0, -1.5, 0.2];
        let p = decode::<f64>(JointType::Revolute, &xi[..JointType::Revolute.num_params()], &com0, &cfg);
        let pre = Displacement { r: rotation(&Vector3::new(0.0, 0.6, 0.8), 0.3), t: Vector3::new(0.05, -0.02, 0.01) };
        let q = 0.4 * p.radius;
        let own = displacement(&p, q);
        let whole = pre.compose(&own);
        // The centre of mass seen 2 cm off along the panel, across the axis.
        let slide = normalize(&(whole.r * p.direction).cross(&(whole.apply(&p.com) - pre.apply(&p.point)))) * 0.02;
        let y = whole.apply(&p.com) + slide;
        let axis = pre.r * p.direction;
        let other = normalize(&axis.cross(&Vector3::new(1.0, 0.0, 0.0)));
        let seen = RotationObs { r: whole.r, axes: vec![(axis, 1e-4), (other, 1e-4)] };
        assert!((observed_coordinate(&p, &pre, &y, Some(&seen)) - q).abs() < 1e-9);
        let from_com = track_coordinate(&p, &pre.inverse_apply(&y));
        assert!((from_com - q).abs() > 0.01, "the slide moves the centre of mass's reading: {from_com} against {q}");
        let not_about_axis = RotationObs { r: whole.r, axes: vec![(other, 1e-4)] };
        for rot in [None, Some(&not_about_axis)] {
            assert_eq!(observed_coordinate(&p, &pre, &y, rot), from_com);
        }
        let s = decode::<f64>(JointType::Prismatic, &xi[..JointType::Prismatic.num_params()], &com0, &cfg);
        let ys = pre.compose(&displacement(&s, 0.17)).apply(&s.com);
        assert!((observed_coordinate(&s, &pre, &ys, Some(&seen)) - 0.17).abs() < 1e-9);
    }

    /// The hand-written 3x3 products agree with nalgebra's to the last bit, value and
    /// derivatives, with dual and with constant right-hand sides: the inference's results must
    /// not depend on which one computed them.
    #[test]
    fn hand_written_products_are_nalgebras_to_the_last_bit() {
        type D = num_dual::DualSVec64<4>;
        let d = |x: f64, k: usize| D::from_re(x).derivative(k % 4);
        let a = Matrix3::from_fn(|i, j| d((0.37 * (i * 3 + j) as f64 + 0.11).sin() * 1.3, i + j));
        let b = Matrix3::from_fn(|i, j| d((0.91 * (i * 3 + j) as f64 - 0.4).cos() / 0.7, 2 * i + j));
        let bc = b.map(|x| x.re);
        let x = Vector3::new(d(0.123, 1), d(-4.56, 2), d(7.89e-3, 3));
        let xc = x.map(|x| x.re);
        let same = |u: &D, v: &D| u.re.to_bits() == v.re.to_bits() && u.eps.0.map(|e| e.map(f64::to_bits)) == v.eps.0.map(|e| e.map(f64::to_bits));
        let all = |u: &[D], v: &[D]| u.iter().zip(v).all(|(u, v)| same(u, v));
        assert!(all(mat_mul(&a, &b).as_slice(), (a * b).as_slice()));
        assert!(all(mat_mul(&a, &bc).as_slice(), (a * bc.map(D::from)).as_slice()));
        assert!(all(mat_vec(&a, &x).as_slice(), (a * x).as_slice()));
        assert!(all(mat_vec(&a, &xc).as_slice(), (a * xc.map(D::from)).as_slice()));
        let pre = Displacement { r: a.map(|x| x.re), t: x.map(|x| x.re * 0.5) };
        let other = Displacement { r: b, t: x };
        let (u, v) = (pre.compose_lifted(&other), pre.lift::<D>().compose(&other));
        assert!(all(u.r.as_slice(), v.r.as_slice()) && all(u.t.as_slice(), v.t.as_slice()));
    }
}
