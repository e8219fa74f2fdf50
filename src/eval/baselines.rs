//! The paper's differentiable-simulation baselines (Table 1, "Diff. sim." and "Diff. sim. tail
//! init"): the true tree, joint types and screw axes given, damping, friction and mass fitted by
//! gradient descent on the simulation loss — the squared error between the simulated and the
//! observed joint coordinates over every window — started from the priors' medians (`diff_sim`)
//! or from their lower 1% tails (`diff_sim_tail_init`). An oracle on the structure, so its IdE
//! is what the physics and the data allow when nothing else is uncertain.
//!
//! The loss is [`physics_prior`] on the observed coordinates with the latent ones integrated out
//! ([`crate::model::dynamics::Observed`]), Gaussian, with a fixed observation variance and a
//! deviation scale of zero: `sum_t (y_t - Psi_t(y_w0))^2 / (2 r^2)`. Its gradient comes from the
//! physics code's dual numbers; the descent is Adam (the paper's gradient descent with per-
//! coordinate steps) in the standardised coordinates of [`crate::model::dynamics::decode`].

use std::time::Instant;

use nalgebra::Vector3;
use serde::Serialize;

use crate::inference::structure::observed_displacements;
use crate::input::GroundTruth;
use crate::model::density::{physics_prior, PartValue};
use crate::model::dynamics::{self, Observed};
use crate::model::likelihood::Evidence;
use crate::model::{track_coordinate, JointParams, JointType, ModelConfig};

/// Where the descent starts, in standardised units of damping, friction and mass.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Start {
    /// The priors' medians (0).
    Median,
    /// The priors' lower 1% tails (-2.326).
    LowerTail,
}

/// One part's fit.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct DiffSimPart {
    pub label: u32,
    pub damping: f64,
    pub friction: f64,
    pub mass: f64,
    pub damping_rel_error: Option<f64>,
    pub friction_rel_error: Option<f64>,
}

/// A `diff_sim` row of `bom eval --baselines` (contract section 4).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct DiffSimRow {
    /// Median over movable parts and over damping and friction of the relative error (IdE).
    pub ide: Option<f64>,
    pub parts: Vec<DiffSimPart>,
    pub runtime_s: f64,
}

/// Observation sd of the loss \[m\]: a scale only (the loss is a sum of squares).
const LOSS_SD_M: f64 = 0.001;
const ITERATIONS: usize = 400;
const LEARNING_RATE: f64 = 0.05;

/// The baseline on evidence `ev` (dynamic mode) against `gt`. Parts without a movable true joint,
/// a true axis, or any window are left out.
pub fn diff_sim(ev: &Evidence, gt: &GroundTruth, model: &ModelConfig, start: Start) -> DiffSimRow {
    let t0 = Instant::now();
    let mut parts = Vec::new();
    let n = ev.parts.len();
    let node_of = |label: u32| if label == 0 { Some(0) } else { ev.parts.iter().position(|p| p.label == label).map(|i| i + 1) };
    // The true tree over the evidence's parts (a part the ground truth does not name hangs from
    // the fixed frame), every part's observed displacement, and the bodies of a subtree: centres
    // of mass where perceived, masses at the prior's median.
    let true_parent: Vec<usize> = ev
        .parts
        .iter()
        .map(|p| gt.parts.iter().find(|g| g.label == p.label).and_then(|g| node_of(g.parent)).unwrap_or(0))
        .collect();
    let transforms: Vec<Vec<crate::model::Displacement<f64>>> = (0..n).map(|m| observed_displacements(ev, m + 1)).collect();
    let bodies: Vec<JointParams<f64>> = (0..n).map(|m| true_params(ev, m, JointType::Rigid, Vector3::z(), None, model)).collect();
    let zeros = vec![0.0; ev.len()];
    let body_values: Vec<PartValue<'_>> = bodies.iter().map(|b| PartValue { params: b, q: &zeros, kd: None }).collect();
    for g in &gt.parts {
        let (Some(joint), Some(dir)) = (JointType::parse(&g.joint), g.axis_direction) else { continue };
        let (Some(node), Some(parent)) = (node_of(g.label), node_of(g.parent)) else { continue };
        if !joint.movable() || ev.windows.is_empty() {
            continue;
        }
        let i = node - 1;
        let desc = crate::model::tree::descendants(&true_parent, i);
        let params = true_params(ev, i, joint, Vector3::from(dir), g.axis_point.map(Vector3::from), model);
        let pre = observed_displacements(ev, parent);
        // Observed coordinates, held over frames in which the part is not seen.
        let mut q = vec![0.0; ev.len()];
        let mut last = 0.0;
        for (t, o) in ev.parts[i].obs.iter().enumerate() {
            if let Some(o) = o {
                last = track_coordinate(&params, &pre[t].inverse_apply(&o.y));
            }
            q[t] = last;
        }
        let observed = Observed { var: vec![LOSS_SD_M * LOSS_SD_M; ev.len()], nu: 0.0 };
        let dim = dynamics::num_params(&ev.effects[i]);
        let x0 = match start {
            Start::Median => 0.0,
            Start::LowerTail => -2.326,
        };
        let mut xi = vec![0.0; dim];
        xi[..3].fill(x0);
        // A deviation scale of zero: the loss is the simulation error alone.
        xi[3] = -30.0;
        // (The rests between windows add terms in the deviation scale alone.)
        let loss = |xi: &[f64]| {
            let value = PartValue { params: &params, q: &q, kd: Some(xi) };
            let (l, g, _) = physics_prior(ev, i, &value, Some(&observed), &pre, &desc, &body_values, &transforms, model, false, None);
            (-l, g.iter().map(|v| -v).collect::<Vec<f64>>())
        };
        let (mut m1, mut m2) = ([0.0f64; 3], [0.0f64; 3]);
        for it in 1..=ITERATIONS {
            let (_, g) = loss(&xi);
            for k in 0..3 {
                if !g[k].is_finite() {
                    continue;
                }
                m1[k] = 0.9 * m1[k] + 0.1 * g[k];
                m2[k] = 0.999 * m2[k] + 0.001 * g[k] * g[k];
                let (a, b) = (m1[k] / (1.0 - 0.9f64.powi(it as i32)), m2[k] / (1.0 - 0.999f64.powi(it as i32)));
                xi[k] -= LEARNING_RATE * a / (b.sqrt() + 1e-12);
            }
        }
        let kp = dynamics::decode::<f64>(joint, &xi, &ev.effects[i], &model.dynamics);
        let rel = |e: f64, t: Option<f64>| t.filter(|t| *t != 0.0).map(|t| (e - t).abs() / t.abs());
        parts.push(DiffSimPart {
            label: g.label,
            damping: kp.damping,
            friction: kp.friction,
            mass: kp.mass,
            damping_rel_error: rel(kp.damping, g.damping),
            friction_rel_error: rel(kp.friction, g.friction),
        });
    }
    let ide = super::median(parts.iter().flat_map(|p| [p.damping_rel_error, p.friction_rel_error]).flatten().collect());
    DiffSimRow { ide, parts, runtime_s: t0.elapsed().as_secs_f64() }
}

/// The joint of part `i` with the true axis: direction `dir` (unit), point `point` (revolute), the
/// perceived reference centre of mass, the noise priors' medians.
fn true_params(ev: &Evidence, i: usize, joint: JointType, dir: Vector3<f64>, point: Option<Vector3<f64>>, model: &ModelConfig) -> JointParams<f64> {
    let com = ev.parts[i].com0;
    let direction = dir / dir.norm();
    let point = point.unwrap_or(com);
    let perp = (com - point) - direction * (com - point).dot(&direction);
    let radius = if joint == JointType::Revolute { (perp.norm_squared() + model.min_radius_m * model.min_radius_m).sqrt() } else { 0.0 };
    JointParams { joint, com, noise: model.noise_median_m, rot_noise: model.rotation_noise_median_rad, direction, point, radius }
}
