//! Windows stage: cut the recording into interaction windows (contract section 1).
//!
//! - **Dynamic mode** (wrenches recorded): a window opens when the applied force exceeds
//!   `force_open_n` and closes once it has stayed below `force_close_n` (hysteresis) for `hold_s`;
//!   `margin_before_s` / `margin_after_s` extend it (the part keeps moving after release). A
//!   lighter push — above `force_close_n` but never above `force_open_n` — opens a window too
//!   when a part moves during it (a light door pushed with 0.8 N swings wide open): the
//!   threshold is there to reject sensor noise, and motion under the force says it was none.
//! - **Kinematic mode** (no wrench): windows are periods of part motion. A part moves while the
//!   speed of its centre of mass, measured over `speed_span_s`, exceeds `speed_open_mps`; the
//!   period ends once the speed has stayed below `speed_close_mps` for `hold_s`. Periods of all
//!   parts are joined, extended by the margins, and windows closer than `merge_gap_s` merged.
//!
//! In both modes a break in the signal longer than `max_unobserved_s` (separate episodes replayed
//! together) ends a period at its last sample. Windows shorter than `min_duration_s` are dropped.

use nalgebra::Point3;
use serde::{Deserialize, Serialize};

use crate::input::WrenchSample;
use crate::perception::PartObservation;

/// Window thresholds (`windows` section of the config).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct WindowConfig {
    pub force_open_n: f64,
    pub force_close_n: f64,
    pub speed_open_mps: f64,
    pub speed_close_mps: f64,
    pub speed_span_s: f64,
    pub hold_s: f64,
    pub margin_before_s: f64,
    pub margin_after_s: f64,
    pub merge_gap_s: f64,
    pub min_duration_s: f64,
    /// A break in the clouds longer than this \[s\] (separate episodes, often of a reset object)
    /// ends any window: a motion or force period never spans it (both modes). Dynamic mode: such
    /// a break between two windows also cuts the tie of the later window's start to where the
    /// earlier one left the joint ([`crate::model::likelihood::Grid::max_unobserved_s`]).
    pub max_unobserved_s: f64,
    /// The live node keeps the evidence of at most this many most recent windows per pushed part
    /// (kinematic mode: in all), so that memory and the time of an update stay bounded over hours
    /// of pushes; older windows are forgotten, counted in the node's report. `bom replay` uses
    /// every window of its bags.
    pub node_max_windows_per_part: usize,
}

impl Default for WindowConfig {
    fn default() -> Self {
        WindowConfig {
            force_open_n: 1.0,
            force_close_n: 0.5,
            speed_open_mps: 0.02,
            speed_close_mps: 0.01,
            speed_span_s: 0.2,
            hold_s: 0.3,
            margin_before_s: 0.3,
            margin_after_s: 0.7,
            merge_gap_s: 0.2,
            min_duration_s: 0.2,
            max_unobserved_s: 5.0,
            node_max_windows_per_part: 4,
        }
    }
}

/// One interaction window [s, header stamps].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Window {
    pub start: f64,
    pub end: f64,
    /// The pushed part (dynamic mode), set by the caller from the contact point over the push's
    /// clouds ([`crate::perception::ContactVotes`]).
    pub pushed_part: Option<u32>,
}

impl Window {
    pub fn contains(&self, t: f64) -> bool {
        t >= self.start && t <= self.end
    }
}

/// Hysteresis thresholding of a signal `(t, value)`: intervals where it rose above `open` until it
/// stayed below `close` for `hold` seconds, or until the last sample before a break in the signal
/// longer than `max_gap` seconds.
///
/// Why the break: a signal that is not there cannot say that something still moves or is still
/// pushed. Bags of separate episodes replayed together leave minutes between their clouds; a span
/// left open at the end of one episode (a registration's jitter above `close`) ran on into the
/// next, and one kinematic window then covered both episodes and the gap, which thinned its
/// evidence to `min_dt_s` over the whole of it (issue 24, class 2).
fn hysteresis(signal: &[(f64, f64)], open: f64, close: f64, hold: f64, max_gap: f64) -> Vec<(f64, f64)> {
    let mut out = Vec::new();
    let mut start: Option<f64> = None;
    let mut below_since: Option<f64> = None;
    let mut previous: Option<f64> = None;
    for &(t, v) in signal {
        if let (Some(s), Some(p)) = (start, previous) {
            if t - p > max_gap {
                out.push((s, below_since.unwrap_or(p)));
                start = None;
                below_since = None;
            }
        }
        previous = Some(t);
        match start {
            None if v > open => {
                start = Some(t);
                below_since = None;
            }
            Some(s) => {
                if v < close {
                    let b = *below_since.get_or_insert(t);
                    if t - b >= hold {
                        out.push((s, b));
                        start = None;
                        below_since = None;
                    }
                } else {
                    below_since = None;
                }
            }
            None => {}
        }
    }
    if let (Some(s), Some(&(t_end, _))) = (start, signal.last()) {
        out.push((s, below_since.unwrap_or(t_end)));
    }
    out
}

/// Speed of a track of positions, measured over `span` seconds (central difference).
fn speeds(track: &[(f64, Point3<f64>)], span: f64) -> Vec<(f64, f64)> {
    let n = track.len();
    let (mut lo, mut hi) = (0usize, 0usize);
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let t = track[i].0;
        while track[lo].0 < t - span / 2.0 {
            lo += 1;
        }
        while hi + 1 < n && track[hi + 1].0 <= t + span / 2.0 {
            hi += 1;
        }
        let dt = track[hi].0 - track[lo].0;
        let v = if dt > 0.0 { (track[hi].1 - track[lo].1).norm() / dt } else { 0.0 };
        out.push((t, v));
    }
    out
}

fn finish(mut spans: Vec<(f64, f64)>, cfg: &WindowConfig, t_min: f64, t_max: f64) -> Vec<Window> {
    spans.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut merged: Vec<(f64, f64)> = Vec::new();
    for (s, e) in spans {
        let (s, e) = ((s - cfg.margin_before_s).max(t_min), (e + cfg.margin_after_s).min(t_max));
        match merged.last_mut() {
            Some(last) if s <= last.1 + cfg.merge_gap_s => last.1 = last.1.max(e),
            _ => merged.push((s, e)),
        }
    }
    merged
        .into_iter()
        .filter(|(s, e)| e - s >= cfg.min_duration_s)
        .map(|(start, end)| Window { start, end, pushed_part: None })
        .collect()
}

/// Periods in which one part's track (time order) moves: speed above `speed_open_mps` until it
/// has stayed below `speed_close_mps` for `hold_s`.
fn moving_spans(obs: &[PartObservation], cfg: &WindowConfig) -> Vec<(f64, f64)> {
    let track: Vec<(f64, Point3<f64>)> = obs.iter().map(|o| (o.stamp, o.com)).collect();
    hysteresis(&speeds(&track, cfg.speed_span_s), cfg.speed_open_mps, cfg.speed_close_mps, cfg.hold_s, cfg.max_unobserved_s)
}

/// Kinematic-mode windows: periods in which any of `tracks` (each one part's, in time order)
/// moves.
pub fn motion_windows<'a>(tracks: impl IntoIterator<Item = &'a [PartObservation]>, cfg: &WindowConfig) -> Vec<Window> {
    let mut spans = Vec::new();
    let (mut t_min, mut t_max) = (f64::INFINITY, f64::NEG_INFINITY);
    for obs in tracks {
        if let (Some(a), Some(b)) = (obs.first(), obs.last()) {
            t_min = t_min.min(a.stamp);
            t_max = t_max.max(b.stamp);
        }
        spans.extend(moving_spans(obs, cfg));
    }
    finish(spans, cfg, t_min, t_max)
}

/// Dynamic-mode windows: periods of applied force above `force_open_n`, and periods above
/// `force_close_n` alone during which (or within `margin_after_s` after which) some part's track
/// of `tracks` (each in time order) moves (its speed above `speed_open_mps`, as in
/// [`motion_windows`]); the tracks are read only when there is such a light push. `t_max` bounds
/// the trailing margin (the last cloud stamp).
pub fn force_windows<'a>(
    wrenches: &[WrenchSample],
    tracks: impl IntoIterator<Item = &'a [PartObservation]>,
    cfg: &WindowConfig,
    t_min: f64,
    t_max: f64,
) -> Vec<Window> {
    let signal: Vec<(f64, f64)> = wrenches.iter().map(|w| (w.stamp, w.force.norm())).collect();
    let mut spans = hysteresis(&signal, cfg.force_open_n, cfg.force_close_n, cfg.hold_s, cfg.max_unobserved_s);
    if cfg.force_close_n < cfg.force_open_n {
        let overlaps = |a: (f64, f64), b: (f64, f64)| a.0 <= b.1 && b.0 <= a.1;
        let light: Vec<(f64, f64)> = hysteresis(&signal, cfg.force_close_n, cfg.force_close_n, cfg.hold_s, cfg.max_unobserved_s)
            .into_iter()
            .filter(|&l| !spans.iter().any(|&s| overlaps(l, s)))
            .collect();
        if !light.is_empty() {
            let moving: Vec<(f64, f64)> = tracks.into_iter().flat_map(|obs| moving_spans(obs, cfg)).collect();
            spans.extend(light.into_iter().filter(|&l| moving.iter().any(|&m| overlaps((l.0, l.1 + cfg.margin_after_s), m))));
        }
    }
    finish(spans, cfg, t_min, t_max)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::perception::PartTracks;

    fn obs(t: f64, x: f64) -> PartObservation {
        PartObservation {
            stamp: t,
            pose: nalgebra::Isometry3::translation(x, 0.0, 0.0),
            com: Point3::new(x, 0.0, 0.0),
            pose_cov: nalgebra::Matrix6::identity() * 1e-6,
            registration_cov: nalgebra::Matrix6::identity() * 1e-6,
            matched: 1.0,
            points: 10,
            outliers: 0,
        }
    }

    /// A light push (0.8 N: above `force_close_n`, below `force_open_n`) is a window when a
    /// part moves under it, and sensor noise of that size on a still object is none.
    #[test]
    fn a_light_push_that_moves_a_part_is_a_window() {
        let cfg = WindowConfig::default();
        let wrenches: Vec<WrenchSample> = (0..1200)
            .map(|i| {
                let t = i as f64 / 200.0;
                let f = if (2.0..3.0).contains(&t) { 0.8 } else { 0.0 };
                WrenchSample { stamp: t, point: Point3::origin(), force: nalgebra::Vector3::new(f, 0.0, 0.0), torque: nalgebra::Vector3::zeros() }
            })
            .collect();
        let track = |speed: f64| -> Vec<PartObservation> {
            (0..180)
                .map(|i| {
                    let t = i as f64 / 30.0;
                    obs(t, speed * (t - 2.1).clamp(0.0, 1.2))
                })
                .collect()
        };
        let w = force_windows(&wrenches, [track(0.2).as_slice()], &cfg, 0.0, 6.0);
        assert_eq!(w.len(), 1, "{w:?}");
        assert!((w[0].start - (2.0 - cfg.margin_before_s)).abs() < 0.01 && (w[0].end - (3.0 + cfg.margin_after_s)).abs() < 0.01, "{w:?}");
        assert!(force_windows(&wrenches, [track(0.0).as_slice()], &cfg, 0.0, 6.0).is_empty());
        // Above `force_open_n`, a push is a window whether or not anything moves.
        let strong: Vec<WrenchSample> = wrenches.iter().map(|w| WrenchSample { force: w.force * 2.0, ..w.clone() }).collect();
        assert_eq!(force_windows(&strong, [track(0.0).as_slice()], &cfg, 0.0, 6.0).len(), 1);
    }

    /// Two episodes replayed together, 300 s apart: the first recording stops while the part
    /// still moves (as a registration's jitter above `speed_close_mps` also keeps a period open),
    /// the second moves it again. The break in the clouds ends the first window; no window spans it.
    #[test]
    fn a_break_in_the_clouds_ends_a_window() {
        let cfg = WindowConfig::default();
        let mut track: Vec<PartObservation> = (0..120)
            .map(|i| {
                let t = i as f64 / 30.0;
                obs(t, 0.1 * (t - 1.0).max(0.0))
            })
            .collect();
        track.extend((0..120).map(|i| {
            let t = 300.0 + i as f64 / 30.0;
            obs(t, 0.1 * (t - 301.5).clamp(0.0, 1.0))
        }));
        let mut tracks = PartTracks::new();
        tracks.insert(1, track);
        let w = motion_windows(tracks.values().map(Vec::as_slice), &cfg);
        assert_eq!(w.len(), 2, "{w:?}");
        assert!(w[0].end < 5.0 && w[1].start > 300.0, "{w:?}");
        // Without the break the first window runs on through the 296 s without clouds.
        let joined = WindowConfig { max_unobserved_s: 1e9, ..cfg };
        let w = motion_windows(tracks.values().map(Vec::as_slice), &joined);
        assert!(w[0].end > 299.0, "{w:?}");
    }

    #[test]
    fn one_motion_period_gives_one_window_with_margins() {
        // Still for 2 s, moves at 0.1 m/s for 2 s, still for 2 s, at 30 Hz.
        let track: Vec<PartObservation> = (0..180)
            .map(|i| {
                let t = i as f64 / 30.0;
                obs(t, 0.1 * (t - 2.0).clamp(0.0, 2.0))
            })
            .collect();
        let mut tracks = PartTracks::new();
        tracks.insert(1, track);
        let cfg = WindowConfig::default();
        let w = motion_windows(tracks.values().map(Vec::as_slice), &cfg);
        assert_eq!(w.len(), 1, "{w:?}");
        // Motion from 2 s to 4 s; the margins around it.
        assert!((w[0].start - (2.0 - cfg.margin_before_s)).abs() < 0.15 && (w[0].end - (4.0 + cfg.margin_after_s)).abs() < 0.2, "{w:?}");
    }
}
