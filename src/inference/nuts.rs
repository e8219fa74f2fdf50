//! BOM-NUTS: the No-U-Turn sampler (Hoffman and Gelman, *JMLR* 15, 2014; the paper's BOM-NUTS
//! row of Table 1) on the model's log density ([`crate::model::density`]), with the `nuts-rs`
//! crate (PyMC's sampler: step size by dual averaging, a diagonal or diagonal-plus-low-rank mass
//! matrix adapted in warm-up, [`MassMatrix`]). A structure's chains draw `draws` each, then go on
//! in rounds of `extend_draws` while its R-hat, bulk ESS or tail ESS misses its limit, up to `max_draws`
//! (the warm-up's adaptation kept; the diagnostics are those of all the draws).
//!
//! NUTS samples continuous latents only, so the discrete ones — the tree and the joint types —
//! are conditioned on: the structures that hold at least `structure_mass` of the SVI posterior's
//! mass (at most `max_structures`), each weighed by the SVI guide's probability of the structure.
//! The most probable one is sampled; the others too with `all_structures` (off since stop 113:
//! their draws are never reported, below), except one with the density of a structure sampled
//! before it (parts hung from a static part instead of the fixed frame,
//! [`Structure::static_collapsed`]; checked on the density's value and gradient at three
//! points), for which that one's draws stand. The
//! weight is the ELBO weighing: the guide's discrete logits
//! sit at `log p(choice) + conditional ELBO` (natural-gradient fixed point, [`super::svi`]), so
//! structures are compared by SVI's lower bound on their marginal likelihood, not by a bridge
//! sampling estimate from NUTS's own draws. Chains start from draws of SVI's guide, run in
//! parallel, and are checked with the rank-normalised split R-hat, the bulk effective sample size
//! and the tail ESS of the 5% and 95% quantiles (Vehtari et al., *Bayesian Analysis* 16(2), 2021;
//! R-hat and ESS from the `mcmc` crate on rank-normalised draws and on quantile indicators) and
//! the divergent transitions of the sampling draws.
//!
//! The reported posterior: joint-type and parent probabilities are the structures' weights
//! summed; axes, kinodynamics, guide-mean parameters and coordinates of each part come from the
//! draws of the most probable structure (medians and 5% / 95% quantiles of the draws, as the
//! paper reports medians); a part whose most probable type is rigid keeps SVI's axis of its more
//! probable movable type. The axis spreads carry the widening SVI gives its own, by the same
//! factor ([`super::AxisSummary::inflation`]: `n / n_eff` of the part's residuals in kinematic
//! mode, the position inflation in dynamic mode; [`widened`]: every angle from the estimated
//! direction and every distance from the estimated point times its square root), because
//! the model's likelihood counts perception's frame-to-frame correlated errors as independent
//! frames, which a sampler cannot undo; the SVI-against-NUTS comparison then measures the guide
//! alone. (Sampling the likelihood raised to `n_eff / n` instead, a coarsened posterior, gave the
//! same cones on the corpus and direction spreads 3.6 times SVI's on the real tracks (median),
//! where every frame's coordinate loses its observation too: README, "BOM-NUTS", stop 65.) Since
//! stop 113 the kinodynamic intervals carry SVI's allowances too: the draws of each part's
//! kinodynamic block are moved so that their covariance has the likelihood part of its
//! precision divided by SVI's variance inflation of that block ([`Kinodynamics::inflation`]:
//! the physics' deviations correlated in time, the windows' disagreement;
//! [`super::laplace::inflated_draws`]), and each interval is widened by the model discrepancy
//! `dynamics.discrepancy_log_sd` in log space ([`super::summary::with_log_discrepancy`]), as
//! SVI's are ([`crate::model::dynamics::log_normal_summary`]); the medians stay the draws'
//! (to the inflation's linear map about their mean). Before, they were the model's posterior
//! alone: on the `validation` objects 3 of 8 damping and friction intervals held the truth,
//! where SVI's held 8 (README, "Stop 113"). The probabilities are the structures' weights.

use std::collections::HashMap;
use std::time::Instant;

use nuts_rs::rand::rngs::ChaCha8Rng as NutsRng;
use nuts_rs::rand::SeedableRng as _;
use nuts_rs::{Chain, CpuLogpFunc, CpuMath, CpuMathError, DiagNutsSettings, HasDims, LogpError, LowRankNutsSettings, Settings};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};
use statrs::distribution::{ContinuousCDF, Normal};

use super::guide::GuideState;
use super::laplace::inflated_draws;
use super::summary::{axis_from_draws, estimate_from_draws, log_correlation, log_covariance, widened, with_log_discrepancy};
use super::svi::Fitted;
use super::{Kinodynamics, Posterior};
use crate::model::density::{Density, NonCentred, Structure};
use crate::model::likelihood::Evidence;
use crate::model::{dynamics, tree, JointParams, JointType, ModelConfig};

/// NUTS settings (`nuts` section of the config).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct NutsConfig {
    /// Run BOM-NUTS on the last update's evidence after SVI (`bom replay|eval --inference nuts`
    /// sets it): the reported posterior is then NUTS's.
    pub enabled: bool,
    /// Chains per structure (run in parallel, one thread each).
    pub chains: usize,
    /// Warm-up (tuning) draws per chain: 800 since stop 111 (nuts-rs's own
    /// default for its low-rank sampler; 1,000 before, Stan's and PyMC's): a compute setting, run
    /// on the `tune` split's dynamic-mode objects and reported on held-out ones (README, stop
    /// 111); at stop 110, before the rest frames were non-centred, 500 let a `microwave` chain
    /// stick in the deviation scale's funnel.
    pub tune: u64,
    /// Sampling draws per chain before the first diagnosis: 500 since stop 112 (1,000 before). A
    /// compute setting, not a model one: a run whose R-hat, bulk ESS or tail ESS misses its limit
    /// goes on by `extend_draws` (below), so the draws follow what the diagnostics need. Chosen
    /// on the `tune` split's dynamic-mode objects (at stop 111 bulk ESS 0.23-0.40 a draw there, so
    /// 2,000 draws over 4 chains reach 400 on most) and reported on held-out ones (README, stop 112).
    pub draws: u64,
    /// Most sampling draws per chain: while a structure's R-hat, bulk or tail ESS misses its limit, its
    /// chains go on by `extend_draws` more (the warm-up's adaptation kept), up to this many (at
    /// most `draws` when smaller: no extension). 8,000 since stop 93 (4,000 before): a compute limit,
    /// not a model setting — it changes nothing on a run whose diagnostics hold sooner; the `tune`
    /// objects `obj090` and `obj096` and the shipped `hingecabinet` (dynamic mode) reach R-hat
    /// <= 1.01 and bulk ESS >= 400 at 5,000-6,000 draws and missed them at 4,000 (README, stop 93).
    pub max_draws: u64,
    /// Draws a chain per extension round (at least 1). A compute schedule, not a model setting: a
    /// run stops after the first round whose diagnostics hold, so a shorter round stops nearer
    /// the draws the diagnostics need. 250 since stop 110 (before: `draws`, 1,000 on the shipped
    /// config, which on `microwave` drew 1,000 more after R-hat missed by 0.001-0.008).
    pub extend_draws: u64,
    /// The mass matrix adapted in warm-up: `diag` (a variance per coordinate) or `low_rank`
    /// (nuts-rs's diagonal plus low-rank update from the draws' and gradients' covariance:
    /// Seyboldt's covadapt), which follows the correlations between an axis and the joint
    /// coordinates of every frame that a diagonal one cannot.
    pub mass_matrix: MassMatrix,
    /// The mean acceptance probability the step size is adapted to (dual averaging; nuts-rs's
    /// default 0.8, ours 0.95: chosen on the `tune` split in stops 62-63, 0.8 -> 0.9 -> 0.95). Higher means smaller steps: fewer divergences where the posterior narrows
    /// (a noise level near its floor), more leapfrog steps a draw.
    pub target_accept: f64,
    /// Largest tree depth (at most `2^maxdepth` leapfrog steps per draw).
    pub maxdepth: u64,
    /// Dynamic mode: sample the coordinates in windows fully non-centred, `q_t = Psi_t + sigma_d
    /// u_t` ([`NonCentred`], why there); overrides `partial_centring`. Stop 108 (README "BOM-NUTS"):
    /// over three seeds it is faster than the centred sampler on `microwave` and `drawer`, slower
    /// on `slidecabinet`, but 0.3-0.75% of its draws diverge where the centred sampler's do not,
    /// and 1.87% on a held-out lid (over the 1% limit).
    pub non_centred: bool,
    /// Dynamic mode: sample the coordinates in windows partially non-centred, each with its own
    /// centring `lambda_t = 1 - (s_t / sigma_d)^2` from SVI's guide (`s_t` the guide's sd of the
    /// coordinate, `sigma_d` the deviation scale at the guide's mean; [`NonCentred::partial`]):
    /// centred where the observations pin a coordinate more tightly than the physics, non-centred
    /// where the physics does. The default since stop 109 (chosen on `tune` 2-part objects and the
    /// shipped 2-part bags, reported on held-out ones: README "BOM-NUTS", stop 109); false samples
    /// the coordinates as they are (centred, the default of stops 90-108).
    pub partial_centring: bool,
    /// Dynamic mode: precondition each movable part's damping and friction with a shear (the
    /// private `Block`) that follows the curved ridge on which they trade (on since stop 90).
    pub shear: bool,
    /// Scale each chain's coordinates so that nuts-rs's first mass matrix is SVI's guide's
    /// variances instead of the start's inverse gradient (the private `start_scales`, why there).
    /// On since stop 111. A constant change of the sampler's coordinates: the posterior is the
    /// same; the warm-up's first draws are cheaper.
    pub start_scales: bool,
    /// Dynamic mode: narrow each kinodynamic block's preconditioner to the curvature of the
    /// coordinates the sampler actually moves (the private `block_curvature`, why there): SVI's
    /// Laplace covariance is of the centred coordinates, and in (partially) non-centred ones a
    /// part's damping and mass also move every non-centred coordinate's trajectory, so the block
    /// can be far narrower there. New in stop 116 and **off**: a constant change of the sampler's
    /// coordinates (the posterior is the same) that made `adroit_door`'s warm-up start three
    /// times faster but finish no run, while on the `tune` object `obj075` (bimodal in its
    /// drawer's damping) all four chains went to the mode far from the truth, where with it off
    /// three of four stay at the truth (README, "Stop 116").
    pub block_curvature: bool,
    /// Structures sampled: those holding this much of the SVI posterior's mass, at most
    /// `max_structures`.
    pub structure_mass: f64,
    pub max_structures: usize,
    /// Sample every structure of `structure_mass` (true), or only the most probable one (false,
    /// the default since stop 113). The reported posterior's continuous latents are the most
    /// probable structure's draws, and the type and parent probabilities are the structures'
    /// SVI weights, so another structure's draws are never reported: sampling it only checks the
    /// convergence of parameters nothing reports, and it costs the most where a structure holds a
    /// few per cent (the `validation` drawer `obj002`: its third structure, weight 0.043, still
    /// missed R-hat at 4,250 draws a chain after 630 s, where the first passed in about 10 s;
    /// README, "Stop 113"). A compute setting: the reported posterior is the same draw for draw.
    pub all_structures: bool,
    /// Acceptance limits reported as warnings: largest R-hat, least bulk ESS, least tail ESS,
    /// largest share of divergent draws. The tail ESS (of the 5% and 95% quantiles, Vehtari et al.
    /// 2021 §4.3) since stop 112: the reported 90% intervals are those quantiles, and Vehtari et
    /// al. advise both ESS above 100 per chain.
    pub r_hat_max: f64,
    pub ess_bulk_min: f64,
    pub ess_tail_min: f64,
    pub divergence_share_max: f64,
    pub seed: u64,
}

impl Default for NutsConfig {
    fn default() -> Self {
        NutsConfig {
            enabled: false,
            chains: 4,
            tune: 800,
            draws: 500,
            max_draws: 8000,
            extend_draws: 250,
            mass_matrix: MassMatrix::LowRank,
            target_accept: 0.95,
            maxdepth: 10,
            non_centred: false,
            partial_centring: true,
            shear: true,
            start_scales: true,
            block_curvature: false,
            structure_mass: 0.99,
            max_structures: 4,
            all_structures: false,
            r_hat_max: 1.01,
            ess_bulk_min: 400.0,
            ess_tail_min: 400.0,
            divergence_share_max: 0.01,
            seed: 0,
        }
    }
}

/// The mass matrix NUTS adapts in warm-up (`nuts.mass_matrix`).
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq, Eq, Default)]
#[serde(rename_all = "snake_case")]
pub enum MassMatrix {
    /// nuts-rs's `DiagNutsSettings`: one variance per coordinate (from draws and gradients).
    Diag,
    /// nuts-rs's `LowRankNutsSettings`: the diagonal one plus the eigenvectors of the draws'
    /// and gradients' covariance whose eigenvalues pass its cutoff. The default (chosen on the
    /// `tune` split, README "BOM-NUTS").
    #[default]
    LowRank,
}

/// The sampler's diagnostics over all sampled structures (the JSON's `model.sampler`).
#[derive(Debug, Clone, PartialEq)]
pub struct SamplerReport {
    pub chains: usize,
    /// Sampling draws per chain (the most of any structure, extensions included).
    pub draws: u64,
    /// Sampling draws over all chains and structures (structures may stop after different
    /// rounds): the denominator of the divergence check.
    pub total_draws: u64,
    /// Over every reported parameter (axis direction and point, kinodynamics, noise level) of
    /// every sampled structure ([`Self::sampled`]): the largest R-hat, the least bulk ESS and the least tail ESS.
    pub r_hat_max: f64,
    pub ess_bulk_min: f64,
    pub ess_tail_min: f64,
    /// Divergent transitions among the sampling draws, all chains and structures.
    pub divergences: u64,
    /// Structures conditioned on, their weights, and the SVI mass they hold together (which of
    /// them ran: `sampled`).
    pub structures: Vec<(Structure, f64)>,
    /// Per structure: the index of an earlier structure with the same density whose draws stand
    /// for it ([`Structure::static_collapsed`]), none when it was sampled itself or not at all.
    pub same_density_as: Vec<Option<usize>>,
    /// Per structure: whether its chains ran (the first always; the others with
    /// `nuts.all_structures`, unless an earlier structure's draws stand for them).
    pub sampled: Vec<bool>,
    pub structure_mass: f64,
    pub runtime_s: f64,
    /// One line per failed diagnostic (empty when all hold).
    pub warnings: Vec<String>,
}

#[derive(Debug, thiserror::Error)]
#[error("log density is not finite")]
struct NonFinite;

impl LogpError for NonFinite {
    fn is_recoverable(&self) -> bool {
        true
    }
}

/// The model's density as nuts-rs's `CpuLogpFunc`, in coordinates preconditioned by SVI's
/// Laplace fits: each part's kinodynamic block is `xi = m + L z` with `m` and `L L^T` the
/// guide's mean and covariance of it (with `nuts.block_curvature`, narrowed to the sampled
/// coordinates' curvature at the guide's mean: [`block_curvature`]), and the sampler moves `z`
/// (a constant linear map, so no Jacobian term); with `nuts.shear`, `m + L z` is the sheared
/// block of [`Block`], which bends this map along the ridge. Why: damping and friction trade off along a long, narrow ridge (a
/// push moves as far with more damping and less friction); with the diagonal mass matrix nuts-rs
/// adapts, the step size shrank to the ridge's width and the drawer bag's damping had a bulk ESS
/// of 4 from 400 draws (step size 0.13-0.18), the other parameters 200-400. A dense mass matrix
/// on those few coordinates is the linear map; the ridge's curvature is the shear's.
///
/// The kinodynamic blocks are those of the [`NonCentred`] coordinates `y`; the sampler's `z` maps
/// to `y` by the blocks and `y` to the model's `x` by [`NonCentred::to_model`].
struct Logp<'a> {
    density: NonCentred<'a>,
    /// The preconditioner of each part's kinodynamic block.
    blocks: Vec<Block>,
    /// The sampler's coordinate is the blocks' divided by this, elementwise ([`start_scales`]).
    scale: Vec<f64>,
}

/// The preconditioner of one kinodynamic block at offset `offset` of the coordinates: the sampler's
/// `z` gives the sheared block `m + L z` (`m` and `L L^T` the guide's mean and covariance of the
/// sheared block, to first order), and the model's block `xi` is that block unsheared.
///
/// The shear follows the ridge on which damping trades for Coulomb friction: a push's
/// resisting force is `b v + mu` (revolute: torques), so along the ridge the damping falls
/// *linearly in the friction `mu`*, while both are sampled as standardised logarithms. When the
/// friction is weakly determined its log ranges over a factor of 5-10, and in `(xi_b, xi_mu)` the
/// ridge is an exponential curve that no linear preconditioner or adapted mass matrix follows
/// (`drawer`: lag-1 autocorrelation 0.8-0.9 of both, bulk ESS 2.5% of the draws; the damping's
/// spread at a given friction a fifth of its marginal one). With
/// `phi(xi_mu) = (exp(s (xi_mu - m_mu)) - 1) / s = (mu / mu_m - 1) / s` (`s` the friction's log-sd,
/// `mu_m` the friction at the guide's mean), the sampler moves `xi_b' = xi_b - beta phi(xi_mu)`:
/// `phi` is linear in `mu` and equals `xi_mu - m_mu` to first order at the mean, so `beta`, the
/// guide's regression slope of `xi_b` on `xi_mu`, straightens the ridge through the mean and
/// along it. The map is triangular with a unit diagonal, so its Jacobian is 1; it is a change of
/// the sampler's coordinates, not of the model (Betancourt, "A conceptual introduction to
/// Hamiltonian Monte Carlo", arXiv:1701.02434, 2017, on reparameterisation).
#[derive(Debug, Clone)]
struct Block {
    offset: usize,
    m: DVector<f64>,
    l: DMatrix<f64>,
    /// `(beta, s, m_mu)` of the damping-friction shear (damping at index 0 of the block, friction
    /// at 1), none when the block has no such pair.
    shear: Option<(f64, f64, f64)>,
}

impl Block {
    /// `phi(xi_mu)` and its derivative.
    fn phi(&self, xi_mu: f64) -> (f64, f64) {
        let Some((_, s, m_mu)) = self.shear else { return (0.0, 0.0) };
        let e = (s * (xi_mu - m_mu)).exp();
        ((e - 1.0) / s, e)
    }

    /// The model's block of the sheared block `v` (in place).
    fn unshear(&self, v: &mut [f64]) {
        if let Some((beta, _, _)) = self.shear {
            v[0] += beta * self.phi(v[1]).0;
        }
    }

    /// The sheared block of the model's block `v` (in place).
    fn shear(&self, v: &mut [f64]) {
        if let Some((beta, _, _)) = self.shear {
            v[0] -= beta * self.phi(v[1]).0;
        }
    }

    /// The gradient over the sheared block from the model's gradient `g` at the model's block `v`
    /// (in place): `d/dxi_mu` gains `g_b beta phi'(xi_mu)`.
    fn pull_back(&self, v: &[f64], g: &mut [f64]) {
        if let Some((beta, _, _)) = self.shear {
            g[1] += g[0] * beta * self.phi(v[1]).1;
        }
    }
}

/// Model coordinates `x` of sampler coordinates `z` under the preconditioner `blocks` and the
/// scales `scale` of [`Logp`].
fn to_model(blocks: &[Block], scale: &[f64], z: &[f64]) -> Vec<f64> {
    let mut x: Vec<f64> = z.iter().zip(scale).map(|(v, s)| v * s).collect();
    // The blocks do not overlap: each reads its own slice before writing it.
    for b in blocks {
        let (o, d) = (b.offset, b.m.len());
        let mut v = &b.m + &b.l * DVector::from_column_slice(&x[o..o + d]);
        b.unshear(v.as_mut_slice());
        x[o..o + d].copy_from_slice(v.as_slice());
    }
    x
}

impl Logp<'_> {
    /// Sampler coordinates of model coordinates `x`.
    fn to_sampler(&self, x: &[f64]) -> Vec<f64> {
        let mut z = x.to_vec();
        for b in &self.blocks {
            let (o, d) = (b.offset, b.m.len());
            let mut v = DVector::from_column_slice(&x[o..o + d]);
            b.shear(v.as_mut_slice());
            let r = v - &b.m;
            let v = b.l.solve_lower_triangular(&r).unwrap_or(r);
            z[o..o + d].copy_from_slice(v.as_slice());
        }
        z.iter().zip(&self.scale).map(|(v, s)| v / s).collect()
    }
}

impl HasDims for Logp<'_> {
    fn dim_sizes(&self) -> HashMap<String, u64> {
        [("unconstrained_parameter".to_string(), self.density.density().dim() as u64)].into_iter().collect()
    }
}

impl CpuLogpFunc for Logp<'_> {
    type LogpError = NonFinite;
    type FlowParameters = ();
    type ExpandedVector = Vec<f64>;

    fn dim(&self) -> usize {
        self.density.density().dim()
    }

    fn logp(&mut self, position: &[f64], gradient: &mut [f64]) -> Result<f64, NonFinite> {
        let x = to_model(&self.blocks, &self.scale, position);
        let l = self.density.log_density(&x, gradient);
        for b in &self.blocks {
            let (o, d) = (b.offset, b.m.len());
            b.pull_back(&x[o..o + d], &mut gradient[o..o + d]);
            let g = b.l.transpose() * DVector::from_column_slice(&gradient[o..o + d]);
            gradient[o..o + d].copy_from_slice(g.as_slice());
        }
        for (g, s) in gradient.iter_mut().zip(&self.scale) {
            *g *= s;
        }
        if l.is_finite() && gradient.iter().all(|g| g.is_finite()) {
            Ok(l)
        } else {
            Err(NonFinite)
        }
    }

    fn expand_vector<R: nuts_rs::rand::Rng + ?Sized>(&mut self, _rng: &mut R, array: &[f64]) -> Result<Vec<f64>, CpuMathError> {
        Ok(array.to_vec())
    }
}

/// The structures holding `mass` of the mean-field posterior `fitted` (at most `max`), with
/// their renormalised weights, most probable first. Each part's (parent, type) choices below
/// probability 1e-4 are left out; combinations that are not trees are skipped.
pub fn structures(fitted: &Posterior, mass: f64, max: usize) -> (Vec<(Structure, f64)>, f64) {
    let n = fitted.joints.len();
    let options: Vec<Vec<(usize, JointType, f64)>> = fitted
        .joints
        .iter()
        .enumerate()
        .map(|(i, j)| {
            let mut o: Vec<(usize, JointType, f64)> = Vec::new();
            // `parent_probs` lists the fixed frame and every other part, in evidence order.
            for (node, &(_, pp)) in (0..=n).filter(|&m| m != i + 1).zip(&j.parent_probs) {
                for t in JointType::ALL {
                    let p = pp * j.type_probs[t.index()];
                    if p >= 1e-4 {
                        o.push((node, t, p));
                    }
                }
            }
            if n == 1 || o.is_empty() {
                // One part: its parent is the fixed frame.
                o = JointType::ALL.iter().map(|&t| (0, t, j.type_probs[t.index()])).filter(|x| x.2 >= 1e-4).collect();
            }
            o.sort_by(|a, b| b.2.total_cmp(&a.2));
            o
        })
        .collect();
    // Best-first over the product, keeping at most 4096 partial combinations.
    let mut partial: Vec<(Vec<usize>, Vec<JointType>, f64)> = vec![(vec![], vec![], 1.0)];
    for opts in &options {
        let mut next = Vec::new();
        for (p, t, w) in &partial {
            for &(node, jt, pr) in opts {
                let (mut p2, mut t2) = (p.clone(), t.clone());
                p2.push(node);
                t2.push(jt);
                next.push((p2, t2, w * pr));
            }
        }
        next.sort_by(|a, b| b.2.total_cmp(&a.2));
        next.truncate(4096);
        partial = next;
    }
    let valid: Vec<(Structure, f64)> = partial.into_iter().filter(|(p, _, _)| tree::is_tree(p)).map(|(parent, types, w)| (Structure { parent, types }, w)).collect();
    let total: f64 = valid.iter().map(|s| s.1).sum();
    let mut out = Vec::new();
    let mut held = 0.0;
    for (s, w) in valid {
        if out.len() >= max.max(1) || (held >= mass && !out.is_empty()) {
            break;
        }
        held += w;
        out.push((s, w));
    }
    let kept: f64 = out.iter().map(|s| s.1).sum();
    for s in &mut out {
        s.1 /= kept;
    }
    (out, if total > 0.0 { held / total } else { 0.0 })
}

/// Draws of one structure's chains, `draws[chain][k]` (model coordinates), their divergent
/// transitions, and the diagnostics of all of them ([`diagnostics`]: largest R-hat, least ESS).
struct StructureDraws {
    draws: Vec<Vec<Vec<f64>>>,
    divergences: u64,
    convergence: Convergence,
}

/// A start for a chain: a draw of SVI's guide for the structure's blocks (guide means plus its
/// sds times standard normals).
pub fn start_from_guide(density: &Density<'_>, guide: &GuideState, rng: &mut ChaCha8Rng) -> Vec<f64> {
    guide_point(density, guide, || StandardNormal.sample(rng))
}

/// The guide's means plus its sds times `z()` (standard normals: a draw; zeros: the mean), in
/// the model's coordinates of `density`.
fn guide_point(density: &Density<'_>, guide: &GuideState, mut z: impl FnMut() -> f64) -> Vec<f64> {
    let ev = density.evidence();
    let frames = ev.len();
    let mut x = vec![0.0; density.dim()];
    let theta = &guide.theta;
    for (i, s) in density.slots().iter().enumerate() {
        let b = guide.layout.blocks[i][s.joint.index()];
        for j in 0..s.np {
            x[s.xi + j] = theta[b.mu + j] + theta[b.log_s + j].exp() * z();
        }
        if let (Some(o), Some((qm, qs))) = (s.q, b.q) {
            for t in 0..frames {
                x[o + t] = theta[qm + t] + theta[qs + t].exp() * z();
            }
        }
        if let (Some(v), Some(vi)) = (s.vel, b.vel) {
            x[v] = theta[vi] + theta[vi + 1].exp() * z();
        }
        // (A guide fitted with other effects has another kinodynamic block: its start stays 0.)
        if let (Some((o, d)), Some(kd)) = (s.kd, b.kd.filter(|kd| kd.dim == s.kd.map_or(0, |k| k.1))) {
            let mean = kd.mean(theta);
            let l = kd.factor(theta);
            let e = nalgebra::DVector::from_iterator(d, (0..d).map(|_| z()));
            let v = mean + l * e;
            x[o..o + d].copy_from_slice(v.as_slice());
        }
    }
    x
}

/// The preconditioner of [`Logp`] from the guide's kinodynamic blocks (identity where the guide
/// has none of the structure's dimension, or its factor is not finite and lower triangular), each
/// with the damping-friction shear of [`Block`] for a movable joint when `shear` is set: `beta`
/// is the guide's regression slope `Sigma_bm / Sigma_mm`, and `L` the Cholesky factor of the
/// covariance the shear's linear part gives, `A Sigma A^T` with `A = I - beta e_b e_mu^T` (the
/// sheared damping uncorrelated with the friction to first order).
fn preconditioner(density: &Density<'_>, guide: &GuideState, model: &ModelConfig, shear: bool) -> Vec<Block> {
    let mut out = Vec::new();
    for (i, s) in density.slots().iter().enumerate() {
        let b = guide.layout.blocks[i][s.joint.index()];
        if let (Some((o, d)), Some(kd)) = (s.kd, b.kd) {
            let (m, l) = (kd.mean(&guide.theta), kd.factor(&guide.theta));
            if kd.dim != d || !m.iter().chain(l.iter()).all(|v| v.is_finite()) || !(0..d).all(|k| l[(k, k)] > 0.0) {
                continue;
            }
            let sheared = (shear && s.joint.movable() && d >= 2)
                .then(|| {
                    let sigma = &l * l.transpose();
                    let beta = sigma[(0, 1)] / sigma[(1, 1)];
                    let mut a = DMatrix::<f64>::identity(d, d);
                    a[(0, 1)] = -beta;
                    let chol = nalgebra::Cholesky::new(&a * sigma * a.transpose())?;
                    let s_mu = model.dynamics.friction_log_sd;
                    (beta.is_finite() && s_mu > 0.0).then(|| (chol.l(), (beta, s_mu, m[1])))
                })
                .flatten();
            let (l, shear) = match sheared {
                Some((l, shear)) => (l, Some(shear)),
                None => (l, None),
            };
            out.push(Block { offset: o, m, l, shear });
        }
    }
    out
}

/// Each kinodynamic block of `logp` narrowed to the curvature of the sampler's own coordinates
/// at `x` (model coordinates; [`run_chains`] gives the guide's mean), in place: with `H` the
/// block's Hessian of `-log p` in its preconditioned coordinates `z` (central differences of the
/// gradient, `2 d` gradients for a block of `d`), eigenvalues below 1 raised to 1, the block's
/// covariance `L L^T` becomes `L H^-1 L^T`. Why: `L L^T` is SVI's Laplace covariance of the
/// block given the *centred* coordinates; in the (partially) non-centred coordinates the sampler
/// moves, a part's damping and mass also move the trajectory `Psi` of every non-centred
/// coordinate (`q = Psi + sigma_d u`), so the observations pin them there. On `adroit_door`'s
/// latch, along its damping and mass, the block's Hessian at the guide's mean had an eigenvalue
/// of 2.95e4 (a conditional sd 1/170 of the guide's); the warm-up's step size fell to
/// 0.002-0.013 and 200 warm-up draws took 570-620 s (README, "Stop 116"). Narrow only: a direction flatter than the guide keeps the guide's width,
/// and the adapted mass matrix widens it where the draws need. A block whose Hessian is not
/// finite, or whose new covariance has no Cholesky factor, is left as it was. A constant linear
/// map of the sampler's coordinates: no Jacobian, the posterior is the same.
fn block_curvature(logp: &mut Logp<'_>, x: &[f64]) {
    let hessians = block_hessians(logp, x);
    for (b, hs) in logp.blocks.iter_mut().zip(hessians) {
        let Some(hs) = hs else { continue };
        let eig = hs.symmetric_eigen();
        if eig.eigenvalues.iter().all(|&v| v <= 1.0) {
            continue;
        }
        let inv = DMatrix::from_diagonal(&eig.eigenvalues.map(|v| 1.0 / v.max(1.0)));
        let cov = &b.l * &eig.eigenvectors * inv * eig.eigenvectors.transpose() * b.l.transpose();
        if let Some(ch) = nalgebra::Cholesky::new((&cov + cov.transpose()) * 0.5) {
            b.l = ch.l();
        }
    }
}

/// The Hessian of `-log p` over each of `logp`'s kinodynamic blocks in its sampler coordinates
/// (the blocks' `z` divided by `logp.scale`; [`run_chains`] narrows with all scales 1) at model
/// coordinates `x`, by central differences of the gradient, all at the same point; none for a
/// block where the density or the Hessian is not finite. `2 d` gradients a block of `d`.
fn block_hessians(logp: &mut Logp<'_>, x: &[f64]) -> Vec<Option<DMatrix<f64>>> {
    let z0 = logp.to_sampler(&logp.density.from_model(x));
    let n = z0.len();
    let mut g = vec![0.0; n];
    if logp.logp(&z0, &mut g).is_err() {
        return vec![None; logp.blocks.len()];
    }
    // A thousandth of the guide's sd: small against the narrowest width met (1/170 of it), large
    // against the gradient's rounding.
    let h = 1e-3;
    let spans: Vec<(usize, usize)> = logp.blocks.iter().map(|b| (b.offset, b.m.len())).collect();
    spans
        .into_iter()
        .map(|(o, d)| {
            let mut hm = DMatrix::<f64>::zeros(d, d);
            let (mut ga, mut gb) = (vec![0.0; n], vec![0.0; n]);
            for k in 0..d {
                let (mut a, mut b) = (z0.clone(), z0.clone());
                a[o + k] += h;
                b[o + k] -= h;
                logp.logp(&a, &mut ga).ok()?;
                logp.logp(&b, &mut gb).ok()?;
                for r in 0..d {
                    hm[(r, k)] = -(ga[o + r] - gb[o + r]) / (2.0 * h);
                }
            }
            let hs = (&hm + hm.transpose()) * 0.5;
            hs.iter().all(|v| v.is_finite()).then_some(hs)
        })
        .collect()
}

/// The guide's sd of each of `logp`'s coordinates before its scales (the kinodynamic blocks'
/// preconditioned coordinates are 1 by construction; other coordinates the guide has no sd for
/// stay 1): each kinematic parameter's, velocity's and centred coordinate's own, and for a
/// (partially) non-centred coordinate `y = lambda Psi + (q - Psi) / sigma_d^(1 - lambda)`, about
/// `min(s_q, sigma_d) / sigma_d^(1 - lambda)` (`s_q` the guide's sd of the coordinate, `sigma_d`
/// the deviation scale at the guide's mean: given `Psi`, `q` varies by at most about `sigma_d`).
fn guide_sds(logp: &Logp<'_>, guide: &GuideState, model: &ModelConfig) -> Vec<f64> {
    let density = logp.density.density();
    let theta = &guide.theta;
    let mut sd = vec![1.0; density.dim()];
    for (i, s) in density.slots().iter().enumerate() {
        let b = guide.layout.blocks[i][s.joint.index()];
        for j in 0..s.np {
            sd[s.xi + j] = theta[b.log_s + j].exp();
        }
        if let (Some(o), Some((_, qs))) = (s.q, b.q) {
            for t in 0..density.evidence().len() {
                sd[o + t] = theta[qs + t].exp();
            }
        }
        if let (Some(v), Some(vi)) = (s.vel, b.vel) {
            sd[v] = theta[vi + 1].exp();
        }
    }
    let deviation: Vec<f64> = (0..density.slots().len()).map(|i| guide_deviation(density, guide, model, i).unwrap_or(f64::NAN)).collect();
    for (i, k, lambda) in logp.density.mapped() {
        let dev = deviation[i];
        sd[k] = if dev.is_finite() && dev > 0.0 { sd[k].min(dev) / dev.powf(1.0 - lambda) } else { 1.0 };
    }
    sd.iter().map(|&v| if v.is_finite() && v > 0.0 { v } else { 1.0 }).collect()
}

/// The scales of [`Logp`] that make nuts-rs's first mass matrix the guide's variances: nuts-rs
/// starts its diagonal from the start's gradient, variance `1 / |g_k|` (its `update_from_grad`),
/// which in coordinates whose posterior sd is `s_k` is `s_k / |e_k|` (`e_k` the start's
/// standardised distance from the mode) against the `s_k^2` it should be — a thousand times too
/// wide for a coordinate in metres with a sd of a millimetre, so that the first step sizes were
/// tiny and each chain's first 9 draws ran to the depth limit (1,023 steps; `microwave`, about a
/// third of the warm-up's steps, stop 110). With `z_k = y_k / d_k` and `d_k = s_k^2 |g_k|` the
/// first variance is `1 / (d_k |g_k|)` in `z`, that is `s_k^2` in `y`. `s_k |g_k|` is clamped to
/// `[0.1, 10]` (a coordinate at its mode has no gradient). A constant diagonal map: no Jacobian,
/// and the adapted mass matrix takes over from the first update as before.
fn start_scales(sd: &[f64], gradient: &[f64]) -> Vec<f64> {
    sd.iter().zip(gradient).map(|(&s, &g)| s * (s * g.abs()).clamp(0.1, 10.0)).collect()
}

/// The coordinates the sampler moves: partially non-centred by `centring` (from
/// [`centring_from_guide`]; [`run_chains`] gives none when `nuts.non_centred` is set, which
/// overrides `nuts.partial_centring`), else as `nuts.non_centred` says.
fn coordinates<'d>(density: Density<'d>, centring: Option<&[Vec<f64>]>, non_centred: bool) -> NonCentred<'d> {
    match centring {
        Some(lambda) => NonCentred::partial(density, |i, t| lambda[i].get(t).copied()),
        None => NonCentred::new(density, non_centred),
    }
}

/// Each part's centring of its window coordinates for [`NonCentred::partial`], `lambda[i][t] =
/// 1 - (s_t / sigma_d)^2` clamped to `[0, 1]`: `s_t` the guide's sd of part `i`'s coordinate at
/// grid frame `t` (mean-field: its conditional posterior sd), `sigma_d` the deviation scale at the
/// guide's kinodynamic mean. Empty for a part without both (0, non-centred, by default).
fn centring_from_guide(density: &Density<'_>, guide: &GuideState, model: &ModelConfig) -> Vec<Vec<f64>> {
    let ev = density.evidence();
    let theta = &guide.theta;
    density
        .slots()
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let b = guide.layout.blocks[i][s.joint.index()];
            let (Some((_, qs)), Some(sd)) = (b.q, guide_deviation(density, guide, model, i)) else { return Vec::new() };
            (0..ev.len()).map(|t| (1.0 - (theta[qs + t].exp() / sd).powi(2)).clamp(0.0, 1.0)).collect()
        })
        .collect()
}

/// Part `i`'s deviation scale `sigma_d` \[m\] at the guide's kinodynamic mean; none when the
/// part has no kinodynamic block or the guide's is of another dimension.
fn guide_deviation(density: &Density<'_>, guide: &GuideState, model: &ModelConfig, i: usize) -> Option<f64> {
    let s = &density.slots()[i];
    let (_, d) = s.kd?;
    let kd = guide.layout.blocks[i][s.joint.index()].kd.filter(|kd| kd.dim == d)?;
    Some(dynamics::decode::<f64>(s.joint, kd.mean(&guide.theta).as_slice(), &density.evidence().effects[i], &model.dynamics).deviation)
}

/// What one chain sends back after a round: its new sampling draws (model coordinates) and the
/// divergent transitions among them.
struct Round {
    draws: Vec<Vec<f64>>,
    divergences: u64,
}

/// The diagnostics of a structure's draws so far, `draws[chain][k]` (model coordinates): largest
/// R-hat and least bulk and tail ESS over the reported scalars.
type Diagnose<'a> = dyn Fn(&[Vec<Vec<f64>>]) -> Convergence + 'a;

/// One structure's sampling job: the evidence and model it is conditioned on, the structure, SVI's
/// guide (chain starts and kinodynamic preconditioning), the settings and the seed.
struct Job<'a> {
    ev: &'a Evidence,
    model: &'a ModelConfig,
    structure: &'a Structure,
    guide: &'a GuideState,
    cfg: &'a NutsConfig,
    seed: u64,
}

/// Run the chains of one structure: warm-up and `cfg.draws` sampling draws each, then
/// `cfg.extend_draws` more while `diagnose` (given every chain's draws so far) misses the R-hat or
/// ESS limit, up to `cfg.max_draws`.
fn sample_structure(job: &Job<'_>, diagnose: &Diagnose<'_>) -> Result<StructureDraws, String> {
    let cfg = job.cfg;
    match cfg.mass_matrix {
        MassMatrix::Diag => {
            let mut settings = DiagNutsSettings { num_tune: cfg.tune, num_draws: cfg.draws, maxdepth: cfg.maxdepth, ..Default::default() };
            settings.adapt_options.step_size_settings.target_accept = cfg.target_accept;
            run_chains(settings, job, diagnose)
        }
        MassMatrix::LowRank => {
            let mut settings = LowRankNutsSettings { num_tune: cfg.tune, num_draws: cfg.draws, maxdepth: cfg.maxdepth, ..Default::default() };
            settings.adapt_options.step_size_settings.target_accept = cfg.target_accept;
            run_chains(settings, job, diagnose)
        }
    }
}

/// [`sample_structure`] with one kind of sampler settings. Each chain lives in its own thread
/// (nuts-rs chains are not `Send`) and draws a round on each command it receives.
fn run_chains<S: Settings>(settings: S, job: &Job<'_>, diagnose: &Diagnose<'_>) -> Result<StructureDraws, String> {
    use std::sync::mpsc;
    let Job { ev, model, structure, guide, cfg, seed } = *job;
    let chains = cfg.chains.max(1);
    let round = cfg.draws.max(1);
    let extend = cfg.extend_draws.max(1);
    let most = cfg.max_draws.max(round);
    // One preconditioner and one centring for all chains: they depend on the guide only.
    let blocks = preconditioner(&Density::new(ev, model, structure.clone()), guide, model, cfg.shear);
    // `non_centred` overrides `partial_centring`.
    let centring = (cfg.partial_centring && !cfg.non_centred).then(|| centring_from_guide(&Density::new(ev, model, structure.clone()), guide, model));
    let centring = centring.as_deref();
    let blocks = if cfg.block_curvature && !blocks.is_empty() {
        let density = Density::new(ev, model, structure.clone());
        let mean = guide_point(&density, guide, || 0.0);
        let scale = vec![1.0; density.dim()];
        let mut logp = Logp { blocks, density: coordinates(density, centring, cfg.non_centred), scale };
        block_curvature(&mut logp, &mean);
        logp.blocks
    } else {
        blocks
    };
    let blocks = blocks.as_slice();
    std::thread::scope(|scope| {
        let (tx, rx) = mpsc::channel::<(usize, Result<Round, String>)>();
        let mut commands = Vec::with_capacity(chains);
        for c in 0..chains {
            let (ctx, crx) = mpsc::channel::<u64>();
            commands.push(ctx);
            let tx = tx.clone();
            let on_panic = tx.clone();
            // A chain that panics still answers its round (an error), so that the others and the
            // caller never wait for it.
            scope.spawn(move || {
                let ran = std::panic::catch_unwind(std::panic::AssertUnwindSafe(move || {
                    let started = Instant::now();
                    let density = Density::new(ev, model, structure.clone());
                    let mut rng = ChaCha8Rng::seed_from_u64(seed.wrapping_add(1000 * c as u64));
                    let x0 = start_from_guide(&density, guide, &mut rng);
                    let scale = vec![1.0; density.dim()];
                    let mut logp = Logp { blocks: blocks.to_vec(), density: coordinates(density, centring, cfg.non_centred), scale };
                    if c == 0 && centring.is_some() {
                        let (low, all) = logp.density.centring_summary();
                        tracing::debug!("NUTS: {low} of {all} window and rest coordinates mostly non-centred (lambda < 0.5)");
                    }
                    let mut z0 = logp.to_sampler(&logp.density.from_model(&x0));
                    if cfg.start_scales {
                        let sd = guide_sds(&logp, guide, model);
                        let mut g0 = vec![0.0; z0.len()];
                        // Unscaled where the density is not finite at the start (the chain's own
                        // start check reports it).
                        if logp.logp(&z0, &mut g0).is_ok() {
                            logp.scale = start_scales(&sd, &g0);
                            z0 = z0.iter().zip(&logp.scale).map(|(v, s)| v / s).collect();
                        }
                    }
                    let scale = logp.scale.clone();
                    // The chain owns `logp`; draws are mapped back to the model by a view of its own.
                    let map = coordinates(Density::new(ev, model, structure.clone()), centring, cfg.non_centred);
                    let math = CpuMath::new(logp);
                    let mut nrng = NutsRng::seed_from_u64(seed.wrapping_add(7919 * c as u64 + 1));
                    let mut chain = match settings.new_chain(c as u64, math, &mut nrng).map_err(|e| e.to_string()).and_then(|mut ch| {
                        ch.set_position(&z0).map_err(|e| format!("chain {c}: start: {e}"))?;
                        Ok(ch)
                    }) {
                        Ok(ch) => ch,
                        Err(e) => {
                            let _ = tx.send((c, Err(e)));
                            return;
                        }
                    };
                    let mut n = settings.hint_num_tune() as u64 + round;
                    let (mut drawn, mut divergent, mut all_steps, mut step_size) = (0u64, 0u64, 0u64, f64::NAN);
                    // Warm-up's own cost, for the debug line at its end (where dynamic-mode time goes).
                    let (mut tune_steps, mut tune_deep, mut tuned) = (0u64, 0u64, 0u64);
                    let mut tune_tenths: Vec<(u64, u64)> = vec![(0, 0); 10];
                    loop {
                        let mut out = Vec::with_capacity(round as usize);
                        let mut divergences = 0u64;
                        for _ in 0..n {
                            match chain.draw() {
                                Ok((draw, info)) => {
                                    if info.tuning {
                                        tuned += 1;
                                        tune_steps += info.num_steps;
                                        let deep = (info.num_steps + 1 >= 1u64 << cfg.maxdepth.min(62)) as u64;
                                        tune_deep += deep;
                                        let k = ((tuned - 1) * 10 / cfg.tune.max(1)).min(9) as usize;
                                        tune_tenths[k].0 += info.num_steps;
                                        tune_tenths[k].1 += deep;
                                        // Progress of a long warm-up (a 4-part object's takes minutes).
                                        if tuned == 1 || tuned == 10 || tuned % 100 == 0 {
                                            tracing::debug!(
                                                "NUTS chain {c}: warm-up {tuned} of {} draws, {:.1} s, {:.1} leapfrog steps per draw, {tune_deep} at the depth limit, step size {:.3}",
                                                cfg.tune,
                                                started.elapsed().as_secs_f64(),
                                                tune_steps as f64 / tuned as f64,
                                                info.step_size
                                            );
                                        }
                                    } else if drawn == 0 && out.is_empty() {
                                        tracing::debug!(
                                            "NUTS chain {c}: warm-up {tuned} draws in {:.1} s, {:.1} leapfrog steps per draw, {tune_deep} at the depth limit, step size {:.3}",
                                            started.elapsed().as_secs_f64(),
                                            tune_steps as f64 / tuned.max(1) as f64,
                                            info.step_size
                                        );
                                        tracing::debug!("NUTS chain {c}: warm-up tenths (leapfrog steps, draws at the depth limit): {tune_tenths:?}");
                                    }
                                    if !info.tuning {
                                        divergences += info.diverging as u64;
                                        all_steps += info.num_steps;
                                        step_size = info.step_size;
                                        out.push(map.to_model(&to_model(blocks, &scale, &draw)));
                                    }
                                }
                                Err(e) => {
                                    let _ = tx.send((c, Err(format!("chain {c}: {e}"))));
                                    return;
                                }
                            }
                        }
                        drawn += out.len() as u64;
                        divergent += divergences;
                        tracing::debug!(
                            "NUTS chain {c}: {:.1} s, {drawn} draws, {:.1} leapfrog steps per draw, step size {step_size:.3}, {divergent} divergent",
                            started.elapsed().as_secs_f64(),
                            all_steps as f64 / drawn.max(1) as f64
                        );
                        if tx.send((c, Ok(Round { draws: out, divergences }))).is_err() {
                            return;
                        }
                        // The next round's length, or the end (0, or the sender dropped).
                        n = crx.recv().unwrap_or(0);
                        if n == 0 {
                            return;
                        }
                    }
                }));
                if ran.is_err() {
                    let _ = on_panic.send((c, Err(format!("chain {c} panicked"))));
                }
            });
        }
        drop(tx);
        let mut draws: Vec<Vec<Vec<f64>>> = vec![Vec::new(); chains];
        let mut divergences = 0;
        loop {
            for _ in 0..chains {
                let (c, r) = rx.recv().map_err(|_| "NUTS: a chain ended without its draws".to_string())?;
                let r = r?;
                draws[c].extend(r.draws);
                divergences += r.divergences;
            }
            let taken = draws.iter().map(|d| d.len() as u64).min().unwrap_or(0);
            let convergence = diagnose(&draws);
            let more = taken + extend <= most && !convergence.holds(cfg);
            for ctx in &commands {
                let _ = ctx.send(if more { extend } else { 0 });
            }
            if !more {
                return Ok(StructureDraws { draws, divergences, convergence });
            }
            let Convergence { r_hat, ess_bulk, ess_tail } = convergence;
            tracing::debug!("NUTS: diagnostics missed after {taken} draws a chain (R-hat {r_hat:.3}, bulk ESS {ess_bulk:.0}, tail ESS {ess_tail:.0}); {extend} more");
        }
    })
}

/// The reported scalars of a draw: per part, the noise level; per movable part, the axis
/// direction (flipped onto `reference[i]`'s side) and, revolute, the axis point closest to the
/// centre of mass; in dynamic mode damping, friction, mass and the physics prior's deviation scale
/// in SI units. Names say which.
fn reported(density: &Density<'_>, x: &[f64], reference: &[Option<nalgebra::Vector3<f64>>], model: &ModelConfig) -> Vec<(String, f64)> {
    let ev = density.evidence();
    let mut out = Vec::new();
    for (i, s) in density.slots().iter().enumerate() {
        let label = ev.parts[i].label;
        let p = density.params(x, i);
        out.push((format!("part {label} noise_m"), p.noise));
        if s.joint.movable() {
            let r = reference[i].unwrap_or(p.direction);
            let d = if p.direction.dot(&r) < 0.0 { -p.direction } else { p.direction };
            for (k, c) in ["x", "y", "z"].iter().enumerate() {
                out.push((format!("part {label} axis.{c}"), d[k]));
            }
            if s.joint == JointType::Revolute {
                let pt = p.point + d * (p.com - p.point).dot(&d);
                for (k, c) in ["x", "y", "z"].iter().enumerate() {
                    out.push((format!("part {label} point.{c}"), pt[k]));
                }
            }
        }
        if let Some((o, _)) = s.kd {
            let kp = dynamics::decode::<f64>(s.joint, &x[o..], &ev.effects[i], &model.dynamics);
            out.push((format!("part {label} damping"), kp.damping));
            out.push((format!("part {label} friction"), kp.friction));
            out.push((format!("part {label} mass"), kp.mass));
            out.push((format!("part {label} deviation_m"), kp.deviation));
        }
    }
    out
}

/// Convergence diagnostics of one scalar's draws or, combined ([`Convergence::worst`]), of
/// several: R-hat, bulk ESS and tail ESS, in draws (Vehtari et al. 2021, §4).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Convergence {
    /// Rank-normalised split R-hat, the larger of bulk and folded (NaN when undefined).
    pub r_hat: f64,
    /// Bulk ESS: split ESS of the rank-normalised draws.
    pub ess_bulk: f64,
    /// Tail ESS: the lesser split ESS of the indicators of the 5% and 95% quantiles (§4.3), the
    /// quantiles that bound the reported 90% intervals.
    pub ess_tail: f64,
}

impl Convergence {
    /// Nothing seen yet: the identity of [`Convergence::worst`].
    const NONE: Convergence = Convergence { r_hat: 1.0, ess_bulk: f64::INFINITY, ess_tail: f64::INFINITY };

    /// The worse of two: the larger R-hat (NaN when either is), the lesser ESS.
    pub fn worst(self, other: Convergence) -> Convergence {
        Convergence {
            r_hat: if self.r_hat.is_nan() || other.r_hat.is_nan() { f64::NAN } else { self.r_hat.max(other.r_hat) },
            ess_bulk: self.ess_bulk.min(other.ess_bulk),
            ess_tail: self.ess_tail.min(other.ess_tail),
        }
    }

    /// Whether all three meet `cfg`'s limits (NaN never does).
    fn holds(&self, cfg: &NutsConfig) -> bool {
        r_hat_ok(self.r_hat, cfg) && ess_ok(self.ess_bulk, cfg.ess_bulk_min) && ess_ok(self.ess_tail, cfg.ess_tail_min)
    }
}

/// Rank-normalised split R-hat (the larger of bulk and folded), bulk ESS and tail ESS of one
/// scalar's draws, `chains[c][k]` (Vehtari et al. 2021, §4).
pub fn rank_diagnostics(chains: &[Vec<f64>]) -> Convergence {
    let z = rank_normalise(chains);
    // The pooled median, and the 5% and 95% quantiles as the reported intervals take them.
    let pooled = estimate_from_draws(&chains.concat());
    let med = pooled.median;
    let folded: Vec<Vec<f64>> = chains.iter().map(|c| c.iter().map(|x| (x - med).abs()).collect()).collect();
    let zf = rank_normalise(&folded);
    let rhat = |c: &Vec<Vec<f64>>| mcmc::rhat::split_potential_scale_reduction_factor(c).unwrap_or(f64::NAN);
    let r = rhat(&z).max(rhat(&zf));
    let ess = |c: &Vec<Vec<f64>>| mcmc::ess::compute_split_effective_sample_size(c).unwrap_or(f64::NAN);
    let ess_bulk = ess(&z);
    // Tail: the indicator of lying at or below the pooled 5% (95%) quantile, its split ESS.
    let below = |q: f64| chains.iter().map(|c| c.iter().map(|&x| if x <= q { 1.0 } else { 0.0 }).collect()).collect::<Vec<Vec<f64>>>();
    let ess_tail = ess(&below(pooled.q05)).min(ess(&below(pooled.q95)));
    Convergence { r_hat: r, ess_bulk, ess_tail }
}

/// Replace every draw by the normal quantile of its fractional rank among all draws,
/// `Phi^-1((r - 3/8) / (S + 1/4))` (ties share their average rank).
fn rank_normalise(chains: &[Vec<f64>]) -> Vec<Vec<f64>> {
    let mut idx: Vec<(usize, usize)> = chains.iter().enumerate().flat_map(|(c, v)| (0..v.len()).map(move |k| (c, k))).collect();
    idx.sort_by(|a, b| chains[a.0][a.1].total_cmp(&chains[b.0][b.1]));
    let s = idx.len() as f64;
    let normal = Normal::standard();
    let mut out: Vec<Vec<f64>> = chains.iter().map(|v| vec![0.0; v.len()]).collect();
    let mut k = 0;
    while k < idx.len() {
        let mut e = k;
        while e + 1 < idx.len() && chains[idx[e + 1].0][idx[e + 1].1] == chains[idx[k].0][idx[k].1] {
            e += 1;
        }
        let rank = (k + e) as f64 / 2.0 + 1.0;
        let z = normal.inverse_cdf((rank - 0.375) / (s + 0.25));
        for &(c, j) in &idx[k..=e] {
            out[c][j] = z;
        }
        k = e + 1;
    }
    out
}

/// BOM-NUTS after a BOM-SVI fit `svi` of the same evidence (module docs). Errors: one line when
/// a chain cannot start or fails (the density not finite at every start, a sampler error).
pub fn sample(ev: &Evidence, model: &ModelConfig, svi: &Fitted, cfg: &NutsConfig) -> Result<(Posterior, SamplerReport), String> {
    let started = Instant::now();
    let (structs, held) = structures(&svi.posterior, cfg.structure_mass, cfg.max_structures);
    let n = ev.parts.len();
    let mut report = SamplerReport {
        chains: cfg.chains.max(1),
        draws: 0,
        total_draws: 0,
        r_hat_max: f64::NAN,
        ess_bulk_min: f64::NAN,
        ess_tail_min: f64::NAN,
        divergences: 0,
        structures: structs.clone(),
        same_density_as: vec![None; structs.len()],
        sampled: vec![false; structs.len()],
        structure_mass: held,
        runtime_s: 0.0,
        warnings: vec![],
    };
    let mut posterior = svi.posterior.clone();
    let mut convergence = Convergence::NONE;
    // The structures sampled so far, static-collapsed, by index.
    let mut sampled: Vec<(usize, Structure)> = Vec::new();
    for (si, (structure, _)) in structs.iter().enumerate() {
        let density = Density::new(ev, model, structure.clone());
        let collapsed = structure.static_collapsed();
        if let Some((sj, _)) = sampled.iter().find(|(_, c)| *c == collapsed) {
            // Checked, not only assumed: a model term that read a part's parent would show here.
            if same_density(&density, &Density::new(ev, model, structs[*sj].0.clone()), &svi.guide, cfg.seed) {
                tracing::info!("NUTS: structure {si} has structure {sj}'s density (parts on a static part): structure {sj}'s draws stand for it");
                report.same_density_as[si] = Some(*sj);
                continue;
            }
            tracing::debug!("NUTS: structure {si} and structure {sj} collapse alike but their densities differ; sampled apart");
        }
        if si > 0 && !cfg.all_structures {
            // Only the first structure's draws are reported (`summarise_map`); its weight still
            // counts in the type and parent probabilities below.
            tracing::debug!("NUTS: structure {si} (weight {:.3}) not sampled: only the most probable structure's draws are reported (nuts.all_structures)", structs[si].1);
            continue;
        }
        sampled.push((si, collapsed));
        report.sampled[si] = true;
        // Reported scalars per chain and draw, axis directions flipped onto SVI's side.
        let reference: Vec<Option<nalgebra::Vector3<f64>>> = posterior.joints.iter().map(|j| j.axis.as_ref().map(|a| a.direction)).collect();
        let diagnose = |d: &[Vec<Vec<f64>>]| diagnostics(&density, d, &reference, model, (si, cfg));
        let job = Job { ev, model, structure, guide: &svi.guide, cfg, seed: cfg.seed.wrapping_add(si as u64 * 100_003) };
        let sd = sample_structure(&job, &diagnose)?;
        report.divergences += sd.divergences;
        report.draws = report.draws.max(sd.draws.iter().map(|d| d.len() as u64).min().unwrap_or(0));
        report.total_draws += sd.draws.iter().map(|d| d.len() as u64).sum::<u64>();
        convergence = convergence.worst(sd.convergence);
        if si == 0 {
            summarise_map(&mut posterior, &density, &sd, model);
        }
    }
    // Type and parent probabilities: the structures' weights summed.
    for i in 0..n {
        let j = &mut posterior.joints[i];
        j.type_probs = [0.0; 3];
        for pp in j.parent_probs.iter_mut() {
            pp.1 = 0.0;
        }
        for (s, w) in &structs {
            j.type_probs[s.types[i].index()] += w;
            let node = s.parent[i];
            let label = if node == 0 { 0 } else { ev.parts[node - 1].label };
            if let Some(pp) = j.parent_probs.iter_mut().find(|p| p.0 == label) {
                pp.1 += w;
            }
        }
        if let Some((s, _)) = structs.first() {
            j.map_type = s.types[i];
            j.parent_index = s.parent[i];
            j.parent = if s.parent[i] == 0 { 0 } else { ev.parts[s.parent[i] - 1].label };
        }
    }
    let finite_or_nan = |e: f64| if e.is_finite() { e } else { f64::NAN };
    report.r_hat_max = convergence.r_hat;
    report.ess_bulk_min = finite_or_nan(convergence.ess_bulk);
    report.ess_tail_min = finite_or_nan(convergence.ess_tail);
    let total = report.total_draws.max(1);
    if !r_hat_ok(report.r_hat_max, cfg) {
        report.warnings.push(format!("NUTS: R-hat {:.3} > {}", report.r_hat_max, cfg.r_hat_max));
    }
    if !ess_ok(report.ess_bulk_min, cfg.ess_bulk_min) {
        report.warnings.push(format!("NUTS: bulk ESS {:.0} < {}", report.ess_bulk_min, cfg.ess_bulk_min));
    }
    if !ess_ok(report.ess_tail_min, cfg.ess_tail_min) {
        report.warnings.push(format!("NUTS: tail ESS {:.0} < {}", report.ess_tail_min, cfg.ess_tail_min));
    }
    if report.divergences as f64 > cfg.divergence_share_max * total as f64 {
        report.warnings.push(format!("NUTS: {} divergent draws of {total}", report.divergences));
    }
    report.runtime_s = started.elapsed().as_secs_f64();
    posterior.runtime_s = svi.posterior.runtime_s + report.runtime_s;
    Ok((posterior, report))
}

/// The largest R-hat and least bulk and tail ESS over the reported scalars ([`reported`]) of one
/// structure's draws `draws[chain][k]` (NaN R-hat when any is NaN). Each scalar outside `cfg`'s
/// limits is a debug line with the structure's index `si` and its chains' medians.
fn diagnostics(density: &Density<'_>, draws: &[Vec<Vec<f64>>], reference: &[Option<nalgebra::Vector3<f64>>], model: &ModelConfig, (si, cfg): (usize, &NutsConfig)) -> Convergence {
    let per_draw: Vec<Vec<Vec<(String, f64)>>> = draws.iter().map(|c| c.iter().map(|x| reported(density, x, reference, model)).collect()).collect();
    let names: Vec<String> = per_draw.first().and_then(|c| c.first()).map(|d| d.iter().map(|(n, _)| n.clone()).collect()).unwrap_or_default();
    let mut all = Convergence::NONE;
    for (k, name) in names.iter().enumerate() {
        let chains: Vec<Vec<f64>> = per_draw.iter().map(|c| c.iter().map(|d| d[k].1).collect()).collect();
        let one = rank_diagnostics(&chains);
        if !one.holds(cfg) && tracing::enabled!(tracing::Level::DEBUG) {
            let med: Vec<f64> = chains.iter().map(|c| estimate_from_draws(c).median).collect();
            let Convergence { r_hat, ess_bulk, ess_tail } = one;
            tracing::debug!("structure {si}: {name}: R-hat {r_hat:.3}, bulk ESS {ess_bulk:.0}, tail ESS {ess_tail:.0}, chain medians {med:.4?}");
        }
        all = all.worst(one);
    }
    all
}

/// Whether densities `a` and `b` (one layout: the same joint types) agree in value and gradient,
/// to a relative 1e-9, at three draws of the guide (seeded by `seed`).
fn same_density(a: &Density<'_>, b: &Density<'_>, guide: &GuideState, seed: u64) -> bool {
    if a.dim() != b.dim() || a.slots() != b.slots() {
        return false;
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5eed);
    let close = |u: f64, v: f64| (u - v).abs() <= 1e-9 * u.abs().max(v.abs()).max(1.0);
    let (mut ga, mut gb) = (vec![0.0; a.dim()], vec![0.0; b.dim()]);
    (0..3).all(|_| {
        let x = start_from_guide(a, guide, &mut rng);
        let (la, lb) = (a.log_density(&x, &mut ga), b.log_density(&x, &mut gb));
        la.is_finite() && close(la, lb) && ga.iter().zip(&gb).all(|(&u, &v)| close(u, v))
    })
}

/// Whether an R-hat meets the configured limit (NaN never does).
fn r_hat_ok(r_hat: f64, cfg: &NutsConfig) -> bool {
    r_hat <= cfg.r_hat_max
}

/// Whether an ESS meets its configured limit `min` (NaN never does).
fn ess_ok(ess: f64, min: f64) -> bool {
    ess >= min
}

/// Axes, kinodynamics, mean parameters and coordinates of every part from the draws of the most
/// probable structure.
fn summarise_map(posterior: &mut Posterior, density: &Density<'_>, sd: &StructureDraws, model: &ModelConfig) {
    let ev = density.evidence();
    let frames = ev.len();
    let all: Vec<&Vec<f64>> = sd.draws.iter().flatten().collect();
    if all.is_empty() {
        return;
    }
    let mean_x: Vec<f64> = (0..density.dim()).map(|k| all.iter().map(|x| x[k]).sum::<f64>() / all.len() as f64).collect();
    for (i, s) in density.slots().iter().enumerate() {
        let j = &mut posterior.joints[i];
        let params: Vec<JointParams<f64>> = all.iter().map(|x| density.params(x, i)).collect();
        j.mean_params[s.joint.index()] = density.params(&mean_x, i);
        if let Some(o) = s.q {
            j.coordinates[s.joint.index()] = mean_x[o..o + frames].to_vec();
        }
        if !s.joint.movable() {
            continue;
        }
        let reference = j.axis.as_ref().map(|a| a.direction).unwrap_or(params[0].direction);
        // SVI's widenings for what the likelihood leaves out (module docs), when SVI reported
        // this joint type.
        let same_type = j.axis.as_ref().is_some_and(|a| a.joint == s.joint);
        let inflation = j.axis.as_ref().map_or(1.0, |a| a.inflation);
        let kd_inflation = j.kinodynamics.filter(|_| same_type).map_or(1.0, |k| k.inflation);
        j.axis = Some(widened(axis_from_draws(s.joint, &reference, &params, &params), inflation).with_model_discrepancy(model));
        j.kinodynamics = s.kd.map(|(o, d)| {
            let block: Vec<Vec<f64>> = all.iter().map(|x| x[o..o + d].to_vec()).collect();
            let kp: Vec<dynamics::KinoParams<f64>> = inflated_draws(&block, kd_inflation).iter().map(|x| dynamics::decode::<f64>(s.joint, x, &ev.effects[i], &model.dynamics)).collect();
            let discrepancy = model.dynamics.discrepancy_log_sd;
            let est = |f: &dyn Fn(&dynamics::KinoParams<f64>) -> f64| with_log_discrepancy(estimate_from_draws(&kp.iter().map(f).collect::<Vec<f64>>()), discrepancy);
            let logs = log_covariance(&kp.iter().map(|k| [k.damping, k.friction, k.mass]).collect::<Vec<_>>());
            Kinodynamics {
                damping: est(&|k| k.damping),
                friction: est(&|k| k.friction),
                mass: est(&|k| k.mass),
                inflation: kd_inflation,
                log_correlation: log_correlation(&logs, discrepancy),
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Independent standard-normal chains mix: R-hat near 1, bulk ESS near the draw count; two
    /// chains stuck at different levels do not.
    #[test]
    fn rank_diagnostics_tell_mixed_from_stuck_chains() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mixed: Vec<Vec<f64>> = (0..4).map(|_| (0..500).map(|_| StandardNormal.sample(&mut rng)).collect()).collect();
        let Convergence { r_hat: r, ess_bulk: ess, ess_tail: tail } = rank_diagnostics(&mixed);
        assert!(r < 1.01, "R-hat {r}");
        assert!(ess > 1500.0, "ESS {ess}");
        assert!(tail > 1000.0, "tail ESS {tail}");
        let stuck: Vec<Vec<f64>> = (0..4).map(|c| (0..500).map(|_| c as f64 + 0.1 * { let z: f64 = StandardNormal.sample(&mut rng); z }).collect()).collect();
        let Convergence { r_hat: r, ess_bulk: ess, ess_tail: tail } = rank_diagnostics(&stuck);
        assert!(r > 1.5, "R-hat {r}");
        assert!(ess < 100.0, "ESS {ess}");
        assert!(tail < 100.0, "tail ESS {tail}");
    }

    /// Chains that mix in the bulk but whose scale wanders slowly (`x = s_t z_t`, `z_t` independent
    /// standard normals, `log s_t` an AR(1) with coefficient 0.99: stochastic volatility, the tails
    /// visited in long spells) pass the bulk ESS limit and fail the tail ESS's: the 90%
    /// interval's ends are what such draws get wrong (Vehtari et al. 2021, §4.3).
    #[test]
    fn tail_ess_sees_chains_whose_tails_mix_slowly() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let (phi, sd) = (0.99f64, 0.7);
        let chains: Vec<Vec<f64>> = (0..4)
            .map(|_| {
                let mut log_s = 0.0;
                (0..1000)
                    .map(|_| {
                        let (e, z): (f64, f64) = (StandardNormal.sample(&mut rng), StandardNormal.sample(&mut rng));
                        log_s = phi * log_s + (1.0 - phi * phi).sqrt() * sd * e;
                        log_s.exp() * z
                    })
                    .collect()
            })
            .collect();
        let d = rank_diagnostics(&chains);
        assert!(d.ess_bulk >= 400.0, "{d:?}");
        assert!(d.ess_tail < 400.0, "{d:?}");
        assert!(!d.holds(&NutsConfig::default()), "{d:?}");
    }

    /// The sheared preconditioner of a kinodynamic block round-trips, and the gradient it pulls
    /// back to the sampler's coordinates is that of the composed function (central differences).
    /// On a Gaussian coordinate of sd `s`, the start scales make nuts-rs's first variance
    /// (`1 / |g|` in the sampler's coordinate) the coordinate's variance `s^2`, wherever the
    /// start lies within the clamp, and keep it finite and positive where the gradient vanishes.
    #[test]
    fn start_scales_make_the_first_mass_matrix_the_guide_variance() {
        let sd = [1e-3, 0.5, 2.0, 1e-4];
        // Gradients of N(0, s^2) at 0.3, -1.7, 2.5 sds and at the mode.
        let e = [0.3, -1.7, 2.5, 0.0];
        let g: Vec<f64> = sd.iter().zip(&e).map(|(s, e)| -e / s).collect();
        let d = start_scales(&sd, &g);
        for k in 0..3 {
            // Sampler coordinate `z = y / d`: gradient `d g`, first variance `1 / |d g|` in `z`,
            // `d^2 / |d g|` in `y`.
            let var_y = d[k] * d[k] / (d[k] * g[k]).abs();
            assert!((var_y / (sd[k] * sd[k]) - 1.0).abs() < 1e-12, "coordinate {k}: {var_y} against {}", sd[k] * sd[k]);
        }
        assert!(d[3].is_finite() && d[3] > 0.0);
    }

    #[test]
    fn sheared_block_round_trips_and_pulls_gradients_back() {
        let l = DMatrix::from_row_slice(4, 4, &[0.3, 0.0, 0.0, 0.0, 0.1, 0.5, 0.0, 0.0, 0.0, 0.2, 0.4, 0.0, 0.05, -0.1, 0.0, 0.2]);
        let b = Block { offset: 1, m: DVector::from_column_slice(&[0.2, -1.5, 0.3, 0.7]), l, shear: Some((-0.8, 1.5, -1.5)) };
        // A curved function of the model's block (damping at offset 1, friction at 2).
        let f = |x: &[f64]| -> (f64, Vec<f64>) {
            let e = x[2].exp();
            let v = -0.5 * (x[1] + 0.6 * e).powi(2) - 0.5 * x[2] * x[2] + (x[3] * x[4]).sin() - 0.1 * x[0] * x[0];
            let g = vec![-0.2 * x[0], -(x[1] + 0.6 * e), -(x[1] + 0.6 * e) * 0.6 * e - x[2], x[4] * (x[3] * x[4]).cos(), x[3] * (x[3] * x[4]).cos()];
            (v, g)
        };
        let blocks = vec![b];
        // The start scales of `Logp` on top of the blocks.
        let scale = [2.0, 0.5, 1.0, 3.0, 0.25];
        let value = |z: &[f64]| f(&to_model(&blocks, &scale, z)).0;
        let z = [0.3, -0.4, 1.1, 0.2, -0.7];
        let x = to_model(&blocks, &scale, &z);
        // Round trip through `to_sampler`'s arithmetic.
        let mut v = DVector::from_column_slice(&x[1..5]);
        blocks[0].shear(v.as_mut_slice());
        let back = blocks[0].l.solve_lower_triangular(&(v - &blocks[0].m)).unwrap();
        for k in 0..4 {
            assert!((back[k] / scale[k + 1] - z[k + 1]).abs() < 1e-12, "round trip: {back} vs {z:?}");
        }
        // The pulled-back gradient, as `Logp::logp` does it.
        let (_, mut g) = f(&x);
        blocks[0].pull_back(&x[1..5], &mut g[1..5]);
        let gz = blocks[0].l.transpose() * DVector::from_column_slice(&g[1..5]);
        g[1..5].copy_from_slice(gz.as_slice());
        for (g, s) in g.iter_mut().zip(&scale) {
            *g *= s;
        }
        for k in 0..5 {
            let h = 1e-6;
            let (mut a, mut c) = (z, z);
            a[k] += h;
            c[k] -= h;
            let fd = (value(&a) - value(&c)) / (2.0 * h);
            assert!((fd - g[k]).abs() < 1e-6 * (1.0 + fd.abs()), "coordinate {k}: {} vs {fd}", g[k]);
        }
    }

    /// On `adroit_door` (a latch hinged on a door; dynamic mode, partially non-centred as the
    /// sampler runs it), SVI's Laplace covariance of a kinodynamic block is far wider than the
    /// sampled coordinates' curvature at the guide's mean; after [`block_curvature`] no block's
    /// Hessian there has an eigenvalue much above 1 (the guide's width or narrower).
    #[test]
    fn block_curvature_narrows_blocks_to_the_sampled_curvature() {
        let cfg = crate::config::Config::new();
        let run = crate::pipeline::replay(&[std::path::PathBuf::from("bags/mujoco/adroit_door.mcap")], &cfg).expect("replay");
        let ev = crate::pipeline::final_evidence(&run, &cfg);
        let fitted = super::super::svi::fit(&ev, &cfg.model, &cfg.inference, None).expect("a fit");
        let joints = &fitted.posterior.joints;
        let structure = Structure { parent: joints.iter().map(|j| j.parent_index).collect(), types: joints.iter().map(|j| j.map_type).collect() };
        let (model, guide) = (&cfg.model, &fitted.guide);
        let density = Density::new(&ev, model, structure.clone());
        let blocks = preconditioner(&density, guide, model, true);
        let centring = centring_from_guide(&density, guide, model);
        let mean = guide_point(&density, guide, || 0.0);
        let scale = vec![1.0; density.dim()];
        let mut logp = Logp { blocks, density: coordinates(density, Some(&centring), false), scale };
        assert!(logp.blocks.len() >= 2, "the door's and the latch's blocks");
        let largest = |logp: &mut Logp<'_>| -> Vec<f64> {
            block_hessians(logp, &mean).into_iter().map(|h| h.expect("a finite Hessian").symmetric_eigen().eigenvalues.max()).collect()
        };
        let before = largest(&mut logp);
        assert!(before.iter().any(|&v| v > 100.0), "a block far narrower than the guide's: {before:?}");
        block_curvature(&mut logp, &mean);
        let after = largest(&mut logp);
        assert!(after.iter().all(|&v| v < 1.2), "largest eigenvalues before {before:?}, after {after:?}");
    }
}
