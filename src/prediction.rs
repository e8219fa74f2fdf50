//! Prediction stage: the posterior predictive of part motion under a measured wrench (the
//! paper's §4.3 tracking experiment, Table 3; issue 28).
//!
//! Given a posterior ([`PredictiveModel`], from a [`Posterior`] or from a replay's JSON summary),
//! the parts' observed state at a time `S` and the wrench applied after it ([`Scene`]), every
//! joint of the MAP tree is simulated forward by the model's own physics Ψ (§3.3,
//! [`dynamics::simulate_joint`]: one joint at a time with its subtree locked, its parent's motion
//! composed afterwards — the approximation the model's windows make), once at the posterior
//! medians and once per posterior draw. A draw takes each joint's type from its probabilities,
//! the axis direction and point from their reported spreads, damping, friction and mass
//! log-normally from their 90% intervals, and the effects model criticism adopted at their
//! medians. Damping, friction and mass are drawn jointly, with the correlation of their logs
//! under the posterior ([`JointModel::log_correlation`]). Each part's centre of mass is reported
//! as the medians' trajectory, the draws' 90% band and the draws' mean ([`Prediction`]).
//!
//! A kinematic-mode posterior (no damping, friction or mass) has no forces to simulate: its joints
//! keep their velocity at `S` along their paths (constant velocity in joint space).
//!
//! What the draws do not carry (stated so that a band is read for what it is): the tree is the
//! MAP one (parent probabilities are not sampled); a drawn movable type whose axis the summary
//! does not report (the less probable movable type) is simulated as rigid; effects stay at their
//! medians; perception noise is not added, so the band is for the true centre of mass.
//!
//! The state at `S`: each part's centre of mass as last observed at or before `S`, and each
//! joint's velocity as the least-squares slope of its coordinate over the observations of the
//! `state_window_s` before `S` (`PredictConfig`; the paper's tracking starts from the first 0.1 s
//! of an interaction). A joint's geometry at `S` is the summary's, moved by its parent's
//! displacement from the summary's reference configuration to `S` (the summary's `com` of each
//! part fixes that displacement; without it the summary's axes are taken as they are at `S`).

use std::collections::BTreeMap;

use nalgebra::{Isometry3, Matrix3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;

use crate::criticism::Finding;
use crate::inference::{Estimate, Posterior};
use crate::input::WrenchSample;
use crate::model::dynamics::{self, JointInWindow, KinoParams, SubtreeBody};
use crate::model::effects::{EffectKind, EffectSet, LimitSpec};
use crate::model::likelihood::{wrench_on_steps, WindowEvidence};
use crate::model::{displacement, track_coordinate, Displacement, JointParams, JointType, ModelConfig};
use crate::perception::{PartGeometry, PartTracks};
use crate::windows::Window;

/// The 95% quantile of the standard normal: a 90% interval spans `2 * Z95` standard deviations.
const Z95: f64 = 1.644_853_626_951_472_2;

/// A positive parameter's posterior as a log-normal: `median * exp(sd_log * z)`, `z ~ N(0, 1)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LogNormal {
    pub median: f64,
    pub sd_log: f64,
}

impl LogNormal {
    /// From a median and a 90% interval `[q05, q95]` (what the summary reports).
    pub fn from_interval(median: f64, q05: f64, q95: f64) -> Self {
        let sd_log = if q05 > 0.0 && q95 > q05 { (q95 / q05).ln() / (2.0 * Z95) } else { 0.0 };
        LogNormal { median, sd_log }
    }

    fn from_estimate(e: &Estimate) -> Self {
        Self::from_interval(e.median, e.q05, e.q95)
    }

    /// The value `z` standard deviations from the median in log space.
    fn at(&self, z: f64) -> f64 {
        self.median * (self.sd_log * z).exp()
    }
}

/// A joint's screw axis as the summary reports it (fixed frame, reference configuration).
#[derive(Debug, Clone, PartialEq)]
pub struct AxisModel {
    /// Prismatic or revolute: the movable type the axis belongs to.
    pub joint: JointType,
    /// Unit direction.
    pub direction: Vector3<f64>,
    /// Root-mean-square angle of the direction's posterior \[deg\].
    pub direction_sd_deg: f64,
    /// A point on a revolute axis \[m\].
    pub point: Option<Vector3<f64>>,
    /// Root-mean-square distance of the point's posterior \[m\] (0 when unknown).
    pub point_sd_m: f64,
}

/// One part's joint in the predictive model.
#[derive(Debug, Clone, PartialEq)]
pub struct JointModel {
    /// Part label (>= 1).
    pub child: u32,
    /// MAP parent label (0: the fixed frame).
    pub parent: u32,
    /// `P(rigid), P(prismatic), P(revolute)`.
    pub type_probs: [f64; 3],
    pub axis: Option<AxisModel>,
    /// The part's centre of mass in the summary's reference configuration \[m, fixed frame\].
    pub com: Option<Vector3<f64>>,
    /// Viscous damping (N·s/m or N·m·s/rad), Coulomb friction (N or N·m), mass \[kg\]; `None` in
    /// kinematic mode and for rigid joints.
    pub damping: Option<LogNormal>,
    pub friction: Option<LogNormal>,
    pub mass: Option<LogNormal>,
    /// Correlation of the logs of damping, friction and mass under the posterior (the summary's
    /// `log_correlation`; the identity where it has none): a draw takes the three jointly.
    pub log_correlation: Matrix3<f64>,
    /// Effects adopted by model criticism, with their medians by name in joint units (radians for
    /// a revolute joint's positions), positions from the summary's reference configuration.
    pub effects: Vec<(EffectKind, BTreeMap<String, f64>)>,
}

impl JointModel {
    /// The most probable joint type.
    pub fn map_type(&self) -> JointType {
        JointType::ALL.into_iter().max_by(|a, b| self.type_probs[a.index()].total_cmp(&self.type_probs[b.index()])).unwrap_or(JointType::Rigid)
    }
}

/// The posterior that prediction needs: one [`JointModel`] per part, in the summary's order.
#[derive(Debug, Clone, PartialEq)]
pub struct PredictiveModel {
    pub joints: Vec<JointModel>,
}

/// Why a prediction cannot be made (`bom predict` exits 3 with the message).
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PredictError {
    #[error("model summary: {0}")]
    Summary(String),
    #[error("the model's parts {model:?} are not the recording's {recording:?} (labels must match: a model of another object?)")]
    Labels { model: Vec<u32>, recording: Vec<u32> },
    #[error("part {0} is never observed at or before {1:.3} s: no state to predict from")]
    NoState(u32, f64),
}

impl PredictiveModel {
    /// From a posterior and the findings of model criticism (their adopted effects).
    pub fn from_posterior(p: &Posterior, findings: &[Finding]) -> Self {
        let joints = p
            .joints
            .iter()
            .map(|j| {
                let axis = j.axis.as_ref().map(|a| AxisModel {
                    joint: a.joint,
                    direction: a.direction,
                    direction_sd_deg: a.direction_sd_deg,
                    point: a.point,
                    point_sd_m: if a.point_sd_m.is_finite() { a.point_sd_m } else { 0.0 },
                });
                let ty = axis.as_ref().map_or(j.map_type, |a| a.joint);
                let kd = j.kinodynamics.as_ref();
                JointModel {
                    child: j.child,
                    parent: j.parent,
                    type_probs: j.type_probs,
                    com: Some(j.mean_params[ty.index()].com),
                    damping: kd.map(|k| LogNormal::from_estimate(&k.damping)),
                    friction: kd.map(|k| LogNormal::from_estimate(&k.friction)),
                    mass: kd.map(|k| LogNormal::from_estimate(&k.mass)),
                    log_correlation: kd.map_or(Matrix3::identity(), |k| k.log_correlation),
                    axis,
                    effects: adopted(findings.iter().filter(|f| f.part == j.child).filter_map(|f| Some((f.effect?, f.params.iter().cloned().collect())))),
                }
            })
            .collect();
        PredictiveModel { joints }
    }

    /// From a replay's JSON summary (contract section 5: `model.joints`, and `criticism` for the
    /// adopted effects; each joint's `com` where present).
    ///
    /// # Errors
    /// [`PredictError::Summary`] naming the field that is missing or malformed.
    pub fn from_summary_json(v: &serde_json::Value) -> Result<Self, PredictError> {
        let bad = |what: String| PredictError::Summary(what);
        let joints = v
            .get("model")
            .filter(|m| !m.is_null())
            .ok_or_else(|| bad("no 'model' (the replay produced no posterior)".into()))?
            .get("joints")
            .and_then(|j| j.as_array())
            .ok_or_else(|| bad("no array 'model.joints'".into()))?;
        let findings: Vec<(u32, EffectKind, BTreeMap<String, f64>)> = v
            .get("criticism")
            .and_then(|c| c.as_array())
            .map(|c| {
                c.iter()
                    .filter_map(|f| {
                        let kind = EffectKind::parse(f.get("effect")?.as_str()?)?;
                        let params = f.get("params")?.as_object()?.iter().filter_map(|(k, x)| Some((k.clone(), x.as_f64()?))).collect();
                        Some((f.get("part")?.as_u64()? as u32, kind, params))
                    })
                    .collect()
            })
            .unwrap_or_default();
        let mut out = Vec::with_capacity(joints.len().min(1024));
        for (k, j) in joints.iter().enumerate() {
            let field = |name: &str| format!("model.joints[{k}].{name}");
            let label = |name: &str| -> Result<u32, PredictError> {
                j.get(name).and_then(|x| x.as_u64()).and_then(|x| u32::try_from(x).ok()).ok_or_else(|| bad(format!("{}: not a part label", field(name))))
            };
            let (child, parent) = (label("child")?, label("parent")?);
            let mut type_probs = [0.0; 3];
            let probs = j.get("type_probs").and_then(|p| p.as_object()).ok_or_else(|| bad(format!("{}: missing", field("type_probs"))))?;
            for t in JointType::ALL {
                type_probs[t.index()] = probs.get(t.name()).and_then(|x| x.as_f64()).filter(|x| x.is_finite()).unwrap_or(0.0);
            }
            let axis = match j.get("axis").filter(|a| !a.is_null()) {
                None => None,
                Some(a) => {
                    let direction = vec3(a.get("direction")).and_then(|d| d.try_normalize(1e-12)).ok_or_else(|| bad(format!("{}: not a direction", field("axis.direction"))))?;
                    let point = match a.get("point").filter(|p| !p.is_null()) {
                        None => None,
                        Some(p) => Some(vec3(Some(p)).ok_or_else(|| bad(format!("{}: not a point", field("axis.point"))))?),
                    };
                    let num = |name: &str| a.get(name).and_then(|x| x.as_f64()).filter(|x| x.is_finite() && *x >= 0.0).unwrap_or(0.0);
                    Some(AxisModel {
                        joint: if point.is_some() { JointType::Revolute } else { JointType::Prismatic },
                        direction,
                        direction_sd_deg: num("direction_sd_deg"),
                        point,
                        point_sd_m: num("point_sd_m"),
                    })
                }
            };
            let estimate = |name: &str| -> Option<LogNormal> {
                let e = j.get(name).filter(|e| !e.is_null())?;
                let median = e.get("median")?.as_f64().filter(|m| *m > 0.0 && m.is_finite())?;
                match (e.get("q05").and_then(|x| x.as_f64()), e.get("q95").and_then(|x| x.as_f64())) {
                    (Some(a), Some(b)) => Some(LogNormal::from_interval(median, a, b)),
                    // Only an sd: its log-scale equivalent to first order.
                    _ => Some(LogNormal { median, sd_log: e.get("sd").and_then(|s| s.as_f64()).map_or(0.0, |s| (s / median).max(0.0)) }),
                }
            };
            out.push(JointModel {
                child,
                parent,
                type_probs,
                axis,
                com: vec3(j.get("com")),
                damping: estimate("damping"),
                friction: estimate("friction"),
                mass: estimate("mass"),
                log_correlation: read_log_correlation(j.get("log_correlation")).ok_or_else(|| bad(format!("{}: not a 3x3 correlation matrix", field("log_correlation"))))?,
                effects: adopted(findings.iter().filter(|(p, _, _)| *p == child).map(|(_, k, p)| (*k, p.clone()))),
            });
        }
        Ok(PredictiveModel { joints: out })
    }

    /// Part labels, in the model's order.
    pub fn labels(&self) -> Vec<u32> {
        self.joints.iter().map(|j| j.child).collect()
    }
}

/// The last finding of each effect kind (a later criticism measures an adopted effect again).
fn adopted(found: impl Iterator<Item = (EffectKind, BTreeMap<String, f64>)>) -> Vec<(EffectKind, BTreeMap<String, f64>)> {
    let mut by_kind: BTreeMap<&'static str, (EffectKind, BTreeMap<String, f64>)> = BTreeMap::new();
    for (k, p) in found {
        by_kind.insert(k.name(), (k, p));
    }
    by_kind.into_values().collect()
}

fn vec3(v: Option<&serde_json::Value>) -> Option<Vector3<f64>> {
    let a = v?.as_array()?;
    if a.len() != 3 {
        return None;
    }
    let x: Vec<f64> = a.iter().filter_map(|x| x.as_f64()).filter(|x| x.is_finite()).collect();
    (x.len() == 3).then(|| Vector3::new(x[0], x[1], x[2]))
}

/// What the recording says about the object: part tracks at cloud rate, part geometry, the
/// measured wrench and the windows (whose pushed part receives it).
#[derive(Debug, Clone, Copy)]
pub struct Scene<'a> {
    pub tracks: &'a PartTracks,
    pub geometry: &'a BTreeMap<u32, PartGeometry>,
    /// Sorted by stamp.
    pub wrenches: &'a [WrenchSample],
    pub windows: &'a [Window],
}

impl Scene<'_> {
    /// Every stamp at which some part was observed, sorted, without repeats \[s\].
    pub fn stamps(&self) -> Vec<f64> {
        let mut s: Vec<f64> = self.tracks.values().flatten().map(|o| o.stamp).collect();
        s.sort_by(f64::total_cmp);
        s.dedup();
        s
    }

    /// Part `label`'s observed centre of mass at exactly `stamp` \[m, fixed frame\], if seen then,
    /// and perception's variance of it per axis \[m²\] (a third of the trace of the pose
    /// covariance carried to the centre of mass: `dc = w x c + u`).
    pub fn observed_com(&self, label: u32, stamp: f64) -> Option<(Vector3<f64>, f64)> {
        let obs = self.tracks.get(&label)?;
        let com = self.geometry.get(&label)?.com;
        let i = obs.partition_point(|o| o.stamp < stamp - 1e-9);
        let o = obs.get(i).filter(|o| (o.stamp - stamp).abs() < 1e-9)?;
        let mut j = nalgebra::Matrix3x6::zeros();
        j.fixed_view_mut::<3, 3>(0, 0).copy_from(&(-com.cross_matrix()));
        j.fixed_view_mut::<3, 3>(0, 3).copy_from(&Matrix3::identity());
        let var = (j * o.pose_cov * j.transpose()).trace() / 3.0;
        Some(((o.pose * nalgebra::Point3::from(com)).coords, if var.is_finite() { var.max(0.0) } else { 0.0 }))
    }
}

/// How one part's prediction compares with its observed centres of mass.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PartScore {
    pub label: u32,
    /// Predicted stamps at which the part was observed.
    pub frames: usize,
    /// Mean squared distance between predicted (medians) and observed centres \[m²\].
    pub mse_m2: f64,
    /// The same for the draws' mean ([`PartPrediction::mean`]) \[m²\].
    pub mse_mean_m2: f64,
    /// Fraction of observed centres inside the 90% band widened by perception's noise: within
    /// `sqrt(band_radius² + (2.5 sigma)²)` of the prediction, `2.5 sigma` the 90% radius of an
    /// isotropic 3-D Gaussian of per-axis sd `sigma` (chi-square, 3 dof). NaN without frames.
    pub coverage_90: f64,
    /// Distance at the last observed stamp \[m\].
    pub final_error_m: f64,
}

/// Score `pred` against the centres of mass observed in `scene` at its stamps.
pub fn score(pred: &Prediction, scene: &Scene<'_>) -> Vec<PartScore> {
    // sqrt of the chi-square(3) 90% quantile.
    const R90: f64 = 2.500_216;
    pred.parts
        .iter()
        .map(|p| {
            let (mut n, mut se, mut se_mean, mut inside, mut last) = (0usize, 0.0, 0.0, 0usize, f64::NAN);
            for (k, &t) in pred.stamps.iter().enumerate() {
                let Some((y, var)) = scene.observed_com(p.label, t) else { continue };
                let d = (y - p.com[k]).norm();
                n += 1;
                se += d * d;
                se_mean += (y - p.mean[k]).norm_squared();
                inside += (d <= (p.band_radius_m[k].powi(2) + R90 * R90 * var).sqrt()) as usize;
                last = d;
            }
            let frac = |x: f64| if n > 0 { x / n as f64 } else { f64::NAN };
            PartScore { label: p.label, frames: n, mse_m2: frac(se), mse_mean_m2: frac(se_mean), coverage_90: frac(inside as f64), final_error_m: last }
        })
        .collect()
}

/// Settings of the posterior predictive (`prediction:` in the configuration).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PredictConfig {
    /// Posterior draws for the band (0: the medians only).
    pub draws: usize,
    /// Seed of the draws.
    pub seed: u64,
    /// Observations before `S` that set each joint's velocity \[s\] (the paper's tracking
    /// starts from the first 0.1 s of an interaction).
    pub state_window_s: f64,
    /// The node's `/bom/predicted_part_poses` (and a replay's output bag): each cloud's message
    /// holds the poses predicted for its stamp plus this \[s\], from the state up to the cloud
    /// before it (0: the cloud's own stamp).
    pub look_ahead_s: f64,
}

impl Default for PredictConfig {
    fn default() -> Self {
        PredictConfig { draws: 100, seed: 0, state_window_s: 0.1, look_ahead_s: 0.0 }
    }
}

/// One part's predicted motion at the prediction's stamps.
#[derive(Debug, Clone)]
pub struct PartPrediction {
    pub label: u32,
    /// Centre of mass at the posterior medians \[m, fixed frame\].
    pub com: Vec<Vector3<f64>>,
    /// The part's rotation from its reference configuration (perception's), at the medians.
    pub rotation: Vec<UnitQuaternion<f64>>,
    /// Per coordinate, the 5% and 95% quantiles of the draws' centres of mass \[m\] (equal to
    /// `com` without draws).
    pub lower: Vec<Vector3<f64>>,
    pub upper: Vec<Vector3<f64>>,
    /// 90% quantile of the draws' distance from `com` \[m\]: a ball holding 90% of the draws.
    pub band_radius_m: Vec<f64>,
    /// The draws' mean centre of mass \[m, fixed frame\] (equal to `com` without draws): the
    /// posterior predictive mean, the prediction of least expected squared error were the draws
    /// the posterior's (`com` is one simulation at the medians, which a wide posterior over a
    /// nonlinear simulation need not be near). Measured, it is better where a part's
    /// kinodynamics are the prior's and worse where they were fitted (README, stop 121).
    pub mean: Vec<Vector3<f64>>,
}

/// The posterior predictive of all parts from `from` on.
#[derive(Debug, Clone)]
pub struct Prediction {
    /// `S` \[s\].
    pub from: f64,
    /// Stamps predicted \[s\], each `>= from`.
    pub stamps: Vec<f64>,
    /// In the model's part order.
    pub parts: Vec<PartPrediction>,
    pub draws: usize,
}

impl Prediction {
    /// Poses at stamp `k`, one per part: position the centre of mass, orientation the rotation
    /// from the reference configuration (contract section 2's `/bom/predicted_part_poses`).
    pub fn poses(&self, k: usize) -> Vec<Isometry3<f64>> {
        self.parts.iter().map(|p| Isometry3::from_parts(Translation3::from(p.com[k]), p.rotation[k])).collect()
    }
}

/// A part's observed state at `S`.
#[derive(Debug, Clone)]
struct PartState {
    com: Vector3<f64>,
    rotation: UnitQuaternion<f64>,
    unit_inertia: Matrix3<f64>,
    /// Where its weight acts ([`crate::model::dynamics::JointInWindow::weight_com`]).
    weight_com: Vector3<f64>,
    /// Observed centres of mass over the state window, `(stamp, com)`.
    recent: Vec<(f64, Vector3<f64>)>,
}

/// One joint of one posterior draw.
#[derive(Debug, Clone)]
struct DrawnJoint {
    joint: JointType,
    direction: Vector3<f64>,
    point: Vector3<f64>,
    damping: f64,
    friction: f64,
    mass: f64,
    /// No kinodynamics (a kinematic-mode posterior): the joint moves at its velocity at `S`.
    kinematic: bool,
}

/// The posterior predictive of `model` in `scene` from `from` \[s\] at `stamps` (each `>= from`;
/// earlier ones are dropped), with `cfg.draws` posterior draws for the band.
///
/// Parts of the scene that the model does not have are ignored (a part seen after the posterior
/// was fitted).
///
/// # Errors
/// [`PredictError`] when a part of the model is not in the scene or was never seen by `from`.
pub fn predict(model: &PredictiveModel, scene: &Scene<'_>, from: f64, stamps: &[f64], cfg: &PredictConfig, mcfg: &ModelConfig) -> Result<Prediction, PredictError> {
    let labels = model.labels();
    let seen: Vec<u32> = scene.tracks.keys().copied().collect();
    if labels.iter().any(|l| !seen.contains(l)) {
        return Err(PredictError::Labels { model: labels, recording: seen });
    }
    let stamps: Vec<f64> = stamps.iter().copied().filter(|&t| t >= from).collect();
    let states = labels.iter().map(|&l| part_state(scene, l, from, cfg.state_window_s).ok_or(PredictError::NoState(l, from))).collect::<Result<Vec<_>, _>>()?;
    let order = topological(model);
    let median = draw(model, None::<&mut rand_chacha::ChaCha8Rng>);
    let sim = Simulation::new(model, scene, &states, &order, from, &stamps, mcfg);
    let med = sim.run(&median);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(cfg.seed);
    let draws: Vec<Vec<Vec<Vector3<f64>>>> = (0..cfg.draws).map(|_| sim.run(&draw(model, Some(&mut rng))).0).collect();
    let parts = labels
        .iter()
        .enumerate()
        .map(|(i, &label)| {
            let n = stamps.len();
            let (mut lower, mut upper, mut band) = (med.0[i].clone(), med.0[i].clone(), vec![0.0; n]);
            let mut mean = med.0[i].clone();
            if !draws.is_empty() {
                for k in 0..n {
                    mean[k] = draws.iter().map(|d| d[i][k]).sum::<Vector3<f64>>() / draws.len() as f64;
                    for a in 0..3 {
                        let mut x: Vec<f64> = draws.iter().map(|d| d[i][k][a]).collect();
                        lower[k][a] = quantile(&mut x, 0.05);
                        upper[k][a] = quantile(&mut x, 0.95);
                    }
                    let mut r: Vec<f64> = draws.iter().map(|d| (d[i][k] - med.0[i][k]).norm()).collect();
                    band[k] = quantile(&mut r, 0.9);
                }
            }
            PartPrediction { label, com: med.0[i].clone(), rotation: med.1[i].clone(), lower, upper, band_radius_m: band, mean }
        })
        .collect();
    Ok(Prediction { from, stamps, parts, draws: cfg.draws })
}

/// The `p`-quantile of `x` (linear between order statistics); `x` is sorted in place.
fn quantile(x: &mut [f64], p: f64) -> f64 {
    x.sort_by(f64::total_cmp);
    if x.is_empty() {
        return f64::NAN;
    }
    let r = p * (x.len() - 1) as f64;
    let (a, b) = (r.floor() as usize, r.ceil() as usize);
    x[a] + (x[b] - x[a]) * (r - a as f64)
}

fn part_state(scene: &Scene<'_>, label: u32, from: f64, window: f64) -> Option<PartState> {
    let obs = scene.tracks.get(&label)?;
    let g = scene.geometry.get(&label)?;
    let com = |o: &crate::perception::PartObservation| (o.pose * nalgebra::Point3::from(g.com)).coords;
    // Tracks are in time order (perception's frames): bisect, a node's tracks are long.
    let hi = obs.partition_point(|o| o.stamp <= from + 1e-9);
    let last = obs[..hi].last()?;
    let lo = obs.partition_point(|o| o.stamp < from - window - 1e-9).min(hi);
    let recent: Vec<(f64, Vector3<f64>)> = obs[lo..hi].iter().map(|o| (o.stamp, com(o))).collect();
    let r = last.pose.rotation.to_rotation_matrix();
    let start = smoothed(&recent, from).unwrap_or_else(|| com(last));
    let weight_com = start + r * (g.centroid - g.com);
    Some(PartState { com: start, rotation: last.pose.rotation, unit_inertia: r.matrix() * g.unit_inertia * r.matrix().transpose(), weight_com, recent })
}

/// Part indices with every parent before its children (a parent outside the model, or a cycle,
/// is taken as the fixed frame).
fn topological(model: &PredictiveModel) -> Vec<(usize, Option<usize>)> {
    let n = model.joints.len();
    let index = |label: u32| model.joints.iter().position(|j| j.child == label);
    let mut out: Vec<(usize, Option<usize>)> = Vec::with_capacity(n);
    let mut placed = vec![false; n];
    for _ in 0..=n {
        for (i, j) in model.joints.iter().enumerate() {
            if placed[i] {
                continue;
            }
            match index(j.parent).filter(|&p| p != i) {
                None => {
                    out.push((i, None));
                    placed[i] = true;
                }
                Some(p) if placed[p] => {
                    out.push((i, Some(p)));
                    placed[i] = true;
                }
                Some(_) => {}
            }
        }
    }
    for (i, done) in placed.iter().enumerate() {
        if !done {
            out.push((i, None));
        }
    }
    out
}

/// A summary's `log_correlation` (rows of a 3x3 matrix): the identity where absent; `None` where
/// it is not a correlation matrix (not 3x3, not finite, not symmetric with a unit diagonal, or
/// not positive definite).
fn read_log_correlation(v: Option<&serde_json::Value>) -> Option<Matrix3<f64>> {
    let Some(v) = v.filter(|v| !v.is_null()) else { return Some(Matrix3::identity()) };
    let rows = v.as_array().filter(|r| r.len() == 3)?;
    let mut m = Matrix3::zeros();
    for (r, row) in rows.iter().enumerate() {
        let row = row.as_array().filter(|x| x.len() == 3)?;
        for (c, x) in row.iter().enumerate() {
            m[(r, c)] = x.as_f64().filter(|x| x.is_finite() && x.abs() <= 1.0)?;
        }
    }
    let ok = (0..3).all(|k| (m[(k, k)] - 1.0).abs() < 1e-9) && (m - m.transpose()).abs().max() < 1e-9 && m.cholesky().is_some();
    ok.then_some(m)
}

/// One posterior draw of every joint (`rng` `None`: the medians and the MAP types).
fn draw<R: Rng>(model: &PredictiveModel, mut rng: Option<&mut R>) -> Vec<DrawnJoint> {
    let mut out = Vec::with_capacity(model.joints.len());
    for j in &model.joints {
        let ty = match rng.as_deref_mut() {
            None => j.axis.as_ref().map_or(j.map_type(), |a| if j.map_type().movable() { a.joint } else { JointType::Rigid }),
            Some(r) => {
                let u: f64 = r.random::<f64>() * j.type_probs.iter().sum::<f64>();
                let mut acc = 0.0;
                let mut t = JointType::Rigid;
                for c in JointType::ALL {
                    acc += j.type_probs[c.index()];
                    if u < acc {
                        t = c;
                        break;
                    }
                }
                t
            }
        };
        // Only the reported axis's type can move (module docs).
        let Some(axis) = j.axis.as_ref().filter(|a| ty.movable() && a.joint == ty) else {
            out.push(DrawnJoint { joint: JointType::Rigid, direction: Vector3::z(), point: Vector3::zeros(), damping: 0.0, friction: 0.0, mass: 0.0, kinematic: false });
            continue;
        };
        // Kinematic mode: no forces to simulate; the joint keeps its observed velocity.
        let kinematic = j.damping.is_none() || j.friction.is_none() || j.mass.is_none();
        let unit = LogNormal { median: 0.0, sd_log: 0.0 };
        let (b, f, m) = (j.damping.unwrap_or(unit), j.friction.unwrap_or(unit), j.mass.unwrap_or(unit));
        let d = axis.direction;
        let e1 = d.cross(&if d.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() }).normalize();
        let e2 = d.cross(&e1);
        let (mut direction, mut point) = (d, axis.point.unwrap_or_else(Vector3::zeros));
        if let Some(r) = rng.as_deref_mut() {
            // Isotropic in the tangent plane with the reported root-mean-square angle and offset.
            let s = axis.direction_sd_deg.to_radians() / 2f64.sqrt();
            let (a, c): (f64, f64) = (r.sample(StandardNormal), r.sample(StandardNormal));
            direction = (d + e1 * (a * s) + e2 * (c * s)).normalize();
            let s = axis.point_sd_m / 2f64.sqrt();
            let (a, c): (f64, f64) = (r.sample(StandardNormal), r.sample(StandardNormal));
            point += e1 * (a * s) + e2 * (c * s);
        }
        // The three log parameters jointly: `z = L e`, `L L^T` their correlation, `e ~ N(0, I)`
        // (with the identity, each its own draw as before).
        let z = match rng.as_deref_mut() {
            Some(r) => {
                let e = Vector3::from_fn(|_, _| r.sample::<f64, _>(StandardNormal));
                let l = j.log_correlation.cholesky().map_or(Matrix3::identity(), |c| c.l());
                l * e
            }
            None => Vector3::zeros(),
        };
        out.push(DrawnJoint { joint: ty, direction, point, damping: b.at(z[0]), friction: f.at(z[1]), mass: m.at(z[2]), kinematic });
    }
    out
}

/// What every draw's simulation shares: the states, the order, the integration steps and the
/// wrench on them.
struct Simulation<'a> {
    model: &'a PredictiveModel,
    states: &'a [PartState],
    order: &'a [(usize, Option<usize>)],
    stamps: &'a [f64],
    from: f64,
    h: f64,
    steps: usize,
    force: Vec<Vector3<f64>>,
    torque: Vec<Vector3<f64>>,
    point: Vec<Vector3<f64>>,
    /// Per step, the pushed part (model index) of the window holding it.
    pushed: Vec<Option<usize>>,
    mcfg: &'a ModelConfig,
}

impl<'a> Simulation<'a> {
    fn new(model: &'a PredictiveModel, scene: &Scene<'_>, states: &'a [PartState], order: &'a [(usize, Option<usize>)], from: f64, stamps: &'a [f64], mcfg: &'a ModelConfig) -> Self {
        let h = mcfg.dynamics.step_s;
        let end = stamps.last().copied().unwrap_or(from);
        let steps = ((end - from) / h).ceil().max(0.0) as usize + 2;
        let (force, torque, point) = wrench_on_steps(scene.wrenches, from, steps, h);
        let pushed = (0..steps)
            .map(|k| {
                let t = from + k as f64 * h;
                let w = scene.windows.iter().find(|w| w.contains(t))?;
                model.joints.iter().position(|j| Some(j.child) == w.pushed_part)
            })
            .collect();
        Simulation { model, states, order, stamps, from, h, steps, force, torque, point, pushed, mcfg }
    }

    /// Centres of mass and rotations of every part at every stamp, for one draw.
    #[allow(clippy::type_complexity)]
    fn run(&self, drawn: &[DrawnJoint]) -> (Vec<Vec<Vector3<f64>>>, Vec<Vec<UnitQuaternion<f64>>>) {
        let n = self.model.joints.len();
        let dyncfg = &self.mcfg.dynamics;
        let radius = |com: &Vector3<f64>, d: &Vector3<f64>, p: &Vector3<f64>| {
            let r = com - p;
            let perp = r - d * r.dot(d);
            (perp.norm_squared() + self.mcfg.min_radius_m.powi(2)).sqrt()
        };
        // Each joint's geometry at `S`: the summary's, moved by the parent's displacement from
        // the summary's reference configuration to `S`.
        let all_com = self.model.joints.iter().all(|j| j.com.is_some());
        let mut to_s: Vec<Displacement<f64>> = vec![Displacement::identity(); n];
        let mut at_s: Vec<JointParams<f64>> = Vec::with_capacity(n);
        at_s.resize_with(n, || blank(&Vector3::zeros()));
        let mut q_ref = vec![0.0; n];
        for &(i, parent) in self.order {
            let (j, d, s) = (&self.model.joints[i], &drawn[i], &self.states[i]);
            let pre = parent.map_or_else(Displacement::identity, |p| to_s[p]);
            let mut reference = blank(&j.com.unwrap_or(s.com));
            reference.joint = d.joint;
            reference.direction = d.direction;
            reference.point = d.point;
            reference.radius = radius(&reference.com, &d.direction, &d.point);
            if all_com && d.joint.movable() {
                q_ref[i] = track_coordinate(&reference, &pre.inverse_apply(&s.com));
            }
            to_s[i] = if all_com { pre.compose(&displacement(&reference, q_ref[i])) } else { Displacement::identity() };
            let mut p = blank(&s.com);
            p.joint = d.joint;
            if d.joint.movable() {
                let pre = if all_com { pre } else { Displacement::identity() };
                p.direction = pre.r * d.direction;
                p.point = pre.apply(&d.point);
                p.radius = radius(&s.com, &p.direction, &p.point);
            }
            at_s[i] = p;
        }
        // Children lists for the locked subtrees.
        let mut desc: Vec<Vec<usize>> = vec![Vec::new(); n];
        for &(i, _) in self.order.iter().rev() {
            let mut mine = Vec::new();
            for &(c, p) in self.order {
                if p == Some(i) {
                    mine.push(c);
                    mine.extend(desc[c].iter().copied());
                }
            }
            desc[i] = mine;
        }
        // Each joint's coordinate [m of path] at every integration step.
        let mut q: Vec<Vec<f64>> = vec![Vec::new(); n];
        for &(i, _) in self.order {
            let (p, d, s) = (&at_s[i], &drawn[i], &self.states[i]);
            if !p.joint.movable() {
                continue;
            }
            let own_subtree = |k: usize| k == i || desc[i].contains(&k);
            let mask = |k: usize| self.pushed[k].is_some_and(own_subtree);
            let force: Vec<Vector3<f64>> = (0..self.steps).map(|k| if mask(k) { self.force[k] } else { Vector3::zeros() }).collect();
            let torque: Vec<Vector3<f64>> = (0..self.steps).map(|k| if mask(k) { self.torque[k] } else { Vector3::zeros() }).collect();
            let win = WindowEvidence {
                frames: vec![0, 1],
                rest: Vec::new(),
                rest_before: Vec::new(),
                frame_substep: vec![0, self.steps - 1],
                pushed: None,
                continues: false,
                hand_off: false,
                h: self.h,
                force,
                torque,
                point: self.point.clone(),
            };
            let (effects, kp) = kinodynamics(&self.model.joints[i], d, p, q_ref[i]);
            let subtree: Vec<SubtreeBody> = desc[i]
                .iter()
                .map(|&m| SubtreeBody {
                    mass: if drawn[m].joint.movable() { drawn[m].mass } else { self.model.joints[m].mass.map_or(dyncfg.mass_median_kg, |x| x.median) },
                    com: self.states[m].com,
                    unit_inertia: self.states[m].unit_inertia,
                    weight_com: self.states[m].weight_com,
                })
                .collect();
            let jw = JointInWindow { joint: p, com: s.com, unit_inertia: s.unit_inertia, weight_com: s.weight_com, subtree, pushed: (0..self.steps).any(mask), effects };
            let v0 = velocity(p, &s.recent);
            q[i] = if d.kinematic {
                (0..self.steps).map(|k| v0 * k as f64 * self.h).collect()
            } else {
                dynamics::simulate_joint(&jw, &win, 0.0, v0, &kp, dyncfg).unwrap_or_else(|| vec![0.0; self.steps])
            };
        }
        // Compose the displacements from `S` down the tree at every stamp.
        let mut com = vec![Vec::with_capacity(self.stamps.len()); n];
        let mut rot = vec![Vec::with_capacity(self.stamps.len()); n];
        for &t in self.stamps {
            let x = ((t - self.from) / self.h).max(0.0);
            let (k, u) = (x.floor() as usize, x.fract());
            let mut disp = vec![Displacement::identity(); n];
            for &(i, parent) in self.order {
                let pre = parent.map_or_else(Displacement::identity, |p| disp[p]);
                let qi = match q[i].len() {
                    0 => 0.0,
                    len => {
                        let (a, b) = (q[i][k.min(len - 1)], q[i][(k + 1).min(len - 1)]);
                        a + (b - a) * u
                    }
                };
                disp[i] = pre.compose(&displacement(&at_s[i], qi));
                com[i].push(disp[i].apply(&self.states[i].com));
                rot[i].push(UnitQuaternion::from_matrix(&disp[i].r) * self.states[i].rotation);
            }
        }
        (com, rot)
    }
}

fn blank(com: &Vector3<f64>) -> JointParams<f64> {
    JointParams { joint: JointType::Rigid, com: *com, noise: 0.0, rot_noise: 0.0, direction: Vector3::zeros(), point: *com, radius: 0.0 }
}

/// The centre of mass at `from` on the least-squares line through the recent observed centres
/// (`None` with fewer than three distinct stamps). Why: a prediction started from the last
/// observed centre carries that frame's perception noise into every predicted frame (one step:
/// the error's variance is twice perception's), where the line's value at its end has
/// `1/n + (t_n - mean t)^2 / S_tt` of it (0.83 for three frames, 0.7 for four).
fn smoothed(recent: &[(f64, Vector3<f64>)], from: f64) -> Option<Vector3<f64>> {
    if recent.len() < 3 {
        return None;
    }
    let (mt, my, slope) = line_fit(recent)?;
    Some(my + slope * (from - mt))
}

/// The least-squares line through points `(t, y)`: `(mean t, mean y, slope)`, so that
/// `y(t) = mean y + slope (t - mean t)`; `None` with fewer than two distinct stamps.
fn line_fit<Y>(pts: &[(f64, Y)]) -> Option<(f64, Y, Y)>
where
    Y: Copy + std::ops::Sub<Output = Y> + std::ops::Mul<f64, Output = Y> + std::ops::Div<f64, Output = Y> + std::iter::Sum<Y>,
{
    if pts.len() < 2 {
        return None;
    }
    let n = pts.len() as f64;
    let mt = pts.iter().map(|x| x.0).sum::<f64>() / n;
    let my = pts.iter().map(|x| x.1).sum::<Y>() / n;
    let stt: f64 = pts.iter().map(|x| (x.0 - mt).powi(2)).sum();
    if stt <= 1e-12 {
        return None;
    }
    Some((mt, my, pts.iter().map(|x| (x.1 - my) * (x.0 - mt)).sum::<Y>() / stt))
}

/// The joint's velocity at `S` \[m of path / s\]: least-squares slope of its coordinate over the
/// recent observations (0 with fewer than two distinct stamps).
fn velocity(p: &JointParams<f64>, recent: &[(f64, Vector3<f64>)]) -> f64 {
    let pts: Vec<(f64, f64)> = recent.iter().map(|(t, y)| (*t, track_coordinate(p, y))).collect();
    line_fit(&pts).map_or(0.0, |(_, _, slope)| slope)
}

/// The physics' parameters of a drawn joint at `S`, with the adopted effects (their positions
/// moved from the summary's reference configuration to `S` by the joint's coordinate `q_ref`
/// there, in metres of path).
fn kinodynamics(j: &JointModel, d: &DrawnJoint, p: &JointParams<f64>, q_ref: f64) -> (EffectSet, KinoParams<f64>) {
    let revolute = p.joint == JointType::Revolute;
    // Positions in joint units (radians for a revolute joint) -> metres of path from `S`.
    let path = |x: f64| if revolute { x * p.radius - q_ref } else { x - q_ref };
    let mut effects = EffectSet::default();
    let mut kp = KinoParams { damping: d.damping, friction: d.friction, mass: d.mass, deviation: 0.0, stiffness: 0.0, rest: 0.0, limit: None, quadratic_damping: 0.0 };
    for (kind, params) in &j.effects {
        let get = |k: &str| params.get(k).copied().filter(|x| x.is_finite());
        match kind {
            EffectKind::Spring => {
                if let (Some(k), Some(r)) = (get("stiffness"), get("rest_position")) {
                    effects.spring = true;
                    kp.stiffness = k.max(0.0);
                    kp.rest = path(r);
                }
            }
            EffectKind::JointLimit => {
                let (lower, upper) = (get("lower").map(path), get("upper").map(path));
                if let (Some(k), true) = (get("stiffness"), lower.is_some() || upper.is_some()) {
                    effects.limit = Some(LimitSpec { lower, upper });
                    kp.limit = Some((lower, upper, k.max(0.0)));
                }
            }
            EffectKind::Gravity => effects.gravity = true,
            EffectKind::QuadraticDamping => {
                if let Some(c) = get("coefficient") {
                    effects.quadratic_damping = true;
                    kp.quadratic_damping = c.max(0.0);
                }
            }
        }
    }
    (effects, kp)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The start state is the least-squares line's value at `S`: exact on a straight track,
    /// nearer a still part's true centre than its last noisy frame, none with fewer than three
    /// frames (the caller then takes the last).
    #[test]
    fn the_start_centre_is_the_recent_line_at_s() {
        let v = Vector3::new(0.1, -0.2, 0.05);
        let line: Vec<(f64, Vector3<f64>)> = (0..4).map(|k| (1.0 + k as f64 / 30.0, Vector3::new(0.3, 0.1, 0.9) + v * (k as f64 / 30.0))).collect();
        let at = smoothed(&line, 1.1).expect("four frames");
        assert!((at - (Vector3::new(0.3, 0.1, 0.9) + v * 0.1)).norm() < 1e-12, "{at}");
        let still = [(0.0, Vector3::new(0.0, 0.0, 0.003)), (0.1, Vector3::new(0.0, 0.0, -0.003)), (0.2, Vector3::new(0.0, 0.0, 0.003)), (0.3, Vector3::new(0.0, 0.0, -0.003))];
        let at = smoothed(&still, 0.3).expect("four frames");
        // the line through +-3 mm alternating ends 1.8 mm below zero, nearer than the last frame's 3 mm
        assert!(at.z.abs() < 0.003 && at.z < 0.0, "{at}");
        assert!(smoothed(&line[..2], 1.1).is_none());
    }

    /// A draw takes damping, friction and mass jointly with the posterior's log correlation (the
    /// identity: apart); the medians draw nothing.
    #[test]
    fn draws_keep_the_kinodynamic_correlation() {
        let joint = |r: f64| JointModel {
            child: 2,
            parent: 1,
            type_probs: [0.0, 1.0, 0.0],
            axis: Some(AxisModel { joint: JointType::Prismatic, direction: Vector3::x(), direction_sd_deg: 1.0, point: None, point_sd_m: 0.0 }),
            com: None,
            damping: Some(LogNormal { median: 4.0, sd_log: 0.5 }),
            friction: Some(LogNormal { median: 1.0, sd_log: 1.0 }),
            mass: Some(LogNormal { median: 0.8, sd_log: 0.2 }),
            log_correlation: Matrix3::new(1.0, r, 0.0, r, 1.0, 0.0, 0.0, 0.0, 1.0),
            effects: Vec::new(),
        };
        let correlation = |r: f64| {
            let model = PredictiveModel { joints: vec![joint(r)] };
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
            let v: Vec<[f64; 3]> = (0..20_000).map(|_| draw(&model, Some(&mut rng))).map(|d| [d[0].damping, d[0].friction, d[0].mass]).collect();
            crate::inference::summary::log_correlation(&crate::inference::summary::log_covariance(&v), 0.0)
        };
        let (tied, apart) = (correlation(-0.8), correlation(0.0));
        assert!((tied[(0, 1)] + 0.8).abs() < 0.02 && tied[(0, 2)].abs() < 0.03, "{tied}");
        assert!(apart[(0, 1)].abs() < 0.03, "{apart}");
        let median = draw(&PredictiveModel { joints: vec![joint(-0.8)] }, None::<&mut rand_chacha::ChaCha8Rng>);
        assert_eq!((median[0].damping, median[0].friction, median[0].mass), (4.0, 1.0, 0.8));
        // A summary's matrix: absent is the identity; not a correlation matrix is refused.
        let read = |v: serde_json::Value| read_log_correlation(Some(&v));
        assert_eq!(read(serde_json::Value::Null), Some(Matrix3::identity()));
        assert!(read(serde_json::json!([[1.0, 0.5, 0.0], [0.5, 1.0, 0.0], [0.0, 0.0, 1.0]])).is_some());
        assert!(read(serde_json::json!([[1.0, 0.5, 0.0], [0.4, 1.0, 0.0], [0.0, 0.0, 1.0]])).is_none());
        assert!(read(serde_json::json!([[1.0, 0.9, 0.9], [0.9, 1.0, -0.9], [0.9, -0.9, 1.0]])).is_none());
        assert!(read(serde_json::json!([[1.0, 0.5], [0.5, 1.0]])).is_none());
    }
}
