//! `bom eval`: contract section 6 metrics against bom_ground_truth.

mod common;

use common::*;

fn eval_json(args: &[&str]) -> serde_json::Value {
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("m.json");
    let mut all = vec!["eval"];
    all.extend_from_slice(args);
    all.extend_from_slice(&["--json", json.to_str().unwrap()]);
    let (code, stdout, stderr) = bom(&all);
    assert_eq!(code, 0, "{stderr}");
    assert!(stdout.contains("joint_accuracy"), "{stdout}");
    serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap()
}

#[test]
fn a_real_drawer_track_scores_perfectly_on_structure() {
    let m = eval_json(&["bags/sturm/drawer_001.mcap"]);
    assert_eq!(m["joint_accuracy"], 1.0);
    assert_eq!(m["parent_accuracy"], 1.0);
    assert!(m["graph_mse"].as_f64().unwrap() < 1e-6);
    // The real tracks know no axes and no kinodynamics.
    assert!(m["axis_angle_deg"].is_null() && m["axis_offset_m"].is_null() && m["ide"].is_null());
    assert!(m.get("baselines").is_none());
}

#[test]
fn a_three_part_cabinet_reports_every_part_and_the_baselines() {
    let m = eval_json(&["bags/mujoco/hingecabinet.mcap", "--baselines"]);
    let parts = m["per_part"].as_array().unwrap();
    assert_eq!(parts.len(), 3);
    for key in ["joint_accuracy", "graph_mse", "parent_accuracy"] {
        let v = m[key].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&v), "{key} = {v}");
    }
    // Each part has 3 candidate parents (the fixed frame and the two other parts).
    assert!((m["baselines"]["disconnected"]["graph_mse"].as_f64().unwrap() - 1.0 / 3.0).abs() < 1e-12);
    assert!((m["baselines"]["clique"]["graph_mse"].as_f64().unwrap() - 2.0 / 3.0).abs() < 1e-12);
    // Differentiable simulation with the true structure and axes (the paper's oracle row): both
    // doors fitted; from the priors' medians their damping and friction come within a factor of
    // two of the truth (0.15-0.24 relative error when written), and the tail start is scored too.
    for row in ["diff_sim", "diff_sim_tail_init"] {
        assert_eq!(m["baselines"][row]["parts"].as_array().unwrap().len(), 2, "{row}");
        assert!(m["baselines"][row]["ide"].is_number(), "{row}");
    }
    for p in m["baselines"]["diff_sim"]["parts"].as_array().unwrap() {
        for k in ["damping_rel_error", "friction_rel_error"] {
            let e = p[k].as_f64().unwrap();
            assert!(e < 0.5, "diff_sim {k} = {e}: {p}");
        }
    }
    // The doors have true axes, so their angle errors are reported; the rigid body has none.
    assert!(parts[1]["axis_angle_deg"].is_number() && parts[2]["axis_angle_deg"].is_number());
    assert!(parts[0]["axis_angle_deg"].is_null());
    let mean: f64 = parts.iter().map(|p| p["graph_mse"].as_f64().unwrap()).sum::<f64>() / 3.0;
    assert!((mean - m["graph_mse"].as_f64().unwrap()).abs() < 1e-12);
    // Calibration: the doors' true damping, friction and axis mostly fall inside the 90%
    // intervals (6 of 6 when written; 0 of 6 when the kinodynamics were conditioned on the
    // guide's coordinates and the axis spread ignored the residuals' autocorrelation).
    let covered = m["coverage"]["all"].as_array().unwrap();
    let (hit, of) = (covered[0].as_u64().unwrap(), covered[1].as_u64().unwrap());
    assert_eq!(of, 6);
    assert!(hit >= 4, "{hit} of {of} inside the 90% intervals: {}", m["coverage"]);
    // Both hinge points are scored against their 90% discs, apart from `all`; the rigid body has
    // none.
    assert_eq!(m["coverage"]["axis_point"][1].as_u64(), Some(2), "{}", m["coverage"]);
    assert!(parts[1]["axis_point_covered"].is_boolean() && parts[2]["axis_point_covered"].is_boolean());
    assert!(parts[0]["axis_point_covered"].is_null());
    // The reported kinodynamics are the collapsed posterior's mode: the right door's damping and
    // friction within 20% of the truth (0.09 and 0.12 when written; 0.47 and 0.36 when that fit
    // stopped after 12 Newton steps, 8 nats below its mode). The left door's sit elsewhere on its
    // damping-friction ridge (errors 0.14-0.47 and 0.2-0.32 at seeds 0, 2, 3), not yet traced.
    let right = &parts[2];
    for key in ["damping_rel_error", "friction_rel_error"] {
        let e = right[key].as_f64().unwrap();
        assert!(e < 0.2, "right door {key} = {e}: {right}");
    }
}

/// A door with a latch on it (frame, door, latch): the latch turns 0.25 rad in one of the four
/// pushes. Before the tree sampler's order followed the best tree, the door hung from its latch in
/// half the samples; before the joint types' step targets had a floor, the latch's revolute type
/// sank 1e5 nats after a warm start and came out rigid. Now the structure is the true one, with
/// sure parents.
#[test]
fn a_latch_on_a_door_is_found_revolute_on_the_door() {
    let m = eval_json(&["bags/mujoco/adroit_door.mcap"]);
    assert_eq!(m["joint_accuracy"], 1.0, "{m}");
    assert_eq!(m["parent_accuracy"], 1.0, "{m}");
    assert!(m["graph_mse"].as_f64().unwrap() < 0.01, "{m}");
}

#[test]
fn a_bag_without_ground_truth_is_invalid_input() {
    let dir = tempfile::tempdir().unwrap();
    let bag = dir.path().join("nogt.mcap");
    let src = shared_dir().join("data/sturm-articulation/second_set/drawer/001.log");
    bom::import::import_tracks(&[src], &bag, None, 30.0, 4).unwrap();
    let (code, _, err) = bom(&["eval", bag.to_str().unwrap()]);
    assert_eq!(code, 3, "{err}");
    assert!(err.contains("nogt.mcap") && err.contains("bom_ground_truth"), "{err}");
}

/// `bom eval --corpus` over a folder of object folders: the real drawer track and a real door
/// track are scored with their calibration; a folder whose bag has no ground truth and one whose
/// bag is not MCAP are each reported in one line and skipped, and the aggregate says how many
/// were scored.
#[test]
fn a_corpus_is_scored_and_bad_objects_are_skipped() {
    let dir = tempfile::tempdir().unwrap();
    let object = |name: &str| {
        let d = dir.path().join(name);
        std::fs::create_dir_all(&d).unwrap();
        d
    };
    std::fs::copy("bags/sturm/drawer_001.mcap", object("a_drawer").join("drawer.mcap")).unwrap();
    std::fs::copy("bags/sturm/left_door_001.mcap", object("b_door").join("door.mcap")).unwrap();
    let src = shared_dir().join("data/sturm-articulation/second_set/drawer/002.log");
    bom::import::import_tracks(&[src], &object("c_nogt").join("nogt.mcap"), None, 30.0, 4).unwrap();
    std::fs::write(object("d_broken").join("broken.mcap"), b"not an mcap file").unwrap();
    let json = dir.path().join("corpus.json");
    let (code, stdout, stderr) = bom(&["eval", "--corpus", dir.path().to_str().unwrap(), "--json", json.to_str().unwrap(), "--jobs", "2"]);
    assert_eq!(code, 0, "{stderr}");
    let r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(r["listed"], 4, "{r}");
    assert_eq!(r["scored"], 2, "{r}");
    let skipped = r["skipped"].as_array().unwrap();
    assert_eq!(skipped.len(), 2);
    assert!(skipped.iter().any(|s| s.as_str().unwrap().contains("c_nogt") && s.as_str().unwrap().contains("bom_ground_truth")), "{skipped:?}");
    assert!(skipped.iter().any(|s| s.as_str().unwrap().contains("broken.mcap")), "{skipped:?}");
    assert!(stdout.contains("2 object runs scored of 4 listed"), "{stdout}");
    let agg = &r["aggregate"][0];
    assert_eq!(agg["parts"], 2);
    assert_eq!(agg["joint_accuracy"], 1.0, "{agg}");
    let cal = &agg["calibration"];
    assert!(cal["brier"].as_f64().unwrap() < 0.1, "{cal}");
    assert_eq!(cal["wrong_confident"], 0);
    let bins = cal["reliability"].as_array().unwrap();
    assert_eq!(bins.iter().map(|b| b["count"].as_u64().unwrap()).sum::<u64>(), 6, "three probabilities per part");
    // One line per skipped object on stderr.
    assert_eq!(stderr.lines().filter(|l| l.starts_with("warning: skipped")).count(), 2, "{stderr}");
}

/// `bom eval --corpus` on the shipped effects corpus (`bags/effects/`: two doors whose range was
/// narrowed so that their pushes reach a stop, absent from the ground truth — `obj093` of the
/// effects corpus's `tune` split, and `obj013` of a further `--tune-only` corpus, seed 300000 —
/// and that corpus's `obj089`, a lid on a spring that a push also drives into a stop):
/// criticism names each joint limit with the held-out error cut to a third, its stops within
/// 0.05 rad of the truth, and the truth inside the reported 90% intervals. The intervals allow for
/// the physics' deviations repeating from frame to frame (`criticism::effect_inflation`; the plain
/// Laplace intervals missed `obj093`'s closing stop, README "Stop 73") and reach the farthest
/// coordinate the door was seen at toward each stop (`criticism::reach_stops`; without it
/// `obj013`'s fitted stops lie 0.02 rad beyond where the door went and both miss, "Stop 74").
/// The lid's spring is named beside its stop, each cutting the held-out error of the other alone
/// to half: the two are fitted together (criticism's pairs; one at a time, the stop alone was
/// adopted and the spring never, "Stop 75").
#[test]
fn the_shipped_undeclared_stops_are_named_inside_their_intervals() {
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("effects.json");
    let (code, _, stderr) = bom(&["eval", "--corpus", "bags/effects/manifest.json", "--json", json.to_str().unwrap(), "--jobs", "2"]);
    assert_eq!(code, 0, "{stderr}");
    let r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(r["scored"], 3, "{r}");
    for o in r["objects"].as_array().unwrap() {
        let c = &o["criticism"];
        let stop = c["effects"].as_array().unwrap().iter().find(|e| e["kind"] == "joint_limit").expect("the stop is scored");
        assert_eq!(stop["named"], true, "{}: {c}", o["name"]);
        let (before, after) = (stop["rmse_before_m"].as_f64().unwrap(), stop["rmse_after_m"].as_f64().unwrap());
        assert!(after <= before / 3.0, "{}: held-out RMSE {before:.4} -> {after:.4} m: {c}", o["name"]);
        assert_eq!(stop["param_ok"], true, "{}: {c}", o["name"]);
        assert_eq!(stop["in_interval"], true, "{}: {c}", o["name"]);
        assert_eq!(c["false_alarms"], 0, "{}: {c}", o["name"]);
        if let Some(spring) = c["effects"].as_array().unwrap().iter().find(|e| e["kind"] == "spring") {
            assert_eq!(spring["named"], true, "{}: {c}", o["name"]);
            let (before, after) = (spring["rmse_before_m"].as_f64().unwrap(), spring["rmse_after_m"].as_f64().unwrap());
            assert!(after <= before / 2.0, "{}: held-out RMSE {before:.4} -> {after:.4} m: {c}", o["name"]);
        }
    }
    let springs = r["objects"].as_array().unwrap().iter().filter(|o| o["criticism"]["effects"].as_array().unwrap().iter().any(|e| e["kind"] == "spring"));
    assert_eq!(springs.count(), 1, "the lid's spring is scored");
}

/// `bom eval --corpus --inference nuts --baselines`: every object is scored on BOM-NUTS and on
/// the BOM-SVI posterior it started from, in one run; the report has the paper's Table 1 (BOM-SVI,
/// BOM-NUTS, Disconnected, Clique on the same objects; no diff-sim rows in kinematic mode) and
/// SVI's 90% intervals against NUTS's.
#[test]
fn a_corpus_gets_table_1_with_svi_and_nuts_side_by_side() {
    let dir = tempfile::tempdir().unwrap();
    for (name, bag) in [("a_drawer", "bags/sturm/drawer_001.mcap"), ("b_door", "bags/sturm/left_door_001.mcap")] {
        std::fs::create_dir_all(dir.path().join(name)).unwrap();
        std::fs::copy(bag, dir.path().join(name).join("track.mcap")).unwrap();
    }
    let cfg = dir.path().join("nuts.yaml");
    std::fs::write(&cfg, "nuts:\n  chains: 2\n  tune: 200\n  draws: 200\n").unwrap();
    let json = dir.path().join("t1.json");
    let (code, stdout, stderr) = bom(&[
        "eval", "--corpus", dir.path().to_str().unwrap(), "--inference", "nuts", "--baselines",
        "--config", cfg.to_str().unwrap(), "--json", json.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{stderr}");
    let r: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let rows = r["table1"].as_array().expect("a Table 1");
    let methods: Vec<&str> = rows.iter().map(|m| m["method"].as_str().unwrap()).collect();
    assert_eq!(methods, ["BOM-SVI", "BOM-NUTS", "Disconnected", "Clique"], "{r}");
    for m in &rows[..2] {
        assert_eq!(m["joint_accuracy"], 1.0, "{m}");
        assert!(m["graph_mse"].as_f64().unwrap() < 0.05, "{m}");
    }
    assert!(rows[0]["runtime_s_median"].as_f64().unwrap() < rows[1]["runtime_s_median"].as_f64().unwrap(), "NUTS runs after SVI");
    for o in r["objects"].as_array().unwrap() {
        assert!(o["svi"]["per_part"].is_array() && o["sampler"]["r_hat_max"].is_f64(), "{o}");
        assert!(o["sampler"]["ess_tail_min"].as_f64().is_some_and(|e| e > 0.0), "the tail ESS reported: {o}");
    }
    let c = &r["svi_vs_nuts"];
    assert_eq!(c["parameters"], 2, "one axis cone per movable part: {c}");
    assert_eq!(c["joint_type_disagreements"], 0, "{c}");
    assert!(c["width_ratio_median"].as_f64().unwrap() > 0.0, "{c}");
    assert!(stdout.contains("Table 1") && stdout.contains("SVI vs NUTS"), "{stdout}");
}
