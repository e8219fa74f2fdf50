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
/// /tf_static), with one bad message of each kind mixed in (issue 27 added a cloud stamped 10^6 s
/// in the future and a wrench of 1e30 N).
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
            20 => {
                let huge = WrenchStamped {
                    header: Header { stamp: Time::from_seconds(t), frame_id: "world".into() },
                    wrench: Wrench { force: Vector3 { x: 1e30, y: 0.0, z: 0.0 }, torque: Vector3::default() },
                };
                w.write("/applied_wrench", "geometry_msgs/msg/WrenchStamped", stamp(t_bad), &huge).unwrap();
            }
            100 => {
                let mut future = c.clone();
                future.header.stamp = Time::from_seconds(t + 1e6);
                w.write("/segmented_points", CLOUDS, stamp(t_bad), &future).unwrap();
            }
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
        ("/applied_wrench.wrench", "implausible wrench", "1.000e30 N"),
        ("/segmented_points", "stamp outlier", "the next message"),
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
    assert_eq!(diag["/applied_wrench.wrench: implausible wrench"], 1, "{diag}");
    assert_eq!(diag["/segmented_points: stamp outlier"], 1, "{diag}");
    // The good clouds around them were used: 150 frames of part 1, and it slides (the 1e30 N
    // wrench, had it been taken, would have made this a dynamic-mode recording; the future stamp,
    // every later cloud "backwards").
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

/// The bags of `../shared/data/damaged-bags/` (each once aborted `bom replay` allocating up to
/// 1.4e17 bytes, or panicked) exit 0 or 3 with one error line naming the file: never a crash.
#[test]
fn damaged_bags_give_an_exit_code_never_a_crash() {
    let dir = shared_dir().join("data/damaged-bags");
    let mut bags: Vec<_> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().path()).filter(|p| p.extension().is_some_and(|e| e == "mcap")).collect();
    bags.sort();
    assert!(bags.len() >= 5, "{}: {} bags", dir.display(), bags.len());
    for bag in &bags {
        let (code, _, stderr) = bom(&["replay", bag.to_str().unwrap()]);
        let name = bag.file_name().unwrap().to_str().unwrap();
        assert!(code == 0 || code == 3, "{name}: exit {code}\n{stderr}");
        assert!(!stderr.contains("panicked") && !stderr.contains("memory allocation"), "{name}:\n{stderr}");
        if code == 3 {
            let errors: Vec<_> = stderr.lines().filter(|l| l.starts_with("error:")).collect();
            assert!(errors.len() == 1 && errors[0].contains(name), "{name}: {errors:?}");
        }
        // The damage itself is reported, naming the file.
        assert!(stderr.lines().any(|l| l.contains("WARN") && l.contains(name) && (l.contains("damaged chunk") || l.contains("truncated bag"))), "{name}:\n{stderr}");
    }
}

/// One random damage of the kinds of issue 27's mutation run: flipped bits, a truncation, a
/// zeroed span, a duplicated span.
fn mutate(bytes: &[u8], rng: &mut impl rand::Rng) -> Vec<u8> {
    let mut b = bytes.to_vec();
    match rng.random_range(0..4) {
        0 => {
            for _ in 0..rng.random_range(1..=16) {
                let i = rng.random_range(0..b.len());
                b[i] ^= 1 << rng.random_range(0..8);
            }
        }
        1 => b.truncate(rng.random_range(0..b.len())),
        2 => {
            let i = rng.random_range(0..b.len());
            let n = rng.random_range(1..=4096).min(b.len() - i);
            b[i..i + n].fill(0);
        }
        _ => {
            let i = rng.random_range(0..b.len());
            let n = rng.random_range(1..=4096).min(b.len() - i);
            let span = b[i..i + n].to_vec();
            let at = rng.random_range(0..b.len());
            b.splice(at..at, span);
        }
    }
    b
}

/// 400 randomly damaged copies of the shipped bags' first 600 kB through bom's reader and every
/// decoder (MCAP records and chunks, CDR, PointCloud2, TF, wrench): no panic, no abort (an abort
/// ends this test binary), bounded memory. The whole pipeline on damaged copies, with timeouts,
/// is `tests/mutate.sh` (README).
#[test]
fn randomly_damaged_bags_never_crash_the_decoders() {
    let mut sources: Vec<_> = ["bags/mujoco", "bags/sturm"]
        .iter()
        .flat_map(|d| std::fs::read_dir(d).unwrap().map(|e| e.unwrap().path()))
        .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
        .collect();
    sources.sort();
    let originals: Vec<Vec<u8>> = sources.iter().map(|p| std::fs::read(p).unwrap().into_iter().take(600_000).collect()).collect();
    let cfg = bom::config::Config::new();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(27);
    let (mut read, mut clouds) = (0, 0);
    for k in 0..400 {
        let src = &originals[k % originals.len()];
        let damaged = mutate(src, &mut rng);
        let mut diag = bom::diagnostics::Diagnostics::default();
        let Ok(contents) = bom::input::read_mcap(&damaged, "damaged", &cfg.input, &mut diag) else { continue };
        read += 1;
        let bag = bom::input::Bag { path: "damaged".into(), messages: contents.messages, ground_truth: None };
        let rec = bom::input::decode_recording_with(&[bag], &cfg.topics, &cfg.fixed_frame, &cfg.input, &mut diag);
        clouds += rec.clouds.len();
    }
    eprintln!("{read} of 400 damaged copies readable, {clouds} clouds decoded");
    // Most damage leaves a readable prefix: the decoders did see data.
    assert!(read > 300 && clouds > 10_000, "{read} copies readable, {clouds} clouds decoded");
}

/// Inputs on which a fuzz target once crashed (`tests/data/fuzz-crashes/`, named by target):
/// through bom's reader and decoders they give an error or warnings, never a panic. The
/// `mcap_bag` one: a 70-byte bag whose attachment record is shorter than its header, on which
/// `mcap` 0.26's record parser slices past the end (bom no longer parses records it does not use).
#[test]
fn fuzz_crash_inputs_are_errors_not_panics() {
    let mut n = 0;
    for e in std::fs::read_dir("tests/data/fuzz-crashes").unwrap() {
        let path = e.unwrap().path();
        let name = path.file_name().unwrap().to_str().unwrap().to_string();
        let bytes = std::fs::read(&path).unwrap();
        assert!(name.starts_with("mcap_bag-"), "{name}: no runner for this target");
        let cfg = bom::config::Config::new();
        let mut diag = bom::diagnostics::Diagnostics::default();
        if let Ok(c) = bom::input::read_mcap(&bytes, &name, &cfg.input, &mut diag) {
            let bag = bom::input::Bag { path: path.clone(), messages: c.messages, ground_truth: None };
            bom::input::decode_recording_with(&[bag], &cfg.topics, &cfg.fixed_frame, &cfg.input, &mut diag);
        }
        let (code, _, stderr) = bom(&["replay", path.to_str().unwrap()]);
        assert!(code == 3 && !stderr.contains("panicked"), "{name}: exit {code}\n{stderr}");
        n += 1;
    }
    assert!(n >= 1);
}
