//! The observation model and the prior on joint coordinates.
//!
//! - [`Evidence`]: the observed part centres of mass on a common time grid (all cloud frames inside
//!   the interaction windows, evenly thinned to at most `max_frames`), with their perception sd.
//! - [`log_likelihood_point`]: the Gaussian likelihood of eq. 2 for one part and frame, with
//!   inverse variance `beta = 1 / (sigma^2 + sd_perception^2)`, sigma inferred; where perception gives a
//!   part's surface normal, [`log_likelihood_normal`] adds the rotation it shows.
//! - [`coordinate_prior`]: the expected log random-walk prior of a joint-coordinate chain under a
//!   mean-field Gaussian guide, analytic with its gradient.

use std::collections::BTreeMap;

use nalgebra::Vector3;

use super::{c, ModelConfig, Real};
use crate::perception::PartTracks;
use crate::windows::Window;

/// One part's observations on the grid.
#[derive(Debug, Clone)]
pub struct PartSeries {
    /// Part label (>= 1).
    pub label: u32,
    /// Perceived reference centre of mass \[m\] (first observation in the windows).
    pub com0: Vector3<f64>,
    /// Per grid frame: observed centre of mass \[m\] and its perception sd \[m\], or None (occluded).
    pub obs: Vec<Option<(Vector3<f64>, f64)>>,
    /// Surface normal at the reference frame (grid frame of the first observation), if the
    /// part's clouds define one there; then `normals` holds the observed normals and their sd \[rad\].
    pub normal0: Option<Vector3<f64>>,
    pub normals: Vec<Option<(Vector3<f64>, f64)>>,
}

/// Observations of all parts on a common time grid.
#[derive(Debug, Clone)]
pub struct Evidence {
    /// Grid stamps \[s\].
    pub times: Vec<f64>,
    /// Whether a grid frame starts a new window (the first frame always does).
    pub window_start: Vec<bool>,
    /// Parts in label order.
    pub parts: Vec<PartSeries>,
}

impl Evidence {
    /// Build the grid from perception tracks and windows: every stamp at which some part was
    /// seen inside a window, thinned so that kept stamps are at least `min_dt` seconds apart and
    /// then evenly to at most `max_frames`. Parts never seen inside a window are left out.
    ///
    /// Why thin in time: tracking errors of real recordings are correlated over a fraction of a
    /// second (jumps, slow drifts), while eq. 2 treats frames as independent; at 30 Hz it would
    /// count one drift as dozens of independent observations and prefer any curve that follows
    /// it (a large-radius arc over a straight slide). Keeping frames `min_dt` apart makes the
    /// independence assumption hold approximately, as in coarsened posteriors (Miller & Dunson,
    /// JASA 2019), and leaves the Occam factor of the richer joint type visible.
    ///
    /// A short window would keep too few frames that way: the spacing in each window is at most
    /// its duration / `min_frames`.
    pub fn new(tracks: &PartTracks, windows: &[Window], min_dt: f64, min_frames: usize, max_frames: usize) -> Evidence {
        let mut stamps: BTreeMap<u64, usize> = BTreeMap::new();
        let key = |t: f64| (t * 1e9).round() as u64;
        for obs in tracks.values() {
            for o in obs {
                if windows.iter().any(|w| w.contains(o.stamp)) {
                    stamps.insert(key(o.stamp), 0);
                }
            }
        }
        let mut all: Vec<u64> = Vec::new();
        for &k in stamps.keys() {
            let new_window = all.last().is_some_and(|&l| {
                windows.iter().position(|w| w.contains(l as f64 * 1e-9)) != windows.iter().position(|w| w.contains(k as f64 * 1e-9))
            });
            let dt = windows
                .iter()
                .find(|w| w.contains(k as f64 * 1e-9))
                .map(|w| min_dt.min((w.end - w.start) / min_frames.max(1) as f64))
                .unwrap_or(min_dt);
            if all.last().is_none_or(|&l| new_window || (k - l) as f64 * 1e-9 >= dt - 1e-6) {
                all.push(k);
            }
        }
        let keep: Vec<u64> = if all.len() > max_frames.max(2) {
            let m = max_frames.max(2);
            (0..m).map(|i| all[i * (all.len() - 1) / (m - 1)]).collect()
        } else {
            all
        };
        let index: BTreeMap<u64, usize> = keep.iter().enumerate().map(|(i, k)| (*k, i)).collect();
        let times: Vec<f64> = keep.iter().map(|k| *k as f64 * 1e-9).collect();
        let window_of = |t: f64| windows.iter().position(|w| w.contains(t));
        let window_start = (0..times.len())
            .map(|i| i == 0 || window_of(times[i]) != window_of(times[i - 1]))
            .collect();
        let mut parts = Vec::new();
        for (&label, obs) in tracks {
            let mut series = vec![None; times.len()];
            let mut normals = vec![None; times.len()];
            for o in obs {
                if let Some(&i) = index.get(&key(o.stamp)) {
                    series[i] = Some((o.com.coords, o.com_sd));
                    normals[i] = o.normal.map(|n| (n, o.normal_sd));
                }
            }
            if let Some(first) = series.iter().position(|o| o.is_some()) {
                let com0 = series[first].expect("observed").0;
                let normal0 = normals[first].map(|n| n.0);
                if normal0.is_none() {
                    normals.iter_mut().for_each(|n| *n = None);
                }
                parts.push(PartSeries { label, com0, obs: series, normal0, normals });
            }
        }
        Evidence { times, window_start, parts }
    }

    /// Number of grid frames.
    pub fn len(&self) -> usize {
        self.times.len()
    }

    pub fn is_empty(&self) -> bool {
        self.times.is_empty()
    }
}

/// `log N(y; x, (sigma^2 + sd^2) I_3)` for one part and frame (eq. 2).
#[inline]
pub fn log_likelihood_point<T: Real>(y: &Vector3<f64>, x: &Vector3<T>, sigma: T, sd: f64) -> T {
    let var = sigma * sigma + sd * sd;
    let d = Vector3::new(c::<T>(y.x) - x.x, c::<T>(y.y) - x.y, c::<T>(y.z) - x.z);
    -(d.dot(&d)) / (var * 2.0) - (var * (2.0 * std::f64::consts::PI)).ln() * 1.5
}

/// `log N(n_obs; n_pred, sd^2 I_2)`: a surface normal observed with angular sd `sd` \[rad\]
/// (small-angle Gaussian on the sphere, two degrees of freedom).
#[inline]
pub fn log_likelihood_normal<T: Real>(n_obs: &Vector3<f64>, n_pred: &Vector3<T>, sd: f64) -> T {
    let d = Vector3::new(c::<T>(n_obs.x) - n_pred.x, c::<T>(n_obs.y) - n_pred.y, c::<T>(n_obs.z) - n_pred.z);
    -(d.dot(&d)) / (2.0 * sd * sd) - c::<T>((2.0 * std::f64::consts::PI * sd * sd).ln())
}

/// Expected log prior `E_q[log p(q)]` of a joint-coordinate chain and its gradient with respect
/// to the guide means `m` and sds `s`.
///
/// Prior: `q_0 = 0` (gauge: the reference configuration is the first grid frame), the first frame
/// of every later window `~ N(0, window_start_sd_m^2)`, and within a window increments
/// `q_k - q_{k-1} ~ N(0, (velocity_sd_mps * dt_k)^2)`. `m[0]` and `s[0]` are ignored.
pub fn coordinate_prior(ev: &Evidence, m: &[f64], s: &[f64], cfg: &ModelConfig) -> (f64, Vec<f64>, Vec<f64>) {
    let n = ev.len();
    let (mut v, mut gm, mut gs) = (0.0, vec![0.0; n], vec![0.0; n]);
    let ln2pi = (2.0 * std::f64::consts::PI).ln();
    let mm = |k: usize| if k == 0 { 0.0 } else { m[k] };
    let ss = |k: usize| if k == 0 { 0.0 } else { s[k] };
    for k in 1..n {
        if ev.window_start[k] {
            let var = cfg.window_start_sd_m.powi(2);
            v += -(mm(k).powi(2) + ss(k).powi(2)) / (2.0 * var) - 0.5 * (var.ln() + ln2pi);
            gm[k] -= mm(k) / var;
            gs[k] -= ss(k) / var;
        } else {
            let dt = (ev.times[k] - ev.times[k - 1]).max(1e-3);
            let var = (cfg.velocity_sd_mps * dt).powi(2);
            let d = mm(k) - mm(k - 1);
            v += -(d * d + ss(k).powi(2) + ss(k - 1).powi(2)) / (2.0 * var) - 0.5 * (var.ln() + ln2pi);
            gm[k] -= d / var;
            gm[k - 1] += d / var;
            gs[k] -= ss(k) / var;
            gs[k - 1] -= ss(k - 1) / var;
        }
    }
    gm[0] = 0.0;
    gs[0] = 0.0;
    (v, gm, gs)
}
