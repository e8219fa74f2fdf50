//! Bad input never crashes bom and never disappears silently: each case gives a one-line warning
//! naming the topic or field, is counted in the JSON summary, and the good messages around it are
//! still used. Unusable input gives the contract's exit codes.

mod common;

use bom::msgs::{Header, PointField, TFMessage, Time, Transform, TransformStamped, Vector3, Wrench, WrenchStamped};
use bom::output::BagWriter;
use common::*;
use rand::SeedableRng;

const CLOUDS: &str = "sensor_msgs/msg/PointCloud2";

/// 4 s of a part sliding 0.3 m along x, clouds in frame `camera` (1 m above `world` on
/// /tf_static), with one bad message of each kind mixed in.
fn bag_with_bad_messages(path: &std::path::Path) {
    let mut w = BagWriter::create(path).unwrap();
    let tf = TFMessage {
        transforms: vec![TransformStamped {
            header: Header { stamp: Time::default(), frame_id: "world".into() },
            child_frame_id: "camera".into(),
            transform: Transform { translation: Vector3 { x: 0.0, y: 0.0, z: 1.0 }, rotation: Default::default() },
        }],
    };
    w.write("/tf_static", "tf2_msgs/msg/TFMessage", 0, &tf).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let stamp = |t: f64| Time::from_seconds(t).nanos();
    for k in 0..150 {
        let t = k as f64 / 30.0;
        let s = ((t - 1.0) / 3.0).clamp(0.0, 1.0);
        let mut c = cloud(t, &blob([0.4 + 0.3 * s, 0.0, -0.3], 4, 0.001, &mut rng));
        c.header.frame_id = "camera".into();
        w.write("/segmented_points", CLOUDS, stamp(t), &c).unwrap();
        let t_bad = t + 0.01;
        match k {
            30 => {
                c.header.stamp = Time::from_seconds(t_bad);
                c.data.truncate(c.data.len() / 2);
                w.write("/segmented_points", CLOUDS, stamp(t_bad), &c).unwrap();
            }
            45 => {
                let mut nan = cloud(t_bad, &vec![[f64::NAN; 3]; 20]);
                nan.header.frame_id = "camera".into();
                nan.is_dense = false;
                w.write("/segmented_points", CLOUDS, stamp(t_bad), &nan).unwrap();
            }
            60 => {
                c.header.stamp = Time::from_seconds(t_bad);
                c.fields[3].datatype = PointField::FLOAT64;
                w.write("/segmented_points", CLOUDS, stamp(t_bad), &c).unwrap();
            }
            75 => {
                c.header.stamp = Time::from_seconds(t_bad);
                c.header.frame_id = "nowhere".into();
                w.write("/segmented_points", CLOUDS, stamp(t_bad), &c).unwrap();
            }
            90 => {
                c.header.stamp = Time::from_seconds(t - 1.0);
                w.write("/segmented_points", CLOUDS, stamp(t_bad), &c).unwrap();
                let wrench = WrenchStamped {
                    header: Header { stamp: Time::from_seconds(t), frame_id: "world".into() },
                    wrench: Wrench { force: Vector3 { x: f64::NAN, y: 0.0, z: 0.0 }, torque: Vector3::default() },
                };
                w.write("/applied_wrench", "geometry_msgs/msg/WrenchStamped", stamp(t_bad), &wrench).unwrap();
            }
            _ => {}
        }
    }
    w.finish().unwrap();
}

#[test]
fn each_bad_message_is_warned_counted_and_skipped() {
    let dir = tempfile::tempdir().unwrap();
    let (bag, json) = (dir.path().join("bad.mcap"), dir.path().join("bad.json"));
    bag_with_bad_messages(&bag);
    let (code, stdout, stderr) = bom(&["replay", bag.to_str().unwrap(), "--json", json.to_str().unwrap()]);
    assert_eq!(code, 0, "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    let expect = [
        ("/segmented_points", "malformed PointCloud2", "shorter than the declared"),
        ("/segmented_points", "non-finite points", "20 NaN"),
        ("/segmented_points", "malformed PointCloud2", "field 'label' has unsupported datatype 8"),
        ("/segmented_points.header.frame_id", "unknown frame", "nowhere"),
        ("/segmented_points", "time went backwards", "message skipped"),
        ("/applied_wrench.wrench", "non-finite wrench", "NaN"),
    ];
    for (topic, kind, detail) in expect {
        let line = stderr.lines().find(|l| l.contains(&format!("{topic}: {kind}")) && l.contains(detail));
        assert!(line.is_some(), "no warning '{topic}: {kind}' with '{detail}' in:\n{stderr}");
    }
    let summary: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let diag = &summary["diagnostics"];
    assert_eq!(diag["/segmented_points: malformed PointCloud2"], 2, "{diag}");
    assert_eq!(diag["/segmented_points.header.frame_id: unknown frame"], 1, "{diag}");
    assert_eq!(diag["/segmented_points: time went backwards"], 1, "{diag}");
    assert_eq!(diag["/applied_wrench.wrench: non-finite wrench"], 1, "{diag}");
    // The good clouds around them were used: 150 frames of part 1, and it slides.
    assert_eq!(summary["parts"][0]["frames"], 150, "{}", summary["parts"]);
    assert_eq!(summary["mode"], "kinematic");
    let p = &summary["model"]["joints"][0]["type_probs"];
    assert!(p["prismatic"].as_f64().unwrap() > 0.9, "{p}\n{stdout}");
}

#[test]
fn truncated_bag_keeps_the_messages_before_the_damage() {
    let dir = tempfile::tempdir().unwrap();
    let src = "bags/sturm/drawer_001.mcap";
    let bytes = std::fs::read(src).unwrap();
    let cut = dir.path().join("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() * 6 / 10]).unwrap();
    let json = dir.path().join("cut.json");
    let (code, _, stderr) = bom(&["replay", cut.to_str().unwrap(), "--json", json.to_str().unwrap()]);
    assert_eq!(code, 0, "{stderr}");
    let line = stderr.lines().find(|l| l.contains("truncated bag")).unwrap_or_else(|| panic!("no truncation warning in {stderr}"));
    assert!(line.contains("cut.mcap") && line.contains("messages before the damage"), "{line}");
    let summary: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let frames = summary["parts"][0]["frames"].as_u64().unwrap();
    assert!(frames > 50 && frames < 265, "{frames} frames kept");
    assert!(summary["model"]["joints"][0]["type_probs"]["prismatic"].as_f64().unwrap() > 0.5);
}

#[test]
fn exit_codes_follow_the_contract() {
    let dir = tempfile::tempdir().unwrap();
    let (code, _, err) = bom(&["replay", "does/not/exist.mcap"]);
    assert_eq!(code, 3, "{err}");
    assert!(err.lines().count() == 1 && err.contains("does/not/exist.mcap"), "{err}");
    let junk = dir.path().join("junk.mcap");
    std::fs::write(&junk, b"this is not an mcap file at all").unwrap();
    let (code, _, err) = bom(&["replay", junk.to_str().unwrap()]);
    assert_eq!(code, 3, "{err}");
    assert!(err.contains("junk.mcap"), "{err}");
    let (code, _, _) = bom(&["replay"]);
    assert_eq!(code, 2);
    let (code, _, err) = bom(&["replay", "bags/sturm/drawer_001.mcap", "--config", "/nonexistent.yaml"]);
    assert_eq!(code, 2, "{err}");
    let bad = dir.path().join("bad.log");
    std::fs::write(&bad, "0.1 0.2 0.3\n0.1 0.2\n").unwrap();
    let (code, _, err) = bom(&["import-tracks", bad.to_str().unwrap(), "--out", dir.path().join("o.mcap").to_str().unwrap()]);
    assert_eq!(code, 3, "{err}");
    assert!(err.contains("bad.log:2") && err.contains("2 columns"), "{err}");
    let (code, _, _) = bom(&["import-tracks", bad.to_str().unwrap(), "--out", "x.mcap", "--joint", "hinge"]);
    assert_eq!(code, 2);
}
