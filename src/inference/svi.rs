//! BOM-SVI, kinematic variant: stochastic variational inference of the tree, the joint types and
//! the continuous parameters (paper §3.4, Algorithm 1), maximising the ELBO with Adam.
//!
//! **Guide** (Pyro style: the model is [`crate::model`], this is the variational family):
//! - tree: parent logits per part, sampled by the DP-DAG sampler with opportunistic rounding
//!   ([`crate::model::tree`]);
//! - joint type: logits per part, sampled by straight-through Gumbel-softmax (paper §3.2);
//! - continuous parameters: a mean-field Gaussian per part *and per joint type* over that type's
//!   standardised parameters and its per-frame coordinates, i.e. `q(theta_k | type = k)`.
//!
//! **Gradients.** Continuous parameters use the reparameterisation trick with gradients of the
//! log-likelihood from forward-mode dual numbers (`num-dual`) through the generic model code, one
//! frame at a time (the global parameters of a joint plus that frame's coordinate: at most 11
//! dual directions). Each type's block is fitted to its own conditional ELBO every iteration, so
//! an alternative type keeps an up-to-date fit instead of starving while it is rarely sampled.
//! The discrete choices use the straight-through estimator: the forward pass takes the hard
//! (rounded) sample, and the gradient of the soft relaxation is applied to the per-choice
//! objective — the conditional ELBO of each joint type, the log-likelihood of the part's subtree
//! under each admissible parent. Taking the per-choice objective rather than linearising the
//! trajectory avoids the first-order bias of plain ST; as `tau -> 0` the expected soft sample is
//! the guide's probability, so the fixed point is `q(type) ∝ p(type) exp(ELBO_type)`, the
//! Bayesian model comparison with its Occam factor.
//!
//! **Schedule.** Phase 1 fits the continuous guides alone until the summed conditional ELBOs
//! settle (they do not depend on the discrete guide); phase 2 also updates the discrete logits
//! until they settle (earlier, their per-choice objectives are still noisy fits and lock in wrong
//! choices); phase 3 runs `final_iters` more at a reduced learning rate and averages the logits
//! (Polyak) for the reported probabilities.
//!
//! The analytic parts of the ELBO (KL of the standard-normal priors, the random-walk prior of
//! the coordinates, guide entropies, categorical KLs) are exact; only the likelihood is sampled.

use std::time::Instant;

use nalgebra::Vector3;
use num_dual::DualSVec64;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Gumbel, StandardNormal};
use serde::{Deserialize, Serialize};

use super::adam::Adam;
use super::{AxisSummary, JointSummary, Posterior};
use crate::model::likelihood::{coordinate_prior, log_likelihood_normal, log_likelihood_point, Evidence};
use crate::model::{decode, displacement, tree, Displacement, JointParams, JointType, ModelConfig};

/// Dual number with enough directions for the largest joint (10 globals) plus one coordinate.
type D = DualSVec64<11>;
const Q_SLOT: usize = 10;

/// SVI settings (`inference` section of the config).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct SviConfig {
    /// Particles (samples of all latent variables) per ELBO gradient.
    pub particles: usize,
    /// Phase 1 (continuous guides only) runs at least `min_iters`; phases 1 and 2 together at
    /// most `max_iters`.
    pub min_iters: usize,
    pub max_iters: usize,
    /// Convergence tests every `check_every` iterations. Phase 1 ends when the summed conditional
    /// ELBOs changed by less than `tol_nats + tol_rel * |ELBO|` between blocks; phase 2 (discrete
    /// logits too) when no logit moved by more than `tol_logits` between blocks, after at least
    /// `min_discrete_iters`.
    pub check_every: usize,
    pub tol_nats: f64,
    pub tol_rel: f64,
    pub min_discrete_iters: usize,
    pub tol_logits: f64,
    /// Iterations at the end with the learning rate scaled by `final_lr_scale`, over which the
    /// discrete logits are averaged (Polyak) for the reported probabilities.
    pub final_iters: usize,
    pub final_lr_scale: f64,
    /// Adam learning rates: standardised globals (mean and log-sd), coordinates \[m\], logits.
    pub lr_global: f64,
    pub lr_coordinate_m: f64,
    pub lr_logits: f64,
    /// Gumbel-softmax temperature and rounding threshold (paper §3.3).
    pub tau: f64,
    pub delta: f64,
    /// Least time between grid frames \[s\] (see [`Evidence::new`] for why), unless a window would
    /// then keep fewer than `min_frames`; and the most grid frames.
    pub min_dt_s: f64,
    pub min_frames: usize,
    pub max_frames: usize,
    /// Initial guide sds: standardised globals, coordinates \[m\].
    pub init_global_sd: f64,
    pub init_coordinate_sd_m: f64,
    /// Samples used for the posterior summaries.
    pub summary_samples: usize,
    pub seed: u64,
}

impl Default for SviConfig {
    fn default() -> Self {
        SviConfig {
            particles: 2,
            min_iters: 150,
            max_iters: 1500,
            check_every: 50,
            tol_nats: 1.0,
            tol_rel: 2e-4,
            min_discrete_iters: 150,
            tol_logits: 0.25,
            final_iters: 100,
            final_lr_scale: 0.3,
            lr_global: 0.03,
            lr_coordinate_m: 0.002,
            lr_logits: 0.05,
            tau: 0.5,
            delta: 0.5,
            min_dt_s: 0.5,
            min_frames: 20,
            max_frames: 200,
            init_global_sd: 0.05,
            init_coordinate_sd_m: 0.003,
            summary_samples: 400,
            seed: 0,
        }
    }
}

/// Where one (part, joint type) block lives in the flat parameter vector.
#[derive(Debug, Clone, Copy)]
struct Block {
    joint: JointType,
    mu: usize,
    log_s: usize,
    /// Offsets of coordinate means and log-sds (movable joints).
    q: Option<(usize, usize)>,
}

#[derive(Debug, Clone)]
struct Layout {
    blocks: Vec<[Block; 3]>,
    type_logits: Vec<usize>,
    parent_logits: Vec<usize>,
    len: usize,
}

impl Layout {
    fn new(n_parts: usize, frames: usize) -> Layout {
        let mut off = 0;
        let mut take = |n: usize| {
            let o = off;
            off += n;
            o
        };
        let mut blocks = Vec::new();
        for _ in 0..n_parts {
            let b = JointType::ALL.map(|joint| {
                let p = joint.num_params();
                let (mu, log_s) = (take(p), take(p));
                let q = joint.movable().then(|| (take(frames), take(frames)));
                Block { joint, mu, log_s, q }
            });
            blocks.push(b);
        }
        let type_logits = (0..n_parts).map(|_| take(3)).collect();
        let parent_logits = (0..n_parts).map(|_| take(n_parts + 1)).collect();
        Layout { blocks, type_logits, parent_logits, len: off }
    }
}

/// One sample of a block: standardised globals, coordinates and the noise used.
struct BlockSample {
    eps: Vec<f64>,
    xi: Vec<f64>,
    q_eps: Vec<f64>,
    q: Vec<f64>,
    params: JointParams<f64>,
}

/// A descendant of the part being differentiated, expressed relative to that part's frame.
struct Member {
    /// Part index.
    m: usize,
    /// Centre of mass per frame relative to the part's displacement (f64).
    z: Vec<Vector3<f64>>,
    /// Reference normal rotated by the displacement relative to the part, per frame.
    n: Vec<Option<Vector3<f64>>>,
    sigma: f64,
}

/// Log-likelihood of a part's subtree with part `i` under joint type `k` and its gradient with
/// respect to that block's standardised globals and coordinates, from dual numbers.
///
/// `pre[t]` is the parent's displacement at frame `t`; `subtree` the descendants relative to
/// part `i`'s frame. Surface normals, where observed, add their likelihood.
#[allow(clippy::too_many_arguments)]
fn block_pass(
    ev: &Evidence,
    i: usize,
    joint: JointType,
    xi: &[f64],
    q: &[f64],
    pre: &[Displacement<f64>],
    subtree: &[Member],
    cfg: &ModelConfig,
) -> (f64, Vec<f64>, Vec<f64>) {
    let np = joint.num_params();
    let xid: Vec<D> = xi.iter().enumerate().map(|(j, &x)| D::from_re(x).derivative(j)).collect();
    let p = decode(joint, &xid, &ev.parts[i].com0, cfg);
    let (mut l, mut gx, mut gq) = (0.0, vec![0.0; np], vec![0.0; ev.len()]);
    for t in 0..ev.len() {
        let own_obs = ev.parts[i].obs[t];
        let any_sub = subtree.iter().any(|mb| ev.parts[mb.m].obs[t].is_some());
        if own_obs.is_none() && !any_sub {
            continue;
        }
        let qt = if joint.movable() && t > 0 { D::from_re(q[t]).derivative(Q_SLOT) } else { D::from_re(q[t]) };
        let s = pre[t].lift::<D>().compose(&displacement(&p, qt));
        let mut ll = D::from_re(0.0);
        if let Some((y, sd)) = own_obs {
            ll += log_likelihood_point(&y, &s.apply(&p.com), p.noise, sd);
        }
        if let (Some((n_obs, sd)), Some(n0)) = (ev.parts[i].normals[t], ev.parts[i].normal0) {
            ll += log_likelihood_normal(&n_obs, &(s.r * n0.map(D::from)), sd);
        }
        for mb in subtree {
            if let Some((y, sd)) = ev.parts[mb.m].obs[t] {
                ll += log_likelihood_point(&y, &s.apply(&mb.z[t].map(D::from)), D::from(mb.sigma), sd);
            }
            if let (Some((n_obs, sd)), Some(n)) = (ev.parts[mb.m].normals[t], mb.n[t]) {
                ll += log_likelihood_normal(&n_obs, &(s.r * n.map(D::from)), sd);
            }
        }
        l += ll.re;
        if let Some(e) = ll.eps.0 {
            for j in 0..np {
                gx[j] += e[j];
            }
            gq[t] = e[Q_SLOT];
        }
    }
    (l, gx, gq)
}

fn softmax(z: &[f64]) -> Vec<f64> {
    let mx = z.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    let e: Vec<f64> = z.iter().map(|v| (v - mx).exp()).collect();
    let s: f64 = e.iter().sum();
    e.iter().map(|v| v / s).collect()
}

/// Gradient of `sum_k q_k a_k + H(q)` with `q = softmax(l)`: `q_j ((a_j - mean a) - (log q_j + H))`.
fn categorical_kl_grad(l: &[f64], a: &[f64]) -> (f64, Vec<f64>) {
    let q = softmax(l);
    let abar: f64 = q.iter().zip(a).map(|(q, a)| q * a).sum();
    let h: f64 = -q.iter().map(|q| if *q > 0.0 { q * q.ln() } else { 0.0 }).sum::<f64>();
    let g = q.iter().zip(a).map(|(&qj, &aj)| if qj > 0.0 { qj * ((aj - abar) - (qj.ln() + h)) } else { 0.0 }).collect();
    (abar + h, g)
}

/// Straight-through gradient: `J^T f` with `J` the Jacobian of `softmax(z / tau)` at the soft sample.
fn st_grad(soft: &[f64], f: &[f64], tau: f64) -> Vec<f64> {
    let sf: f64 = soft.iter().zip(f).map(|(s, f)| s * f).sum();
    soft.iter().zip(f).map(|(s, fj)| s * (fj - sf) / tau).collect()
}

/// Transform of every part at every frame for a tree and per-part selected samples.
fn part_transforms(parent: &[usize], chosen: &[&BlockSample], frames: usize) -> Vec<Vec<Displacement<f64>>> {
    let n = parent.len();
    let mut out: Vec<Option<Vec<Displacement<f64>>>> = vec![None; n];
    // Resolve in dependency order; the tree guarantees termination.
    while out.iter().any(|o| o.is_none()) {
        for i in 0..n {
            if out[i].is_some() {
                continue;
            }
            let pre = if parent[i] == 0 { Some(vec![Displacement::identity(); frames]) } else { out[parent[i] - 1].clone() };
            if let Some(pre) = pre {
                let s = chosen[i];
                out[i] = Some((0..frames).map(|t| pre[t].compose(&displacement(&s.params, s.q[t]))).collect());
            }
        }
    }
    out.into_iter().map(|o| o.expect("resolved")).collect()
}

fn inverse(d: &Displacement<f64>) -> Displacement<f64> {
    let rt = d.r.transpose();
    Displacement { r: rt, t: -(rt * d.t) }
}

fn descendants(parent: &[usize], i: usize) -> Vec<usize> {
    (0..parent.len())
        .filter(|&m| {
            let mut node = parent[m];
            let mut steps = 0;
            while node != 0 && steps <= parent.len() {
                if node == i + 1 {
                    return true;
                }
                node = parent[node - 1];
                steps += 1;
            }
            false
        })
        .collect()
}

/// Fit the guide to the evidence and summarise the posterior. Returns `None` when there is no
/// part with observations.
pub fn fit(ev: &Evidence, model: &ModelConfig, cfg: &SviConfig) -> Option<Posterior> {
    let started = Instant::now();
    let n = ev.parts.len();
    let k_frames = ev.len();
    if n == 0 || k_frames == 0 {
        return None;
    }
    let layout = Layout::new(n, k_frames);
    let mut theta = vec![0.0; layout.len];
    let mut lr = vec![cfg.lr_global; layout.len];
    init_guide(ev, model, cfg, &layout, &mut theta, &mut lr);
    let mut adam = Adam::new(layout.len);
    let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
    let gumbel = Gumbel::new(0.0, 1.0).expect("valid Gumbel");
    let log_prior_type: Vec<f64> = model.type_prior.iter().map(|p| p.max(1e-300).ln()).collect();

    // Phase 1 fits the continuous guides alone (their conditional ELBOs do not depend on the
    // discrete guide), so that the straight-through updates of the logits in phase 2 start from
    // meaningful per-choice objectives; phase 3 averages at a reduced learning rate.
    let mut phase = 1;
    let mut discrete_iters = 0;
    let mut block_sum = 0.0;
    let mut last_block: Option<f64> = None;
    let mut last_logits: Option<Vec<f64>> = None;
    let mut final_left: Option<usize> = None;
    let mut f_avg = vec![[0.0f64; 3]; n];
    let mut avg_type = vec![[0.0f64; 3]; n];
    let mut avg_parent = vec![vec![0.0f64; n + 1]; n];
    let mut avg_count = 0usize;
    let mut iters = 0;

    loop {
        iters += 1;
        let mut grad = vec![0.0; layout.len];
        let mut block_elbo = 0.0;

        // Analytic terms of every block: -KL of the globals, coordinate prior and entropy.
        let mut analytic = vec![[0.0f64; 3]; n];
        for i in 0..n {
            for (k, b) in layout.blocks[i].iter().enumerate() {
                let np = b.joint.num_params();
                let mut a = 0.0;
                for j in 0..np {
                    let (mu, ls) = (theta[b.mu + j], theta[b.log_s + j]);
                    let s2 = (2.0 * ls).exp();
                    a += 0.5 * (1.0 + 2.0 * ls - mu * mu - s2);
                    grad[b.mu + j] -= mu;
                    grad[b.log_s + j] += 1.0 - s2;
                }
                if let Some((qm, qs)) = b.q {
                    let s: Vec<f64> = (0..k_frames).map(|t| theta[qs + t].exp()).collect();
                    let (v, gm, gs) = coordinate_prior(ev, &theta[qm..qm + k_frames], &s, model);
                    a += v;
                    for t in 1..k_frames {
                        a += theta[qs + t] + 0.5 * (1.0 + (2.0 * std::f64::consts::PI).ln());
                        grad[qm + t] += gm[t];
                        grad[qs + t] += gs[t] * s[t] + 1.0;
                    }
                }
                analytic[i][k] = a;
            }
        }
        // Categorical KL terms (types; parents under the uniform tree prior).
        for i in 0..n {
            let l = &theta[layout.type_logits[i]..layout.type_logits[i] + 3];
            let (_, g) = categorical_kl_grad(l, &log_prior_type);
            for k in 0..3 {
                grad[layout.type_logits[i] + k] += g[k];
            }
            if n > 1 {
                let o = layout.parent_logits[i];
                let cand: Vec<usize> = (0..=n).filter(|&j| j != i + 1).collect();
                let l: Vec<f64> = cand.iter().map(|&j| theta[o + j]).collect();
                let (_, g) = categorical_kl_grad(&l, &vec![0.0; cand.len()]);
                for (c, &j) in cand.iter().enumerate() {
                    grad[o + j] += g[c];
                }
            }
        }

        let parent_logits: Vec<Vec<f64>> =
            (0..n).map(|i| theta[layout.parent_logits[i]..layout.parent_logits[i] + n + 1].to_vec()).collect();
        let pw = 1.0 / cfg.particles as f64;
        let mut particle_grad = vec![0.0; layout.len];
        for _ in 0..cfg.particles {
            let g_tree = tree::sample(&parent_logits, cfg.tau, cfg.delta, &mut rng);
            // Joint types by Gumbel-softmax; the hard sample is the arg max.
            let mut type_soft = Vec::with_capacity(n);
            let mut chosen_type = Vec::with_capacity(n);
            for i in 0..n {
                let l = &theta[layout.type_logits[i]..layout.type_logits[i] + 3];
                let z: Vec<f64> = l.iter().map(|v| (v + gumbel.sample(&mut rng)) / cfg.tau).collect();
                let s = softmax(&z);
                let best = (0..3).max_by(|&a, &b| s[a].total_cmp(&s[b])).unwrap_or(0);
                type_soft.push(s);
                chosen_type.push(best);
            }
            // Reparameterised samples of every block.
            let samples: Vec<Vec<BlockSample>> = (0..n)
                .map(|i| {
                    layout.blocks[i]
                        .iter()
                        .map(|b| sample_block(ev, i, b, &theta, model, &mut rng))
                        .collect()
                })
                .collect();
            let chosen: Vec<&BlockSample> = (0..n).map(|i| &samples[i][chosen_type[i]]).collect();
            let transforms = part_transforms(&g_tree.parent, &chosen, k_frames);
            let positions: Vec<Vec<Vector3<f64>>> = (0..n)
                .map(|m| (0..k_frames).map(|t| transforms[m][t].apply(&chosen[m].params.com)).collect())
                .collect();
            let normals: Vec<Vec<Option<Vector3<f64>>>> = (0..n)
                .map(|m| (0..k_frames).map(|t| ev.parts[m].normal0.map(|n0| transforms[m][t].r * n0)).collect())
                .collect();

            for i in 0..n {
                let pre: Vec<Displacement<f64>> = if g_tree.parent[i] == 0 {
                    vec![Displacement::identity(); k_frames]
                } else {
                    transforms[g_tree.parent[i] - 1].clone()
                };
                let desc = descendants(&g_tree.parent, i);
                let inv: Vec<Displacement<f64>> = (0..k_frames).map(|t| inverse(&transforms[i][t])).collect();
                let subtree: Vec<Member> = desc
                    .iter()
                    .map(|&m| {
                        Member {
                            m,
                            z: (0..k_frames).map(|t| inv[t].apply(&positions[m][t])).collect(),
                            n: (0..k_frames).map(|t| normals[m][t].map(|n| inv[t].r * n)).collect(),
                            sigma: chosen[m].params.noise,
                        }
                    })
                    .collect();
                let mut f = [0.0; 3];
                for (k, b) in layout.blocks[i].iter().enumerate() {
                    let s = &samples[i][k];
                    let (l, gx, gq) = block_pass(ev, i, b.joint, &s.xi, &s.q, &pre, &subtree, model);
                    f[k] = l + analytic[i][k];
                    for j in 0..gx.len() {
                        particle_grad[b.mu + j] += pw * gx[j];
                        particle_grad[b.log_s + j] += pw * gx[j] * s.eps[j] * theta[b.log_s + j].exp();
                    }
                    if let Some((qm, qs)) = b.q {
                        for t in 1..k_frames {
                            particle_grad[qm + t] += pw * gq[t];
                            particle_grad[qs + t] += pw * gq[t] * s.q_eps[t] * theta[qs + t].exp();
                        }
                    }
                }
                for k in 0..3 {
                    block_elbo += pw * f[k];
                    if final_left.is_some() {
                        f_avg[i][k] += pw * f[k];
                    }
                }
                let g = st_grad(&type_soft[i], &f, cfg.tau);
                for k in 0..3 {
                    particle_grad[layout.type_logits[i] + k] += pw * g[k];
                }
                // Parents: log-likelihood of the subtree of i re-attached under each admissible node.
                let adm = &g_tree.admissible[i];
                if n > 1 && adm.len() > 1 {
                    let mut members = vec![i];
                    members.extend(&desc);
                    let fj: Vec<f64> = adm
                        .iter()
                        .map(|&j| {
                            let mut ll = 0.0;
                            for t in 0..k_frames {
                                let new_pre = if j == 0 { Displacement::identity() } else { transforms[j - 1][t] };
                                let d = new_pre.compose(&inverse(&pre[t]));
                                for &m in &members {
                                    if let Some((y, sd)) = ev.parts[m].obs[t] {
                                        ll += log_likelihood_point(&y, &d.apply(&positions[m][t]), chosen[m].params.noise, sd);
                                    }
                                    if let (Some((n_obs, sd)), Some(n)) = (ev.parts[m].normals[t], normals[m][t]) {
                                        ll += log_likelihood_normal(&n_obs, &(d.r * n), sd);
                                    }
                                }
                            }
                            ll
                        })
                        .collect();
                    let soft: Vec<f64> = adm.iter().map(|&j| g_tree.soft[i][j]).collect();
                    let g = st_grad(&soft, &fj, cfg.tau);
                    for (c, &j) in adm.iter().enumerate() {
                        particle_grad[layout.parent_logits[i] + j] += pw * g[c];
                    }
                }
            }
        }
        for (g, p) in grad.iter_mut().zip(&particle_grad) {
            *g += p;
        }
        if phase == 1 {
            for i in 0..n {
                for k in 0..3 {
                    grad[layout.type_logits[i] + k] = 0.0;
                }
                for j in 0..=n {
                    grad[layout.parent_logits[i] + j] = 0.0;
                }
            }
        }
        block_sum += block_elbo;

        let scale = if final_left.is_some() { cfg.final_lr_scale } else { 1.0 };
        adam.step(&mut theta, &grad, &lr, scale);

        match final_left.as_mut() {
            Some(left) => {
                for i in 0..n {
                    for k in 0..3 {
                        avg_type[i][k] += theta[layout.type_logits[i] + k];
                    }
                    for j in 0..=n {
                        avg_parent[i][j] += theta[layout.parent_logits[i] + j];
                    }
                }
                avg_count += 1;
                *left -= 1;
                if *left == 0 {
                    break;
                }
            }
            None => {
                if phase == 2 {
                    discrete_iters += 1;
                }
                if iters % cfg.check_every == 0 {
                    let mean = block_sum / cfg.check_every as f64;
                    block_sum = 0.0;
                    let logits: Vec<f64> = (0..n)
                        .flat_map(|i| {
                            let t = &theta[layout.type_logits[i]..layout.type_logits[i] + 3];
                            let p = &theta[layout.parent_logits[i]..layout.parent_logits[i] + n + 1];
                            t.iter().chain(p).copied().collect::<Vec<_>>()
                        })
                        .collect();
                    if phase == 1 {
                        let settled = matches!(last_block, Some(prev) if (mean - prev).abs() < cfg.tol_nats + cfg.tol_rel * mean.abs());
                        if settled && iters >= cfg.min_iters {
                            phase = 2;
                        }
                    } else {
                        let settled = matches!(&last_logits, Some(prev) if prev.iter().zip(&logits).all(|(a, b)| (a - b).abs() < cfg.tol_logits || (a.abs() > 1e8)));
                        if settled && discrete_iters >= cfg.min_discrete_iters {
                            final_left = Some(cfg.final_iters.max(1));
                        }
                    }
                    last_block = Some(mean);
                    last_logits = Some(logits);
                }
                if iters >= cfg.max_iters {
                    final_left = Some(cfg.final_iters.max(1));
                }
                if phase == 1 && iters + cfg.min_discrete_iters >= cfg.max_iters {
                    phase = 2;
                }
            }
        }
    }

    let type_logits: Vec<[f64; 3]> = avg_type.iter().map(|a| a.map(|v| v / avg_count as f64)).collect();
    let parent_logits: Vec<Vec<f64>> = avg_parent.iter().map(|a| a.iter().map(|v| v / avg_count as f64).collect()).collect();
    // ELBO of the fitted guide: sum over parts of E_q(type)[conditional ELBO] - KL(q(type) || p(type)),
    // plus the tree's prior and entropy terms.
    let mut elbo = 0.0;
    for i in 0..n {
        let f: Vec<f64> = f_avg[i].iter().map(|v| v / avg_count.max(1) as f64).collect();
        let a: Vec<f64> = (0..3).map(|k| f[k] + log_prior_type[k]).collect();
        elbo += categorical_kl_grad(&type_logits[i], &a).0;
        if n > 1 {
            let l: Vec<f64> = (0..=n).filter(|&j| j != i + 1).map(|j| parent_logits[i][j]).collect();
            elbo += categorical_kl_grad(&l, &vec![0.0; l.len()]).0;
        }
    }
    elbo += tree::log_prior(n);
    Some(summarise(ev, model, cfg, &layout, &theta, &type_logits, &parent_logits, elbo, iters, started, &mut rng))
}

fn sample_block(ev: &Evidence, i: usize, b: &Block, theta: &[f64], model: &ModelConfig, rng: &mut ChaCha8Rng) -> BlockSample {
    let np = b.joint.num_params();
    let eps: Vec<f64> = (0..np).map(|_| StandardNormal.sample(rng)).collect();
    let xi: Vec<f64> = (0..np).map(|j| theta[b.mu + j] + theta[b.log_s + j].exp() * eps[j]).collect();
    let k = ev.len();
    let (q_eps, q) = match b.q {
        Some((qm, qs)) => {
            let e: Vec<f64> = (0..k).map(|t| if t == 0 { 0.0 } else { StandardNormal.sample(rng) }).collect();
            let q = (0..k).map(|t| if t == 0 { 0.0 } else { theta[qm + t] + theta[qs + t].exp() * e[t] }).collect();
            (e, q)
        }
        None => (vec![0.0; k], vec![0.0; k]),
    };
    let params = decode(b.joint, &xi, &ev.parts[i].com0, model);
    BlockSample { eps, xi, q_eps, q, params }
}

/// Initialise the guide from the data: axes by principal components and circle fits,
/// coordinates by projection, the noise from the initial residuals.
fn init_guide(ev: &Evidence, model: &ModelConfig, cfg: &SviConfig, layout: &Layout, theta: &mut [f64], lr: &mut [f64]) {
    let k_frames = ev.len();
    for (i, part) in ev.parts.iter().enumerate() {
        let seen: Vec<(usize, Vector3<f64>)> = part.obs.iter().enumerate().filter_map(|(t, o)| o.map(|o| (t, o.0))).collect();
        let track: Vec<Vector3<f64>> = seen.iter().map(|s| s.1).collect();
        for b in &layout.blocks[i] {
            let np = b.joint.num_params();
            let mut mu = vec![0.0; np];
            let q_seen: Vec<f64> = match b.joint {
                JointType::Rigid => vec![0.0; track.len()],
                JointType::Prismatic => {
                    let (v, q) = crate::model::prismatic::init(&track, &part.com0);
                    mu[4..7].copy_from_slice(&v);
                    q
                }
                JointType::Revolute => {
                    let (v, q) = crate::model::revolute::init(&track, &part.com0, model);
                    mu[4..10].copy_from_slice(&v);
                    q
                }
            };
            // Coordinates on the whole grid: observed values, held over occlusions.
            let mut q = vec![0.0; k_frames];
            let mut last = 0.0;
            let mut it = seen.iter().zip(&q_seen).peekable();
            for (t, qt) in q.iter_mut().enumerate() {
                while let Some(((ts, _), qv)) = it.peek() {
                    if *ts <= t {
                        last = **qv;
                        it.next();
                    } else {
                        break;
                    }
                }
                *qt = if t == 0 { 0.0 } else { last };
            }
            // Noise from the residuals of this initial fit.
            let p = decode::<f64>(b.joint, &mu, &part.com0, model);
            let (mut ss, mut cnt) = (0.0f64, 0.0f64);
            for (t, y) in &seen {
                let x = displacement(&p, q[*t]).apply(&p.com);
                ss += (y - x).norm_squared() / 3.0;
                cnt += 1.0;
            }
            let rms = (ss / cnt.max(1.0)).sqrt().max(1e-4);
            mu[3] = ((rms / model.noise_median_m).ln() / model.noise_log_sd).clamp(-3.0, 3.0);
            for j in 0..np {
                theta[b.mu + j] = mu[j];
                theta[b.log_s + j] = cfg.init_global_sd.ln();
            }
            if let Some((qm, qs)) = b.q {
                for t in 0..k_frames {
                    theta[qm + t] = q[t];
                    theta[qs + t] = cfg.init_coordinate_sd_m.ln();
                    lr[qm + t] = cfg.lr_coordinate_m;
                }
            }
        }
        for k in 0..3 {
            lr[layout.type_logits[i] + k] = cfg.lr_logits;
        }
        for j in 0..=ev.parts.len() {
            lr[layout.parent_logits[i] + j] = cfg.lr_logits;
            if j == i + 1 {
                theta[layout.parent_logits[i] + j] = -1e9;
                lr[layout.parent_logits[i] + j] = 0.0;
            }
        }
    }
}

#[allow(clippy::too_many_arguments)]
fn summarise(
    ev: &Evidence,
    model: &ModelConfig,
    cfg: &SviConfig,
    layout: &Layout,
    theta: &[f64],
    type_logits: &[[f64; 3]],
    parent_logits: &[Vec<f64>],
    elbo: f64,
    iterations: usize,
    started: Instant,
    rng: &mut ChaCha8Rng,
) -> Posterior {
    let n = ev.parts.len();
    let marg = tree::parent_marginals(parent_logits, 2000, rng);
    // MAP tree: the most frequent hard sample.
    let mut counts: std::collections::HashMap<Vec<usize>, usize> = std::collections::HashMap::new();
    for _ in 0..500 {
        *counts.entry(tree::sample(parent_logits, 1.0, 0.5, rng).parent).or_default() += 1;
    }
    let map_tree = counts.into_iter().max_by_key(|(_, c)| *c).map(|(t, _)| t).unwrap_or(vec![0; n]);
    let mut joints = Vec::new();
    for i in 0..n {
        let probs = softmax(&type_logits[i]);
        let type_probs = [probs[0], probs[1], probs[2]];
        let map_type = JointType::ALL[(0..3).max_by(|&a, &b| probs[a].total_cmp(&probs[b])).unwrap_or(0)];
        // The axis of the more probable movable type.
        let axis_type = if probs[2] >= probs[1] { JointType::Revolute } else { JointType::Prismatic };
        let b = layout.blocks[i][axis_type.index()];
        let axis = Some(axis_summary(ev, i, &b, theta, model, cfg.summary_samples, rng));
        let mean_params: [JointParams<f64>; 3] = JointType::ALL.map(|jt| {
            let bl = layout.blocks[i][jt.index()];
            decode::<f64>(jt, &theta[bl.mu..bl.mu + jt.num_params()], &ev.parts[i].com0, model)
        });
        let coordinates: [Vec<f64>; 3] = JointType::ALL.map(|jt| match layout.blocks[i][jt.index()].q {
            Some((qm, _)) => (0..ev.len()).map(|t| if t == 0 { 0.0 } else { theta[qm + t] }).collect(),
            None => vec![0.0; ev.len()],
        });
        let parent_probs: Vec<(u32, f64)> = (0..=n)
            .filter(|&j| j != i + 1)
            .map(|j| (if j == 0 { 0 } else { ev.parts[j - 1].label }, marg[i][j]))
            .collect();
        let parent = map_tree[i];
        joints.push(JointSummary {
            child: ev.parts[i].label,
            parent: if parent == 0 { 0 } else { ev.parts[parent - 1].label },
            parent_index: parent,
            parent_probs,
            type_probs,
            map_type,
            axis,
            mean_params,
            coordinates,
        });
    }
    Posterior {
        joints,
        elbo,
        iterations,
        runtime_s: started.elapsed().as_secs_f64(),
    }
}

fn axis_summary(ev: &Evidence, i: usize, b: &Block, theta: &[f64], model: &ModelConfig, samples: usize, rng: &mut ChaCha8Rng) -> AxisSummary {
    let np = b.joint.num_params();
    let mean = decode::<f64>(b.joint, &theta[b.mu..b.mu + np], &ev.parts[i].com0, model);
    let (mut dirs, mut points) = (Vec::new(), Vec::new());
    for _ in 0..samples.max(2) {
        let xi: Vec<f64> = (0..np)
            .map(|j| theta[b.mu + j] + theta[b.log_s + j].exp() * { let e: f64 = StandardNormal.sample(rng); e })
            .collect();
        let p = decode::<f64>(b.joint, &xi, &ev.parts[i].com0, model);
        let d = if p.direction.dot(&mean.direction) < 0.0 { -p.direction } else { p.direction };
        dirs.push(d);
        // The point of the axis line closest to the part's centre of mass.
        let foot = p.point + d * (p.com - p.point).dot(&d);
        points.push(foot);
    }
    let m = dirs.iter().sum::<Vector3<f64>>();
    let dir = m / m.norm();
    let sd_deg = (dirs.iter().map(|d| d.dot(&dir).clamp(-1.0, 1.0).acos().powi(2)).sum::<f64>() / dirs.len() as f64).sqrt().to_degrees();
    let (point, point_sd) = if b.joint == JointType::Revolute {
        let pm = points.iter().sum::<Vector3<f64>>() / points.len() as f64;
        let sd = (points.iter().map(|p| (p - pm).norm_squared()).sum::<f64>() / points.len() as f64).sqrt();
        (Some(pm), sd)
    } else {
        (None, f64::NAN)
    };
    AxisSummary { joint: b.joint, direction: dir, direction_sd_deg: sd_deg, point, point_sd_m: point_sd }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::likelihood::PartSeries;

    /// The dual-number gradient of a block's log-likelihood matches central finite differences.
    #[test]
    fn block_gradient_matches_finite_differences() {
        let model = ModelConfig::default();
        let k = 12;
        let obs = (0..k)
            .map(|t| {
                let a = 0.08 * t as f64;
                Some((Vector3::new(0.5 * a.cos() + 0.003, 0.5 * a.sin(), 0.8 + 0.002 * t as f64), 0.002))
            })
            .collect();
        let ev = Evidence {
            times: (0..k).map(|t| t as f64 / 30.0).collect(),
            window_start: (0..k).map(|t| t == 0).collect(),
            parts: vec![PartSeries {
                label: 1,
                com0: Vector3::new(0.5, 0.0, 0.8),
                obs,
                normal0: Some(Vector3::new(1.0, 0.0, 0.0)),
                normals: (0..k).map(|t| { let a = 0.07 * t as f64; Some((Vector3::new(a.cos(), a.sin(), 0.0), 0.02)) }).collect(),
            }],
        };
        let pre = vec![Displacement::identity(); k];
        for joint in [JointType::Prismatic, JointType::Revolute] {
            let np = joint.num_params();
            let xi: Vec<f64> = (0..np).map(|j| 0.3 * ((j as f64) * 1.7).sin() + if j == 4 { 2.0 } else { 0.0 }).collect();
            let q: Vec<f64> = (0..k).map(|t| 0.04 * t as f64).collect();
            let (_, gx, gq) = block_pass(&ev, 0, joint, &xi, &q, &pre, &[], &model);
            let h = 1e-6;
            for j in 0..np {
                let (mut a, mut b) = (xi.clone(), xi.clone());
                a[j] += h;
                b[j] -= h;
                let fd = (block_pass(&ev, 0, joint, &a, &q, &pre, &[], &model).0 - block_pass(&ev, 0, joint, &b, &q, &pre, &[], &model).0) / (2.0 * h);
                assert!((fd - gx[j]).abs() <= 1e-4 * (1.0 + fd.abs()), "{joint:?} xi[{j}]: fd {fd} vs dual {}", gx[j]);
            }
            for t in [1, 5, 11] {
                let (mut a, mut b) = (q.clone(), q.clone());
                a[t] += h;
                b[t] -= h;
                let fd = (block_pass(&ev, 0, joint, &xi, &a, &pre, &[], &model).0 - block_pass(&ev, 0, joint, &xi, &b, &pre, &[], &model).0) / (2.0 * h);
                assert!((fd - gq[t]).abs() <= 1e-4 * (1.0 + fd.abs()), "{joint:?} q[{t}]: fd {fd} vs dual {}", gq[t]);
            }
        }
    }

    #[test]
    fn straight_through_and_categorical_gradients_match_finite_differences() {
        let l = [0.3, -1.0, 0.7];
        let a = [-1.0, 0.5, 0.2];
        let (_, g) = categorical_kl_grad(&l, &a);
        for j in 0..3 {
            let (mut p, mut m) = (l, l);
            p[j] += 1e-6;
            m[j] -= 1e-6;
            let fd = (categorical_kl_grad(&p, &a).0 - categorical_kl_grad(&m, &a).0) / 2e-6;
            assert!((fd - g[j]).abs() < 1e-6, "{fd} {}", g[j]);
        }
        // ST: J^T f of softmax(z / tau) against finite differences of sum_k softmax_k f_k.
        let (z, f, tau) = ([0.1, 0.4, -0.2], [3.0, -1.0, 0.5], 0.5);
        let soft = softmax(&z.map(|v| v / tau));
        let g = st_grad(&soft, &f, tau);
        for j in 0..3 {
            let (mut p, mut m) = (z, z);
            p[j] += 1e-6;
            m[j] -= 1e-6;
            let val = |z: [f64; 3]| softmax(&z.map(|v| v / tau)).iter().zip(&f).map(|(s, f)| s * f).sum::<f64>();
            assert!(((val(p) - val(m)) / 2e-6 - g[j]).abs() < 1e-6);
        }
    }
}
