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
use crate::criticism::{self, Criticism, Finding};
use crate::inference::nuts::{self, SamplerReport};
use crate::inference::{svi, Posterior};
use crate::input::{self, CloudFrame, GroundTruth, InputError, Recording, WrenchSample};
use crate::model::effects::{EffectKind, EffectSet, LimitSpec};
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
    /// BOM-SVI, refits after an adopted effect included.
    pub inference: Duration,
    pub criticism: Duration,
    pub total: Duration,
}

/// One posterior update, after a window closed.
#[derive(Debug, Clone)]
pub struct Update {
    /// End of the window that triggered it \[s\].
    pub stamp: f64,
    pub num_windows: usize,
    pub posterior: Posterior,
    /// Model criticism of the posterior before any effect it adopted (the posterior is then the
    /// refit with it).
    pub criticism: Criticism,
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
    /// Model criticism over the run: every effect adopted (when it was), then the last update's
    /// unexplained residuals.
    pub findings: Vec<Finding>,
    /// The model's effects at the end, per part label: declared, then adopted.
    pub effects: BTreeMap<u32, EffectSet>,
    pub ground_truth: Option<GroundTruth>,
    pub diagnostics: Diagnostics,
    pub timing: Timing,
    /// BOM-NUTS's diagnostics when it gave the posterior (`nuts.enabled`).
    pub sampler: Option<SamplerReport>,
    /// The measured wrenches (all bags), for evidence rebuilt after the run ([`final_evidence`]).
    pub wrenches: Vec<WrenchSample>,
}

/// The evidence of the last update of `run`: all windows, the model's final effects.
pub fn final_evidence(run: &Run, cfg: &Config) -> Evidence {
    let src = EvidenceSource { tracks: &run.tracks, geometry: &run.geometry, windows: &run.windows, wrenches: &run.wrenches };
    Evidence::new(src.tracks, src.geometry, src.windows, src.wrenches, &run.effects, &grid(cfg))
}

fn progress(msg: &str) -> ProgressBar {
    let pb = ProgressBar::new_spinner();
    pb.set_style(ProgressStyle::with_template("{spinner} {msg} [{elapsed}]").unwrap_or_else(|_| ProgressStyle::default_spinner()));
    pb.set_message(msg.to_string());
    pb.enable_steady_tick(Duration::from_millis(120));
    pb
}

/// What the stages before the model make of bags: decoded messages, part tracks at cloud rate,
/// part geometry and interaction windows (input -> perception -> windows).
#[derive(Debug)]
pub struct Observed {
    pub recording: Recording,
    pub tracks: PartTracks,
    /// Geometry of every part's model at the end of the recording.
    pub geometry: BTreeMap<u32, PartGeometry>,
    pub windows: Vec<Window>,
    pub ground_truth: Option<GroundTruth>,
    /// `kinematic` (no wrench) or `dynamic`.
    pub mode: &'static str,
}

/// Input, perception and windows on bags (what [`replay`] does before inference, and what
/// `bom predict` needs of its wrench bag); bad input is counted in `diag`.
///
/// # Errors
/// [`ReplayError`] when a bag cannot be read at all or holds no usable cloud.
pub fn observe(bags: &[PathBuf], cfg: &Config, diag: &mut Diagnostics) -> Result<Observed, ReplayError> {
    let pb = ProgressBar::hidden();
    observe_with(bags, cfg, diag, &mut Timing::default(), &pb)
}

fn observe_with(bags: &[PathBuf], cfg: &Config, diag: &mut Diagnostics, timing: &mut Timing, pb: &ProgressBar) -> Result<Observed, ReplayError> {
    let t0 = Instant::now();
    let mut read = Vec::new();
    for path in bags {
        read.push(input::read_bag_with(path, &cfg.input, diag)?);
    }
    let ground_truth = read.iter().find_map(|b| b.ground_truth.clone());
    timing.read = t0.elapsed();

    pb.set_message("decoding messages");
    let t = Instant::now();
    let recording = input::decode_recording_with(&read, &cfg.topics, &cfg.fixed_frame, &cfg.input, diag);
    drop(read);
    timing.decode = t.elapsed();
    if recording.clouds.is_empty() {
        return Err(ReplayError::NoClouds {
            bags: bags.iter().map(|b| b.display().to_string()).collect::<Vec<_>>().join(", "),
            topic: cfg.topics.points.clone(),
        });
    }

    pb.set_message("perception");
    let t = Instant::now();
    let mut perception = Perception::new(cfg.perception.clone());
    let gate = push_gate(cfg);
    let pushes: Vec<_> = recording.clouds.iter().map(|c| gate.push(&recording.wrenches, c.stamp)).collect();
    let tracks = perception.observe_all(&recording.clouds, &pushes);
    let geometry = perception.geometry();
    timing.perception = t.elapsed();

    pb.set_message("windows");
    let t = Instant::now();
    let mode = if recording.wrenches.is_empty() { "kinematic" } else { "dynamic" };
    let windows = find_windows(&recording, &tracks, cfg, diag);
    timing.windows = t.elapsed();
    Ok(Observed { recording, tracks, geometry, windows, ground_truth, mode })
}

/// When perception takes a cloud as pushed ([`perception::PushGate`]): a force above the windows'
/// `force_close_n` (a push, as windows see one) in a wrench sample no older than the windows'
/// `hold_s` (the time a push may pause below that force and still be one push).
pub fn push_gate(cfg: &Config) -> perception::PushGate {
    perception::PushGate { force_n: cfg.windows.force_close_n, max_age_s: cfg.windows.hold_s }
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
    let Observed { recording, tracks, geometry, windows, ground_truth, mode } = observe_with(bags, cfg, &mut diag, &mut timing, &pb).inspect_err(|_| pb.finish_and_clear())?;

    let declared = ground_truth.as_ref().map(declared_effects).unwrap_or_default();
    let mut effects = Effects { declared: declared.clone(), adopted: BTreeMap::new() };
    let t = Instant::now();
    let mut updates = Vec::new();
    let mut findings = Vec::new();
    let mut warm = None;
    // The last update's guide, for BOM-NUTS.
    let mut last_guide = None;
    for w in 0..windows.len() {
        pb.set_message(format!("BOM-SVI after window {}/{}", w + 1, windows.len()));
        let src = EvidenceSource { tracks: &tracks, geometry: &geometry, windows: &windows[..=w], wrenches: &recording.wrenches };
        if let Some((fitted, criticism)) = update(src, &mut effects, cfg, warm.as_ref()) {
            findings = criticism.findings.clone();
            timing.criticism += Duration::from_secs_f64(criticism.runtime_s);
            updates.push(Update { stamp: windows[w].end, num_windows: w + 1, posterior: fitted.posterior, criticism });
            warm = Some(fitted.warm);
            last_guide = Some(fitted.guide);
        }
    }
    timing.inference = t.elapsed().saturating_sub(timing.criticism);
    pb.finish_and_clear();

    let parts = tracks
        .iter()
        .map(|(&label, obs)| PartStats {
            label,
            frames: obs.len(),
            points_per_frame: obs.iter().map(|o| o.points as f64).sum::<f64>() / obs.len().max(1) as f64,
        })
        .collect();
    let mut posterior = updates.last().map(|u| u.posterior.clone());
    let mut sampler = None;
    if let (true, Some(post), Some(guide), Some(warm)) = (cfg.nuts.enabled, posterior.as_ref(), last_guide, warm) {
        // BOM-NUTS on the last update's evidence (all windows, the final effects), from its SVI fit.
        let t = Instant::now();
        let src = EvidenceSource { tracks: &tracks, geometry: &geometry, windows: &windows, wrenches: &recording.wrenches };
        let ev = src.evidence(&effects, cfg);
        let svi_fit = svi::Fitted { posterior: post.clone(), guide, warm, type_scale: Vec::new() };
        match nuts::sample(&ev, &cfg.model, &svi_fit, &cfg.nuts) {
            Ok((p, report)) => {
                for w in &report.warnings {
                    tracing::warn!("{w}");
                }
                posterior = Some(p);
                sampler = Some(report);
            }
            Err(e) => tracing::error!("NUTS failed: {e}; the posterior is SVI's"),
        }
        timing.inference += t.elapsed();
    }
    timing.total = t0.elapsed();
    Ok(Run { bags: bags.to_vec(), mode, parts, windows, tracks, geometry, updates, posterior, findings, effects: effects.all(), ground_truth, diagnostics: diag, timing, sampler, wrenches: recording.wrenches })
}

/// The effects of the model, per part label: declared by the recording, and adopted by model
/// criticism (kept for every later update).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Effects {
    pub declared: BTreeMap<u32, EffectSet>,
    pub adopted: BTreeMap<u32, EffectSet>,
}

impl Effects {
    /// Declared and adopted together.
    pub fn all(&self) -> BTreeMap<u32, EffectSet> {
        let mut out = self.declared.clone();
        for (label, set) in &self.adopted {
            let e = out.entry(*label).or_default();
            for kind in set.kinds() {
                *e = e.with(kind, set.limit);
            }
        }
        out
    }
}

/// What an update's evidence is built from: perception's tracks and geometry, the windows closed
/// so far and the measured wrenches.
#[derive(Debug, Clone, Copy)]
pub struct EvidenceSource<'a> {
    pub tracks: &'a PartTracks,
    pub geometry: &'a BTreeMap<u32, PartGeometry>,
    pub windows: &'a [Window],
    pub wrenches: &'a [WrenchSample],
}

impl EvidenceSource<'_> {
    /// The evidence with the model's current effects.
    pub fn evidence(&self, effects: &Effects, cfg: &Config) -> Evidence {
        Evidence::new(self.tracks, self.geometry, self.windows, self.wrenches, &effects.all(), &grid(cfg))
    }
}

/// One posterior update on all windows so far: [`fit_update`], then [`criticise_update`] (which
/// may adopt an effect and refit). Returns the final fit and the criticism, or `None` when no part
/// was seen inside a window.
pub fn update(
    src: EvidenceSource<'_>,
    effects: &mut Effects,
    cfg: &Config,
    warm: Option<&svi::WarmStart>,
) -> Option<(svi::Fitted, Criticism)> {
    let (ev, fitted) = fit_update(src, effects, cfg, warm)?;
    let (criticism, refit) = criticise_update(src, &ev, &fitted, effects, cfg);
    Some((refit.unwrap_or(fitted), criticism))
}

/// BOM-SVI on all windows so far with the model's current effects, warm-started from `warm`:
/// the evidence and the fit, or `None` when no part was seen inside a window.
pub fn fit_update(
    src: EvidenceSource<'_>,
    effects: &Effects,
    cfg: &Config,
    warm: Option<&svi::WarmStart>,
) -> Option<(Evidence, svi::Fitted)> {
    let ev = src.evidence(effects, cfg);
    let fitted = svi::fit(&ev, &cfg.model, &cfg.inference, warm)?;
    Some((ev, fitted))
}

/// Model criticism of a fit to `ev` (the evidence of `src`); when it adopts an effect, the effect
/// joins `effects.adopted` (kept for later updates while their criticism supports it; one it
/// retracts leaves) and the posterior is refitted with the new set, warm-started from `fitted`.
/// Returns the criticism and the refit, if any. Both `bom replay` and `bom node` go through here
/// (the node publishes the fit first, so criticism never delays the posterior).
pub fn criticise_update(
    src: EvidenceSource<'_>,
    ev: &Evidence,
    fitted: &svi::Fitted,
    effects: &mut Effects,
    cfg: &Config,
) -> (Criticism, Option<svi::Fitted>) {
    let criticism = criticism::criticise(ev, &fitted.posterior, &effects.adopted, &cfg.model.dynamics, &cfg.criticism);
    let adopted = criticism.adopted();
    if adopted.is_empty() && criticism.retracted.is_empty() {
        return (criticism, None);
    }
    for &(label, kind) in &criticism.retracted {
        if let Some(set) = effects.adopted.get_mut(&label) {
            *set = set.without(kind);
        }
    }
    for (label, kind, limit) in adopted {
        let set = effects.adopted.entry(label).or_default();
        *set = set.with(kind, limit);
    }
    (criticism, svi::fit(&src.evidence(effects, cfg), &cfg.model, &cfg.inference, Some(&fitted.warm)))
}

/// The evidence grid of the configuration.
pub fn grid(cfg: &Config) -> Grid {
    Grid {
        min_dt_s: cfg.inference.min_dt_s,
        min_frames: cfg.inference.min_frames,
        max_frames: cfg.inference.max_frames,
        rest_after_s: cfg.inference.rest_after_s,
        rest_before_s: cfg.inference.rest_before_s,
        max_unobserved_s: cfg.windows.max_unobserved_s,
        step_s: cfg.model.dynamics.step_s,
        contact_sd_m: cfg.model.contact_sd_m,
        contact_firm: cfg.model.contact_firm,
        contact_force_n: cfg.windows.force_close_n,
        contact_range_m: cfg.perception.contact_range_m,
        voxel_m: cfg.perception.voxel_m,
    }
}

/// The effects the recording declares per part label (contract section 3, `effects`): declared
/// effects are part of the model from the start; undeclared ones are for model criticism to find.
/// Kinds: `spring`, `gravity`, `quadratic_damping`, and `joint_limit` (its `lower` and `upper` keys [m of
/// path from the first observation] anchor the stops; without either, one stop at 0 above).
/// Other kinds (`extra_friction`: a larger Coulomb friction) need nothing beyond the base model.
pub fn declared_effects(gt: &GroundTruth) -> BTreeMap<u32, EffectSet> {
    let mut out: BTreeMap<u32, EffectSet> = BTreeMap::new();
    for e in &gt.effects {
        let Some(part) = e.get("part").and_then(|p| p.as_u64()) else { continue };
        let Some(kind) = e.get("kind").and_then(|k| k.as_str()).and_then(EffectKind::parse) else { continue };
        let side = |k: &str| e.get(k).and_then(|p| p.as_f64());
        let limit = match (side("lower"), side("upper")) {
            (None, None) => LimitSpec { lower: None, upper: Some(0.0) },
            (lower, upper) => LimitSpec { lower, upper },
        };
        let set = out.entry(part as u32).or_default();
        *set = set.with(kind, Some(limit));
    }
    out
}

fn find_windows(rec: &Recording, tracks: &PartTracks, cfg: &Config, diag: &mut Diagnostics) -> Vec<Window> {
    let t_min = rec.clouds.first().map(|c| c.stamp).unwrap_or(0.0);
    let t_max = rec.clouds.last().map(|c| c.stamp).unwrap_or(0.0);
    let mut ws = if rec.wrenches.is_empty() {
        windows::motion_windows(tracks.values().map(Vec::as_slice), &cfg.windows)
    } else {
        let mut ws = windows::force_windows(&rec.wrenches, tracks.values().map(Vec::as_slice), &cfg.windows, t_min, t_max);
        for w in &mut ws {
            w.pushed_part =
                pushed_part(rec, w, cfg.windows.force_open_n, cfg.windows.force_close_n).or_else(|| pushed_part(rec, w, cfg.windows.force_close_n, cfg.windows.force_close_n));
        }
        ws
    };
    if ws.is_empty() {
        diag.warn(&cfg.topics.points, "no interaction window", "no motion or force period found; using the whole recording as one window");
        ws.push(Window { start: t_min, end: t_max, pushed_part: None });
    }
    ws
}

/// The pushed part of window `w`: the push starts at the first wrench sample in `w` above
/// `threshold` \[N\] and lasts while the force stays above `close_n`; every cloud in that time
/// votes with the contact point of the last wrench sample at or before it
/// ([`perception::ContactVotes`]).
/// A push that no cloud falls in takes the part nearest its first sample's contact point in the
/// cloud nearest in time.
fn pushed_part(rec: &Recording, w: &Window, threshold: f64, close_n: f64) -> Option<u32> {
    let first = rec.wrenches.iter().position(|s| w.contains(s.stamp) && s.force.norm() > threshold)?;
    let contact = &rec.wrenches[first];
    let end = rec.wrenches[first..].iter().find(|s| s.force.norm() <= close_n || !w.contains(s.stamp)).map_or(w.end, |s| s.stamp);
    let mut votes = perception::ContactVotes::default();
    for cloud in rec.clouds.iter().filter(|c| c.stamp >= contact.stamp && c.stamp <= end) {
        // The contact point of the last wrench sample at or before the cloud (wrenches are in
        // time order), as the node has it when the cloud arrives.
        let k = rec.wrenches.partition_point(|s| s.stamp <= cloud.stamp);
        if let Some(s) = k.checked_sub(1).and_then(|i| rec.wrenches.get(i)) {
            votes.add(cloud, &s.point);
        }
    }
    votes.part().or_else(|| {
        let cloud: &CloudFrame = rec.clouds.iter().min_by(|a, b| (a.stamp - contact.stamp).abs().total_cmp(&(b.stamp - contact.stamp).abs()))?;
        perception::nearest_part(cloud, &contact.point).map(|(l, _)| l)
    })
}
