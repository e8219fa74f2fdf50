//! `bom replay --out` and `--json` on a bundled bag: the output bag decodes with bom's own reader
//! (CI checks it with the Python `rosbags` reader too) and matches the JSON summary.

mod common;

use bom::msgs::{decode_cdr, MarkerArray, ObjectModel, PoseArray};
use common::*;

#[test]
fn output_bag_and_json_agree() {
    let dir = tempfile::tempdir().unwrap();
    let (out, json) = (dir.path().join("out.mcap"), dir.path().join("out.json"));
    let (code, stdout, stderr) = bom(&["replay", "bags/sturm/left_door_001.mcap", "--out", out.to_str().unwrap(), "--json", json.to_str().unwrap(), "--timing"]);
    assert_eq!(code, 0, "{stderr}");
    assert!(stdout.contains("=> revolute") && stdout.contains("timing [s]:"), "{stdout}");
    let summary: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let joint = &summary["model"]["joints"][0];
    assert_eq!(summary["mode"], "kinematic");
    assert_eq!(joint["child"], 1);
    assert_eq!(joint["parent"], 0);
    assert!(joint["damping"].is_null() && joint["axis"]["point"].is_array());

    let mut diag = bom::diagnostics::Diagnostics::default();
    let bag = bom::input::read_bag(&out, &mut diag).unwrap();
    assert_eq!(diag.total(), 0);
    let models: Vec<ObjectModel> = bag.messages.iter().filter(|m| m.topic == "/bom/object_model").map(|m| decode_cdr(&m.data).unwrap()).collect();
    assert_eq!(models.len(), summary["windows"].as_array().unwrap().len());
    let last = models.last().unwrap();
    assert_eq!(last.header.frame_id, "world");
    assert_eq!(last.joints[0].most_probable_type, "revolute");
    assert!((last.joints[0].p_revolute - joint["type_probs"]["revolute"].as_f64().unwrap()).abs() < 1e-12);
    let dir_json: Vec<f64> = joint["axis"]["direction"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    let d = last.joints[0].axis_direction;
    assert!((d.x - dir_json[0]).abs() + (d.y - dir_json[1]).abs() + (d.z - dir_json[2]).abs() < 1e-12);
    assert!(bag.messages.iter().filter(|m| m.topic == "/bom/markers").all(|m| decode_cdr::<MarkerArray>(&m.data).unwrap().markers.len() == 4));
    let poses: Vec<PoseArray> = bag.messages.iter().filter(|m| m.topic == "/bom/predicted_part_poses").map(|m| decode_cdr(&m.data).unwrap()).collect();
    assert!(poses.len() > 100, "{} pose arrays", poses.len());
    assert!(poses.iter().all(|p| p.poses.len() == 1 && p.header.frame_id == "world"));
    // Predicted poses track the observed handle to within a few centimetres.
    let run = replay(&["bags/sturm/left_door_001.mcap".into()]);
    let obs = &run.tracks[&1];
    let mut worst: f64 = 0.0;
    for p in &poses {
        let t = p.header.stamp.seconds();
        if let Some(o) = obs.iter().find(|o| (o.stamp - t).abs() < 1e-6) {
            let q = p.poses[0].position;
            worst = worst.max(((q.x - o.com.x).powi(2) + (q.y - o.com.y).powi(2) + (q.z - o.com.z).powi(2)).sqrt());
        }
    }
    assert!(worst < 0.05, "predicted pose {worst} m from the observation");
}

/// Model criticism leaves the process in every form the contract names: the summary line, the
/// JSON `criticism` list, `/bom/model_criticism` in the output bag (the same findings, its last
/// message), and `--plot` figures.
#[test]
fn model_criticism_reaches_json_bag_and_plots() {
    use bom::msgs::ModelCriticism;
    let dir = tempfile::tempdir().unwrap();
    let (out, json, plots) = (dir.path().join("out.mcap"), dir.path().join("out.json"), dir.path().join("plots"));
    let args = ["replay", "bags/mujoco/drawer_limit_undeclared.mcap", "--out", out.to_str().unwrap(), "--json", json.to_str().unwrap(), "--plot", plots.to_str().unwrap()];
    let (code, stdout, stderr) = bom(&args);
    assert_eq!(code, 0, "{stderr}");
    assert!(stdout.contains("added joint_limit"), "{stdout}");
    let summary: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let found = &summary["criticism"][0];
    assert_eq!(found["effect"], "joint_limit");
    assert!(found["params"]["upper"].is_number() && found["params"]["lower"].is_number(), "{found}");
    let mut diag = bom::diagnostics::Diagnostics::default();
    let bag = bom::input::read_bag(&out, &mut diag).unwrap();
    let msgs: Vec<ModelCriticism> = bag.messages.iter().filter(|m| m.topic == "/bom/model_criticism").map(|m| decode_cdr(&m.data).unwrap()).collect();
    let last = msgs.last().expect("a ModelCriticism message");
    assert_eq!(last.header.frame_id, "world");
    let f = last.findings.iter().find(|f| f.effect == "joint_limit").expect("the stop in the bag");
    assert_eq!(f.part, 2);
    assert!((f.rmse_before_m - found["rmse_before_m"].as_f64().unwrap()).abs() < 1e-12);
    assert!((f.rmse_after_m - found["rmse_after_m"].as_f64().unwrap()).abs() < 1e-12);
    assert!(f.param_names.iter().any(|n| n == "upper") && f.param_names.len() == f.param_values.len());
    let svg = std::fs::read_to_string(plots.join("part2_joint_limit.svg")).unwrap();
    assert!(svg.starts_with("<svg") && svg.contains("predicted after") && svg.matches("<circle").count() > 20);
}

/// `--inference nuts`: the output bag carries SVI's object models and then, stamped as the last
/// of them, BOM-NUTS's (`inference` "nuts", the JSON's joint type and axis), as the node
/// publishes them.
#[test]
fn nuts_posterior_follows_svi_in_the_output_bag() {
    let dir = tempfile::tempdir().unwrap();
    let (out, json, cfg) = (dir.path().join("out.mcap"), dir.path().join("out.json"), dir.path().join("cfg.yaml"));
    std::fs::write(&cfg, "nuts:\n  chains: 2\n  tune: 200\n  draws: 200\n").unwrap();
    let (code, _, stderr) = bom(&[
        "replay", "bags/sturm/left_door_001.mcap", "--inference", "nuts", "--config", cfg.to_str().unwrap(),
        "--out", out.to_str().unwrap(), "--json", json.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{stderr}");
    let summary: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(summary["model"]["inference"], "nuts");
    let mut diag = bom::diagnostics::Diagnostics::default();
    let bag = bom::input::read_bag(&out, &mut diag).unwrap();
    let models: Vec<(u64, ObjectModel)> =
        bag.messages.iter().filter(|m| m.topic == "/bom/object_model").map(|m| (m.log_time, decode_cdr(&m.data).unwrap())).collect();
    assert_eq!(models.len(), summary["windows"].as_array().unwrap().len() + 1);
    let (last, svi) = (&models[models.len() - 1], &models[models.len() - 2]);
    assert_eq!(svi.1.inference, "svi");
    assert_eq!(last.1.inference, "nuts");
    assert_eq!(last.0, svi.0, "stamped as the SVI posterior it samples from");
    let joint = &summary["model"]["joints"][0];
    assert_eq!(last.1.joints[0].most_probable_type, "revolute");
    assert!((last.1.joints[0].p_revolute - joint["type_probs"]["revolute"].as_f64().unwrap()).abs() < 1e-12);
    let d = last.1.joints[0].axis_direction;
    let dir_json: Vec<f64> = joint["axis"]["direction"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    assert!((d.x - dir_json[0]).abs() + (d.y - dir_json[1]).abs() + (d.z - dir_json[2]).abs() < 1e-12);
}
