//! `bom eval --corpus`: the metrics of contract section 6 over a corpus of objects, with the
//! calibration of the joint-type posterior (issue 24).
//!
//! A corpus is a manifest (`manifest.json`, as `bags/generate/corpus.py` writes it: per object its
//! `name`, `split` and bag lists `continuous` and `episodes`, paths relative to the manifest), a
//! folder holding one, or a folder of objects, each a folder of bags (split `all`). Every object
//! is replayed on its own (all its bags together) and scored against its `bom_ground_truth`; an
//! object whose bags cannot be read, or that has no ground truth or no posterior, is reported in
//! one line and skipped, and the aggregate says how many were scored.
//!
//! Calibration of the discrete posterior (beyond the paper, which reports Joint% only):
//! - Brier score: per part `sum_k (P(type k) - 1[k true])^2` over the three joint types (0 for a
//!   certain right call, 2 for a certain wrong one), averaged over parts;
//! - expected calibration error (ECE): the top-label confidence `max_k P(k)` in ten equal bins,
//!   `sum_b n_b / N |accuracy_b - confidence_b|` (Guo et al., ICML 2017);
//! - reliability table: every `(P(type k), 1[k true])` pair of every part (three a part), in ten
//!   bins of `P`: the mean predicted probability against the observed frequency per bin, so that
//!   both over- and under-confidence show;
//! - wrong calls at `P >= 0.95`: parts whose most probable joint type is wrong with probability
//!   at least 0.95 (likewise parents).
//!
//! With `--inference nuts` every object is also scored on its BOM-SVI posterior (the one NUTS
//! starts from, same run), and with `--baselines` on the paper's baselines; the report then has
//! the paper's Table 1 (`table1`, one row per method on the same objects) and, with NUTS, SVI's
//! 90% intervals against NUTS's (`svi_vs_nuts`, issue 26).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Instant;

use serde::{Deserialize, Serialize};

use super::criticism::{CriticismAggregate, CriticismRow, TrueEffect};
use super::{evaluate, median, Metrics};
use crate::config::Config;
use crate::model::JointType;
use crate::pipeline;

/// Which bag list of a manifest object to replay.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Layout {
    /// One bag with every interaction.
    Continuous,
    /// One bag per interaction, each from the object's initial state.
    Episodes,
}

/// One object of a corpus.
#[derive(Debug, Clone, Deserialize, Serialize)]
pub struct CorpusObject {
    pub name: String,
    #[serde(default = "all_split")]
    pub split: String,
    #[serde(default)]
    pub family: Option<String>,
    #[serde(default)]
    pub continuous: Vec<PathBuf>,
    #[serde(default)]
    pub episodes: Vec<PathBuf>,
    /// Undeclared effects acting in the recordings (an effects corpus, issue 25), scored against
    /// criticism's findings; absent in a structure corpus.
    #[serde(default)]
    pub effects: Option<Vec<TrueEffect>>,
    #[serde(default)]
    pub category: Option<String>,
}

fn all_split() -> String {
    "all".into()
}

#[derive(Debug, Deserialize)]
struct Manifest {
    objects: Vec<CorpusObject>,
}

/// Why a corpus could not be listed (exit code 3).
#[derive(Debug, thiserror::Error)]
pub enum CorpusError {
    #[error("{path}: {why}")]
    Unreadable { path: String, why: String },
}

/// The objects of a corpus: a manifest file, a folder with `manifest.json`, or a folder of
/// object folders (each holding `*.mcap`; both layouts then list the same bags). Paths come back
/// absolute or relative to the working directory.
///
/// # Errors
/// [`CorpusError`] when the manifest cannot be read or parsed, or the folder cannot be listed.
pub fn list(path: &Path) -> Result<Vec<CorpusObject>, CorpusError> {
    let err = |p: &Path, why: String| CorpusError::Unreadable { path: p.display().to_string(), why };
    let manifest = if path.is_dir() { path.join("manifest.json") } else { path.to_path_buf() };
    if manifest.is_file() {
        let text = std::fs::read_to_string(&manifest).map_err(|e| err(&manifest, e.to_string()))?;
        let m: Manifest = serde_json::from_str(&text).map_err(|e| err(&manifest, format!("not a corpus manifest: {e}")))?;
        let root = manifest.parent().unwrap_or(Path::new("."));
        return Ok(m
            .objects
            .into_iter()
            .map(|mut o| {
                o.continuous = o.continuous.iter().map(|p| root.join(p)).collect();
                o.episodes = o.episodes.iter().map(|p| root.join(p)).collect();
                o
            })
            .collect());
    }
    let mut objects = Vec::new();
    let entries = std::fs::read_dir(path).map_err(|e| err(path, e.to_string()))?;
    let mut dirs: Vec<PathBuf> = entries.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.is_dir()).collect();
    dirs.sort();
    for d in dirs {
        let mut bags: Vec<PathBuf> = std::fs::read_dir(&d)
            .map_err(|e| err(&d, e.to_string()))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "mcap"))
            .collect();
        bags.sort();
        let name = d.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        objects.push(CorpusObject { name, split: all_split(), family: None, continuous: bags.clone(), episodes: bags, effects: None, category: None });
    }
    Ok(objects)
}

/// One part's discrete posterior against the truth.
#[derive(Debug, Clone, Serialize)]
pub struct PartCall {
    pub label: u32,
    pub true_joint: String,
    /// `P(rigid), P(prismatic), P(revolute)`.
    pub type_probs: [f64; 3],
    pub joint_correct: bool,
    /// Posterior probability of the MAP parent, and whether it is right (contract's reading).
    pub parent_prob: f64,
    pub parent_correct: bool,
}

/// One scored object.
#[derive(Debug, Clone, Serialize)]
pub struct ObjectRow {
    pub name: String,
    pub split: String,
    pub family: Option<String>,
    pub layout: Layout,
    pub bags: Vec<PathBuf>,
    pub runtime_s: f64,
    pub metrics: Metrics,
    pub calls: Vec<PartCall>,
    /// With BOM-NUTS: the metrics of the BOM-SVI posterior it started from, SVI's share of the
    /// runtime, and the sampler's diagnostics (`metrics` are then NUTS's).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub svi: Option<Metrics>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub svi_runtime_s: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sampler: Option<SamplerRow>,
    /// Criticism against the object's undeclared effects (effects corpus only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub criticism: Option<CriticismRow>,
}

/// BOM-NUTS's diagnostics of one object (as the JSON's `model.sampler`).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct SamplerRow {
    pub r_hat_max: f64,
    pub ess_bulk_min: f64,
    pub ess_tail_min: f64,
    pub divergences: u64,
    /// Sampling draws, all chains and structures (the sampler's `total_draws`: each structure
    /// counted with the rounds it took).
    pub draws: u64,
    pub runtime_s: f64,
}

/// One row of the paper's Table 1 over the scored objects (medians and means as in
/// [`Aggregate`]; a metric a method cannot score is `None`).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Table1Row {
    pub method: String,
    pub joint_accuracy: Option<f64>,
    pub graph_mse: Option<f64>,
    pub ide: Option<f64>,
    pub axis_angle_deg: Option<f64>,
    pub coverage_fraction: Option<f64>,
    pub runtime_s_median: Option<f64>,
}

/// BOM-SVI's 90% intervals against BOM-NUTS's on the same objects (issue 26): per parameter
/// (damping, friction: interval width; axis direction: radius of the 90% cone) where both
/// posteriors call the part movable, the ratio SVI / NUTS, and each method's coverage of the
/// truth on those parameters.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct IntervalComparison {
    pub parameters: usize,
    pub width_ratio_median: Option<f64>,
    /// Parameters whose SVI interval is narrower than a third of NUTS's.
    pub narrower_than_third: usize,
    pub coverage_svi: [usize; 2],
    pub coverage_nuts: [usize; 2],
    /// Parts whose most probable joint type differs between the two.
    pub joint_type_disagreements: usize,
}

/// A bin of the reliability table.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ReliabilityBin {
    pub lo: f64,
    pub hi: f64,
    pub count: usize,
    pub mean_predicted: Option<f64>,
    pub observed_frequency: Option<f64>,
}

/// Calibration of the joint-type probabilities (module docs).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Calibration {
    pub brier: Option<f64>,
    pub ece: Option<f64>,
    pub reliability: Vec<ReliabilityBin>,
    /// Parts whose MAP joint type is wrong with `P >= 0.95`, and their share of the parts.
    pub wrong_confident: usize,
    pub wrong_confident_fraction: Option<f64>,
    /// Parts whose MAP parent is wrong with `P >= 0.95`.
    pub wrong_confident_parents: usize,
}

/// Accuracy over the parts of one true joint type.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct TypeAccuracy {
    pub joint: String,
    pub parts: usize,
    pub accuracy: Option<f64>,
}

/// The aggregate of a set of scored objects.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Aggregate {
    pub objects: usize,
    pub parts: usize,
    pub joint_accuracy: Option<f64>,
    pub per_type: Vec<TypeAccuracy>,
    pub parent_accuracy: Option<f64>,
    /// Mean over objects of each object's graph MSE.
    pub graph_mse: Option<f64>,
    /// Medians over all movable parts of the corpus (pooled).
    pub ide: Option<f64>,
    pub axis_angle_deg: Option<f64>,
    pub axis_offset_m: Option<f64>,
    /// 90% interval coverage, pooled: inside / counted.
    pub coverage: [usize; 2],
    pub coverage_fraction: Option<f64>,
    /// Revolute hinge points inside their 90% disc, pooled: inside / counted (not in `coverage`;
    /// [`super::PartMetrics::axis_point_covered`]).
    pub axis_point_coverage: [usize; 2],
    pub calibration: Calibration,
    pub runtime_s_median: Option<f64>,
    pub runtime_s_max: Option<f64>,
}

/// Per-part agreement of the MAP joint types between the two layouts of the same objects.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Agreement {
    pub objects: usize,
    pub parts: usize,
    pub same_joint_type: usize,
    pub fraction: Option<f64>,
}

/// The report of `bom eval --corpus`.
#[derive(Debug, Clone, Serialize)]
pub struct CorpusReport {
    pub corpus: String,
    pub split: String,
    pub layouts: Vec<Layout>,
    /// Objects listed (after the split filter), scored, and skipped with why.
    pub listed: usize,
    pub scored: usize,
    pub skipped: Vec<String>,
    /// One aggregate per layout, in `layouts` order.
    pub aggregate: Vec<Aggregate>,
    /// With both layouts: how often they agree.
    pub agreement: Option<Agreement>,
    /// With NUTS or baselines: the paper's Table 1 on the first layout's objects.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub table1: Option<Vec<Table1Row>>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub svi_vs_nuts: Option<IntervalComparison>,
    /// With an effects corpus: criticism per effect kind, one per layout (issue 25).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub criticism: Option<Vec<CriticismAggregate>>,
    pub objects: Vec<ObjectRow>,
}

/// Score one object's bags: replay, then [`evaluate`] against its ground truth.
fn score(o: &CorpusObject, layout: Layout, cfg: &Config, baselines: bool) -> Result<ObjectRow, String> {
    let bags = match layout {
        Layout::Continuous => &o.continuous,
        Layout::Episodes => &o.episodes,
    };
    if bags.is_empty() {
        return Err(format!("{}: no {} bags listed", o.name, format!("{layout:?}").to_lowercase()));
    }
    let t = Instant::now();
    let run = pipeline::replay(bags, cfg).map_err(|e| format!("{}: {e}", o.name))?;
    let runtime_s = t.elapsed().as_secs_f64();
    let gt = run.ground_truth.as_ref().ok_or_else(|| format!("{}: no 'bom_ground_truth' metadata record", o.name))?;
    let post = run.posterior.as_ref().ok_or_else(|| format!("{}: no posterior (no part seen inside a window)", o.name))?;
    let mut metrics = evaluate(gt, post, baselines);
    if baselines {
        super::add_diff_sim(&mut metrics, &run, gt, cfg);
    }
    let svi_post = run.sampler.as_ref().and_then(|_| run.updates.last()).map(|u| &u.posterior);
    let sampler = run.sampler.as_ref().map(|r| SamplerRow {
        r_hat_max: r.r_hat_max,
        ess_bulk_min: r.ess_bulk_min,
        ess_tail_min: r.ess_tail_min,
        divergences: r.divergences,
        draws: r.total_draws,
        runtime_s: r.runtime_s,
    });
    let calls = metrics
        .per_part
        .iter()
        .map(|m| {
            let j = post.joints.iter().find(|j| j.child == m.label);
            let type_probs = j.map(|j| j.type_probs).unwrap_or([1.0 / 3.0; 3]);
            let parent_prob = j.and_then(|j| j.parent_probs.iter().find(|(l, _)| *l == j.parent).map(|x| x.1)).unwrap_or(0.0);
            PartCall { label: m.label, true_joint: m.true_joint.clone(), type_probs, joint_correct: m.joint_correct, parent_prob, parent_correct: m.parent_correct }
        })
        .collect();
    Ok(ObjectRow {
        name: o.name.clone(),
        split: o.split.clone(),
        family: o.family.clone(),
        layout,
        bags: bags.clone(),
        runtime_s,
        metrics,
        calls,
        criticism: o.effects.as_ref().map(|t| super::criticism::score(t, o.category.as_deref(), &run.findings, Some(post), Some(gt))),
        svi: svi_post.map(|p| evaluate(gt, p, false)),
        svi_runtime_s: sampler.as_ref().map(|r| runtime_s - r.runtime_s),
        sampler,
    })
}

/// The calibration of a set of part calls (module docs).
pub fn calibration(calls: &[&PartCall]) -> Calibration {
    let n = calls.len();
    let truth = |c: &PartCall| JointType::parse(&c.true_joint).map(|t| t.index());
    let scored: Vec<(&PartCall, usize)> = calls.iter().filter_map(|c| truth(c).map(|t| (*c, t))).collect();
    let brier = (!scored.is_empty()).then(|| {
        scored.iter().map(|(c, t)| (0..3).map(|k| (c.type_probs[k] - (k == *t) as u8 as f64).powi(2)).sum::<f64>()).sum::<f64>() / scored.len() as f64
    });
    let bin = |p: f64| ((p * 10.0).floor() as usize).min(9);
    // ECE on the top label.
    let mut top = vec![(0usize, 0.0f64, 0.0f64); 10];
    for (c, t) in &scored {
        let k = (0..3).max_by(|&a, &b| c.type_probs[a].total_cmp(&c.type_probs[b])).unwrap_or(0);
        let p = c.type_probs[k];
        let b = &mut top[bin(p)];
        b.0 += 1;
        b.1 += p;
        b.2 += (k == *t) as u8 as f64;
    }
    let ece = (!scored.is_empty()).then(|| top.iter().map(|(m, p, a)| if *m == 0 { 0.0 } else { (a - p).abs() / scored.len() as f64 }).sum::<f64>());
    // Reliability over every (P(k), 1[k true]) pair.
    let mut rel = vec![(0usize, 0.0f64, 0.0f64); 10];
    for (c, t) in &scored {
        for k in 0..3 {
            let b = &mut rel[bin(c.type_probs[k])];
            b.0 += 1;
            b.1 += c.type_probs[k];
            b.2 += (k == *t) as u8 as f64;
        }
    }
    let reliability = rel
        .iter()
        .enumerate()
        .map(|(i, (m, p, a))| ReliabilityBin {
            lo: i as f64 / 10.0,
            hi: (i + 1) as f64 / 10.0,
            count: *m,
            mean_predicted: (*m > 0).then(|| p / *m as f64),
            observed_frequency: (*m > 0).then(|| a / *m as f64),
        })
        .collect();
    let wrong_confident = calls.iter().filter(|c| !c.joint_correct && c.type_probs.iter().cloned().fold(0.0, f64::max) >= 0.95).count();
    Calibration {
        brier,
        ece,
        reliability,
        wrong_confident,
        wrong_confident_fraction: (n > 0).then(|| wrong_confident as f64 / n as f64),
        wrong_confident_parents: calls.iter().filter(|c| !c.parent_correct && c.parent_prob >= 0.95).count(),
    }
}

/// Metrics of several objects pooled: joint accuracy over all parts, the mean of the objects'
/// graph MSE, medians over all movable parts (IdE, axis angle) and revolute axes (offset), and
/// the 90% intervals' coverage summed.
struct Pooled {
    joint_accuracy: Option<f64>,
    graph_mse: Option<f64>,
    ide: Option<f64>,
    axis_angle_deg: Option<f64>,
    axis_offset_m: Option<f64>,
    coverage: [usize; 2],
    axis_point_coverage: [usize; 2],
}

fn pooled(ms: &[&Metrics]) -> Pooled {
    let pm: Vec<&super::PartMetrics> = ms.iter().flat_map(|m| m.per_part.iter()).collect();
    let movable = |m: &&&super::PartMetrics| JointType::parse(&m.true_joint).is_some_and(|t| t.movable());
    Pooled {
        joint_accuracy: (!pm.is_empty()).then(|| pm.iter().filter(|m| m.joint_correct).count() as f64 / pm.len() as f64),
        graph_mse: (!ms.is_empty()).then(|| ms.iter().map(|m| m.graph_mse).sum::<f64>() / ms.len() as f64),
        ide: median(pm.iter().filter(movable).flat_map(|m| [m.damping_rel_error, m.friction_rel_error]).flatten().collect()),
        axis_angle_deg: median(pm.iter().filter(movable).filter_map(|m| m.axis_angle_deg).collect()),
        axis_offset_m: median(pm.iter().filter_map(|m| m.axis_offset_m).collect()),
        coverage: ms.iter().fold([0, 0], |a, m| [a[0] + m.coverage.all[0], a[1] + m.coverage.all[1]]),
        axis_point_coverage: ms.iter().fold([0, 0], |a, m| [a[0] + m.coverage.axis_point[0], a[1] + m.coverage.axis_point[1]]),
    }
}

/// The aggregate of scored objects.
pub fn aggregate(rows: &[&ObjectRow]) -> Aggregate {
    let calls: Vec<&PartCall> = rows.iter().flat_map(|r| r.calls.iter()).collect();
    let parts = calls.len();
    let frac = |k: usize, n: usize| (n > 0).then(|| k as f64 / n as f64);
    let per_type = JointType::ALL
        .iter()
        .map(|t| {
            let of: Vec<&&PartCall> = calls.iter().filter(|c| JointType::parse(&c.true_joint) == Some(*t)).collect();
            TypeAccuracy { joint: t.name().into(), parts: of.len(), accuracy: frac(of.iter().filter(|c| c.joint_correct).count(), of.len()) }
        })
        .collect();
    let p = pooled(&rows.iter().map(|r| &r.metrics).collect::<Vec<_>>());
    let times: Vec<f64> = rows.iter().map(|r| r.runtime_s).collect();
    Aggregate {
        objects: rows.len(),
        parts,
        joint_accuracy: p.joint_accuracy,
        per_type,
        parent_accuracy: frac(calls.iter().filter(|c| c.parent_correct).count(), parts),
        graph_mse: p.graph_mse,
        ide: p.ide,
        axis_angle_deg: p.axis_angle_deg,
        axis_offset_m: p.axis_offset_m,
        coverage: p.coverage,
        coverage_fraction: frac(p.coverage[0], p.coverage[1]),
        axis_point_coverage: p.axis_point_coverage,
        calibration: calibration(&calls),
        runtime_s_median: median(times.clone()),
        runtime_s_max: times.iter().cloned().reduce(f64::max),
    }
}

/// The paper's Table 1 over `rows` (module docs): BOM-SVI (its posterior before NUTS where NUTS
/// ran), BOM-NUTS, and with baselines Diff. sim., Diff. sim. tail init (IdE and runtime),
/// Disconnected and Clique (graph MSE).
pub fn table1(rows: &[&ObjectRow]) -> Vec<Table1Row> {
    let scored = |method: &str, ms: &[&Metrics], times: Vec<f64>| {
        let p = pooled(ms);
        Table1Row {
            method: method.into(),
            joint_accuracy: p.joint_accuracy,
            graph_mse: p.graph_mse,
            ide: p.ide,
            axis_angle_deg: p.axis_angle_deg,
            coverage_fraction: (p.coverage[1] > 0).then(|| p.coverage[0] as f64 / p.coverage[1] as f64),
            runtime_s_median: median(times),
        }
    };
    let nuts = rows.iter().any(|r| r.sampler.is_some());
    let svi: Vec<&Metrics> = rows.iter().map(|r| r.svi.as_ref().unwrap_or(&r.metrics)).collect();
    let mut out = vec![scored("BOM-SVI", &svi, rows.iter().map(|r| r.svi_runtime_s.unwrap_or(r.runtime_s)).collect())];
    if nuts {
        let with: Vec<&&ObjectRow> = rows.iter().filter(|r| r.sampler.is_some()).collect();
        out.push(scored("BOM-NUTS", &with.iter().map(|r| &r.metrics).collect::<Vec<_>>(), with.iter().map(|r| r.runtime_s).collect()));
    }
    let bl: Vec<&super::Baselines> = rows.iter().filter_map(|r| r.metrics.baselines.as_ref()).collect();
    if !bl.is_empty() {
        let empty = |method: &str| Table1Row { method: method.into(), joint_accuracy: None, graph_mse: None, ide: None, axis_angle_deg: None, coverage_fraction: None, runtime_s_median: None };
        for (name, pick) in [("Diff. sim.", 0), ("Diff. sim. tail init", 1)] {
            let rows: Vec<&super::baselines::DiffSimRow> = bl.iter().filter_map(|b| if pick == 0 { b.diff_sim.as_ref() } else { b.diff_sim_tail_init.as_ref() }).collect();
            if rows.is_empty() {
                continue;
            }
            let mut r = empty(name);
            r.ide = median(rows.iter().flat_map(|d| d.parts.iter().flat_map(|p| [p.damping_rel_error, p.friction_rel_error])).flatten().collect());
            r.runtime_s_median = median(rows.iter().map(|d| d.runtime_s).collect());
            out.push(r);
        }
        let mean = |v: Vec<f64>| (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64);
        let mut r = empty("Disconnected");
        r.graph_mse = mean(bl.iter().map(|b| b.disconnected.graph_mse).collect());
        out.push(r);
        let mut r = empty("Clique");
        r.graph_mse = mean(bl.iter().map(|b| b.clique.graph_mse).collect());
        out.push(r);
    }
    out
}

/// Whether the true axis lies in a part's 90% posterior cone before the model discrepancy.
fn inside_cone(m: &super::PartMetrics) -> Option<bool> {
    m.axis_angle_deg.zip(m.axis_cone_posterior_deg).map(|(a, c)| a <= c)
}

/// SVI's 90% intervals against NUTS's on the objects NUTS sampled ([`IntervalComparison`]); the
/// axes by the posteriors' own cones, before the model discrepancy that both carry.
pub fn svi_vs_nuts(rows: &[&ObjectRow]) -> IntervalComparison {
    let mut c = IntervalComparison { parameters: 0, width_ratio_median: None, narrower_than_third: 0, coverage_svi: [0, 0], coverage_nuts: [0, 0], joint_type_disagreements: 0 };
    let mut ratios = Vec::new();
    for r in rows.iter().filter(|r| r.sampler.is_some()) {
        let Some(svi) = &r.svi else { continue };
        for n in &r.metrics.per_part {
            let Some(s) = svi.per_part.iter().find(|s| s.label == n.label) else { continue };
            c.joint_type_disagreements += (s.estimated_joint != n.estimated_joint) as usize;
            let width = |iv: Option<[f64; 2]>| iv.map(|[lo, hi]| hi - lo);
            let pairs = [
                (width(s.damping_interval), width(n.damping_interval), s.damping_covered, n.damping_covered),
                (width(s.friction_interval), width(n.friction_interval), s.friction_covered, n.friction_covered),
                // The posterior's own cones: the model discrepancy added to both would hide
                // the guide's difference.
                (s.axis_cone_posterior_deg, n.axis_cone_posterior_deg, inside_cone(s), inside_cone(n)),
            ];
            for (ws, wn, cs, cn) in pairs {
                let (Some(ws), Some(wn)) = (ws, wn) else { continue };
                if !(wn > 0.0 && ws.is_finite()) {
                    continue;
                }
                c.parameters += 1;
                ratios.push(ws / wn);
                c.narrower_than_third += (ws < wn / 3.0) as usize;
                if let (Some(a), Some(b)) = (cs, cn) {
                    c.coverage_svi = [c.coverage_svi[0] + a as usize, c.coverage_svi[1] + 1];
                    c.coverage_nuts = [c.coverage_nuts[0] + b as usize, c.coverage_nuts[1] + 1];
                }
            }
        }
    }
    c.width_ratio_median = median(ratios);
    c
}

/// Agreement of the MAP joint types between the continuous and the episode replays of the same
/// objects (by object name and part label).
pub fn agreement(rows: &[ObjectRow]) -> Agreement {
    let (mut objects, mut parts, mut same) = (0, 0, 0);
    for a in rows.iter().filter(|r| r.layout == Layout::Continuous) {
        let Some(b) = rows.iter().find(|r| r.layout == Layout::Episodes && r.name == a.name) else { continue };
        objects += 1;
        for m in &a.metrics.per_part {
            let Some(o) = b.metrics.per_part.iter().find(|o| o.label == m.label) else { continue };
            parts += 1;
            same += (m.estimated_joint.is_some() && m.estimated_joint == o.estimated_joint) as usize;
        }
    }
    Agreement { objects, parts, same_joint_type: same, fraction: (parts > 0).then(|| same as f64 / parts as f64) }
}

/// Evaluate a corpus: the objects of `split` (`all` for every one) in each of `layouts`, `jobs`
/// objects at a time. Each object that cannot be scored gets one line on stderr and a `skipped`
/// entry.
///
/// # Errors
/// [`CorpusError`] when the corpus cannot be listed.
pub fn run(corpus: &Path, split: &str, layouts: &[Layout], cfg: &Config, jobs: usize, baselines: bool) -> Result<CorpusReport, CorpusError> {
    // The cores are shared among the objects scored at once (each fit's own threads, see
    // `SviConfig::threads`), unless the configuration names a number.
    let mut cfg = cfg.clone();
    if cfg.inference.threads == 0 {
        cfg.inference.threads = (crate::parallel::resolve_threads(0) / jobs.max(1)).max(1);
    }
    let cfg = &cfg;
    let objects: Vec<CorpusObject> = list(corpus)?.into_iter().filter(|o| split == "all" || o.split == split).collect();
    let tasks: Vec<(usize, Layout)> = layouts.iter().flat_map(|&l| (0..objects.len()).map(move |i| (i, l))).collect();
    let next = AtomicUsize::new(0);
    let results: Mutex<Vec<(usize, Result<ObjectRow, String>)>> = Mutex::new(Vec::new());
    std::thread::scope(|s| {
        for _ in 0..jobs.max(1) {
            s.spawn(|| loop {
                let k = next.fetch_add(1, Ordering::SeqCst);
                let Some(&(i, layout)) = tasks.get(k) else { break };
                let r = score(&objects[i], layout, cfg, baselines);
                match &r {
                    Ok(row) => eprintln!(
                        "[{}/{}] {} ({:?}): joints {}/{} right, {:.1} s",
                        k + 1,
                        tasks.len(),
                        row.name,
                        layout,
                        row.calls.iter().filter(|c| c.joint_correct).count(),
                        row.calls.len(),
                        row.runtime_s
                    ),
                    Err(e) => eprintln!("warning: skipped {e}"),
                }
                results.lock().expect("no panic holds the lock").push((k, r));
            });
        }
    });
    let mut results = results.into_inner().expect("threads joined");
    results.sort_by_key(|(k, _)| *k);
    let mut rows = Vec::new();
    let mut skipped = Vec::new();
    for (_, r) in results {
        match r {
            Ok(row) => rows.push(row),
            Err(e) => skipped.push(e),
        }
    }
    let aggregate = layouts.iter().map(|l| aggregate(&rows.iter().filter(|r| r.layout == *l).collect::<Vec<_>>())).collect();
    let agreement = (layouts.len() > 1).then(|| agreement(&rows));
    let first: Vec<&ObjectRow> = rows.iter().filter(|r| Some(&r.layout) == layouts.first()).collect();
    let table1 = (cfg.nuts.enabled || baselines).then(|| table1(&first));
    let svi_vs_nuts = cfg.nuts.enabled.then(|| svi_vs_nuts(&first));
    let criticism = objects.iter().any(|o| o.effects.is_some()).then(|| {
        layouts
            .iter()
            .map(|l| super::criticism::aggregate(&rows.iter().filter(|r| r.layout == *l).filter_map(|r| r.criticism.as_ref()).collect::<Vec<_>>()))
            .collect()
    });
    Ok(CorpusReport {
        corpus: corpus.display().to_string(),
        split: split.into(),
        layouts: layouts.to_vec(),
        listed: objects.len(),
        scored: rows.len(),
        skipped,
        aggregate,
        agreement,
        table1,
        svi_vs_nuts,
        criticism,
        objects: rows,
    })
}

/// A readable table of the report.
pub fn render(r: &CorpusReport) -> String {
    use std::fmt::Write;
    let opt = |v: Option<f64>, p: usize| v.map(|x| format!("{x:.p$}")).unwrap_or_else(|| "-".into());
    let mut s = String::new();
    let _ = writeln!(s, "corpus {} (split {}): {} object runs scored of {} listed x {} layout(s)", r.corpus, r.split, r.scored, r.listed, r.layouts.len());
    for e in &r.skipped {
        let _ = writeln!(s, "  skipped: {e}");
    }
    let _ = writeln!(
        s,
        "  {:>11} {:>5} {:>5} {:>6} {:>6} {:>6} {:>6} {:>6} {:>7} {:>6} {:>7} {:>8} {:>6} {:>6} {:>6} {:>5}",
        "layout", "objs", "parts", "joint", "rigid", "prism", "revol", "parent", "gMSE", "IdE", "axis°", "offset", "cov90", "Brier", "ECE", "P95x"
    );
    for (l, a) in r.layouts.iter().zip(&r.aggregate) {
        let t = |i: usize| opt(a.per_type[i].accuracy, 3);
        let _ = writeln!(
            s,
            "  {:>11} {:>5} {:>5} {:>6} {:>6} {:>6} {:>6} {:>6} {:>7} {:>6} {:>7} {:>8} {:>6} {:>6} {:>6} {:>5}",
            format!("{l:?}").to_lowercase(),
            a.objects,
            a.parts,
            opt(a.joint_accuracy, 3),
            t(0),
            t(1),
            t(2),
            opt(a.parent_accuracy, 3),
            opt(a.graph_mse, 4),
            opt(a.ide, 3),
            opt(a.axis_angle_deg, 2),
            opt(a.axis_offset_m, 4),
            opt(a.coverage_fraction, 3),
            opt(a.calibration.brier, 3),
            opt(a.calibration.ece, 3),
            a.calibration.wrong_confident,
        );
    }
    for (l, a) in r.layouts.iter().zip(&r.aggregate) {
        let _ = write!(s, "  reliability ({}): P bin -> observed (n):", format!("{l:?}").to_lowercase());
        for b in a.calibration.reliability.iter().filter(|b| b.count > 0) {
            let _ = write!(s, " [{:.1},{:.1}) {:.2}->{} ({})", b.lo, b.hi, b.mean_predicted.unwrap_or(0.0), opt(b.observed_frequency, 2), b.count);
        }
        let _ = writeln!(
            s,
            "\n  runtime per object ({}): median {} s, max {} s; wrong parents at P>=0.95: {}; hinge points in their 90% disc: {}/{}",
            format!("{l:?}").to_lowercase(),
            opt(a.runtime_s_median, 2),
            opt(a.runtime_s_max, 2),
            a.calibration.wrong_confident_parents,
            a.axis_point_coverage[0],
            a.axis_point_coverage[1]
        );
    }
    if let Some(g) = &r.agreement {
        let _ = writeln!(s, "  continuous vs episodes: same joint type on {}/{} parts ({}) of {} objects", g.same_joint_type, g.parts, opt(g.fraction, 3), g.objects);
    }
    if let Some(t) = &r.table1 {
        let _ = writeln!(s, "  Table 1 ({} layout):", r.layouts.first().map(|l| format!("{l:?}").to_lowercase()).unwrap_or_default());
        let _ = writeln!(s, "  {:<22} {:>7} {:>8} {:>7} {:>7} {:>7} {:>9}", "method", "joint", "gMSE", "IdE", "axis°", "cov90", "time [s]");
        for row in t {
            let _ = writeln!(
                s,
                "  {:<22} {:>7} {:>8} {:>7} {:>7} {:>7} {:>9}",
                row.method,
                opt(row.joint_accuracy, 3),
                opt(row.graph_mse, 4),
                opt(row.ide, 3),
                opt(row.axis_angle_deg, 2),
                opt(row.coverage_fraction, 3),
                opt(row.runtime_s_median, 2)
            );
        }
    }
    for (l, c) in r.layouts.iter().zip(r.criticism.iter().flatten()) {
        let _ = writeln!(s, "  criticism ({}, {} objects): kind: primary named (after <= before/3), median after/before, param ok, truth in 90% interval, secondary named", format!("{l:?}").to_lowercase(), c.objects);
        for k in &c.per_kind {
            let _ = writeln!(
                s,
                "    {:<18} {:>3} {:>3} ({:>3}) {:>6} {:>3}/{:<3} {:>3}/{:<3} {}/{}",
                k.kind,
                k.primary,
                k.named,
                k.named_third,
                opt(k.ratio_median, 2),
                k.param_ok[0],
                k.param_ok[1],
                k.in_interval[0],
                k.in_interval[1],
                k.secondary[0],
                k.secondary[1]
            );
        }
        let _ = writeln!(
            s,
            "    all primary: {}/{} named, {} with after <= before/3; effect-free objects with an added effect {}/{}; false alarms {}; extra friction absorbed {}/{}; findings with after >= before {}",
            c.named, c.primary, c.named_third, c.effect_free_alarmed, c.effect_free, c.false_alarms, c.absorbed[0], c.absorbed[1], c.after_not_below_before
        );
    }
    if let Some(c) = &r.svi_vs_nuts {
        let _ = writeln!(
            s,
            "  SVI vs NUTS 90% intervals: {} parameters, width ratio median {}, narrower than a third {}, coverage SVI {}/{} NUTS {}/{}, joint types differ on {} parts",
            c.parameters,
            opt(c.width_ratio_median, 2),
            c.narrower_than_third,
            c.coverage_svi[0],
            c.coverage_svi[1],
            c.coverage_nuts[0],
            c.coverage_nuts[1],
            c.joint_type_disagreements
        );
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn call(true_joint: &str, p: [f64; 3]) -> PartCall {
        let t = JointType::parse(true_joint).unwrap().index();
        let k = (0..3).max_by(|&a, &b| p[a].total_cmp(&p[b])).unwrap();
        PartCall { label: 1, true_joint: true_joint.into(), type_probs: p, joint_correct: k == t, parent_prob: 1.0, parent_correct: true }
    }

    /// Brier, ECE and the reliability table against hand-computed values: a certain right call
    /// scores 0, a certain wrong one 2 and counts as a confident mistake; a 0.6 call right half
    /// the time is off the diagonal by 0.1.
    #[test]
    fn calibration_by_hand() {
        let calls = [call("revolute", [0.0, 0.0, 1.0]), call("revolute", [0.0, 1.0, 0.0])];
        let c = calibration(&calls.iter().collect::<Vec<_>>());
        assert!((c.brier.unwrap() - 1.0).abs() < 1e-12);
        assert_eq!(c.wrong_confident, 1);
        assert!((c.ece.unwrap() - 0.5).abs() < 1e-12, "top label 1.0, right half the time");
        let calls = [call("prismatic", [0.2, 0.6, 0.2]), call("revolute", [0.2, 0.6, 0.2])];
        let c = calibration(&calls.iter().collect::<Vec<_>>());
        assert!((c.ece.unwrap() - 0.1).abs() < 1e-12);
        assert_eq!(c.wrong_confident, 0);
        let b6 = &c.reliability[6];
        assert_eq!(b6.count, 2);
        assert!((b6.observed_frequency.unwrap() - 0.5).abs() < 1e-12);
        let b2 = &c.reliability[2];
        assert_eq!(b2.count, 4);
        assert!((b2.observed_frequency.unwrap() - 0.25).abs() < 1e-12);
        // 0.04 + 0.16 + 0.04 for the right call, 0.04 + 0.36 + 0.64 for the wrong one
        assert!((c.brier.unwrap() - 0.64).abs() < 1e-12);
    }
}
