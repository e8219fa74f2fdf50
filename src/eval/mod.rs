//! `bom eval`: the metrics of contract section 6 — a replay's posterior against the bags'
//! `bom_ground_truth` (the paper's Joint%, Graph MSE and IdE, Table 1, plus parent accuracy and
//! axis errors).

pub mod baselines;
pub mod corpus;
pub mod criticism;
pub mod tracking;

use nalgebra::Vector3;
use serde::Serialize;

use crate::inference::Posterior;
use crate::input::{GroundTruth, GtPart};
use crate::model::JointType;

/// The metrics of one part (`null` where the ground truth or the estimate lacks the quantity).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct PartMetrics {
    pub label: u32,
    pub true_joint: String,
    pub estimated_joint: Option<String>,
    pub joint_correct: bool,
    pub true_parent: u32,
    pub estimated_parent: Option<u32>,
    pub parent_correct: bool,
    /// Mean over candidate parents of `(1[true] - P)^2`.
    pub graph_mse: f64,
    pub axis_angle_deg: Option<f64>,
    /// Distance between the estimated and the true axis lines (contract section 6) \[m\].
    pub axis_offset_m: Option<f64>,
    /// Distance from the true axis point (on the hinge, by the part) to the estimated axis line
    /// \[m\] (beyond contract section 6). Two nearly parallel lines come closest far from the
    /// object, so the line distance can be millimetres while the axes are centimetres apart
    /// where the door hangs; this says how far off the hinge is where it matters.
    pub axis_offset_at_point_m: Option<f64>,
    /// `|median - true| / |true|` of damping and friction (dynamic mode; not defined for a true
    /// value of 0).
    pub damping_rel_error: Option<f64>,
    pub friction_rel_error: Option<f64>,
    /// The posterior medians and true values behind those errors (damping N·s/m or N·m·s/rad,
    /// friction N or N·m, the joint's own units; beyond contract section 6): the sign of an
    /// error, which the relative error drops, is what tells a bias from noise.
    pub damping_median: Option<f64>,
    pub damping_true: Option<f64>,
    pub friction_median: Option<f64>,
    pub friction_true: Option<f64>,
    /// Whether the true value lies in the 90% posterior interval (calibration, beyond contract
    /// section 6): damping and friction in `[q05, q95]` (not defined for a true value of 0, which
    /// a positive parameter's interval cannot hold), the axis direction within the 90% credible
    /// cone.
    pub damping_covered: Option<bool>,
    pub friction_covered: Option<bool>,
    pub axis_covered: Option<bool>,
    /// The 90% intervals themselves, for the report.
    pub damping_interval: Option<[f64; 2]>,
    pub friction_interval: Option<[f64; 2]>,
    pub axis_cone_deg: Option<f64>,
    /// The posterior's own 90% cone, before the model discrepancy (`model.axis_discrepancy_deg`):
    /// what SVI's and NUTS's axes are compared by ([`corpus::svi_vs_nuts`]).
    pub axis_cone_posterior_deg: Option<f64>,
    /// A true revolute joint called revolute: whether the true hinge point lies within the 90%
    /// disc of the estimated point, `axis_offset_at_point_m <= 2.146 point_sd_m / sqrt(2)` (the
    /// sampled points spread across the axis, `point_sd_m` their RMS distance: a 2-D Gaussian's
    /// Rayleigh quantile; the axis's tilt at the true point is not added). Not in
    /// [`Coverage::all`].
    pub axis_point_covered: Option<bool>,
    /// Revolute axes: the reported point spread (RMS distance, m), the posterior's own before
    /// the model discrepancy (`model.axis_point_discrepancy_m`), and the turn the part was seen
    /// to make (rad).
    pub axis_point_sd_m: Option<f64>,
    pub axis_point_posterior_sd_m: Option<f64>,
    pub axis_turn_rad: Option<f64>,
}

/// Calibration over all movable parts: how often the truth lies in the 90% posterior interval.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Coverage {
    /// Cases inside / cases counted, per quantity and in all.
    pub damping: [usize; 2],
    pub friction: [usize; 2],
    pub axis_angle: [usize; 2],
    /// The revolute hinge points ([`PartMetrics::axis_point_covered`]); not counted in `all`
    /// (added in stop 77, after `all` had been reported for many stops).
    pub axis_point: [usize; 2],
    pub all: [usize; 2],
    /// `all[0] / all[1]`.
    pub fraction: Option<f64>,
}

/// A baseline that scores the tree only.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct GraphRow {
    pub graph_mse: f64,
}

/// The paper's baselines (contract section 4, `--baselines`): the empty graph (every `P = 0`),
/// the complete graph (every `P = 1`), and differentiable simulation with the true structure and
/// axes, from the priors' medians and from their 1% tails ([`baselines`]; dynamic mode only).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Baselines {
    pub disconnected: GraphRow,
    pub clique: GraphRow,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub diff_sim: Option<baselines::DiffSimRow>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub diff_sim_tail_init: Option<baselines::DiffSimRow>,
}

/// The report of `bom eval` (contract section 6).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Metrics {
    pub joint_accuracy: f64,
    pub graph_mse: f64,
    pub parent_accuracy: f64,
    pub ide: Option<f64>,
    pub axis_angle_deg: Option<f64>,
    pub axis_offset_m: Option<f64>,
    pub coverage: Coverage,
    pub per_part: Vec<PartMetrics>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub baselines: Option<Baselines>,
    /// `--tracking` (contract section 5): leave-one-interaction-out prediction ([`tracking`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tracking: Option<tracking::Tracking>,
}

/// The median of `v` (`None` when empty).
pub fn median(mut v: Vec<f64>) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    Some(if n % 2 == 1 { v[n / 2] } else { 0.5 * (v[n / 2 - 1] + v[n / 2]) })
}

/// Static nodes: the fixed frame (0) and parts joined to it by rigid joints only.
fn static_nodes(gt: &GroundTruth) -> Vec<u32> {
    let mut out = vec![0];
    loop {
        let before = out.len();
        for p in &gt.parts {
            if JointType::parse(&p.joint) == Some(JointType::Rigid) && out.contains(&p.parent) && !out.contains(&p.label) {
                out.push(p.label);
            }
        }
        if out.len() == before {
            return out;
        }
    }
}

/// Angle between two axis directions, sign ignored \[deg\].
fn axis_angle(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    (a.dot(b).abs() / (a.norm() * b.norm())).clamp(-1.0, 1.0).acos().to_degrees()
}

/// Distance between the lines `p1 + s d1` and `p2 + t d2` \[m\].
fn line_distance(p1: &Vector3<f64>, d1: &Vector3<f64>, p2: &Vector3<f64>, d2: &Vector3<f64>) -> f64 {
    let n = d1.cross(d2);
    let w = p2 - p1;
    if n.norm() < 1e-9 {
        // Parallel: the distance from p2 to the first line.
        point_line_distance(p2, p1, d1)
    } else {
        w.dot(&n).abs() / n.norm()
    }
}

/// Distance from the point `q` to the line `p + s d` \[m\].
fn point_line_distance(q: &Vector3<f64>, p: &Vector3<f64>, d: &Vector3<f64>) -> f64 {
    let (w, d) = (q - p, d / d.norm());
    (w - d * w.dot(&d)).norm()
}

fn part_metrics(gt: &GroundTruth, part: &GtPart, post: &Posterior, statics: &[u32]) -> PartMetrics {
    let joint = post.joints.iter().find(|j| j.child == part.label);
    let true_type = JointType::parse(&part.joint);
    let est_type = joint.map(|j| j.map_type);
    // Candidates: the fixed frame and every other part of the ground truth.
    let candidates: Vec<u32> = std::iter::once(0).chain(gt.parts.iter().map(|p| p.label).filter(|&l| l != part.label)).collect();
    let prob = |c: u32| joint.and_then(|j| j.parent_probs.iter().find(|(l, _)| *l == c).map(|x| x.1)).unwrap_or(0.0);
    let graph_mse =
        candidates.iter().map(|&c| ((c == part.parent) as u8 as f64 - prob(c)).powi(2)).sum::<f64>() / candidates.len() as f64;
    let est_parent = joint.map(|j| j.parent);
    let parent_correct = match est_parent {
        Some(p) => p == part.parent || (statics.contains(&part.parent) && statics.contains(&p)),
        None => false,
    };
    let axis = joint.and_then(|j| j.axis.as_ref()).filter(|_| est_type.is_some_and(|t| t.movable()));
    let axis_angle_deg = match (axis, part.axis_direction) {
        (Some(a), Some(d)) if true_type.is_some_and(|t| t.movable()) => Some(axis_angle(&a.direction, &Vector3::from(d))),
        _ => None,
    };
    let axis_offset_m = match (axis.and_then(|a| a.point.map(|p| (p, a.direction))), part.axis_direction, part.axis_point) {
        (Some((p, d)), Some(td), Some(tp)) if true_type == Some(JointType::Revolute) => {
            Some(line_distance(&p, &d, &Vector3::from(tp), &Vector3::from(td)))
        }
        _ => None,
    };
    let axis_offset_at_point_m = match (axis.and_then(|a| a.point.map(|p| (p, a.direction))), part.axis_point) {
        (Some((p, d)), Some(tp)) if true_type == Some(JointType::Revolute) => Some(point_line_distance(&Vector3::from(tp), &p, &d)),
        _ => None,
    };
    let kd = joint.and_then(|j| j.kinodynamics.as_ref()).filter(|_| est_type.is_some_and(|t| t.movable()) && true_type.is_some_and(|t| t.movable()));
    let rel = |est: Option<f64>, truth: Option<f64>| match (est, truth) {
        (Some(e), Some(t)) if t != 0.0 => Some((e - t).abs() / t.abs()),
        _ => None,
    };
    let inside = |iv: Option<[f64; 2]>, truth: Option<f64>| match (iv, truth) {
        (Some([lo, hi]), Some(t)) if t != 0.0 => Some(lo <= t && t <= hi),
        _ => None,
    };
    let damping_interval = kd.map(|k| [k.damping.q05, k.damping.q95]);
    let friction_interval = kd.map(|k| [k.friction.q05, k.friction.q95]);
    let axis_cone_deg = axis.map(|a| a.direction_q90_deg);
    let (damping_median, friction_median) = (kd.map(|k| k.damping.median), kd.map(|k| k.friction.median));
    PartMetrics {
        label: part.label,
        true_joint: part.joint.clone(),
        estimated_joint: est_type.map(|t| t.name().to_string()),
        joint_correct: est_type.is_some() && est_type == true_type,
        true_parent: part.parent,
        estimated_parent: est_parent,
        parent_correct,
        graph_mse,
        axis_angle_deg,
        axis_offset_m,
        axis_offset_at_point_m,
        damping_rel_error: rel(damping_median, part.damping),
        friction_rel_error: rel(friction_median, part.friction),
        damping_median,
        damping_true: kd.and(part.damping),
        friction_median,
        friction_true: kd.and(part.friction),
        damping_covered: inside(damping_interval, part.damping),
        friction_covered: inside(friction_interval, part.friction),
        axis_covered: axis_angle_deg.zip(axis_cone_deg).map(|(a, c)| a <= c),
        damping_interval,
        friction_interval,
        axis_cone_deg,
        axis_cone_posterior_deg: axis.map(|a| a.posterior_q90_deg),
        axis_point_covered: axis
            .filter(|a| a.joint == JointType::Revolute && a.point_sd_m.is_finite())
            .zip(axis_offset_at_point_m)
            .map(|(a, d)| d <= crate::inference::RAYLEIGH_Q90 / std::f64::consts::SQRT_2 * a.point_sd_m),
        axis_point_sd_m: axis.map(|a| a.point_sd_m).filter(|v| v.is_finite()),
        axis_point_posterior_sd_m: axis.map(|a| a.point_posterior_sd_m).filter(|v| v.is_finite()),
        axis_turn_rad: joint.filter(|_| axis.is_some()).map(|j| j.turn_rad()).filter(|v| v.is_finite()),
    }
}

/// Compute the metrics of a posterior against ground truth. `baselines` adds the paper's
/// Disconnected and Clique rows.
pub fn evaluate(gt: &GroundTruth, post: &Posterior, baselines: bool) -> Metrics {
    let statics = static_nodes(gt);
    let per_part: Vec<PartMetrics> = gt.parts.iter().map(|p| part_metrics(gt, p, post, &statics)).collect();
    let n = per_part.len().max(1) as f64;
    let movable = |m: &&PartMetrics| JointType::parse(&m.true_joint).is_some_and(|t| t.movable());
    let ide = median(
        per_part.iter().filter(movable).flat_map(|m| [m.damping_rel_error, m.friction_rel_error]).flatten().collect(),
    );
    let k = gt.parts.len() as f64;
    let count = |f: &dyn Fn(&PartMetrics) -> Option<bool>| {
        let v: Vec<bool> = per_part.iter().filter(movable).filter_map(f).collect();
        [v.iter().filter(|b| **b).count(), v.len()]
    };
    let (d, f, a) = (count(&|m| m.damping_covered), count(&|m| m.friction_covered), count(&|m| m.axis_covered));
    let all = [d[0] + f[0] + a[0], d[1] + f[1] + a[1]];
    let axis_point = count(&|m| m.axis_point_covered);
    let coverage = Coverage { damping: d, friction: f, axis_angle: a, axis_point, all, fraction: (all[1] > 0).then(|| all[0] as f64 / all[1] as f64) };
    Metrics {
        joint_accuracy: per_part.iter().filter(|m| m.joint_correct).count() as f64 / n,
        graph_mse: per_part.iter().map(|m| m.graph_mse).sum::<f64>() / n,
        parent_accuracy: per_part.iter().filter(|m| m.parent_correct).count() as f64 / n,
        ide,
        axis_angle_deg: median(per_part.iter().filter(movable).filter_map(|m| m.axis_angle_deg).collect()),
        axis_offset_m: median(per_part.iter().filter_map(|m| m.axis_offset_m).collect()),
        coverage,
        // Each part has one true parent among k candidates (the fixed frame and k - 1 parts).
        baselines: baselines.then(|| Baselines {
            disconnected: GraphRow { graph_mse: 1.0 / k.max(1.0) },
            clique: GraphRow { graph_mse: (k - 1.0).max(0.0) / k.max(1.0) },
            diff_sim: None,
            diff_sim_tail_init: None,
        }),
        tracking: None,
        per_part,
    }
}

/// Add the differentiable-simulation baselines ([`baselines::diff_sim`], from the priors'
/// medians and from their 1% tails) to `metrics.baselines` when there are some and `run` is in
/// dynamic mode (windows with wrenches); otherwise nothing.
pub fn add_diff_sim(metrics: &mut Metrics, run: &crate::pipeline::Run, gt: &GroundTruth, cfg: &crate::config::Config) {
    if let (Some(b), false) = (metrics.baselines.as_mut(), run.windows.is_empty() || run.wrenches.is_empty()) {
        let ev = crate::pipeline::final_evidence(run, cfg);
        b.diff_sim = Some(baselines::diff_sim(&ev, gt, &cfg.model, baselines::Start::Median));
        b.diff_sim_tail_init = Some(baselines::diff_sim(&ev, gt, &cfg.model, baselines::Start::LowerTail));
    }
}

/// A readable table of `--tracking`: per held-out window, open-loop and one-step MSE of bom and
/// the two Kalman filters, and the band's coverage (bom: the simulation at the posterior medians;
/// the mean line adds the open-loop MSE of the draws' mean).
pub fn render_tracking(t: &tracking::Tracking) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    let _ = writeln!(s, "  tracking (leave one interaction out), MSE [m^2]: bom / const. velocity / const. acceleration");
    let row = |m: &Option<tracking::Mse>| m.map_or("-".to_string(), |m| format!("{:.3e} / {:.3e} / {:.3e}", m.mse_bom_m2, m.mse_const_vel_m2, m.mse_const_acc_m2));
    for i in &t.interactions {
        let _ = write!(s, "    window {:>2} ({:>8.2}-{:>8.2} s, part {:>2}): open loop {}  one step {}", i.window, i.start_s, i.end_s, i.pushed_part.map_or("-".into(), |p| p.to_string()), row(&i.open_loop), row(&i.one_step));
        match (&i.skipped, i.coverage_90) {
            (Some(why), _) => {
                let _ = writeln!(s, "  ({why})");
            }
            (None, Some(c)) => {
                let _ = writeln!(s, "  band {c:.2}");
            }
            _ => {
                let _ = writeln!(s);
            }
        }
    }
    let draws_mean = t.open_loop.and_then(|m| m.mse_bom_mean_m2).map_or("-".to_string(), |x| format!("{x:.3e}"));
    let _ = writeln!(s, "    mean: open loop {} (bom's draws' mean {draws_mean})  one step {}  band coverage {}  one step bom best {}/{}", row(&t.open_loop), row(&t.one_step), t.coverage_90.map_or("-".into(), |c| format!("{c:.2}")), t.one_step_bom_best[0], t.one_step_bom_best[1]);
    s
}

/// A readable table of the metrics.
pub fn render(m: &Metrics) -> String {
    use std::fmt::Write;
    let opt = |v: Option<f64>, p: usize| v.map(|x| format!("{x:.p$}")).unwrap_or_else(|| "-".into());
    let mark = |c: Option<bool>| match c {
        Some(true) => "in",
        Some(false) => "OUT",
        None => "-",
    };
    let mut s = String::new();
    let _ = writeln!(
        s,
        "  {:>5} {:>10} {:>10} {:>6} {:>7} {:>9} {:>10} {:>10} {:>9} {:>9} {:>9}  in 90% interval (damping, friction, axis)",
        "part", "true", "estimated", "parent", "P-MSE", "axis[deg]", "offset[m]", "at pt [m]", "damp.err", "fric.err", "correct"
    );
    for p in &m.per_part {
        let _ = writeln!(
            s,
            "  {:>5} {:>10} {:>10} {:>6} {:>7.4} {:>9} {:>10} {:>10} {:>9} {:>9} {:>9}  {} {} {}",
            p.label,
            p.true_joint,
            p.estimated_joint.as_deref().unwrap_or("-"),
            p.estimated_parent.map(|x| x.to_string()).unwrap_or("-".into()),
            p.graph_mse,
            opt(p.axis_angle_deg, 2),
            opt(p.axis_offset_m, 4),
            opt(p.axis_offset_at_point_m, 4),
            opt(p.damping_rel_error, 3),
            opt(p.friction_rel_error, 3),
            if p.joint_correct && p.parent_correct { "yes" } else { "no" },
            mark(p.damping_covered),
            mark(p.friction_covered),
            mark(p.axis_covered),
        );
    }
    let _ = writeln!(
        s,
        "  joint_accuracy {:.3}  graph_mse {:.4}  parent_accuracy {:.3}  ide {}  axis_angle_deg {}  axis_offset_m {}",
        m.joint_accuracy,
        m.graph_mse,
        m.parent_accuracy,
        opt(m.ide, 3),
        opt(m.axis_angle_deg, 2),
        opt(m.axis_offset_m, 4)
    );
    let c = &m.coverage;
    let _ = writeln!(
        s,
        "  90% interval coverage: damping {}/{}, friction {}/{}, axis {}/{}, all {}/{} = {}; hinge point {}/{}",
        c.damping[0],
        c.damping[1],
        c.friction[0],
        c.friction[1],
        c.axis_angle[0],
        c.axis_angle[1],
        c.all[0],
        c.all[1],
        opt(c.fraction, 3),
        c.axis_point[0],
        c.axis_point[1]
    );
    if let Some(b) = &m.baselines {
        let _ = writeln!(s, "  baselines: Disconnected graph_mse {:.3}, Clique graph_mse {:.3}", b.disconnected.graph_mse, b.clique.graph_mse);
        for (name, row) in [("Diff. sim.", &b.diff_sim), ("Diff. sim. tail init", &b.diff_sim_tail_init)] {
            if let Some(r) = row {
                let _ = writeln!(s, "  baselines: {name} (true structure and axes) ide {} in {:.2} s", opt(r.ide, 3), r.runtime_s);
            }
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn line_distances_and_angles() {
        let (z, x) = (Vector3::z(), Vector3::x());
        assert!((line_distance(&Vector3::zeros(), &z, &Vector3::new(0.3, 0.4, 2.0), &z) - 0.5).abs() < 1e-12);
        assert!((line_distance(&Vector3::zeros(), &z, &Vector3::new(0.0, 0.7, 1.0), &x) - 0.7).abs() < 1e-12);
        assert!((axis_angle(&z, &-z)).abs() < 1e-6);
        // Nearly parallel hinges 5 cm apart by the door cross far away: the line distance is
        // small, the distance at the door's hinge point is not.
        let tilted = Vector3::new(0.01, 0.0, 1.0);
        let (door, estimate) = (Vector3::new(0.0, 0.0, 1.0), Vector3::new(0.05, 0.0, 1.0));
        assert!(line_distance(&estimate, &tilted, &door, &z) < 1e-9);
        assert!((point_line_distance(&door, &estimate, &tilted) - 0.05).abs() < 1e-4);
        assert!((axis_angle(&z, &Vector3::new(0.0, 1.0, 1.0)) - 45.0).abs() < 1e-9);
    }
}
