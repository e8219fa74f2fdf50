//! The human summaries printed by `bom replay` and `bom predict`.

use std::fmt::Write;

use crate::criticism::Finding;
use crate::pipeline::Run;

/// A readable table of parts, windows and joints.
pub fn render(run: &Run) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "bom {} — {} mode, {} bag(s)", env!("CARGO_PKG_VERSION"), run.mode, run.bags.len());
    for p in &run.parts {
        let _ = writeln!(s, "  part {:>2}: {:>5} frames, {:>8.1} points/frame", p.label, p.frames, p.points_per_frame);
    }
    let _ = writeln!(s, "  windows: {}", run.windows.len());
    for w in &run.windows {
        let _ = writeln!(s, "    {:>9.3} s .. {:>9.3} s", w.start, w.end);
    }
    match &run.posterior {
        None => {
            let _ = writeln!(s, "  no posterior (no part observed inside a window)");
        }
        Some(p) => {
            let _ = writeln!(s, "  posterior: ELBO {:.1} nats, {} iterations, {:.2} s", p.elbo, p.iterations, p.runtime_s);
            if let Some(n) = &run.sampler {
                let _ = writeln!(
                    s,
                    "  BOM-NUTS: {} structure(s), {} chains x {} draws, R-hat max {:.3}, bulk ESS min {:.0}, tail ESS min {:.0}, {} divergent, {:.2} s",
                    n.structures.len(),
                    n.chains,
                    n.draws,
                    n.r_hat_max,
                    n.ess_bulk_min,
                    n.ess_tail_min,
                    n.divergences,
                    n.runtime_s
                );
            }
            let _ = writeln!(
                s,
                "  {:>5} {:>6} {:>7}  {:>6} {:>9} {:>8}  {:<24} {:>7}  {:<26} {:>8}",
                "part", "parent", "P(par)", "rigid", "prismatic", "revolute", "axis direction", "sd[deg]", "axis point [m]", "sd[m]"
            );
            for j in &p.joints {
                let ppar = j.parent_probs.iter().find(|(l, _)| *l == j.parent).map(|x| x.1).unwrap_or(f64::NAN);
                let (dir, dsd, pt, psd) = match (&j.axis, j.map_type.movable()) {
                    (Some(a), true) => (
                        format!("[{:+.3}, {:+.3}, {:+.3}]", a.direction.x, a.direction.y, a.direction.z),
                        format!("{:.2}", a.direction_sd_deg),
                        a.point.map(|p| format!("[{:+.3}, {:+.3}, {:+.3}]", p.x, p.y, p.z)).unwrap_or("-".into()),
                        if a.point_sd_m.is_finite() { format!("{:.4}", a.point_sd_m) } else { "-".into() },
                    ),
                    _ => ("-".into(), "-".into(), "-".into(), "-".into()),
                };
                let _ = writeln!(
                    s,
                    "  {:>5} {:>6} {:>7.3}  {:>6.3} {:>9.3} {:>8.3}  {:<24} {:>7}  {:<26} {:>8}   => {}",
                    j.child, j.parent, ppar, j.type_probs[0], j.type_probs[1], j.type_probs[2], dir, dsd, pt, psd, j.map_type.name()
                );
            }
        }
    }
    for line in criticism_lines(run) {
        let _ = writeln!(s, "  {line}");
    }
    if run.diagnostics.total() > 0 {
        let _ = writeln!(s, "  bad input (skipped, counted):");
        for (k, n) in run.diagnostics.counts() {
            let _ = writeln!(s, "    {n:>6} x {k}");
        }
    }
    s
}

/// Model criticism in a few lines: each part's held-out residual against its noise level, then
/// each finding (the effect added and the held-out error before and after, or the pattern of an
/// unexplained residual).
pub fn criticism_lines(run: &Run) -> Vec<String> {
    let mut out = Vec::new();
    let Some(last) = run.updates.last() else { return out };
    if last.criticism.parts.is_empty() && run.findings.is_empty() {
        return out;
    }
    out.push("model criticism (held-out windows):".into());
    for p in &last.criticism.parts {
        let rmse = if p.rmse_m.is_finite() { format!("{:.4} m", p.rmse_m) } else { "- (one window)".into() };
        out.push(format!("  part {:>2}: residual RMSE {rmse}, noise level {:.4} m", p.label, p.noise_rmse_m));
    }
    for f in &run.findings {
        out.push(format!("  {}", finding_line(f)));
    }
    out
}

/// One finding in one line: the effect added and the held-out error before and after, or the
/// pattern of an unexplained residual.
pub fn finding_line(f: &Finding) -> String {
    let params: Vec<String> = f
        .params
        .iter()
        .map(|(k, v)| match f.intervals.iter().find(|(n, _)| n == k) {
            Some((_, [lo, hi])) => format!("{k} {v:.3} [{lo:.3}, {hi:.3}]"),
            None => format!("{k} {v:.3}"),
        })
        .collect();
    match f.effect {
        Some(_) => format!(
            "part {:>2}: added {} ({}): held-out RMSE {:.4} m -> {:.4} m, ELBO +{:.1} nats",
            f.part,
            f.name(),
            params.join(", "),
            f.rmse_before_m,
            f.rmse_after_m,
            f.evidence_nats
        ),
        None => format!(
            "part {:>2}: unexplained residual, held-out RMSE {:.4} m ({}); the best effect gains {:.1} nats",
            f.part,
            f.rmse_before_m,
            params.join(", "),
            f.evidence_nats
        ),
    }
}

/// A readable summary of `bom predict`: per part, the predicted displacement of the centre of
/// mass over the horizon, its 90% band at the end, and the error against the observations.
pub fn render_prediction(p: &crate::output::json::PredictionJson) -> String {
    let mut s = String::new();
    let horizon = p.stamps.last().map_or(0.0, |t| t - p.from_s);
    let _ = writeln!(s, "bom {} — prediction from {:.3} s over {:.2} s ({} stamps, {} draws)", p.bom_version, p.from_s, horizon, p.stamps.len(), p.draws);
    let _ = writeln!(s, "  {:>5} {:>12} {:>12} {:>12} {:>12} {:>10} {:>8}", "part", "moved [m]", "band90 [m]", "RMSE [m]", "RMSE mean", "final [m]", "cover90");
    for q in &p.parts {
        let moved = match (q.com.first(), q.com.last()) {
            (Some(a), Some(b)) => ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2) + (b[2] - a[2]).powi(2)).sqrt(),
            _ => 0.0,
        };
        let opt = |x: Option<f64>, w: usize, d: usize| x.map_or(format!("{:>w$}", "-"), |x| format!("{x:>w$.d$}"));
        let _ = writeln!(
            s,
            "  {:>5} {:>12.4} {:>12.4} {} {} {} {}",
            q.label,
            moved,
            q.band_radius_m.last().copied().unwrap_or(0.0),
            opt(q.mse_m2.map(f64::sqrt), 12, 4),
            opt(q.mse_mean_m2.map(f64::sqrt), 12, 4),
            opt(q.final_error_m, 10, 4),
            opt(q.coverage_90, 8, 2)
        );
    }
    s
}
