//! Inference stage: posterior over the Bayesian object model given the evidence (paper §3.4).
//!
//! [`svi`] is BOM-SVI with the guide of [`guide`]; [`nuts`] is BOM-NUTS on the model's log
//! density ([`crate::model::density`]) for the structures SVI found. Inference is separate from
//! the model ([`crate::model`]) and returns a [`Posterior`], a summary that later stages (criticism,
//! output) read without knowing how it was obtained.

pub mod adam;
pub mod guide;
pub mod laplace;
pub mod nuts;
pub mod structure;
pub mod summary;
pub mod svi;

use nalgebra::{Matrix3, Vector3};

use crate::model::{JointParams, JointType};

/// Posterior summary of a screw axis.
#[derive(Debug, Clone)]
pub struct AxisSummary {
    /// Joint type whose axis this is (prismatic or revolute).
    pub joint: JointType,
    /// Posterior mean unit direction, fixed frame.
    pub direction: Vector3<f64>,
    /// Root-mean-square angle of posterior samples to `direction` \[deg\].
    pub direction_sd_deg: f64,
    /// 90% quantile of that angle: the radius of the 90% credible cone around `direction` \[deg\].
    pub direction_q90_deg: f64,
    /// Revolute: posterior mean of the axis point closest to the part's centre of mass \[m\].
    pub point: Option<Vector3<f64>>,
    /// Root-mean-square distance of sampled points to `point` \[m\] (NaN when no point).
    pub point_sd_m: f64,
    /// Factor (>= 1) by which the variance of the axis parameters' draws was widened before the
    /// spreads were taken, for what the likelihood's independent frames leave out: in kinematic
    /// mode `n / n_eff` of the part's residuals (perception's errors are correlated from frame to
    /// frame; `svi::comparison_weights`), in dynamic mode the position inflation (`svi`'s
    /// `position_inflation`); 1: none. BOM-NUTS widens its draws by the same factor, so that SVI
    /// and NUTS differ only by the guide ([`nuts`] module docs).
    pub inflation: f64,
    /// The model discrepancy in `direction_sd_deg` and `direction_q90_deg` \[deg\]: the sd per
    /// direction across the axis of the tilt added to the posterior's
    /// ([`ModelConfig::axis_discrepancy_deg`](crate::model::ModelConfig::axis_discrepancy_deg);
    /// 0: none, the spreads are the posterior's alone).
    pub discrepancy_deg: f64,
    /// The posterior's own RMS angle and 90% cone, before the discrepancy \[deg\]: what SVI
    /// and NUTS are compared by (the discrepancy is the same for both).
    pub posterior_sd_deg: f64,
    pub posterior_q90_deg: f64,
    /// The model discrepancy in `point_sd_m`: the sd per direction across the axis of the
    /// displacement added to the posterior's point \[m\]
    /// ([`ModelConfig::axis_point_discrepancy_m`](crate::model::ModelConfig::axis_point_discrepancy_m);
    /// 0: none).
    pub point_discrepancy_m: f64,
    /// The posterior's own point spread, before the discrepancy \[m\] (NaN when no point).
    pub point_posterior_sd_m: f64,
}

/// The turn a revolute joint was seen to make \[rad\]: the range (largest minus smallest) of its
/// coordinates `q` \[m of centre-of-mass path\] over the radius `r` \[m\] of that path
/// ([`crate::model::revolute`]). NaN when there are no coordinates or `r` is not positive.
fn observed_turn(coordinates: &[f64], radius: f64) -> f64 {
    let (lo, hi) = coordinates.iter().filter(|q| q.is_finite()).fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &q| (lo.min(q), hi.max(q)));
    if hi >= lo && radius > 0.0 {
        (hi - lo) / radius
    } else {
        f64::NAN
    }
}

/// `sqrt(-2 ln 0.1)`: the 90% quantile of the length of a 2-D standard normal vector (Rayleigh).
pub(crate) const RAYLEIGH_Q90: f64 = 2.145_966_026_289_347;

impl AxisSummary {
    /// The spreads with a model discrepancy: an isotropic tilt across the axis of sd `sd_deg`
    /// per direction and, for a revolute axis, an isotropic displacement of the point across the
    /// axis of sd `point_sd_m` per direction, both independent of the posterior's and added in
    /// quadrature — the RMS angle `sqrt(s^2 + 2 sd^2)`, the 90% cone `sqrt(q90^2 + (2.146
    /// sd)^2)` (exact for an isotropic Gaussian posterior, whose angle is Rayleigh), the point's
    /// RMS distance `sqrt(s_p^2 + 2 point_sd^2)`. The direction, point and the posterior's own
    /// spreads (`posterior_sd_deg`, `posterior_q90_deg`, `point_posterior_sd_m`) stay. Applied
    /// once: the spreads it widens are always the posterior's. A negative or NaN sd counts as 0.
    pub fn with_discrepancy(self, sd_deg: f64, point_sd_m: f64) -> AxisSummary {
        let clean = |v: f64| if v.is_finite() { v.max(0.0) } else { 0.0 };
        let (sd, psd) = (clean(sd_deg), if self.point.is_some() { clean(point_sd_m) } else { 0.0 });
        AxisSummary {
            direction_sd_deg: self.posterior_sd_deg.hypot(std::f64::consts::SQRT_2 * sd),
            direction_q90_deg: self.posterior_q90_deg.hypot(RAYLEIGH_Q90 * sd).min(180.0),
            discrepancy_deg: sd,
            point_sd_m: self.point_posterior_sd_m.hypot(std::f64::consts::SQRT_2 * psd),
            point_discrepancy_m: psd,
            ..self
        }
    }

    /// [`Self::with_discrepancy`] with the model's discrepancies, `model.axis_discrepancy_deg`
    /// and `model.axis_point_discrepancy_m`.
    pub fn with_model_discrepancy(self, model: &crate::model::ModelConfig) -> AxisSummary {
        self.with_discrepancy(model.axis_discrepancy_deg, model.axis_point_discrepancy_m)
    }
}

/// Posterior summary of one positive scalar parameter (its SI unit).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Estimate {
    pub median: f64,
    pub sd: f64,
    /// 5% and 95% quantiles: the 90% credible interval.
    pub q05: f64,
    pub q95: f64,
}

/// Kinodynamic parameters of a joint (dynamic mode): viscous damping (N·s/m or N·m·s/rad),
/// Coulomb friction (N or N·m), mass of the child part (kg).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Kinodynamics {
    pub damping: Estimate,
    pub friction: Estimate,
    pub mass: Estimate,
    /// The variance inflation the intervals allow for (>= 1; 1 for none): the likelihood part of
    /// the block's precision divided by it ([`laplace::inflated`]), for the physics' deviations
    /// correlated in time or the windows' disagreement (`svi::variance_inflation`,
    /// [`laplace::cluster_inflation`]). BOM-NUTS applies SVI's to its draws
    /// ([`laplace::inflated_draws`]).
    pub inflation: f64,
    /// Correlation matrix of (log damping, log friction, log mass), in that order, under the
    /// posterior with the model discrepancy's independent log noise on each (the identity where
    /// unknown; [`summary::log_correlation`]). The guide's kinodynamic block is one full Gaussian:
    /// damping trades for Coulomb friction along a ridge and both grow with the mass, so the three
    /// drawn apart from their intervals spread a prediction wider than the posterior does.
    pub log_correlation: Matrix3<f64>,
}

/// Posterior of the joint attaching one part.
#[derive(Debug, Clone)]
pub struct JointSummary {
    /// Part label.
    pub child: u32,
    /// MAP parent label (0 = fixed frame), from the most probable tree.
    pub parent: u32,
    /// MAP parent as a node index (0 = fixed frame, `j + 1` = part `j` in evidence order).
    pub parent_index: usize,
    /// `P(parent = label)` for every candidate.
    pub parent_probs: Vec<(u32, f64)>,
    /// `P(rigid), P(prismatic), P(revolute)`.
    pub type_probs: [f64; 3],
    pub map_type: JointType,
    /// Axis of the more probable movable type (its `joint` says which).
    pub axis: Option<AxisSummary>,
    /// Kinodynamics of the same type (dynamic mode only).
    pub kinodynamics: Option<Kinodynamics>,
    /// Guide-mean physical parameters per joint type (rigid, prismatic, revolute).
    pub mean_params: [JointParams<f64>; 3],
    /// Guide-mean joint coordinates per type on the evidence grid [m of path].
    pub coordinates: [Vec<f64>; 3],
}

impl JointSummary {
    /// The turn the part was seen to make about its revolute axis \[rad\]: the range of the
    /// revolute joint's guide-mean coordinate over the evidence over that joint's mean radius;
    /// NaN when the reported axis is not revolute.
    pub fn turn_rad(&self) -> f64 {
        match &self.axis {
            Some(a) if a.joint == JointType::Revolute => {
                let k = JointType::Revolute.index();
                observed_turn(&self.coordinates[k], self.mean_params[k].radius)
            }
            _ => f64::NAN,
        }
    }
}

/// A fitted posterior.
#[derive(Debug, Clone)]
pub struct Posterior {
    /// One per part, in evidence (label) order.
    pub joints: Vec<JointSummary>,
    /// ELBO estimate at convergence \[nats\].
    pub elbo: f64,
    pub iterations: usize,
    /// Wall time of the fit \[s\].
    pub runtime_s: f64,
}
