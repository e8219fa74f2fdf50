//! `bom eval --tracking` (contract sections 4-5; issue 28): how well the posterior predicts part
//! motion under pushes it was not fitted on — the paper's Table 3 (§4.3, tracking MSE of part
//! centres under novel actions against constant-velocity and constant-acceleration models).
//!
//! Leave one interaction out: for every window with a pushed part, BOM-SVI is fitted on the
//! other windows (with criticism, as a replay would: effects adopted on them join the model;
//! the recording's declared effects are in it from the start), and the held-out window is
//! predicted with [`crate::prediction`]:
//! - **open loop**: from the state observed over the window's first 0.1 s
//!   ([`PredictConfig::state_window_s`]) and the measured wrench, every part's centre of mass over
//!   the rest of the window (the simulation at the posterior medians, and the 90% band of
//!   [`PredictConfig::draws`] posterior draws; the draws' mean is scored beside it);
//! - **one step** (what a tracker uses): at each cloud of the window, the next cloud's centres
//!   from everything observed up to it (the state at this cloud) and the wrench up to the next.
//!
//! The baselines are Kalman filters per part on the observed centres (axes independent):
//! constant velocity (white-noise acceleration) and constant acceleration (white-noise jerk),
//! continuous-time process noise (Bar-Shalom, Li & Kirubarajan, *Estimation with Applications to
//! Tracking and Navigation*, 2001, §6.2), measurement variance perception's own per frame. The
//! process noise intensities are [`TrackingConfig`]'s, chosen on the corpus's `tune` split (README).
//! Open loop, the filters see the same first 0.1 s; one step, every observation before the
//! predicted cloud.

use nalgebra::{SMatrix, SVector, Vector3};
use serde::Serialize;

use crate::config::Config;
use crate::pipeline::{self, Effects, EvidenceSource, Run};
use crate::prediction::{self, PredictConfig, PredictiveModel, Scene};

/// Settings of the tracking evaluation.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrackingConfig {
    /// Process noise intensity of the constant-velocity filter (white acceleration) \[m²/s³\].
    pub const_vel_q: f64,
    /// Process noise intensity of the constant-acceleration filter (white jerk) \[m²/s⁵\].
    pub const_acc_q: f64,
}

impl Default for TrackingConfig {
    fn default() -> Self {
        TrackingConfig { const_vel_q: 0.1, const_acc_q: 10.0 }
    }
}

/// Process noise intensities tried for each filter ([`Tracking::kalman_grid`]): decades around
/// any plausible push (constant velocity m²/s³, constant acceleration m²/s⁵).
pub const CONST_VEL_Q_GRID: [f64; 7] = [1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0];
pub const CONST_ACC_Q_GRID: [f64; 7] = [1e-2, 1e-1, 1.0, 10.0, 100.0, 1e3, 1e4];

/// One filter at one process noise intensity: its MSEs averaged over the scored windows as the
/// headline numbers are.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct GridRow {
    /// `const_vel` or `const_acc`.
    pub filter: String,
    pub q: f64,
    pub open_loop_mse_m2: Option<f64>,
    pub one_step_mse_m2: Option<f64>,
}

/// Mean squared distance of predicted from observed centres of mass \[m²\], bom and baselines.
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct Mse {
    /// bom's: the simulation at the posterior medians ([`prediction::PartPrediction::com`]).
    pub mse_bom_m2: f64,
    /// Open loop (beyond the contract): bom's MSE with the posterior draws' mean centre of mass
    /// ([`prediction::PartPrediction::mean`]), the prediction of least expected squared error
    /// were the draws the posterior's; measured and not made the headline (README, stop 121).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mse_bom_mean_m2: Option<f64>,
    pub mse_const_vel_m2: f64,
    pub mse_const_acc_m2: f64,
    /// Predicted (part, cloud) pairs with an observation.
    pub frames: usize,
}

/// One held-out interaction.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Interaction {
    /// Index of the window (time order) and its span \[s\].
    pub window: usize,
    pub start_s: f64,
    pub end_s: f64,
    pub pushed_part: Option<u32>,
    /// Whether another window (one the posterior was fitted on) pushes the same part (beyond the
    /// contract): where none does, that part's kinodynamics are its prior's.
    pub pushed_elsewhere: bool,
    pub open_loop: Option<Mse>,
    pub one_step: Option<Mse>,
    /// Open loop: fraction of observed centres inside the 90% band (widened by perception's noise,
    /// [`prediction::PartScore::coverage_90`]).
    pub coverage_90: Option<f64>,
    /// Why the window was not scored, when it was not.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub skipped: Option<String>,
}

/// The JSON `tracking` object (contract section 5).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Tracking {
    /// Means over the scored held-out windows of their MSEs.
    pub open_loop: Option<Mse>,
    pub one_step: Option<Mse>,
    /// Open loop over the windows whose pushed part another window pushes, and over those where
    /// the held-out push is the part's only one (beyond the contract; [`Interaction::pushed_elsewhere`]).
    pub open_loop_pushed_elsewhere: Option<Mse>,
    pub open_loop_only_push: Option<Mse>,
    /// Open loop: observed centres inside the 90% band, pooled over windows.
    pub coverage_90: Option<f64>,
    /// One step: held-out windows where bom's MSE is below both filters', and windows scored.
    pub one_step_bom_best: [usize; 2],
    pub interactions: Vec<Interaction>,
    /// Both filters over [`CONST_VEL_Q_GRID`] / [`CONST_ACC_Q_GRID`] (beyond the contract): how
    /// the baselines' process noise was chosen (on the `tune` split) and how much it matters.
    pub kalman_grid: Vec<GridRow>,
}

/// Leave-one-interaction-out tracking of a replay (dynamic mode; kinematic windows have no
/// wrench to predict under and are skipped).
pub fn evaluate(run: &Run, cfg: &Config) -> Tracking {
    let tcfg = &cfg.tracking;
    let scene = Scene { tracks: &run.tracks, geometry: &run.geometry, wrenches: &run.wrenches, windows: &run.windows };
    let stamps = scene.stamps();
    let declared = run.ground_truth.as_ref().map(pipeline::declared_effects).unwrap_or_default();
    let mut interactions = Vec::new();
    // Per window, per grid entry (constant velocity's, then constant acceleration's): the sum of
    // squared errors and the count, open loop and one step.
    let mut grid: Vec<Vec<[f64; 4]>> = Vec::new();
    let grid_q: Vec<(usize, f64)> = CONST_VEL_Q_GRID.iter().map(|&q| (2, q)).chain(CONST_ACC_Q_GRID.iter().map(|&q| (3, q))).collect();
    let kalman = |order: usize, seen: &[(f64, Vector3<f64>, f64)], q: f64| -> Option<Box<dyn Fn(f64) -> Vector3<f64>>> {
        match order {
            2 => Kalman::<2>::run(seen, q).map(|f| Box::new(move |t| f.predict(t)) as Box<dyn Fn(f64) -> Vector3<f64>>),
            _ => Kalman::<3>::run(seen, q).map(|f| Box::new(move |t| f.predict(t)) as Box<dyn Fn(f64) -> Vector3<f64>>),
        }
    };
    for (w, win) in run.windows.iter().enumerate() {
        let mut g = vec![[0.0; 4]; grid_q.len()];
        let pushed_elsewhere = win.pushed_part.is_some() && run.windows.iter().enumerate().any(|(k, x)| k != w && x.pushed_part == win.pushed_part);
        let mut row = Interaction { window: w, start_s: win.start, end_s: win.end, pushed_part: win.pushed_part, pushed_elsewhere, open_loop: None, one_step: None, coverage_90: None, skipped: None };
        if run.wrenches.is_empty() || win.pushed_part.is_none() {
            row.skipped = Some("no wrench or no pushed part".into());
            interactions.push(row);
            grid.push(Vec::new());
            continue;
        }
        let others: Vec<_> = run.windows.iter().enumerate().filter(|(k, _)| *k != w).map(|(_, x)| *x).collect();
        let src = EvidenceSource { tracks: &run.tracks, geometry: &run.geometry, windows: &others, wrenches: &run.wrenches };
        let mut effects = Effects { declared: declared.clone(), adopted: Default::default() };
        let Some((fitted, criticism)) = (!others.is_empty()).then(|| pipeline::update(src, &mut effects, cfg, None)).flatten() else {
            row.skipped = Some("no posterior from the other windows".into());
            interactions.push(row);
            grid.push(Vec::new());
            continue;
        };
        let model = PredictiveModel::from_posterior(&fitted.posterior, &criticism.findings);
        let held: Vec<f64> = stamps.iter().copied().filter(|&t| win.contains(t)).collect();
        let from = win.start + cfg.prediction.state_window_s;
        // Open loop.
        let ahead: Vec<f64> = held.iter().copied().filter(|&t| t > from).collect();
        let pcfg = PredictConfig { seed: w as u64, ..cfg.prediction };
        match prediction::predict(&model, &scene, from, &ahead, &pcfg, &cfg.model) {
            Ok(pred) => {
                let mut acc = Accumulator::default();
                for (i, part) in pred.parts.iter().enumerate() {
                    let label = part.label;
                    let seen: Vec<(f64, Vector3<f64>, f64)> = held.iter().filter(|&&t| t <= from).filter_map(|&t| scene.observed_com(label, t).map(|(y, v)| (t, y, v))).collect();
                    let (cv, ca) = (Kalman::<2>::run(&seen, tcfg.const_vel_q), Kalman::<3>::run(&seen, tcfg.const_acc_q));
                    let filters: Vec<_> = grid_q.iter().map(|&(o, q)| kalman(o, &seen, q)).collect();
                    for (k, &t) in pred.stamps.iter().enumerate() {
                        let Some((y, _)) = scene.observed_com(label, t) else { continue };
                        acc.add(&pred.parts[i].com[k], Some(&pred.parts[i].mean[k]), cv.as_ref().map(|f| f.predict(t)), ca.as_ref().map(|f| f.predict(t)), &y);
                        for (e, f) in g.iter_mut().zip(&filters) {
                            if let Some(f) = f {
                                e[0] += (f(t) - y).norm_squared();
                                e[1] += 1.0;
                            }
                        }
                    }
                }
                let scores = prediction::score(&pred, &scene);
                let (inside, n) = scores.iter().filter(|s| s.frames > 0).fold((0.0, 0usize), |(a, n), s| (a + s.coverage_90 * s.frames as f64, n + s.frames));
                row.coverage_90 = (n > 0).then(|| inside / n as f64);
                row.open_loop = acc.mse();
            }
            Err(e) => row.skipped = Some(format!("open loop: {e}")),
        }
        // One step: from every cloud of the window to the next.
        let one = PredictConfig { draws: 0, ..cfg.prediction };
        let mut acc = Accumulator::default();
        for pair in held.windows(2) {
            let (t0, t1) = (pair[0], pair[1]);
            let Ok(pred) = prediction::predict(&model, &scene, t0, &[t1], &one, &cfg.model) else { continue };
            for part in &pred.parts {
                let Some((y, _)) = scene.observed_com(part.label, t1) else { continue };
                let seen: Vec<(f64, Vector3<f64>, f64)> = stamps.iter().filter(|&&t| t <= t0).filter_map(|&t| scene.observed_com(part.label, t).map(|(y, v)| (t, y, v))).collect();
                let cv = Kalman::<2>::run(&seen, tcfg.const_vel_q).map(|f| f.predict(t1));
                let ca = Kalman::<3>::run(&seen, tcfg.const_acc_q).map(|f| f.predict(t1));
                acc.add(&part.com[0], None, cv, ca, &y);
                for (e, &(o, q)) in g.iter_mut().zip(&grid_q) {
                    if let Some(f) = kalman(o, &seen, q) {
                        e[2] += (f(t1) - y).norm_squared();
                        e[3] += 1.0;
                    }
                }
            }
        }
        row.one_step = acc.mse();
        interactions.push(row);
        grid.push(g);
    }
    let mean = |f: &dyn Fn(&Interaction) -> Option<Mse>| {
        let v: Vec<Mse> = interactions.iter().filter_map(f).collect();
        (!v.is_empty()).then(|| {
            let n = v.len() as f64;
            Mse {
                mse_bom_m2: v.iter().map(|m| m.mse_bom_m2).sum::<f64>() / n,
                mse_bom_mean_m2: v.iter().map(|m| m.mse_bom_mean_m2).sum::<Option<f64>>().map(|s| s / n),
                mse_const_vel_m2: v.iter().map(|m| m.mse_const_vel_m2).sum::<f64>() / n,
                mse_const_acc_m2: v.iter().map(|m| m.mse_const_acc_m2).sum::<f64>() / n,
                frames: v.iter().map(|m| m.frames).sum(),
            }
        })
    };
    let (inside, n) = interactions.iter().fold((0.0, 0usize), |(a, n), r| match (r.coverage_90, r.open_loop) {
        (Some(c), Some(m)) => (a + c * m.frames as f64, n + m.frames),
        _ => (a, n),
    });
    let scored: Vec<&Mse> = interactions.iter().filter_map(|r| r.one_step.as_ref()).collect();
    Tracking {
        open_loop: mean(&|r| r.open_loop),
        one_step: mean(&|r| r.one_step),
        open_loop_pushed_elsewhere: mean(&|r| r.open_loop.filter(|_| r.pushed_elsewhere)),
        open_loop_only_push: mean(&|r| r.open_loop.filter(|_| !r.pushed_elsewhere)),
        coverage_90: (n > 0).then(|| inside / n as f64),
        one_step_bom_best: [scored.iter().filter(|m| m.mse_bom_m2 < m.mse_const_vel_m2.min(m.mse_const_acc_m2)).count(), scored.len()],
        kalman_grid: grid_q
            .iter()
            .enumerate()
            .map(|(e, &(order, q))| {
                // The mean over windows of each window's MSE, as the headline numbers.
                let mean = |s: usize| {
                    let v: Vec<f64> = grid.iter().filter_map(|g| g.get(e)).filter(|x| x[s + 1] > 0.0).map(|x| x[s] / x[s + 1]).collect();
                    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
                };
                GridRow { filter: if order == 2 { "const_vel" } else { "const_acc" }.into(), q, open_loop_mse_m2: mean(0), one_step_mse_m2: mean(2) }
            })
            .collect(),
        interactions,
    }
}

#[derive(Default)]
struct Accumulator {
    bom: f64,
    /// Squared errors of the draws' mean (open loop), and their count.
    mean: f64,
    n_mean: usize,
    cv: f64,
    ca: f64,
    n: usize,
}

impl Accumulator {
    /// One observed centre `y` against the three predictions, and bom's draws' mean where there
    /// is one (a filter without observations yet predicts nothing: the pair is not counted).
    fn add(&mut self, bom: &Vector3<f64>, mean: Option<&Vector3<f64>>, cv: Option<Vector3<f64>>, ca: Option<Vector3<f64>>, y: &Vector3<f64>) {
        if let (Some(cv), Some(ca)) = (cv, ca) {
            self.bom += (bom - y).norm_squared();
            if let Some(m) = mean {
                self.mean += (m - y).norm_squared();
                self.n_mean += 1;
            }
            self.cv += (cv - y).norm_squared();
            self.ca += (ca - y).norm_squared();
            self.n += 1;
        }
    }

    fn mse(&self) -> Option<Mse> {
        let n = self.n as f64;
        let mean = (self.n_mean > 0).then(|| self.mean / self.n_mean as f64);
        (self.n > 0).then(|| Mse { mse_bom_m2: self.bom / n, mse_bom_mean_m2: mean, mse_const_vel_m2: self.cv / n, mse_const_acc_m2: self.ca / n, frames: self.n })
    }
}

/// A Kalman filter of order `N - 1` (2: constant velocity, 3: constant acceleration) on a 3-D
/// position, the axes independent and alike: state `[p, v(, a)]` per axis.
#[derive(Debug, Clone)]
pub struct Kalman<const N: usize> {
    /// Per axis, the state mean.
    x: [SVector<f64, N>; 3],
    /// The state covariance (the same for every axis: same model, same measurement variance).
    p: SMatrix<f64, N, N>,
    t: f64,
    q: f64,
}

impl<const N: usize> Kalman<N> {
    /// Prior on the derivatives at the first observation: 1 m/s and 10 m/s² standard deviations.
    const DERIVATIVE_SD: [f64; 2] = [1.0, 10.0];

    /// Filter the observations `(stamp, position, variance per axis)`, in time order, with
    /// process noise intensity `q`; `None` without observations.
    pub fn run(obs: &[(f64, Vector3<f64>, f64)], q: f64) -> Option<Self> {
        let (t0, y0, r0) = obs.first()?;
        let mut x = [SVector::<f64, N>::zeros(); 3];
        for (a, xa) in x.iter_mut().enumerate() {
            xa[0] = y0[a];
        }
        let mut p = SMatrix::<f64, N, N>::zeros();
        p[(0, 0)] = r0.max(1e-12);
        for k in 1..N {
            p[(k, k)] = Self::DERIVATIVE_SD[k - 1].powi(2);
        }
        let mut f = Kalman { x, p, t: *t0, q };
        for (t, y, r) in &obs[1..] {
            f.step(*t);
            f.update(y, r.max(1e-12));
        }
        Some(f)
    }

    /// Transition and continuous white-noise process covariance over `dt`.
    fn model(&self, dt: f64) -> (SMatrix<f64, N, N>, SMatrix<f64, N, N>) {
        let mut f = SMatrix::<f64, N, N>::identity();
        let mut q = SMatrix::<f64, N, N>::zeros();
        // F_ij = dt^(j-i) / (j-i)!; Q_ij = q dt^(2N-1-i-j) / ((N-1-i)! (N-1-j)! (2N-1-i-j)).
        let fact = |n: usize| (1..=n).map(|k| k as f64).product::<f64>();
        for i in 0..N {
            for j in 0..N {
                if j >= i {
                    f[(i, j)] = dt.powi((j - i) as i32) / fact(j - i);
                }
                let e = 2 * N - 1 - i - j;
                q[(i, j)] = self.q * dt.powi(e as i32) / (fact(N - 1 - i) * fact(N - 1 - j) * e as f64);
            }
        }
        (f, q)
    }

    fn step(&mut self, t: f64) {
        let dt = (t - self.t).max(0.0);
        let (f, q) = self.model(dt);
        for x in &mut self.x {
            *x = f * *x;
        }
        self.p = f * self.p * f.transpose() + q;
        self.t = t;
    }

    fn update(&mut self, y: &Vector3<f64>, r: f64) {
        let s = self.p[(0, 0)] + r;
        let k: SVector<f64, N> = self.p.column(0) / s;
        for (a, x) in self.x.iter_mut().enumerate() {
            let innovation = y[a] - x[0];
            *x += k * innovation;
        }
        self.p -= k * self.p.row(0);
    }

    /// The predicted position at `t` (no update).
    pub fn predict(&self, t: f64) -> Vector3<f64> {
        let (f, _) = self.model((t - self.t).max(0.0));
        Vector3::from_fn(|a, _| (f * self.x[a])[0])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Noise-free motion of the filter's own order is followed exactly once it has converged.
    #[test]
    fn filters_follow_their_own_motion_model() {
        let line: Vec<(f64, Vector3<f64>, f64)> = (0..30).map(|k| {
            let t = k as f64 / 30.0;
            (t, Vector3::new(0.1 + 0.2 * t, -0.3 * t, 0.5), 1e-8)
        }).collect();
        let f = Kalman::<2>::run(&line, 1e-6).unwrap();
        assert!((f.predict(1.5) - Vector3::new(0.4, -0.45, 0.5)).norm() < 1e-3);
        let para: Vec<(f64, Vector3<f64>, f64)> = (0..30).map(|k| {
            let t = k as f64 / 30.0;
            (t, Vector3::new(t * t, 0.0, 0.0), 1e-8)
        }).collect();
        let cv = Kalman::<2>::run(&para, 1e-6).unwrap();
        let ca = Kalman::<3>::run(&para, 1e-6).unwrap();
        assert!((ca.predict(1.5).x - 2.25).abs() < 1e-2, "{}", ca.predict(1.5).x);
        assert!((cv.predict(1.5).x - 2.25).abs() > 0.1);
        // The process covariance of constant velocity (Bar-Shalom et al. eq. 6.2.2-12).
        let (_, q) = cv.model(0.5);
        assert!((q[(0, 0)] - 1e-6 * 0.125 / 3.0).abs() < 1e-15 && (q[(0, 1)] - 1e-6 * 0.125).abs() < 1e-15 && (q[(1, 1)] - 1e-6 * 0.5).abs() < 1e-15);
    }
}
