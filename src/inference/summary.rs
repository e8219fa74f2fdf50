//! Posterior summaries of a fitted guide: parent marginals and the most probable tree, joint-type
//! probabilities, axes with their spread, kinodynamic parameters with their 90% intervals.

use nalgebra::{Matrix3, Vector3};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

use super::guide::{Block, Layout};
use super::laplace::inflated;
use super::{AxisSummary, Estimate, JointSummary, Kinodynamics};
use crate::model::likelihood::Evidence;
use crate::model::{decode, dynamics, tree, JointParams, JointType, ModelConfig};

/// `softmax(z)`.
pub fn softmax(z: &[f64]) -> Vec<f64> {
    let mx = z.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    let e: Vec<f64> = z.iter().map(|v| (v - mx).exp()).collect();
    let s: f64 = e.iter().sum();
    e.iter().map(|v| v / s).collect()
}

/// Summaries of every joint. `type_logits` and `parent_logits` are the (averaged) discrete
/// guide; `samples` the number of draws used for spreads; `inflation[i][type]` the variance
/// inflation factor of the physics prior's correlated deviations, or of the windows'
/// disagreement where that is larger (see `svi::variance_inflation`, [`super::laplace::cluster_inflation`]),
/// by which the kinodynamic intervals are widened: the physics part
/// of the guide's precision (its inverse covariance minus the standard-normal prior's identity)
/// is divided by it ([`inflated`]).
#[allow(clippy::too_many_arguments)]
pub fn joints(
    ev: &Evidence,
    model: &ModelConfig,
    layout: &Layout,
    theta: &[f64],
    inflation: &[[f64; 3]],
    axis_inflation: &[f64],
    type_logits: &[[f64; 3]],
    parent_logits: &[Vec<f64>],
    samples: usize,
    rng: &mut ChaCha8Rng,
) -> Vec<JointSummary> {
    let n = ev.parts.len();
    let sampler = tree::Sampler::new(parent_logits);
    let marg = sampler.parent_marginals(2000, rng);
    // The most probable tree: the most frequent hard sample.
    let mut counts: std::collections::HashMap<Vec<usize>, usize> = std::collections::HashMap::new();
    for _ in 0..500 {
        *counts.entry(sampler.draw(1.0, 0.5, rng).parent).or_default() += 1;
    }
    let map_tree = counts.into_iter().max_by(|a, b| a.1.cmp(&b.1).then(b.0.cmp(&a.0))).map(|(t, _)| t).unwrap_or(vec![0; n]);
    (0..n)
        .map(|i| {
            let probs = softmax(&type_logits[i]);
            let type_probs = [probs[0], probs[1], probs[2]];
            let map_type = JointType::ALL[(0..3).max_by(|&a, &b| probs[a].total_cmp(&probs[b])).unwrap_or(0)];
            // The axis and kinodynamics of the more probable movable type.
            let axis_type = if probs[2] >= probs[1] { JointType::Revolute } else { JointType::Prismatic };
            let b = layout.blocks[i][axis_type.index()];
            let axis = Some(axis_summary(ev, i, &b, theta, model, axis_inflation[i], samples, rng).with_model_discrepancy(model));
            let kinodynamics = b.kd.map(|kd| {
                let mean = kd.mean(theta);
                let l = kd.factor(theta);
                let cov = inflated(&l * l.transpose(), inflation[i][axis_type.index()]);
                let est = |j: usize, (median, sd_log): (f64, f64)| {
                    let (median, sd, q05, q95) = dynamics::log_normal_summary(median, sd_log, mean[j], cov[(j, j)].sqrt(), model.dynamics.discrepancy_log_sd);
                    Estimate { median, sd, q05, q95 }
                };
                let [d, f, m] = dynamics::prior_scales(axis_type, &model.dynamics);
                // The block's covariance in the parameters' logs: `ln p = ln median + sd_log * x`.
                let scale = Matrix3::from_diagonal(&Vector3::new(d.1, f.1, m.1));
                let log_cov = scale * cov.fixed_view::<3, 3>(0, 0) * scale;
                Kinodynamics {
                    damping: est(0, d),
                    friction: est(1, f),
                    mass: est(2, m),
                    inflation: inflation[i][axis_type.index()].max(1.0),
                    log_correlation: log_correlation(&log_cov, model.dynamics.discrepancy_log_sd),
                }
            });
            let mean_params: [JointParams<f64>; 3] = JointType::ALL.map(|jt| {
                let bl = layout.blocks[i][jt.index()];
                decode::<f64>(jt, &theta[bl.mu..bl.mu + jt.num_params()], &ev.parts[i].com0, model)
            });
            let coordinates: [Vec<f64>; 3] = JointType::ALL.map(|jt| match layout.blocks[i][jt.index()].q {
                Some((qm, _)) => (0..ev.len()).map(|t| theta[qm + t]).collect(),
                None => vec![0.0; ev.len()],
            });
            let parent_probs: Vec<(u32, f64)> =
                (0..=n).filter(|&j| j != i + 1).map(|j| (if j == 0 { 0 } else { ev.parts[j - 1].label }, marg[i][j])).collect();
            let parent = map_tree[i];
            JointSummary {
                child: ev.parts[i].label,
                parent: if parent == 0 { 0 } else { ev.parts[parent - 1].label },
                parent_index: parent,
                parent_probs,
                type_probs,
                map_type,
                axis,
                kinodynamics,
                mean_params,
                coordinates,
            }
        })
        .collect()
}

/// The axis of block `b` of part `i`: mean direction and point (the point of the axis closest to
/// the part's centre of mass), their spreads, and the 90% quantile of the angle between sampled
/// directions and the mean (the radius of the 90% credible cone).
#[allow(clippy::too_many_arguments)]
fn axis_summary(ev: &Evidence, i: usize, b: &Block, theta: &[f64], model: &ModelConfig, inflation: f64, samples: usize, rng: &mut ChaCha8Rng) -> AxisSummary {
    let np = b.joint.num_params();
    let widen = inflation.max(1.0).sqrt();
    let mean = decode::<f64>(b.joint, &theta[b.mu..b.mu + np], &ev.parts[i].com0, model);
    // The estimate from the guide's draws, the spreads from the same draws widened by the
    // inflation (so that widening never moves the estimate).
    let (mut draws, mut wide) = (Vec::new(), Vec::new());
    for _ in 0..samples.max(2) {
        let e: Vec<f64> = (0..np).map(|_| StandardNormal.sample(rng)).collect();
        let draw = |w: f64| -> Vec<f64> { (0..np).map(|j| theta[b.mu + j] + theta[b.log_s + j].exp() * w * e[j]).collect() };
        draws.push(decode::<f64>(b.joint, &draw(1.0), &ev.parts[i].com0, model));
        wide.push(decode::<f64>(b.joint, &draw(widen), &ev.parts[i].com0, model));
    }
    AxisSummary { inflation: widen * widen, ..axis_from_draws(b.joint, &mean.direction, &draws, &wide) }
}

/// An axis summary from posterior draws of a joint's parameters: the mean direction (draws
/// flipped onto the side of `reference`) and the mean of the axis points closest to each draw's
/// centre of mass (revolute) from `draws`; the spreads (RMS angle and distance, 90% quantile of
/// the angle) from `spread` (the same draws widened, or `draws` itself). Needs at least one draw.
pub fn axis_from_draws(joint: JointType, reference: &Vector3<f64>, draws: &[JointParams<f64>], spread: &[JointParams<f64>]) -> AxisSummary {
    let on_axis = |p: &JointParams<f64>| {
        let d = if p.direction.dot(reference) < 0.0 { -p.direction } else { p.direction };
        (d, p.point + d * (p.com - p.point).dot(&d))
    };
    let (dirs, points): (Vec<Vector3<f64>>, Vec<Vector3<f64>>) = draws.iter().map(on_axis).unzip();
    let (wide_dirs, wide_points): (Vec<Vector3<f64>>, Vec<Vector3<f64>>) = spread.iter().map(on_axis).unzip();
    let m = dirs.iter().sum::<Vector3<f64>>();
    let dir = m / m.norm();
    let mut angles: Vec<f64> = wide_dirs.iter().map(|d| d.dot(&dir).clamp(-1.0, 1.0).acos().to_degrees()).collect();
    let sd_deg = (angles.iter().map(|a| a * a).sum::<f64>() / angles.len() as f64).sqrt();
    angles.sort_by(|a, b| a.total_cmp(b));
    let q90 = angles[((angles.len() - 1) as f64 * 0.9).round() as usize];
    let (point, point_sd) = if joint == JointType::Revolute {
        let pm = points.iter().sum::<Vector3<f64>>() / points.len() as f64;
        let sd = (wide_points.iter().map(|p| (p - pm).norm_squared()).sum::<f64>() / wide_points.len() as f64).sqrt();
        (Some(pm), sd)
    } else {
        (None, f64::NAN)
    };
    AxisSummary {
        joint,
        direction: dir,
        direction_sd_deg: sd_deg,
        direction_q90_deg: q90,
        point,
        point_sd_m: point_sd,
        inflation: 1.0,
        discrepancy_deg: 0.0,
        posterior_sd_deg: sd_deg,
        posterior_q90_deg: q90,
        point_discrepancy_m: 0.0,
        point_posterior_sd_m: point_sd,
    }
}

/// `axis` with its spreads widened for a variance inflation `inflation` (>= 1; less counts as 1):
/// every sampled direction's angle to the estimate and every sampled point's distance to the
/// estimated point times `sqrt(inflation)`, so the RMS angle, the 90% cone and the point spread
/// scale by it and the estimate stays. Why in these terms and not in the standardised
/// coordinates of the draws: a joint's direction is `v / |v|` of its coordinates `v`
/// ([`crate::model::prismatic`], [`crate::model::revolute`]), whose length the data do not fix,
/// so widening `v` about the draws' mean widens the angles by more than the factor wherever
/// `|v|` varies (on `left_door_001`, NUTS's direction spread by 3.8 for a factor of 1.6).
pub fn widened(axis: AxisSummary, inflation: f64) -> AxisSummary {
    let inflation = inflation.max(1.0);
    let w = inflation.sqrt();
    let (sd, q90) = (axis.posterior_sd_deg * w, (axis.posterior_q90_deg * w).min(180.0));
    let (d, p) = (axis.discrepancy_deg, axis.point_discrepancy_m);
    AxisSummary { point_posterior_sd_m: axis.point_posterior_sd_m * w, inflation, posterior_sd_deg: sd, posterior_q90_deg: q90, ..axis }.with_discrepancy(d, p)
}

/// The correlation matrix of the covariance `cov` (3x3, of the kinodynamic parameters' logs)
/// once an independent log discrepancy of sd `discrepancy` is added to each variance (as
/// [`dynamics::log_normal_summary`] adds it to each interval). A parameter whose variance is not
/// positive and finite is uncorrelated with the others.
pub fn log_correlation(cov: &Matrix3<f64>, discrepancy: f64) -> Matrix3<f64> {
    let var = |j: usize| cov[(j, j)] + discrepancy * discrepancy;
    Matrix3::from_fn(|j, k| {
        if j == k {
            return 1.0;
        }
        let (a, b) = (var(j), var(k));
        let r = cov[(j, k)] / (a * b).sqrt();
        if a > 0.0 && b > 0.0 && r.is_finite() {
            r.clamp(-1.0, 1.0)
        } else {
            0.0
        }
    })
}

/// The sample covariance (3x3) of the logs of draws `v` (each `[damping, friction, mass]`); the
/// zero matrix for fewer than two draws or any draw not positive.
pub fn log_covariance(v: &[[f64; 3]]) -> Matrix3<f64> {
    if v.len() < 2 || v.iter().flatten().any(|x| !(*x > 0.0)) {
        return Matrix3::zeros();
    }
    let logs: Vec<Vector3<f64>> = v.iter().map(|x| Vector3::new(x[0].ln(), x[1].ln(), x[2].ln())).collect();
    let mean = logs.iter().sum::<Vector3<f64>>() / logs.len() as f64;
    logs.iter().map(|x| (x - mean) * (x - mean).transpose()).sum::<Matrix3<f64>>() / (logs.len() - 1) as f64
}

/// Median, standard deviation and 5% / 95% quantiles of draws of a scalar (at least one; NaNs
/// sort last).
pub fn estimate_from_draws(v: &[f64]) -> Estimate {
    let mut v = v.to_vec();
    v.sort_by(|a, b| a.total_cmp(b));
    let q = |p: f64| v[((v.len() - 1) as f64 * p).round() as usize];
    let mean = v.iter().sum::<f64>() / v.len() as f64;
    let sd = (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (v.len() as f64 - 1.0).max(1.0)).sqrt();
    Estimate { median: q(0.5), sd, q05: q(0.05), q95: q(0.95) }
}

/// A positive parameter's estimate from draws (`e`, median > 0) times `exp(delta)` with an
/// independent model discrepancy `delta ~ N(0, discrepancy^2)` (log-sd; 0 for none), as
/// [`dynamics::log_normal_summary`] gives SVI's: each half of the 90% interval in log space,
/// `ln(median / q05)` and `ln(q95 / median)`, becomes its root-sum-square with `1.645 *
/// discrepancy` (exact for a log-normal posterior, each side apart for a skewed one), the median
/// stays, and the sd scales with the interval's width. `e` unchanged when its median is not positive.
pub fn with_log_discrepancy(e: Estimate, discrepancy: f64) -> Estimate {
    const Z: f64 = 1.644_853_6;
    if !(e.median > 0.0) || !(discrepancy > 0.0) {
        return e;
    }
    let lm = e.median.ln();
    let widen = |half: f64| half.max(0.0).hypot(Z * discrepancy);
    let (q05, q95) = ((lm - widen(lm - e.q05.max(f64::MIN_POSITIVE).ln())).exp(), (lm + widen(e.q95.ln() - lm)).exp());
    let sd = if e.q95 > e.q05 {
        e.sd * (q95 - q05) / (e.q95 - e.q05)
    } else {
        // A point mass: the discrepancy's own log-normal sd.
        dynamics::log_normal_summary(e.median, 1.0, 0.0, 0.0, discrepancy).1
    };
    Estimate { median: e.median, sd, q05, q95 }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    /// The discrepancy widens an estimate as [`dynamics::log_normal_summary`] widens SVI's: a
    /// log-normal posterior's draws give its interval, and a point mass the discrepancy's own;
    /// the median never moves.
    #[test]
    fn log_discrepancy_widens_like_the_log_normal_summary() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let (median, s, delta) = (2.0_f64, 0.05, 0.1);
        let draws: Vec<f64> = (0..200_000).map(|_| median * (s * { let z: f64 = StandardNormal.sample(&mut rng); z }).exp()).collect();
        let e = with_log_discrepancy(estimate_from_draws(&draws), delta);
        let (m, _, q05, q95) = dynamics::log_normal_summary(median, 1.0, 0.0, s, delta);
        assert!((e.median / m - 1.0).abs() < 2e-3 && (e.q05 / q05 - 1.0).abs() < 3e-3 && (e.q95 / q95 - 1.0).abs() < 3e-3, "{e:?} vs {q05}..{q95}");
        let point = with_log_discrepancy(Estimate { median, sd: 0.0, q05: median, q95: median }, delta);
        let (_, sd, q05, q95) = dynamics::log_normal_summary(median, 1.0, 0.0, 0.0, delta);
        assert_eq!(point.median, median);
        assert!((point.q05 / q05 - 1.0).abs() < 1e-12 && (point.q95 / q95 - 1.0).abs() < 1e-12 && (point.sd / sd - 1.0).abs() < 1e-12, "{point:?}");
        let none = with_log_discrepancy(e, 0.0);
        assert_eq!((none.q05, none.q95), (e.q05, e.q95));
    }

    /// The kinodynamic correlation: the draws' log covariance gives back the correlation they were
    /// drawn with; the discrepancy, independent on each parameter, weakens it by the variances it
    /// adds; a parameter without variance is uncorrelated.
    #[test]
    fn log_correlation_of_draws_and_with_the_discrepancy() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        // ln(damping, friction, mass) with sds 0.4, 0.8, 0.2 and correlations -0.7, 0.3, 0.
        let sd: Vector3<f64> = Vector3::new(0.4, 0.8, 0.2);
        let r = Matrix3::new(1.0, -0.7, 0.3, -0.7, 1.0, 0.0, 0.3, 0.0, 1.0);
        let l = r.cholesky().expect("positive definite").l();
        let draws: Vec<[f64; 3]> = (0..50_000)
            .map(|_| {
                let z: Vector3<f64> = l * Vector3::from_fn(|_, _| StandardNormal.sample(&mut rng));
                [2.0 * (sd[0] * z[0]).exp(), 0.5 * (sd[1] * z[1]).exp(), 1.5 * (sd[2] * z[2]).exp()]
            })
            .collect();
        let cov = log_covariance(&draws);
        let back = log_correlation(&cov, 0.0);
        assert!((back - r).abs().max() < 0.02, "{back}");
        assert!((cov[(1, 1)] / 0.64 - 1.0).abs() < 0.03, "{cov}");
        let delta = 0.3;
        let weak = log_correlation(&cov, delta);
        let expect = cov[(0, 1)] / ((cov[(0, 0)] + delta * delta) * (cov[(1, 1)] + delta * delta)).sqrt();
        assert!((weak[(0, 1)] - expect).abs() < 1e-12 && weak[(0, 1)].abs() < back[(0, 1)].abs(), "{weak}");
        assert_eq!(weak, weak.transpose());
        let flat = Matrix3::new(1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0);
        assert_eq!(log_correlation(&flat, 0.0), Matrix3::identity());
        assert_eq!(log_covariance(&draws[..1]), Matrix3::zeros());
    }

    /// Directions about z tilted by an isotropic Gaussian of `sd` rad per direction across it, as
    /// prismatic joint parameters.
    fn tilted(rng: &mut ChaCha8Rng, n: usize, sd: f64) -> Vec<JointParams<f64>> {
        (0..n)
            .map(|_| {
                let (a, b): (f64, f64) = (StandardNormal.sample(rng), StandardNormal.sample(rng));
                let direction = Vector3::new(sd * a, sd * b, 1.0).normalize();
                JointParams { joint: JointType::Prismatic, com: Vector3::zeros(), noise: 0.0, rot_noise: 0.0, direction, point: Vector3::zeros(), radius: 0.0 }
            })
            .collect()
    }

    /// The discrepancy added in quadrature gives the spreads of draws tilted once more by an
    /// independent tilt of that sd (Monte Carlo, 20,000 draws: within 3%); it moves no direction,
    /// keeps the posterior's own spreads, and widening afterwards widens only the posterior's
    /// part (the discrepancy is added once).
    #[test]
    fn the_axis_discrepancy_adds_an_independent_tilt() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let (post_sd, disc_sd) = (1.0_f64.to_radians(), 1.6_f64.to_radians());
        let draws = tilted(&mut rng, 20_000, post_sd);
        let axis = axis_from_draws(JointType::Prismatic, &Vector3::z(), &draws, &draws);
        let with = axis.clone().with_discrepancy(1.6, 0.0);
        // The same draws with a second, independent tilt.
        let both: Vec<JointParams<f64>> = draws
            .iter()
            .zip(tilted(&mut rng, 20_000, disc_sd))
            .map(|(d, t)| {
                let (a, b) = (t.direction.x / t.direction.z, t.direction.y / t.direction.z);
                let v = d.direction / d.direction.z + Vector3::new(a, b, 0.0);
                JointParams { direction: v.normalize(), ..*d }
            })
            .collect();
        let sampled = axis_from_draws(JointType::Prismatic, &Vector3::z(), &both, &both);
        for (got, want, what) in [(with.direction_sd_deg, sampled.direction_sd_deg, "RMS angle"), (with.direction_q90_deg, sampled.direction_q90_deg, "90% cone")] {
            assert!((got / want - 1.0).abs() < 0.03, "{what}: {got:.4} deg in quadrature, {want:.4} deg sampled");
        }
        assert_eq!(with.direction, axis.direction);
        assert_eq!((with.posterior_sd_deg, with.posterior_q90_deg, with.discrepancy_deg), (axis.direction_sd_deg, axis.direction_q90_deg, 1.6));
        let none = axis.clone().with_discrepancy(0.0, 0.0);
        assert_eq!((none.direction_sd_deg, none.direction_q90_deg), (axis.direction_sd_deg, axis.direction_q90_deg));
        let wide = widened(with.clone(), 4.0);
        assert!((wide.posterior_q90_deg - 2.0 * axis.direction_q90_deg).abs() < 1e-9, "{wide:?}");
        assert!((wide.direction_q90_deg - wide.posterior_q90_deg.hypot(crate::inference::RAYLEIGH_Q90 * 1.6)).abs() < 1e-9, "{wide:?}");
    }

    /// A point discrepancy added in quadrature gives the RMS distance of points displaced once
    /// more by an independent isotropic displacement across the axis (Monte Carlo, 20,000 draws:
    /// within 3%); it moves no point, keeps the posterior's own spread, leaves a prismatic axis
    /// (no point) alone, and survives widening once.
    #[test]
    fn the_point_discrepancy_adds_an_independent_displacement() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let (post, disc) = (0.004, 0.01);
        let revolute = |x: f64, y: f64| JointParams {
            joint: JointType::Revolute,
            com: Vector3::new(0.3, 0.0, 0.0),
            noise: 0.0,
            rot_noise: 0.0,
            direction: Vector3::z(),
            point: Vector3::new(x, y, 0.0),
            radius: 0.3,
        };
        let mut normal = || -> f64 { StandardNormal.sample(&mut rng) };
        let (mut draws, mut both) = (Vec::new(), Vec::new());
        for _ in 0..20_000 {
            let (x, y) = (post * normal(), post * normal());
            draws.push(revolute(x, y));
            both.push(revolute(x + disc * normal(), y + disc * normal()));
        }
        let axis = axis_from_draws(JointType::Revolute, &Vector3::z(), &draws, &draws);
        let with = axis.clone().with_discrepancy(0.0, disc);
        let sampled = axis_from_draws(JointType::Revolute, &Vector3::z(), &both, &both);
        assert!((with.point_sd_m / sampled.point_sd_m - 1.0).abs() < 0.03, "{:.5} m in quadrature, {:.5} m sampled", with.point_sd_m, sampled.point_sd_m);
        assert_eq!((with.point, with.point_posterior_sd_m, with.point_discrepancy_m), (axis.point, axis.point_sd_m, disc));
        let wide = widened(with, 4.0);
        assert!((wide.point_sd_m - (2.0 * axis.point_sd_m).hypot(std::f64::consts::SQRT_2 * disc)).abs() < 1e-12, "{wide:?}");
        let slider = axis_from_draws(JointType::Prismatic, &Vector3::z(), &tilted(&mut rng, 10, 0.01), &tilted(&mut rng, 10, 0.01));
        let slider = slider.with_discrepancy(1.0, disc);
        assert!(slider.point_sd_m.is_nan() && slider.point_discrepancy_m == 0.0, "{slider:?}");
    }
}
