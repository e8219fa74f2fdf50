//! The whole pipeline on recorded bags (`bom replay`): input -> perception -> windows -> model ->
//! inference -> output, as the node runs it, as fast as the machine allows.
//!
//! Each closed window is new evidence: after every window the posterior is refitted with all
//! windows so far (contract section 1), and each update is kept so that the output bag carries
//! the model as the node would have published it.

pub mod online;

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use indicatif::{ProgressBar, ProgressStyle};

use crate::config::Config;
use crate::diagnostics::Diagnostics;
use crate::inference::{svi, Posterior};
use crate::input::{self, CloudFrame, GroundTruth, InputError, Recording};
use crate::model::likelihood::{Evidence, Grid};
use crate::perception::{self, PartGeometry, PartTracks, Perception};
use crate::windows::{self, Window};

/// Why a replay could not run (exit code 3).
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    #[error(transparent)]
    Input(#[from] InputError),
    #[error("{bags}: no usable sensor_msgs/msg/PointCloud2 message on '{topic}'")]
    NoClouds { bags: String, topic: String },
}

/// Per-part statistics of the recording.
#[derive(Debug, Clone)]
pub struct PartStats {
    pub label: u32,
    /// Frames in which the part was seen.
    pub frames: usize,
    /// Mean inlier points per seen frame.
    pub points_per_frame: f64,
}

/// Wall time per stage.
#[derive(Debug, Clone, Default)]
pub struct Timing {
    pub read: Duration,
    pub decode: Duration,
    pub perception: Duration,
    pub windows: Duration,
    pub inference: Duration,
    pub total: Duration,
}

/// One posterior update, after a window closed.
#[derive(Debug, Clone)]
pub struct Update {
    /// End of the window that triggered it \[s\].
    pub stamp: f64,
    pub num_windows: usize,
    pub posterior: Posterior,
}

/// Everything a replay produced.
#[derive(Debug, Clone)]
pub struct Run {
    pub bags: Vec<PathBuf>,
    /// `kinematic` (no wrench) or `dynamic`.
    pub mode: &'static str,
    pub parts: Vec<PartStats>,
    pub windows: Vec<Window>,
    pub tracks: PartTracks,
    /// Geometry of every part's model at the end of the recording.
    pub geometry: BTreeMap<u32, PartGeometry>,
    pub updates: Vec<Update>,
    /// The posterior after the last window.
    pub posterior: Option<Posterior>,
    pub ground_truth: Option<GroundTruth>,
    pub diagnostics: Diagnostics,
    pub timing: Timing,
}

fn progress(msg: &str) -> ProgressBar {
    let pb = ProgressBar::new_spinner();
    pb.set_style(ProgressStyle::with_template("{spinner} {msg} [{elapsed}]").unwrap_or_else(|_| ProgressStyle::default_spinner()));
    pb.set_message(msg.to_string());
    pb.enable_steady_tick(Duration::from_millis(120));
    pb
}

/// Run the pipeline on bags (several bags = several interactions with one object).
///
/// # Errors
/// [`ReplayError`] when a bag cannot be read at all or holds no usable cloud.
pub fn replay(bags: &[PathBuf], cfg: &Config) -> Result<Run, ReplayError> {
    let t0 = Instant::now();
    let mut timing = Timing::default();
    let mut diag = Diagnostics::default();
    let pb = progress("reading bags");
    let mut read = Vec::new();
    for path in bags {
        read.push(input::read_bag(path, &mut diag)?);
    }
    let ground_truth = read.iter().find_map(|b| b.ground_truth.clone());
    timing.read = t0.elapsed();

    pb.set_message("decoding messages");
    let t = Instant::now();
    let recording = input::decode_recording(&read, &cfg.topics, &cfg.fixed_frame, &mut diag);
    drop(read);
    timing.decode = t.elapsed();
    if recording.clouds.is_empty() {
        pb.finish_and_clear();
        return Err(ReplayError::NoClouds {
            bags: bags.iter().map(|b| b.display().to_string()).collect::<Vec<_>>().join(", "),
            topic: cfg.topics.points.clone(),
        });
    }

    pb.set_message("perception");
    let t = Instant::now();
    let mut perception = Perception::new(cfg.perception.clone());
    let tracks = perception.observe_all(&recording.clouds);
    let geometry = perception.geometry();
    timing.perception = t.elapsed();

    pb.set_message("windows");
    let t = Instant::now();
    let mode = if recording.wrenches.is_empty() { "kinematic" } else { "dynamic" };
    let windows = find_windows(&recording, &tracks, cfg, &mut diag);
    timing.windows = t.elapsed();

    let springs = ground_truth.as_ref().map(declared_springs).unwrap_or_default();
    let t = Instant::now();
    let mut updates = Vec::new();
    let mut warm = None;
    for w in 0..windows.len() {
        pb.set_message(format!("BOM-SVI after window {}/{}", w + 1, windows.len()));
        let ev = Evidence::new(&tracks, &geometry, &windows[..=w], &recording.wrenches, &springs, &grid(cfg));
        if let Some(fitted) = svi::fit(&ev, &cfg.model, &cfg.inference, warm.as_ref()) {
            updates.push(Update { stamp: windows[w].end, num_windows: w + 1, posterior: fitted.posterior });
            warm = Some(fitted.guide);
        }
    }
    timing.inference = t.elapsed();
    pb.finish_and_clear();

    let parts = tracks
        .iter()
        .map(|(&label, obs)| PartStats {
            label,
            frames: obs.len(),
            points_per_frame: obs.iter().map(|o| o.points as f64).sum::<f64>() / obs.len().max(1) as f64,
        })
        .collect();
    let posterior = updates.last().map(|u| u.posterior.clone());
    timing.total = t0.elapsed();
    Ok(Run { bags: bags.to_vec(), mode, parts, windows, tracks, geometry, updates, posterior, ground_truth, diagnostics: diag, timing })
}

/// The evidence grid of the configuration.
pub fn grid(cfg: &Config) -> Grid {
    Grid {
        min_dt_s: cfg.inference.min_dt_s,
        min_frames: cfg.inference.min_frames,
        max_frames: cfg.inference.max_frames,
        step_s: cfg.model.dynamics.step_s,
        contact_range_m: cfg.perception.contact_range_m,
        voxel_m: cfg.perception.voxel_m,
    }
}

/// Labels of the parts on which the recording declares a spring (contract section 3, `effects`):
/// declared effects are part of the model from the start; undeclared ones are for model criticism
/// to find.
pub fn declared_springs(gt: &GroundTruth) -> Vec<u32> {
    gt.effects
        .iter()
        .filter(|e| e.get("kind").and_then(|k| k.as_str()) == Some("spring"))
        .filter_map(|e| e.get("part").and_then(|p| p.as_u64()).map(|p| p as u32))
        .collect()
}

fn find_windows(rec: &Recording, tracks: &PartTracks, cfg: &Config, diag: &mut Diagnostics) -> Vec<Window> {
    let t_min = rec.clouds.first().map(|c| c.stamp).unwrap_or(0.0);
    let t_max = rec.clouds.last().map(|c| c.stamp).unwrap_or(0.0);
    let mut ws = if rec.wrenches.is_empty() {
        windows::motion_windows(tracks, &cfg.windows)
    } else {
        let mut ws = windows::force_windows(&rec.wrenches, &cfg.windows, t_min, t_max);
        for w in &mut ws {
            w.pushed_part = pushed_part(rec, w, cfg.windows.force_open_n);
        }
        ws
    };
    if ws.is_empty() {
        diag.warn(&cfg.topics.points, "no interaction window", "no motion or force period found; using the whole recording as one window");
        ws.push(Window { start: t_min, end: t_max, pushed_part: None });
    }
    ws
}

fn pushed_part(rec: &Recording, w: &Window, threshold: f64) -> Option<u32> {
    let contact = rec.wrenches.iter().find(|s| w.contains(s.stamp) && s.force.norm() > threshold)?;
    let cloud: &CloudFrame = rec.clouds.iter().min_by(|a, b| (a.stamp - contact.stamp).abs().total_cmp(&(b.stamp - contact.stamp).abs()))?;
    perception::nearest_part(cloud, &contact.point).map(|(l, _)| l)
}
