//! The posterior predictive (`bom::prediction`, `bom predict`) on bundled bags: the model read
//! back from the JSON summary predicts what the posterior itself predicts; predictions follow the
//! observed parts far better than a part left standing; draws are reproducible by seed and
//! widen the band; bad input exits as the contract says.

mod common;

use std::path::PathBuf;

use bom::config::Config;
use bom::diagnostics::Diagnostics;
use bom::output::json;
use bom::pipeline;
use bom::prediction::{predict, score, PredictConfig, PredictiveModel, Scene};
use common::*;

const DRAWER: &str = "bags/mujoco/drawer.mcap";

#[test]
fn summary_json_model_predicts_like_the_posterior_and_tracks_the_drawer() {
    let cfg = Config::new();
    let run = replay(&[DRAWER.into()]);
    let post = run.posterior.as_ref().expect("posterior");
    let direct = PredictiveModel::from_posterior(post, &run.findings);
    let text = serde_json::to_string(&json::summary(&run)).unwrap();
    let read = PredictiveModel::from_summary_json(&serde_json::from_str(&text).unwrap()).unwrap();
    assert_eq!(direct.labels(), read.labels());
    // The kinodynamics' log correlation travels through the JSON with them (a rigid joint's
    // kinodynamics are not written): the drawer's damping and friction trade against each other
    // under its posterior (not the identity).
    for (d, r) in direct.joints.iter().zip(&read.joints).filter(|(_, r)| r.damping.is_some()) {
        assert!((d.log_correlation - r.log_correlation).abs().max() < 1e-9, "part {}", d.child);
    }
    let drawer = read.joints.iter().find(|j| j.child == 2).expect("the drawer");
    assert!(drawer.damping.is_some() && drawer.log_correlation[(0, 1)].abs() > 0.05, "{}", drawer.log_correlation);

    let mut diag = Diagnostics::default();
    let obs = pipeline::observe(&[PathBuf::from(DRAWER)], &cfg, &mut diag).unwrap();
    let scene = Scene { tracks: &obs.tracks, geometry: &obs.geometry, wrenches: &obs.recording.wrenches, windows: &obs.windows };
    let from = obs.windows[0].start;
    let stamps = scene.stamps();
    let pcfg = PredictConfig { draws: 30, seed: 4, ..PredictConfig::default() };
    let a = predict(&direct, &scene, from, &stamps, &pcfg, &cfg.model).unwrap();
    let b = predict(&read, &scene, from, &stamps, &pcfg, &cfg.model).unwrap();
    assert!(a.stamps.iter().all(|&t| t >= from) && a.stamps.len() > 200);
    for (p, q) in a.parts.iter().zip(&b.parts) {
        // The JSON carries the 90% intervals, not the posterior's exact log-normal: medians agree
        // to rounding, bands to a few per cent.
        let gap = p.com.iter().zip(&q.com).map(|(x, y)| (x - y).norm()).fold(0.0, f64::max);
        assert!(gap < 1e-6, "part {}: medians differ by {gap} m", p.label);
    }

    // The drawer (label 2) moves ~10 cm over four pushes; predicted open loop from before the first
    // push it stays within a few millimetres, far better than a drawer left where it was.
    let scores = score(&a, &scene);
    let drawer = scores.iter().find(|s| s.label == 2).unwrap();
    let start = a.parts[1].com[0];
    let (mut still, mut n) = (0.0, 0);
    for &t in &a.stamps {
        if let Some((y, _)) = scene.observed_com(2, t) {
            still += (y - start).norm_squared();
            n += 1;
        }
    }
    let still = still / n as f64;
    assert!(drawer.frames > 200 && drawer.mse_m2 < 0.05 * still, "drawer MSE {} vs standing still {still}", drawer.mse_m2);
    assert!(drawer.coverage_90 >= 0.8, "coverage {}", drawer.coverage_90);

    // Reproducible by seed; the band of the moving drawer opens as it moves, the cabinet's stays shut.
    let c = predict(&direct, &scene, from, &stamps, &pcfg, &cfg.model).unwrap();
    assert_eq!(a.parts[1].band_radius_m, c.parts[1].band_radius_m);
    // A stamp before the state's (a clock reset in the node's stream) is not predicted: no stamps,
    // no poses (the node then publishes nothing for that cloud, see `node::Predictor`).
    let back = predict(&direct, &scene, from, &[from - 1.0], &pcfg, &cfg.model).unwrap();
    assert!(back.stamps.is_empty() && back.parts.iter().all(|p| p.com.is_empty()));
    assert!(a.parts[1].band_radius_m.last().unwrap() > &1e-3);
    assert!(a.parts[0].band_radius_m.iter().all(|r| *r < 1e-6));
    for k in 0..a.stamps.len() {
        for ax in 0..3 {
            assert!(a.parts[1].lower[k][ax] <= a.parts[1].upper[k][ax]);
        }
    }
}

#[test]
fn bom_predict_command_and_its_exit_codes() {
    let dir = tempfile::tempdir().unwrap();
    let (model, out) = (dir.path().join("drawer.json"), dir.path().join("pred.json"));
    let (code, _, err) = bom(&["replay", DRAWER, "--json", model.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    let m = model.to_str().unwrap();
    let (code, stdout, err) = bom(&["predict", "--model", m, "--wrench", DRAWER, "--draws", "20", "--json", out.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    assert!(stdout.contains("prediction from"), "{stdout}");
    let p: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    let stamps = p["stamps"].as_array().unwrap().len();
    for part in p["parts"].as_array().unwrap() {
        assert_eq!(part["com"].as_array().unwrap().len(), stamps);
        assert_eq!(part["band_radius_m"].as_array().unwrap().len(), stamps);
        assert_eq!(part["mean"].as_array().unwrap().len(), stamps);
        assert_eq!(part["observed"].as_array().unwrap().len(), stamps);
    }

    // A bag without /applied_wrench: exit 3, one line naming the topic.
    let (code, _, err) = bom(&["predict", "--model", m, "--wrench", "bags/sturm/left_door_001.mcap"]);
    assert_eq!(code, 3, "{err}");
    assert!(err.contains("/applied_wrench") && err.trim().lines().count() == 1, "{err}");
    // A model of another object: exit 3 naming the labels.
    let other = dir.path().join("other.json");
    let (code, _, err) = bom(&["replay", "bags/mujoco/hingecabinet.mcap", "--json", other.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    let (code, _, err) = bom(&["predict", "--model", other.to_str().unwrap(), "--wrench", DRAWER]);
    assert_eq!(code, 3, "{err}");
    assert!(err.contains("labels must match"), "{err}");
    // Not a summary: exit 3; a stamp outside the bag: exit 2.
    std::fs::write(dir.path().join("bad.json"), "{\"model\": null}").unwrap();
    let (code, _, err) = bom(&["predict", "--model", dir.path().join("bad.json").to_str().unwrap(), "--wrench", DRAWER]);
    assert_eq!(code, 3, "{err}");
    let (code, _, err) = bom(&["predict", "--model", m, "--wrench", DRAWER, "--from", "1e6"]);
    assert_eq!(code, 2, "{err}");
}

/// `bom eval --tracking` on the drawer: every push held out in turn is predicted open loop far
/// better than a constant-velocity filter does, its band covers the observed drawer, and the JSON
/// carries the contract's `tracking` object with one row per window.
#[test]
fn eval_tracking_leaves_each_push_out() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("eval.json");
    let (code, stdout, err) = bom(&["eval", DRAWER, "--tracking", "--json", out.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    assert!(stdout.contains("tracking (leave one interaction out)"), "{stdout}");
    let m: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    let t = &m["tracking"];
    let rows = t["interactions"].as_array().unwrap();
    assert_eq!(rows.len(), 4, "{t}");
    for key in ["open_loop", "one_step"] {
        for field in ["mse_bom_m2", "mse_const_vel_m2", "mse_const_acc_m2"] {
            assert!(t[key][field].as_f64().is_some_and(|x| x.is_finite() && x >= 0.0), "{key}.{field}: {t}");
        }
    }
    let ol = &t["open_loop"];
    assert!(ol["mse_bom_m2"].as_f64().unwrap() < 0.1 * ol["mse_const_vel_m2"].as_f64().unwrap(), "{ol}");
    // Open loop the draws' mean is scored beside the medians' simulation; one step has no draws.
    assert!(ol["mse_bom_mean_m2"].as_f64().is_some_and(|x| x.is_finite() && x >= 0.0), "{ol}");
    assert!(t["one_step"].get("mse_bom_mean_m2").is_none(), "{t}");
    // The drawer is pushed in every window, so no held-out push is its part's only one.
    assert!(rows.iter().all(|r| r["pushed_elsewhere"] == true) && t["open_loop_only_push"].is_null(), "{t}");
    assert_eq!(t["open_loop_pushed_elsewhere"], t["open_loop"]);
    assert!(t["coverage_90"].as_f64().unwrap() >= 0.8, "{t}");
    assert_eq!(t["kalman_grid"].as_array().unwrap().len(), 14);
}
