//! Posterior-predictive residuals of one joint: the observed joint coordinates and centres of mass
//! on the evidence grid, the joint's physics in every window (the model's
//! [`crate::model::dynamics::simulate_window`]), its predictions from a window's first frame, and
//! the structure of what the predictions miss.

use nalgebra::{Matrix3, Vector3};

use crate::inference::Posterior;
use crate::model::dynamics::{self, DynamicsConfig, JointInWindow, KinoParams, SubtreeBody};
use crate::model::effects::EffectSet;
use crate::model::likelihood::{Evidence, WindowEvidence};
use crate::model::physics::{generalised_force, JointKind};
use crate::model::{displacement, observed_coordinate, tree, Displacement, JointParams, JointType};

/// The MAP tree of a posterior as parent node indices (0 = fixed frame, `k + 1` = part `k`).
fn map_parents(post: &Posterior) -> Vec<usize> {
    post.joints.iter().map(|j| j.parent_index).collect()
}

/// Every part's displacement from its reference configuration at every grid frame, under the MAP
/// tree and joint types with guide-mean parameters and coordinates.
pub fn part_transforms(post: &Posterior, frames: usize) -> Vec<Vec<Displacement<f64>>> {
    tree::part_transforms(&map_parents(post), frames, |i, t| {
        let j = &post.joints[i];
        let (params, q) = (&j.mean_params[j.map_type.index()], &j.coordinates[j.map_type.index()]);
        displacement(params, q.get(t).copied().unwrap_or(0.0))
    })
}

/// One window of one joint, as its physics sees it: the joint moved by the parent's displacement
/// at the window's start, the child and its locked subtree there, and the window's frames at
/// which the part was seen.
#[derive(Debug, Clone)]
pub struct JointWindow {
    /// Index into [`Evidence::windows`].
    pub index: usize,
    pub joint: JointParams<f64>,
    pub com: Vector3<f64>,
    /// Where the child's weight acts ([`JointInWindow::weight_com`]).
    pub weight_com: Vector3<f64>,
    pub unit_inertia: Matrix3<f64>,
    pub subtree: Vec<SubtreeBody>,
    pub pushed: bool,
    /// The window with only the frames at which the part was seen (the first is its start).
    pub win: WindowEvidence,
}

/// One joint's observations and physics over all windows.
#[derive(Debug, Clone)]
pub struct JointSeries {
    /// Part index (evidence order) and label.
    pub part: usize,
    pub label: u32,
    /// The joint at guide-mean parameters, reference configuration.
    pub params: JointParams<f64>,
    /// The parent's displacement at every grid frame.
    pub pre: Vec<Displacement<f64>>,
    /// Observed joint coordinate at every grid frame [m of path] (NaN: not seen), by
    /// [`crate::model::observed_coordinate`].
    pub q: Vec<f64>,
    pub windows: Vec<JointWindow>,
}

impl JointSeries {
    /// The series of part `i`, or `None` when its MAP joint is rigid or it was never seen at the
    /// start of a window.
    pub fn new(ev: &Evidence, post: &Posterior, transforms: &[Vec<Displacement<f64>>], i: usize, cfg: &DynamicsConfig) -> Option<JointSeries> {
        let j = &post.joints[i];
        if !j.map_type.movable() {
            return None;
        }
        let params = j.mean_params[j.map_type.index()];
        let k = ev.len();
        let pre: Vec<Displacement<f64>> = match j.parent_index {
            0 => vec![Displacement::identity(); k],
            p => transforms[p - 1].clone(),
        };
        // A hinge's coordinate from its observed turn where the shape shows it
        // ([`observed_coordinate`]): criticism's residuals are otherwise a panel's slide in its
        // own plane, which an effect would "explain".
        let q: Vec<f64> = (0..k)
            .map(|t| match &ev.parts[i].obs[t] {
                Some(o) => observed_coordinate(&params, &pre[t], &o.y, ev.parts[i].rot[t].as_ref()),
                None => f64::NAN,
            })
            .collect();
        let desc = tree::descendants(&map_parents(post), i);
        let rotate = |d: &Displacement<f64>, u: &Matrix3<f64>| d.r * u * d.r.transpose();
        let windows: Vec<JointWindow> = ev
            .windows
            .iter()
            .enumerate()
            .filter_map(|(w, win)| {
                let f0 = win.frames[0];
                if q[f0].is_nan() {
                    return None;
                }
                // A push on a descendant reaches this joint whole only through rigid joints; through
                // a movable one (a latch on a door) the subtree is not locked and the joint's
                // share of the push is unknown: such a window cannot be predicted here.
                if win.pushed.is_some_and(|p| p != i && desc.contains(&p) && !rigidly_attached(post, p, i)) {
                    return None;
                }
                // A push whose hand is on something other than the part it was given to (an
                // unseen part, farther than the contact's reach from every point of this one)
                // moves this joint by an unknown share of the measured wrench: no prediction.
                if win.hand_off && win.pushed.is_some_and(|p| p == i || desc.contains(&p)) {
                    return None;
                }
                let keep: Vec<usize> = (0..win.frames.len()).filter(|&k| !q[win.frames[k]].is_nan()).collect();
                if keep.len() < 2 {
                    return None;
                }
                let mut sub = win.clone();
                sub.frames = keep.iter().map(|&k| win.frames[k]).collect();
                sub.frame_substep = keep.iter().map(|&k| win.frame_substep[k]).collect();
                let own = pre[f0].compose(&displacement(&params, q[f0]));
                let mut joint = params;
                joint.direction = pre[f0].r * params.direction;
                joint.point = pre[f0].apply(&params.point);
                let subtree = desc
                    .iter()
                    .map(|&m| {
                        let jm = &post.joints[m];
                        SubtreeBody {
                            mass: jm.kinodynamics.map_or(cfg.mass_median_kg, |kd| kd.mass.median),
                            com: transforms[m][f0].apply(&jm.mean_params[jm.map_type.index()].com),
                            unit_inertia: rotate(&transforms[m][f0], &ev.parts[m].unit_inertia),
                            weight_com: transforms[m][f0].apply(&(jm.mean_params[jm.map_type.index()].com + ev.parts[m].weight_offset)),
                        }
                    })
                    .collect();
                Some(JointWindow {
                    index: w,
                    joint,
                    com: own.apply(&params.com),
                    weight_com: own.apply(&(params.com + ev.parts[i].weight_offset)),
                    unit_inertia: rotate(&own, &ev.parts[i].unit_inertia),
                    subtree,
                    pushed: win.pushed.is_some_and(|p| p == i || desc.contains(&p)),
                    win: sub,
                })
            })
            .collect();
        if windows.is_empty() {
            return None;
        }
        Some(JointSeries { part: i, label: ev.parts[i].label, params, pre, q, windows })
    }

    /// The physics' view of window `w` (index into `self.windows`) with `effects`.
    pub fn joint_in_window(&self, w: usize, effects: EffectSet) -> JointInWindow<'_> {
        let jw = &self.windows[w];
        JointInWindow { joint: &jw.joint, com: jw.com, unit_inertia: jw.unit_inertia, weight_com: jw.weight_com, subtree: jw.subtree.clone(), pushed: jw.pushed, effects }
    }

    /// Log posterior density of the standardised kinodynamic parameters `xi` given the windows
    /// `use_window` selects (physics prior of [`dynamics::window_prior`] on the observed
    /// coordinates, plus the `N(0, I)` prior), and its gradient.
    pub fn log_posterior(&self, xi: &[f64], effects: EffectSet, use_window: &dyn Fn(usize) -> bool, cfg: &DynamicsConfig) -> (f64, Vec<f64>) {
        let mut l = -0.5 * xi.iter().map(|x| x * x).sum::<f64>();
        let mut g: Vec<f64> = xi.iter().map(|x| -x).collect();
        for w in 0..self.windows.len() {
            if !use_window(w) {
                continue;
            }
            let (lw, gw, _) = dynamics::window_prior(&self.joint_in_window(w, effects), &self.windows[w].win, &self.q, None, xi, cfg);
            l += lw;
            for (a, b) in g.iter_mut().zip(gw) {
                *a += b;
            }
        }
        (l, g)
    }

    /// The value of [`JointSeries::log_posterior`] alone, simulated in `f64`
    /// ([`dynamics::window_prior_value`]): what a grid search over the parameters needs, at a
    /// fraction of the dual numbers' cost.
    pub fn log_posterior_value(&self, xi: &[f64], effects: EffectSet, use_window: &dyn Fn(usize) -> bool, cfg: &DynamicsConfig) -> f64 {
        let prior = -0.5 * xi.iter().map(|x| x * x).sum::<f64>();
        prior + (0..self.windows.len()).filter(|&w| use_window(w)).map(|w| dynamics::window_prior_value(&self.joint_in_window(w, effects), &self.windows[w].win, &self.q, None, xi, cfg)).sum::<f64>()
    }

    /// Per window, the derivatives of the physics prior ([`dynamics::window_prior`]) at
    /// standardised parameters `xi` with `effects` with respect to the window's observed
    /// coordinates, one per frame of the window (the first through the simulation's start): for a
    /// Gaussian deviation `-(q_t - Psi_t) / sigma_d^2`, down-weighted where a Student-t one is large.
    /// Their autocorrelation measures how much the frames repeat each other
    /// ([`crate::inference::laplace::deviation_inflation`]).
    pub fn deviation_scores(&self, xi: &[f64], effects: EffectSet, cfg: &DynamicsConfig) -> Vec<Vec<f64>> {
        (0..self.windows.len()).map(|w| dynamics::window_prior(&self.joint_in_window(w, effects), &self.windows[w].win, &self.q, None, xi, cfg).2).collect()
    }

    /// Predicted coordinates of window `w` from its start ([`JointSeries::start`]), at rest, with
    /// parameters `xi` (the plug-in posterior-predictive mean): one per frame of the window.
    pub fn predict(&self, w: usize, xi: &[f64], effects: EffectSet, cfg: &DynamicsConfig) -> Vec<f64> {
        let jw = self.joint_in_window(w, effects);
        let win = &self.windows[w].win;
        let kp: KinoParams<f64> = dynamics::decode(self.params.joint, xi, &effects, cfg);
        let q0 = self.start(w);
        match dynamics::simulate_window(&jw, win, q0, &kp, cfg) {
            Some(traj) => win.frame_substep.iter().map(|&s| traj[s]).collect(),
            None => vec![q0; win.frames.len()],
        }
    }

    /// The coordinate at which window `w` starts [m of path]: the median of its first three
    /// observed frames, all before the push (windows open `margin_before_s` ahead of the force),
    /// so that one noisy frame does not offset a whole prediction.
    pub fn start(&self, w: usize) -> f64 {
        let win = &self.windows[w].win;
        let mut first: Vec<f64> = win.frames.iter().take(3).map(|&t| self.q[t]).collect();
        first.sort_by(f64::total_cmp);
        first[first.len() / 2]
    }

    /// The centre of mass at coordinate `q` and grid frame `t` [m, fixed frame].
    pub fn com_at(&self, t: usize, q: f64) -> Vector3<f64> {
        self.pre[t].compose(&displacement(&self.params, q)).apply(&self.params.com)
    }

    /// The generalised force of the measured wrench on the joint at frame `k` of window `w` (N or
    /// N·m), 0 when the window does not push the part.
    pub fn force_at(&self, w: usize, k: usize) -> f64 {
        let jw = &self.windows[w];
        if !jw.pushed {
            return 0.0;
        }
        let n = jw.win.frame_substep[k].min(jw.win.force.len().saturating_sub(1));
        if jw.win.force.is_empty() {
            return 0.0;
        }
        let kind = if jw.joint.joint == JointType::Revolute { JointKind::Revolute } else { JointKind::Prismatic };
        generalised_force(kind, &jw.joint.direction, &jw.joint.point, &jw.win.point[n], &jw.win.force[n], &jw.win.torque[n])
    }
}

/// Whether part `m`, a descendant of part `i`, hangs from it by rigid joints only (MAP types).
fn rigidly_attached(post: &Posterior, m: usize, i: usize) -> bool {
    let mut node = m;
    for _ in 0..=post.joints.len() {
        if node == i {
            return true;
        }
        let j = &post.joints[node];
        if j.map_type.movable() || j.parent_index == 0 {
            return false;
        }
        node = j.parent_index - 1;
    }
    false
}

/// One held-out frame: stamp \[s\], observed and predicted joint coordinate [m of path], the
/// centre-of-mass error \[m\], the observed velocity \[m/s of path\] and the applied generalised force.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ResidualPoint {
    pub window: usize,
    pub t: f64,
    /// Time since the window's start \[s\].
    pub since_start: f64,
    pub observed: f64,
    pub predicted: f64,
    pub com_error_m: f64,
    pub velocity: f64,
    pub force: f64,
}

/// Root-mean-square centre-of-mass error of residual points \[m\] (NaN when none).
pub fn rmse(points: &[ResidualPoint]) -> f64 {
    if points.is_empty() {
        return f64::NAN;
    }
    (points.iter().map(|p| p.com_error_m * p.com_error_m).sum::<f64>() / points.len() as f64).sqrt()
}

/// The structure of a residual: which signal it follows — its correlation with joint position,
/// velocity, the velocity's sign, the applied force and the time since the window's start
/// (Pearson; 0 where a quantity does not vary) — and where in the window it lies: its
/// centre-of-mass RMS error \[m\] in each phase of a push ([`Phases`]) and when it peaks.
///
/// Why both (issue 25): a correlation says what the missing term depends on, the phases say when
/// it acts. An error that grows only while the part coasts points at the damping law (quadratic
/// damping, a latch), one that appears at rest after the push at a restoring or holding force (a
/// spring, gravity, a stop the part rests against), one confined to the push at the force's
/// transmission (the contact, the lever arm).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Pattern {
    pub position: f64,
    pub velocity: f64,
    pub velocity_sign: f64,
    pub force: f64,
    pub time: f64,
    pub phases: Phases,
}

/// Where in its windows a residual lies: the centre-of-mass RMS error \[m\] over the held-out
/// frames of each phase (0 where a phase has no frame) and the time of the largest error as a
/// fraction of its window's held-out span (0 at its first frame, 1 at its last).
///
/// Phases, per window: *push* — the applied generalised force above a tenth of the window's
/// largest; *coast* — no push, the joint moving faster than a tenth of the window's largest
/// observed speed; *rest* — neither. Thresholds relative to each window, so that they hold for
/// any force scale and units (N or N·m, m/s or rad/s of path).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Phases {
    pub rmse_push_m: f64,
    pub rmse_coast_m: f64,
    pub rmse_rest_m: f64,
    pub peak_at: f64,
}

impl Phases {
    /// The phases of one part's held-out residual points (any number of windows; all zero when
    /// there are none).
    pub fn of(points: &[ResidualPoint]) -> Phases {
        let mut windows: Vec<usize> = points.iter().map(|p| p.window).collect();
        windows.sort_unstable();
        windows.dedup();
        let (mut sq, mut n) = ([0.0f64; 3], [0usize; 3]);
        let mut peak: Option<(f64, f64)> = None;
        for w in windows {
            let pts: Vec<&ResidualPoint> = points.iter().filter(|p| p.window == w).collect();
            let max_f = pts.iter().map(|p| p.force.abs()).fold(0.0, f64::max);
            let max_v = pts.iter().map(|p| p.velocity.abs()).fold(0.0, f64::max);
            let (t0, t1) = pts.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| (a.min(p.since_start), b.max(p.since_start)));
            for p in &pts {
                let phase = if max_f > 0.0 && p.force.abs() > 0.1 * max_f {
                    0
                } else if max_v > 0.0 && p.velocity.abs() > 0.1 * max_v {
                    1
                } else {
                    2
                };
                sq[phase] += p.com_error_m * p.com_error_m;
                n[phase] += 1;
                if peak.is_none_or(|(e, _)| p.com_error_m > e) {
                    let at = if t1 > t0 { (p.since_start - t0) / (t1 - t0) } else { 0.0 };
                    peak = Some((p.com_error_m, at));
                }
            }
        }
        let rms = |k: usize| if n[k] > 0 { (sq[k] / n[k] as f64).sqrt() } else { 0.0 };
        Phases { rmse_push_m: rms(0), rmse_coast_m: rms(1), rmse_rest_m: rms(2), peak_at: peak.map_or(0.0, |p| p.1) }
    }

    /// `(name, value)` pairs, in the order of the fields.
    pub fn entries(&self) -> [(&'static str, f64); 4] {
        [("rmse_push_m", self.rmse_push_m), ("rmse_coast_m", self.rmse_coast_m), ("rmse_rest_m", self.rmse_rest_m), ("peak_at", self.peak_at)]
    }
}

impl Pattern {
    pub fn of(points: &[ResidualPoint]) -> Pattern {
        let r: Vec<f64> = points.iter().map(|p| p.observed - p.predicted).collect();
        let corr = |x: Vec<f64>| pearson(&x, &r);
        Pattern {
            position: corr(points.iter().map(|p| p.observed).collect()),
            velocity: corr(points.iter().map(|p| p.velocity).collect()),
            velocity_sign: corr(points.iter().map(|p| if p.velocity.abs() < 1e-3 { 0.0 } else { p.velocity.signum() }).collect()),
            force: corr(points.iter().map(|p| p.force).collect()),
            time: corr(points.iter().map(|p| p.since_start).collect()),
            phases: Phases::of(points),
        }
    }

    /// Every entry of the diagnosis: the correlations ([`Pattern::entries`]) then the phases
    /// ([`Phases::entries`]).
    pub fn diagnosis(&self) -> Vec<(&'static str, f64)> {
        self.entries().into_iter().chain(self.phases.entries()).collect()
    }

    /// `(name, correlation)` pairs, in the order of the correlation fields.
    pub fn entries(&self) -> [(&'static str, f64); 5] {
        [
            ("corr_position", self.position),
            ("corr_velocity", self.velocity),
            ("corr_velocity_sign", self.velocity_sign),
            ("corr_force", self.force),
            ("corr_time", self.time),
        ]
    }

    /// The quantity the residual follows most closely.
    pub fn strongest(&self) -> (&'static str, f64) {
        self.entries().into_iter().max_by(|a, b| a.1.abs().total_cmp(&b.1.abs())).unwrap_or(("none", 0.0))
    }
}

fn pearson(x: &[f64], y: &[f64]) -> f64 {
    let n = x.len() as f64;
    if x.len() < 3 {
        return 0.0;
    }
    let (mx, my) = (x.iter().sum::<f64>() / n, y.iter().sum::<f64>() / n);
    let (mut sxy, mut sxx, mut syy) = (0.0, 0.0, 0.0);
    for (a, b) in x.iter().zip(y) {
        sxy += (a - mx) * (b - my);
        sxx += (a - mx) * (a - mx);
        syy += (b - my) * (b - my);
    }
    if sxx <= 1e-18 || syy <= 1e-18 {
        0.0
    } else {
        sxy / (sxx * syy).sqrt()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(window: usize, since_start: f64, force: f64, velocity: f64, com_error_m: f64) -> ResidualPoint {
        ResidualPoint { window, t: since_start, since_start, observed: 0.0, predicted: 0.0, com_error_m, velocity, force }
    }

    /// A push (force on), a coast (force off, moving) and a rest: each frame's error lands in its
    /// phase, relative to each window's own force and speed scales, and the peak is placed in its
    /// window's span.
    #[test]
    fn phases_split_the_error_by_the_push_it_falls_in() {
        let mut pts = Vec::new();
        for k in 0..10 {
            let t = k as f64 * 0.1;
            // Window 0 in newtons and m/s: push 0-0.3 s, coast 0.4-0.6 s, rest after; error 1 cm at rest.
            let (f, v, e) = match k {
                0..=3 => (5.0, 0.2, 0.0),
                4..=6 => (0.0, 0.1, 0.0),
                _ => (0.0, 0.001, 0.01),
            };
            pts.push(point(0, t, f, v, e));
            // Window 1 a thousand times smaller force and speed: the same phases; error 2 cm coasting.
            pts.push(point(1, t, f * 1e-3, v * 1e-3, if (4..=6).contains(&k) { 0.02 } else { 0.0 }));
        }
        let p = Phases::of(&pts);
        assert_eq!(p.rmse_push_m, 0.0);
        assert!((p.rmse_coast_m - (0.02f64.powi(2) * 3.0 / 6.0).sqrt()).abs() < 1e-12, "{p:?}");
        assert!((p.rmse_rest_m - (0.01f64.powi(2) * 3.0 / 6.0).sqrt()).abs() < 1e-12, "{p:?}");
        // The largest error (2 cm) first at 0.4 s of a window spanning 0-0.9 s.
        assert!((p.peak_at - 0.4 / 0.9).abs() < 1e-12, "{p:?}");
        assert_eq!(Phases::of(&[]), Phases::default());
    }
}
