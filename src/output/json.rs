//! The JSON summary of contract section 5.

use std::collections::BTreeMap;

use serde::Serialize;

use crate::criticism::Finding;

use crate::inference::nuts::SamplerReport;
use crate::inference::Posterior;
use crate::pipeline::Run;

#[derive(Debug, Serialize)]
pub struct PartJson {
    pub label: u32,
    pub frames: usize,
    pub points_per_frame: f64,
}

#[derive(Debug, Serialize)]
pub struct WindowJson {
    pub start_s: f64,
    pub end_s: f64,
    pub pushed_part: Option<u32>,
}

#[derive(Debug, Serialize)]
pub struct AxisJson {
    pub direction: [f64; 3],
    pub direction_sd_deg: f64,
    /// Radius of the 90% credible cone around `direction` (beyond the contract's example).
    pub direction_q90_deg: f64,
    pub point: Option<[f64; 3]>,
    pub point_sd_m: Option<f64>,
    /// Factor (>= 1) by which the axis draws' variance was widened before the spreads were taken
    /// (`n / n_eff` of the part's residuals in kinematic mode; beyond the contract's example;
    /// [`crate::inference::AxisSummary::inflation`]).
    pub variance_inflation: f64,
    /// The model discrepancy in `direction_sd_deg` and `direction_q90_deg` (sd of a tilt per
    /// direction across the axis, deg; `model.axis_discrepancy_deg`), and the posterior's own
    /// spreads before it (beyond the contract's example;
    /// [`crate::inference::AxisSummary::with_discrepancy`]).
    pub direction_discrepancy_deg: f64,
    pub direction_posterior_sd_deg: f64,
    pub direction_posterior_q90_deg: f64,
    /// Revolute: the turn the part was seen to make (rad), the model discrepancy in `point_sd_m`
    /// (sd per direction across the axis, m; `model.axis_point_discrepancy_m`), and the
    /// posterior's own point spread before it (m; beyond the contract's example;
    /// [`crate::inference::AxisSummary::with_discrepancy`]).
    pub turn_rad: Option<f64>,
    pub point_discrepancy_m: Option<f64>,
    pub point_posterior_sd_m: Option<f64>,
}

/// A kinodynamic parameter: median, sd and (beyond the contract's example) the 90% interval.
#[derive(Debug, Serialize)]
pub struct EstimateJson {
    pub median: f64,
    pub sd: f64,
    pub q05: f64,
    pub q95: f64,
}

fn estimate(e: &crate::inference::Estimate) -> EstimateJson {
    EstimateJson { median: e.median, sd: e.sd, q05: e.q05, q95: e.q95 }
}

#[derive(Debug, Serialize)]
pub struct JointJson {
    pub child: u32,
    pub parent: u32,
    pub parent_probs: BTreeMap<String, f64>,
    pub type_probs: BTreeMap<String, f64>,
    pub axis: Option<AxisJson>,
    /// The part's centre of mass in the reference configuration (its first observation) \[m, fixed
    /// frame\] (beyond the contract's example: `bom predict` moves nested axes with it).
    pub com: [f64; 3],
    /// Rotational inertia about the centre of mass per kilogram \[m²\], rows of a 3x3 matrix in
    /// fixed-frame axes, in the reference configuration: perception's hull model of the part
    /// (beyond the contract's example; `None` where no geometry, e.g. the node's posteriors). With
    /// `mass`, `com` and the axis it gives the joint's generalised inertia, which the physics uses
    /// ([`crate::model::physics::generalised_inertia`]) and a planner needs.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub unit_inertia: Option<[[f64; 3]; 3]>,
    pub damping: Option<EstimateJson>,
    pub friction: Option<EstimateJson>,
    pub mass: Option<EstimateJson>,
    /// Correlation of the logs of `damping`, `friction` and `mass`, rows of a 3x3 matrix in that
    /// order (beyond the contract's example; with the kinodynamics only): the three are not
    /// independent under the posterior, and `bom predict` draws them jointly
    /// ([`crate::inference::Kinodynamics::log_correlation`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub log_correlation: Option<[[f64; 3]; 3]>,
}

#[derive(Debug, Serialize)]
pub struct ModelJson {
    /// `svi` or `nuts`.
    pub inference: String,
    pub runtime_s: f64,
    pub elbo: f64,
    pub iterations: usize,
    pub joints: Vec<JointJson>,
    /// BOM-NUTS's diagnostics (contract section 5), with `inference` `nuts`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sampler: Option<SamplerJson>,
}

/// `model.sampler` (contract section 5): chains, sampling draws per chain, the largest R-hat and
/// least bulk ESS over the reported parameters, divergent draws, NUTS's own wall time \[s\]; also
/// the structures sampled (tree as parent labels, joint types) with their weights.
#[derive(Debug, Serialize)]
pub struct SamplerJson {
    pub chains: usize,
    pub draws: u64,
    /// Beyond the contract: sampling draws over all chains and structures (the divergences'
    /// denominator; `chains * draws * structures` overstates it when structures stop after
    /// different rounds).
    pub total_draws: u64,
    pub r_hat_max: Option<f64>,
    pub ess_bulk_min: Option<f64>,
    /// Beyond the contract: the least tail ESS (of the 5% and 95% quantiles) over the reported
    /// parameters.
    pub ess_tail_min: Option<f64>,
    pub divergences: u64,
    pub runtime_s: f64,
    pub structure_mass: f64,
    pub structures: Vec<StructureJson>,
    pub warnings: Vec<String>,
}

/// One structure NUTS conditioned on.
#[derive(Debug, Serialize)]
pub struct StructureJson {
    /// Part label -> parent label (0 the fixed frame).
    pub parents: BTreeMap<String, u32>,
    /// Part label -> joint type.
    pub types: BTreeMap<String, String>,
    pub weight: f64,
    /// Beyond the contract: the index in `structures` of an earlier structure with the same
    /// density (parts hung from a static part instead of the fixed frame), whose draws stand for
    /// this one; absent when this one was sampled itself or not at all (`sampled`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub same_density_as: Option<usize>,
    /// Beyond the contract: whether this structure's chains ran (the most probable always; the
    /// others with `nuts.all_structures`).
    pub sampled: bool,
}

fn sampler_json(run: &Run, s: &SamplerReport) -> SamplerJson {
    let labels: Vec<u32> = run.posterior.as_ref().map(|p| p.joints.iter().map(|j| j.child).collect()).unwrap_or_default();
    let label = |node: usize| if node == 0 { 0 } else { labels.get(node - 1).copied().unwrap_or(0) };
    SamplerJson {
        chains: s.chains,
        draws: s.draws,
        total_draws: s.total_draws,
        r_hat_max: finite(s.r_hat_max),
        ess_bulk_min: finite(s.ess_bulk_min),
        ess_tail_min: finite(s.ess_tail_min),
        divergences: s.divergences,
        runtime_s: s.runtime_s,
        structure_mass: s.structure_mass,
        structures: s
            .structures
            .iter()
            .enumerate()
            .map(|(k, (st, w))| StructureJson {
                parents: st.parent.iter().enumerate().map(|(i, &p)| (labels.get(i).copied().unwrap_or(0).to_string(), label(p))).collect(),
                types: st.types.iter().enumerate().map(|(i, t)| (labels.get(i).copied().unwrap_or(0).to_string(), t.name().to_string())).collect(),
                weight: *w,
                same_density_as: s.same_density_as.get(k).copied().flatten(),
                sampled: s.sampled.get(k).copied().unwrap_or(false),
            })
            .collect(),
        warnings: s.warnings.clone(),
    }
}

/// One finding of model criticism (contract section 5, `criticism`).
#[derive(Debug, Serialize)]
pub struct FindingJson {
    pub part: u32,
    /// `spring`, `joint_limit`, `gravity`, `quadratic_damping`, or `unexplained`.
    pub effect: String,
    /// The effect's posterior medians (joint units), or the residual's correlations.
    pub params: BTreeMap<String, f64>,
    /// 90% intervals of the effect's parameters, `[5%, 95%]` by name (not in the contract's
    /// example; absent when unexplained).
    #[serde(skip_serializing_if = "BTreeMap::is_empty")]
    pub intervals_90: BTreeMap<String, [f64; 2]>,
    pub rmse_before_m: f64,
    pub rmse_after_m: f64,
    /// ELBO gain of the effect \[nats\] (the best candidate's when unexplained).
    pub evidence_nats: f64,
}

/// A part's held-out residual level.
#[derive(Debug, Serialize)]
pub struct ResidualJson {
    pub part: u32,
    pub rmse_m: Option<f64>,
    pub noise_rmse_m: f64,
    pub pattern: BTreeMap<String, f64>,
}

fn finding_json(f: &Finding) -> FindingJson {
    FindingJson {
        part: f.part,
        effect: f.name().into(),
        params: f.params.iter().cloned().collect(),
        intervals_90: f.intervals.iter().cloned().collect(),
        rmse_before_m: f.rmse_before_m,
        rmse_after_m: f.rmse_after_m,
        evidence_nats: f.evidence_nats,
    }
}

/// The whole summary.
#[derive(Debug, Serialize)]
pub struct Summary {
    pub bom_version: String,
    pub bags: Vec<String>,
    pub mode: String,
    pub parts: Vec<PartJson>,
    pub windows: Vec<WindowJson>,
    pub model: Option<ModelJson>,
    pub criticism: Vec<FindingJson>,
    /// Per movable part, the held-out residual of the final model and the level the position
    /// noise alone gives (not in the contract's example; the "residual level" of model criticism).
    pub residuals: Vec<ResidualJson>,
    /// Bad-input events by `topic: kind` (not in the contract's example; never silent).
    pub diagnostics: BTreeMap<String, u64>,
}

fn finite(x: f64) -> Option<f64> {
    x.is_finite().then_some(x)
}

/// The JSON of one posterior's joints.
pub fn model_json(p: &Posterior) -> ModelJson {
    let joints = p
        .joints
        .iter()
        .map(|j| JointJson {
            child: j.child,
            parent: j.parent,
            parent_probs: j.parent_probs.iter().map(|(l, p)| (l.to_string(), *p)).collect(),
            type_probs: crate::model::JointType::ALL.iter().map(|t| (t.name().to_string(), j.type_probs[t.index()])).collect(),
            // A rigid joint has no axis.
            axis: j.axis.as_ref().filter(|_| j.map_type.movable()).map(|a| AxisJson {
                direction: [a.direction.x, a.direction.y, a.direction.z],
                direction_sd_deg: a.direction_sd_deg,
                direction_q90_deg: a.direction_q90_deg,
                point: a.point.map(|p| [p.x, p.y, p.z]),
                point_sd_m: finite(a.point_sd_m),
                variance_inflation: a.inflation,
                direction_discrepancy_deg: a.discrepancy_deg,
                direction_posterior_sd_deg: a.posterior_sd_deg,
                direction_posterior_q90_deg: a.posterior_q90_deg,
                turn_rad: finite(j.turn_rad()),
                point_discrepancy_m: a.point.map(|_| a.point_discrepancy_m),
                point_posterior_sd_m: finite(a.point_posterior_sd_m),
            }),
            com: {
                let ty = j.axis.as_ref().filter(|_| j.map_type.movable()).map_or(j.map_type, |a| a.joint);
                let c = j.mean_params[ty.index()].com;
                [c.x, c.y, c.z]
            },
            unit_inertia: None,
            // Kinodynamics are unknown in kinematic mode and for rigid joints (contract section 5).
            damping: j.kinodynamics.as_ref().filter(|_| j.map_type.movable()).map(|k| estimate(&k.damping)),
            friction: j.kinodynamics.as_ref().filter(|_| j.map_type.movable()).map(|k| estimate(&k.friction)),
            mass: j.kinodynamics.as_ref().filter(|_| j.map_type.movable()).map(|k| estimate(&k.mass)),
            log_correlation: j.kinodynamics.as_ref().filter(|_| j.map_type.movable()).map(|k| [0, 1, 2].map(|r| [0, 1, 2].map(|c| k.log_correlation[(r, c)]))),
        })
        .collect();
    ModelJson { inference: "svi".into(), runtime_s: p.runtime_s, elbo: p.elbo, iterations: p.iterations, joints, sampler: None }
}

/// Build the summary of a replay.
pub fn summary(run: &Run) -> Summary {
    Summary {
        bom_version: env!("CARGO_PKG_VERSION").into(),
        bags: run.bags.iter().map(|b| b.display().to_string()).collect(),
        mode: run.mode.into(),
        parts: run
            .parts
            .iter()
            .map(|p| PartJson { label: p.label, frames: p.frames, points_per_frame: p.points_per_frame })
            .collect(),
        windows: run
            .windows
            .iter()
            .map(|w| WindowJson { start_s: w.start, end_s: w.end, pushed_part: w.pushed_part })
            .collect(),
        model: run.posterior.as_ref().map(|p| {
            let mut m = model_json(p);
            for j in &mut m.joints {
                j.unit_inertia = run.geometry.get(&j.child).map(|g| {
                    let u = &g.unit_inertia;
                    [0, 1, 2].map(|r| [u[(r, 0)], u[(r, 1)], u[(r, 2)]])
                });
            }
            if let Some(s) = &run.sampler {
                m.inference = "nuts".into();
                m.sampler = Some(sampler_json(run, s));
            }
            m
        }),
        criticism: run.findings.iter().map(finding_json).collect(),
        residuals: run
            .updates
            .last()
            .map(|u| {
                u.criticism
                    .parts
                    .iter()
                    .map(|p| ResidualJson {
                        part: p.label,
                        rmse_m: finite(p.rmse_m),
                        noise_rmse_m: p.noise_rmse_m,
                        pattern: p.pattern.diagnosis().iter().map(|(k, v)| (k.to_string(), *v)).collect(),
                    })
                    .collect()
            })
            .unwrap_or_default(),
        diagnostics: run.diagnostics.counts().clone(),
    }
}

/// One part in the JSON of `bom predict` (contract section 4): per predicted stamp, the centre of
/// mass at the posterior medians, the draws' per-coordinate 90% interval and 90% ball radius
/// \[m, fixed frame\], the observed centre where the part was seen (else null); and how the
/// prediction compares with those observations.
#[derive(Debug, Serialize)]
pub struct PredictedPartJson {
    pub label: u32,
    pub com: Vec<[f64; 3]>,
    pub lower: Vec<[f64; 3]>,
    pub upper: Vec<[f64; 3]>,
    pub band_radius_m: Vec<f64>,
    /// The draws' mean centre of mass (beyond the contract; `com` without draws): the prediction
    /// of least expected squared error were the draws the posterior's
    /// ([`crate::prediction::PartPrediction::mean`]).
    pub mean: Vec<[f64; 3]>,
    /// Rotation from the part's reference configuration at the medians, `[x, y, z, w]`.
    pub orientation: Vec<[f64; 4]>,
    pub observed: Vec<Option<[f64; 3]>>,
    pub observed_frames: usize,
    pub mse_m2: Option<f64>,
    /// `mse_m2` of `mean` (beyond the contract).
    pub mse_mean_m2: Option<f64>,
    pub coverage_90: Option<f64>,
    pub final_error_m: Option<f64>,
}

/// The JSON of `bom predict`: the posterior predictive of every part from `from_s` on.
#[derive(Debug, Serialize)]
pub struct PredictionJson {
    pub bom_version: String,
    pub model: String,
    pub wrench: String,
    pub from_s: f64,
    pub draws: usize,
    pub stamps: Vec<f64>,
    pub parts: Vec<PredictedPartJson>,
}

/// Build the JSON of a prediction, with the observations of `scene` at its stamps.
pub fn prediction_json(model: &str, wrench: &str, pred: &crate::prediction::Prediction, scene: &crate::prediction::Scene<'_>) -> PredictionJson {
    let v = |x: &nalgebra::Vector3<f64>| [x.x, x.y, x.z];
    let scores = crate::prediction::score(pred, scene);
    PredictionJson {
        bom_version: env!("CARGO_PKG_VERSION").into(),
        model: model.into(),
        wrench: wrench.into(),
        from_s: pred.from,
        draws: pred.draws,
        stamps: pred.stamps.clone(),
        parts: pred
            .parts
            .iter()
            .zip(&scores)
            .map(|(p, s)| PredictedPartJson {
                label: p.label,
                com: p.com.iter().map(v).collect(),
                lower: p.lower.iter().map(v).collect(),
                upper: p.upper.iter().map(v).collect(),
                band_radius_m: p.band_radius_m.clone(),
                mean: p.mean.iter().map(v).collect(),
                orientation: p.rotation.iter().map(|q| [q.i, q.j, q.k, q.w]).collect(),
                observed: pred.stamps.iter().map(|&t| scene.observed_com(p.label, t).map(|(y, _)| v(&y))).collect(),
                observed_frames: s.frames,
                mse_m2: finite(s.mse_m2),
                mse_mean_m2: finite(s.mse_mean_m2),
                coverage_90: finite(s.coverage_90),
                final_error_m: finite(s.final_error_m),
            })
            .collect(),
    }
}
