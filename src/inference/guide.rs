//! The guide of BOM-SVI (Pyro's term for the variational family), separate from the model of
//! [`crate::model`]:
//!
//! - tree: parent logits per part, sampled by the DP-DAG sampler with opportunistic rounding
//!   ([`crate::model::tree`]);
//! - joint type: logits per part, sampled by Gumbel-softmax (paper §3.2);
//! - per part *and per joint type* `k`, `q(theta | type = k)`: a mean-field Gaussian over the
//!   type's standardised kinematic parameters and its per-frame joint coordinates, and (dynamic
//!   mode, movable types) a full-rank Gaussian over its standardised kinodynamic parameters —
//!   damping, friction and mass are strongly correlated in the posterior (a heavier door with less
//!   damping moves almost the same way), which a mean-field guide would ignore and so report
//!   intervals too narrow.
//!
//! All guide parameters live in one flat vector; [`Layout`] says where.

use nalgebra::{DMatrix, DVector, Vector3};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

use crate::model::likelihood::Evidence;
use crate::model::{decode, dynamics, Displacement, JointParams, JointType, ModelConfig};

/// A full-rank Gaussian block `xi = mu + L eps` over `dim` standardised parameters: `mu` at
/// `mu..mu+dim`, the lower triangle of `L` row by row at `chol..`, its diagonal stored as logs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KdBlock {
    pub dim: usize,
    pub mu: usize,
    pub chol: usize,
}

impl KdBlock {
    fn len(dim: usize) -> usize {
        dim + dim * (dim + 1) / 2
    }

    fn idx(&self, i: usize, j: usize) -> usize {
        self.chol + i * (i + 1) / 2 + j
    }

    /// The Cholesky factor `L`.
    pub fn factor(&self, theta: &[f64]) -> DMatrix<f64> {
        DMatrix::from_fn(self.dim, self.dim, |i, j| match i.cmp(&j) {
            std::cmp::Ordering::Greater => theta[self.idx(i, j)],
            std::cmp::Ordering::Equal => theta[self.idx(i, j)].exp(),
            std::cmp::Ordering::Less => 0.0,
        })
    }

    /// Mean of the standardised parameters.
    pub fn mean(&self, theta: &[f64]) -> DVector<f64> {
        DVector::from_column_slice(&theta[self.mu..self.mu + self.dim])
    }

    /// A reparameterised sample: `(eps, xi)`.
    pub fn sample(&self, theta: &[f64], rng: &mut ChaCha8Rng) -> (Vec<f64>, Vec<f64>) {
        let eps = DVector::from_fn(self.dim, |_, _| StandardNormal.sample(rng));
        let xi = self.mean(theta) + self.factor(theta) * &eps;
        (eps.as_slice().to_vec(), xi.as_slice().to_vec())
    }

    /// `-KL(q || N(0, I))` and its gradient (added to `grad`).
    pub fn neg_kl(&self, theta: &[f64], grad: &mut [f64]) -> f64 {
        let l = self.factor(theta);
        let mu = self.mean(theta);
        let mut v = 0.5 * (self.dim as f64 - mu.norm_squared() - l.norm_squared());
        for i in 0..self.dim {
            grad[self.mu + i] -= mu[i];
            v += theta[self.idx(i, i)];
            for j in 0..=i {
                // d/dL_ij of -0.5 |L|^2 is -L_ij; the log-diagonal adds its chain rule and +1.
                if i == j {
                    grad[self.idx(i, i)] += 1.0 - l[(i, i)] * l[(i, i)];
                } else {
                    grad[self.idx(i, j)] -= l[(i, j)];
                }
            }
        }
        v
    }

    /// Chain rule of a gradient `g` with respect to a sample `xi = mu + L eps` into the block's
    /// parameters, scaled by `w`.
    pub fn add_sample_grad(&self, theta: &[f64], g: &[f64], eps: &[f64], w: f64, grad: &mut [f64]) {
        for i in 0..self.dim {
            grad[self.mu + i] += w * g[i];
            for j in 0..=i {
                let d = w * g[i] * eps[j];
                grad[self.idx(i, j)] += if i == j { d * theta[self.idx(i, i)].exp() } else { d };
            }
        }
    }
}

/// Where one (part, joint type) block lives in the flat parameter vector.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Block {
    pub joint: JointType,
    /// Means and log-sds of the standardised kinematic parameters.
    pub mu: usize,
    pub log_s: usize,
    /// Means and log-sds of the per-frame coordinates (movable joints).
    pub q: Option<(usize, usize)>,
    /// Mean and log-sd (at `+1`) of the standardised velocity scale of the coordinates' random
    /// walk (kinematic mode, movable joints).
    pub vel: Option<usize>,
    /// Kinodynamic parameters (dynamic mode, movable joints).
    pub kd: Option<KdBlock>,
}

/// The layout of the guide's parameter vector.
#[derive(Debug, Clone, PartialEq)]
pub struct Layout {
    pub blocks: Vec<[Block; 3]>,
    pub type_logits: Vec<usize>,
    pub parent_logits: Vec<usize>,
    pub len: usize,
}

impl Layout {
    /// The layout for `n_parts` parts on `frames` grid frames; `kd[i]` is the number of
    /// kinodynamic parameters of part `i`'s movable types (0 in kinematic mode).
    pub fn new(n_parts: usize, frames: usize, kd: &[usize]) -> Layout {
        let mut off = 0;
        let mut take = |n: usize| {
            let o = off;
            off += n;
            o
        };
        let mut blocks = Vec::new();
        for part_kd in kd.iter().take(n_parts) {
            let b = JointType::ALL.map(|joint| {
                let p = joint.num_params();
                let (mu, log_s) = (take(p), take(p));
                let q = joint.movable().then(|| (take(frames), take(frames)));
                let vel = (joint.movable() && *part_kd == 0).then(|| take(2));
                let kd = (joint.movable() && *part_kd > 0).then(|| {
                    let dim = *part_kd;
                    let mu = take(KdBlock::len(dim));
                    KdBlock { dim, mu, chol: mu + dim }
                });
                Block { joint, mu, log_s, q, vel, kd }
            });
            blocks.push(b);
        }
        let type_logits = (0..n_parts).map(|_| take(3)).collect();
        let parent_logits = (0..n_parts).map(|_| take(n_parts + 1)).collect();
        Layout { blocks, type_logits, parent_logits, len: off }
    }
}

/// The number of kinodynamic parameters of each part in `ev` (0 in kinematic mode).
pub fn kd_dims(ev: &Evidence) -> Vec<usize> {
    ev.parts
        .iter()
        .enumerate()
        .map(|(i, _)| if ev.windows.is_empty() { 0 } else { dynamics::num_params(&ev.effects[i]) })
        .collect()
}

/// The guide after a fit, kept to warm-start the next one (a new window adds evidence).
#[derive(Debug, Clone)]
pub struct GuideState {
    pub labels: Vec<u32>,
    pub times: Vec<f64>,
    pub layout: Layout,
    pub theta: Vec<f64>,
}

/// Per-parameter learning rates of the layout.
pub fn learning_rates(layout: &Layout, global: f64, coordinate: f64, kinodynamic: f64) -> Vec<f64> {
    let mut lr = vec![global; layout.len];
    for b in layout.blocks.iter().flatten() {
        if let Some(kd) = b.kd {
            for v in lr.iter_mut().skip(kd.mu).take(KdBlock::len(kd.dim)) {
                *v = kinodynamic;
            }
        }
        if let Some((qm, _)) = b.q {
            let frames = b.q.map(|(m, s)| s - m).unwrap_or(0);
            for v in lr.iter_mut().skip(qm).take(frames) {
                *v = coordinate;
            }
        }
    }
    lr
}

/// Initialise the guide from the data: every block of part `i` from its motion relative to the
/// observed motion of its parent `parents[i]` ([`init_block`]), kinodynamics at their prior
/// medians; logits are set by the caller.
pub fn init_from_data(
    ev: &Evidence,
    model: &ModelConfig,
    layout: &Layout,
    parents: &[usize],
    init_global_sd: f64,
    init_coordinate_sd: f64,
    init_kd_sd: f64,
) -> Vec<f64> {
    let k_frames = ev.len();
    let mut theta = vec![0.0; layout.len];
    for i in 0..ev.parts.len() {
        let pre = super::structure::observed_displacements(ev, parents[i]);
        for b in &layout.blocks[i] {
            let (mu, q) = init_block(ev, i, b.joint, &pre, model);
            for (j, m) in mu.iter().enumerate() {
                theta[b.mu + j] = *m;
                theta[b.log_s + j] = init_global_sd.ln();
            }
            if let Some((qm, qs)) = b.q {
                for t in 0..k_frames {
                    theta[qm + t] = q[t];
                    theta[qs + t] = init_coordinate_sd.ln();
                }
            }
            if let Some(v) = b.vel {
                theta[v] = 0.0;
                theta[v + 1] = 0.5f64.ln();
            }
            if let Some(kd) = b.kd {
                for d in 0..kd.dim {
                    theta[kd.mu + d] = 0.0;
                    theta[kd.idx(d, d)] = init_kd_sd.ln();
                }
            }
        }
    }
    theta
}

/// Standardised parameters (means) and coordinates of joint type `joint` for part `i` from its
/// motion relative to a parent whose displacement at each grid frame is `pre`: axes by principal
/// components, observed rotations or circle fits, coordinates by projection, the noises from the
/// residuals of that fit.
pub fn init_block(ev: &Evidence, i: usize, joint: JointType, pre: &[Displacement<f64>], model: &ModelConfig) -> (Vec<f64>, Vec<f64>) {
    let part = &ev.parts[i];
    let inv: Vec<Displacement<f64>> = pre.iter().map(|d| Displacement { r: d.r.transpose(), t: -(d.r.transpose() * d.t) }).collect();
    let seen: Vec<(usize, Vector3<f64>)> = part.obs.iter().enumerate().filter_map(|(t, o)| o.map(|o| (t, inv[t].apply(&o.y)))).collect();
    let track: Vec<Vector3<f64>> = seen.iter().map(|s| s.1).collect();
    let np = joint.num_params();
    let mut mu = vec![0.0; np];
    let q_seen: Vec<f64> = match joint {
        JointType::Rigid => vec![0.0; track.len()],
        JointType::Prismatic => {
            let (v, q) = crate::model::prismatic::init(&track, &part.com0);
            mu[crate::model::rigid::NUM_PARAMS..].copy_from_slice(&v);
            q
        }
        JointType::Revolute => {
            // From the observed rotations where the part's shape shows them, else from the arc
            // of its centre of mass.
            let rots: Option<Vec<nalgebra::Matrix3<f64>>> = seen.iter().map(|(t, _)| part.rot[*t].as_ref().map(|r| inv[*t].r * r.r)).collect();
            let (v, q) = rots
                .and_then(|r| crate::model::revolute::init_from_rotations(&track, &r, &part.com0, part.reach, model))
                .unwrap_or_else(|| crate::model::revolute::init(&track, &part.com0, part.reach, model));
            mu[crate::model::rigid::NUM_PARAMS..].copy_from_slice(&v);
            q
        }
    };
    let q = hold_over_occlusions(&seen, &q_seen, ev.len());
    let p = decode::<f64>(joint, &mu, &part.com0, model);
    let (pos, rot) = residual_rms(ev, i, &p, &q, pre);
    mu[3] = ((pos.max(1e-4) / model.noise_median_m).ln() / model.noise_log_sd).clamp(-3.0, 3.0);
    if let Some(r) = rot {
        mu[4] = ((r.max(1e-4) / model.rotation_noise_median_rad).ln() / model.rotation_noise_log_sd).clamp(-3.0, 3.0);
    }
    (mu, q)
}

/// Coordinates on the whole grid from the values at the seen frames, held over occlusions (and
/// back to the start from the first seen frame).
fn hold_over_occlusions(seen: &[(usize, Vector3<f64>)], q_seen: &[f64], frames: usize) -> Vec<f64> {
    let mut q = vec![0.0; frames];
    let mut last = q_seen.first().copied().unwrap_or(0.0);
    let mut it = seen.iter().zip(q_seen).peekable();
    for (t, qt) in q.iter_mut().enumerate() {
        while let Some(((ts, _), qv)) = it.peek() {
            if *ts <= t {
                last = **qv;
                it.next();
            } else {
                break;
            }
        }
        *qt = last;
    }
    q
}

/// Root-mean-square residuals of a fit under the parent's displacements `pre`: position per axis
/// \[m\] and rotation per observable axis \[rad\] (None without rotation observations).
fn residual_rms(ev: &Evidence, i: usize, p: &JointParams<f64>, q: &[f64], pre: &[Displacement<f64>]) -> (f64, Option<f64>) {
    let part = &ev.parts[i];
    let (mut ss, mut cnt, mut rs, mut rc) = (0.0, 0.0, 0.0, 0.0);
    for t in 0..ev.len() {
        let d = pre[t].compose(&crate::model::displacement(p, q[t]));
        if let Some(o) = &part.obs[t] {
            ss += (o.y - d.apply(&p.com)).norm_squared() / 3.0;
            cnt += 1.0;
        }
        if let Some(o) = &part.rot[t] {
            let w = o.error(&d.r);
            for (a, _) in &o.axes {
                rs += w.dot(a).powi(2);
                rc += 1.0;
            }
        }
    }
    ((ss / f64::max(cnt, 1.0)).sqrt(), (rc > 0.0).then(|| (rs / rc).sqrt()))
}

impl GuideState {
    /// Carry a previous fit over to a new layout: per part label and joint type, the kinematic
    /// and kinodynamic parameters and the logits; coordinates at grid stamps both fits share.
    /// Everything else keeps the values of `theta` (initialised from the data).
    pub fn warm_start(&self, ev: &Evidence, layout: &Layout, theta: &mut [f64]) {
        let key = |t: f64| (t * 1e6).round() as i64;
        let old_t: std::collections::HashMap<i64, usize> = self.times.iter().enumerate().map(|(i, t)| (key(*t), i)).collect();
        let old_index = |label: u32| self.labels.iter().position(|&l| l == label);
        let n = ev.parts.len();
        for (i, part) in ev.parts.iter().enumerate() {
            let Some(o) = old_index(part.label) else { continue };
            for (k, b) in layout.blocks[i].iter().enumerate() {
                let ob = &self.layout.blocks[o][k];
                let np = b.joint.num_params();
                theta[b.mu..b.mu + np].copy_from_slice(&self.theta[ob.mu..ob.mu + np]);
                theta[b.log_s..b.log_s + np].copy_from_slice(&self.theta[ob.log_s..ob.log_s + np]);
                if let (Some((qm, qs)), Some((om, os))) = (b.q, ob.q) {
                    for (t, time) in ev.times.iter().enumerate() {
                        if let Some(&ot) = old_t.get(&key(*time)) {
                            theta[qm + t] = self.theta[om + ot];
                            theta[qs + t] = self.theta[os + ot];
                        }
                    }
                }
                if let (Some(v), Some(ov)) = (b.vel, ob.vel) {
                    theta[v..v + 2].copy_from_slice(&self.theta[ov..ov + 2]);
                }
                if let (Some(kd), Some(okd)) = (b.kd, ob.kd) {
                    if kd.dim == okd.dim {
                        let len = KdBlock::len(kd.dim);
                        theta[kd.mu..kd.mu + len].copy_from_slice(&self.theta[okd.mu..okd.mu + len]);
                    }
                }
            }
            let (tl, otl) = (layout.type_logits[i], self.layout.type_logits[o]);
            theta[tl..tl + 3].copy_from_slice(&self.theta[otl..otl + 3]);
            for j in 0..=n {
                let old_j = if j == 0 { Some(0) } else { old_index(ev.parts[j - 1].label).map(|x| x + 1) };
                if let Some(oj) = old_j {
                    theta[layout.parent_logits[i] + j] = self.theta[self.layout.parent_logits[o] + oj];
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    /// The full-rank block's KL and reparameterisation gradients against finite differences.
    #[test]
    fn full_rank_block_gradients() {
        let kd = KdBlock { dim: 3, mu: 0, chol: 3 };
        let mut theta: Vec<f64> = (0..KdBlock::len(3)).map(|i| 0.1 * (i as f64 * 1.3).sin()).collect();
        theta[kd.idx(1, 1)] = -0.4;
        let mut g = vec![0.0; theta.len()];
        let v = kd.neg_kl(&theta, &mut g);
        // The KL of N(mu, L L^T) against N(0, I), written out.
        let l = kd.factor(&theta);
        let cov = &l * l.transpose();
        let mu = kd.mean(&theta);
        let kl = 0.5 * (cov.trace() + mu.norm_squared() - 3.0 - cov.determinant().ln());
        assert!((v + kl).abs() < 1e-12, "{v} vs {kl}");
        for p in 0..theta.len() {
            let (mut a, mut b) = (theta.clone(), theta.clone());
            a[p] += 1e-6;
            b[p] -= 1e-6;
            let fd = (kd.neg_kl(&a, &mut [0.0; 9]) - kd.neg_kl(&b, &mut [0.0; 9])) / 2e-6;
            assert!((fd - g[p]).abs() < 1e-6, "param {p}: {fd} vs {}", g[p]);
        }
        // d/dtheta of f(xi(theta)) = a . xi for a fixed eps.
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let (eps, _) = kd.sample(&theta, &mut rng);
        let a = [0.7, -1.1, 0.4];
        let f = |th: &[f64]| {
            let xi = kd.mean(th) + kd.factor(th) * DVector::from_column_slice(&eps);
            xi.iter().zip(&a).map(|(x, a)| x * a).sum::<f64>()
        };
        let mut g = vec![0.0; theta.len()];
        kd.add_sample_grad(&theta, &a, &eps, 1.0, &mut g);
        for p in 0..theta.len() {
            let (mut x, mut y) = (theta.clone(), theta.clone());
            x[p] += 1e-6;
            y[p] -= 1e-6;
            let fd = (f(&x) - f(&y)) / 2e-6;
            assert!((fd - g[p]).abs() < 1e-6, "param {p}: {fd} vs {}", g[p]);
        }
    }
}
