//! SVG figures of model criticism (`bom replay --plot DIR`, plotters): per movable part, the
//! observed joint coordinate of every held-out window against the model's prediction from the
//! window's start — before and after the effect criticism added, or the current model's alone.

use std::path::{Path, PathBuf};

use plotters::prelude::*;

use crate::criticism::ResidualPoint;
use crate::pipeline::Run;

/// Write the figures into `dir` (created if missing); returns the files written.
///
/// # Errors
/// A one-line description naming the file.
pub fn write_criticism_plots(run: &Run, dir: &Path) -> Result<Vec<PathBuf>, String> {
    std::fs::create_dir_all(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let mut written = Vec::new();
    let Some(last) = run.updates.last() else { return Ok(written) };
    for part in &last.criticism.parts {
        let findings: Vec<_> = run.findings.iter().filter(|f| f.part == part.label).collect();
        if findings.is_empty() {
            let path = dir.join(format!("part{}_residual.svg", part.label));
            let title = format!("part {}: held-out prediction, RMSE {:.4} m (noise level {:.4} m)", part.label, part.rmse_m, part.noise_rmse_m);
            figure(&path, &title, &part.residuals, None)?;
            written.push(path);
        }
        for f in findings {
            let path = dir.join(format!("part{}_{}.svg", part.label, f.name()));
            let title = match f.effect {
                Some(_) => format!("part {}: {} added, held-out RMSE {:.4} m -> {:.4} m", f.part, f.name(), f.rmse_before_m, f.rmse_after_m),
                None => format!("part {}: unexplained residual, held-out RMSE {:.4} m", f.part, f.rmse_before_m),
            };
            figure(&path, &title, &f.before, f.effect.is_some().then_some(&f.after[..]))?;
            written.push(path);
        }
    }
    Ok(written)
}

/// One figure: observed coordinates (dots), predictions before (red) and after (blue), one line
/// per window.
fn figure(path: &Path, title: &str, before: &[ResidualPoint], after: Option<&[ResidualPoint]>) -> Result<(), String> {
    let err = |e: &dyn std::fmt::Display| format!("{}: {e}", path.display());
    let all = before.iter().chain(after.unwrap_or_default());
    let (mut t0, mut t1, mut y0, mut y1) = (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
    for p in all {
        t0 = t0.min(p.t);
        t1 = t1.max(p.t);
        y0 = y0.min(p.observed.min(p.predicted));
        y1 = y1.max(p.observed.max(p.predicted));
    }
    if !(t0 < t1) {
        (t0, t1) = (0.0, 1.0);
    }
    if !(y0 < y1) {
        (y0, y1) = (-0.01, 0.01);
    }
    let pad = 0.05 * (y1 - y0);
    let root = SVGBackend::new(path, (900, 420)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 18))
        .margin(12)
        .x_label_area_size(36)
        .y_label_area_size(64)
        .build_cartesian_2d(t0..t1, (y0 - pad)..(y1 + pad))
        .map_err(|e| err(&e))?;
    chart.configure_mesh().x_desc("time [s]").y_desc("joint coordinate [m of path]").draw().map_err(|e| err(&e))?;
    chart
        .draw_series(before.iter().map(|p| Circle::new((p.t, p.observed), 2, BLACK.filled())))
        .map_err(|e| err(&e))?
        .label("observed")
        .legend(|(x, y)| Circle::new((x + 10, y), 3, BLACK.filled()));
    let mut lines = vec![(before, RED, if after.is_some() { "predicted before" } else { "predicted" })];
    if let Some(a) = after {
        lines.push((a, BLUE, "predicted after"));
    }
    for (points, colour, label) in lines {
        let mut windows: Vec<usize> = points.iter().map(|p| p.window).collect();
        windows.dedup();
        for (k, w) in windows.iter().enumerate() {
            let series = chart
                .draw_series(LineSeries::new(points.iter().filter(|p| p.window == *w).map(|p| (p.t, p.predicted)), colour.stroke_width(2)))
                .map_err(|e| err(&e))?;
            if k == 0 {
                series.label(label).legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2)));
            }
        }
    }
    chart.configure_series_labels().background_style(WHITE.mix(0.8)).border_style(BLACK).draw().map_err(|e| err(&e))?;
    root.present().map_err(|e| err(&e))
}
