//! The kinematic BOM on the real recorded tracks (bags/sturm, made by bags/make_sturm_bags.sh from
//! ../shared/data/sturm-articulation): joint types must come out right, with honest uncertainty.

mod common;

use std::collections::BTreeMap;
use std::path::PathBuf;

use common::*;

fn truth(name: &str) -> usize {
    if name.contains("drawer") || name.contains("sliding") { 1 } else { 2 }
}

#[test]
fn joint_types_of_every_real_track() {
    let mut bags: Vec<PathBuf> = std::fs::read_dir("bags/sturm").unwrap().map(|e| e.unwrap().path()).filter(|p| p.extension().is_some_and(|e| e == "mcap")).collect();
    bags.sort();
    assert_eq!(bags.len(), 49, "one bag per track of ../shared/data/sturm-articulation");
    // (right, total) per object class and per joint type.
    let mut by_class: BTreeMap<String, (usize, usize)> = BTreeMap::new();
    let mut by_type: BTreeMap<usize, (usize, usize)> = BTreeMap::new();
    for bag in &bags {
        let name = bag.file_stem().unwrap().to_string_lossy().to_string();
        let run = replay(std::slice::from_ref(bag));
        // The bag's own ground truth agrees with the class.
        let gt = run.ground_truth.as_ref().expect("bom_ground_truth");
        assert_eq!(gt.parts[0].joint, ["rigid", "prismatic", "revolute"][truth(&name)]);
        let p = type_probs(&run);
        let top = (0..3).max_by(|&a, &b| p[a].total_cmp(&p[b])).unwrap();
        let ok = (top == truth(&name)) as usize;
        let class = name.rsplit_once('_').unwrap().0.to_string();
        let e = by_class.entry(class).or_default();
        e.0 += ok;
        e.1 += 1;
        let e = by_type.entry(truth(&name)).or_default();
        e.0 += ok;
        e.1 += 1;
        println!("{name:24} P = [{:.3} {:.3} {:.3}] {}", p[0], p[1], p[2], if ok == 1 { "ok" } else { "WRONG" });
    }
    for (c, (r, t)) in &by_class {
        println!("class {c:16} {r}/{t}");
    }
    let (right, total): (usize, usize) = by_type.values().fold((0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    assert!(right as f64 >= 0.95 * total as f64, "{right}/{total} right");
    for (t, (r, n)) in &by_type {
        assert!(*r as f64 >= 0.9 * *n as f64, "joint type {t}: {r}/{n} right");
    }
}

/// The first 10% of a door track (15 frames, 0.5 s, the handle moving 13 mm at 1-3 mm noise) says
/// less than the whole track: it has moved, so it is not rigid, but a 13 mm arc of a door is not
/// yet known to be an arc, so the whole track's certainty that it is revolute is not there yet.
#[test]
fn a_tenth_of_a_door_track_is_less_certain() {
    let dir = tempfile::tempdir().unwrap();
    let src = shared_dir().join("data/sturm-articulation/cabinet_one/004.log");
    let text = std::fs::read_to_string(&src).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    let part = dir.path().join("first_tenth.log");
    std::fs::write(&part, lines[..lines.len() / 10].join("\n")).unwrap();
    let (full, tenth) = (dir.path().join("full.mcap"), dir.path().join("tenth.mcap"));
    bom::import::import_tracks(std::slice::from_ref(&src), &full, None, 30.0, 4).unwrap();
    bom::import::import_tracks(&[part], &tenth, None, 30.0, 4).unwrap();
    let (pf, pt) = (type_probs(&replay(&[full])), type_probs(&replay(&[tenth])));
    println!("whole track {pf:?}, first tenth {pt:?}");
    assert!(pf[2] > 0.95, "whole door track: {pf:?}");
    assert!(pt[2] < pf[2] - 0.1, "first tenth {pt:?} is as sure of the door as the whole track {pf:?}");
    assert!(pt[0] < 0.5, "the first tenth moved 13 mm at 1-3 mm noise, yet P(rigid) = {}", pt[0]);
}
