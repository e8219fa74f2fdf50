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

/// The index of the first frame at which a track has turned `deg` degrees about the circle
/// fitted to the whole of it (a door, `revolute`), or gone `deg / 90` of its whole travel from its
/// first position (a drawer or slider: the share of a 90-degree door's sweep); at least 5.
fn cut_index(points: &[nalgebra::Vector3<f64>], revolute: bool, deg: f64) -> usize {
    let n = points.len();
    let first = if revolute {
        // Plane of the track (its two principal directions), then the circle in it by linear
        // least squares (Kasa): x^2 + y^2 = 2 a x + 2 b y + k.
        let mean = points.iter().sum::<nalgebra::Vector3<f64>>() / n as f64;
        let m = nalgebra::DMatrix::from_fn(n, 3, |r, c| points[r][c] - mean[c]);
        let v = m.clone().svd(false, true).v_t.unwrap();
        let (e1, e2) = (v.row(0).transpose(), v.row(1).transpose());
        let xy: Vec<(f64, f64)> = (0..n).map(|r| (m.row(r).dot(&e1.transpose()), m.row(r).dot(&e2.transpose()))).collect();
        let a = nalgebra::DMatrix::from_fn(n, 3, |r, c| [2.0 * xy[r].0, 2.0 * xy[r].1, 1.0][c]);
        let b = nalgebra::DVector::from_fn(n, |r, _| xy[r].0 * xy[r].0 + xy[r].1 * xy[r].1);
        let s = a.svd(true, true).solve(&b, 1e-12).unwrap();
        let mut angle = 0.0f64;
        let mut prev = (xy[0].1 - s[1]).atan2(xy[0].0 - s[0]);
        let mut turned = vec![0.0];
        for &(x, y) in &xy[1..] {
            let now = (y - s[1]).atan2(x - s[0]);
            let mut d = now - prev;
            d -= (d / std::f64::consts::TAU).round() * std::f64::consts::TAU;
            angle += d;
            prev = now;
            turned.push(angle.abs().to_degrees());
        }
        turned.iter().position(|&t| t >= deg)
    } else {
        let travel: Vec<f64> = points.iter().map(|p| (p - points[0]).norm()).collect();
        let whole = travel.iter().cloned().fold(0.0, f64::max);
        travel.iter().position(|&s| s >= whole * deg / 90.0)
    };
    first.unwrap_or(n - 1).max(5)
}

/// Issue 24, class 3, on real data: the first 15 and 25 degrees of every door track of
/// `../shared/data/sturm-articulation` (`cabinet_one`, `second_set` doors and dishwasher; radius
/// 0.33-0.67 m, so the handle's path bends 3-15 mm from a straight line) and the same share of
/// every drawer and sliding-door track (15/90 and 25/90 of its travel): 94 short tracks. Frames of
/// such a short track are closer in time than perception's errors are correlated, and counted
/// as independent they called these arcs and lines either way at P = 1.00 (9 wrong calls at
/// P >= 0.95 before the coarsened comparison, `inference.coarsen`). What is asked is
/// what a planner needs: right, or honestly unsure — at most one wrong call at P >= 0.95 and
/// a Brier score of the type probabilities no worse than 0.33 (summed over the three types).
#[test]
fn shallow_arcs_of_real_tracks_are_right_or_unsure() {
    let data = shared_dir().join("data/sturm-articulation");
    let dir = tempfile::tempdir().unwrap();
    let mut files: Vec<PathBuf> = Vec::new();
    for folder in ["cabinet_one", "second_set/left_door", "second_set/right_door", "second_set/dishwasher", "second_set/drawer", "second_set/sliding_cabinet"] {
        let mut f: Vec<PathBuf> = std::fs::read_dir(data.join(folder)).unwrap().map(|e| e.unwrap().path()).filter(|p| p.extension().is_some_and(|e| e == "log")).collect();
        f.sort();
        files.extend(f);
    }
    assert_eq!(files.len(), 47, "the door, dishwasher, drawer and sliding-door tracks");
    let (mut brier, mut wrong, mut wrong_confident, mut cuts) = (0.0, 0, 0, 0);
    let mut by_folder: BTreeMap<String, (usize, usize)> = BTreeMap::new();
    for file in &files {
        let folder = file.parent().unwrap().file_name().unwrap().to_string_lossy().to_string();
        let revolute = !(folder == "drawer" || folder == "sliding_cabinet");
        let text = std::fs::read_to_string(file).unwrap();
        let lines: Vec<&str> = text.lines().filter(|l| !l.trim().is_empty()).collect();
        let points: Vec<nalgebra::Vector3<f64>> = lines
            .iter()
            .map(|l| {
                let v: Vec<f64> = l.split_whitespace().take(3).map(|x| x.parse().unwrap()).collect();
                nalgebra::Vector3::new(v[0], v[1], v[2])
            })
            .collect();
        for deg in [15.0, 25.0] {
            let k = cut_index(&points, revolute, deg);
            let name = format!("{folder}_{}_cut{deg}", file.file_stem().unwrap().to_string_lossy());
            let (log, bag) = (dir.path().join(format!("{name}.log")), dir.path().join(format!("{name}.mcap")));
            std::fs::write(&log, lines[..=k].join("\n")).unwrap();
            bom::import::import_tracks(&[log], &bag, None, 30.0, 4).unwrap();
            let p = type_probs(&replay(&[bag]));
            let truth = if revolute { 2 } else { 1 };
            let top = (0..3).max_by(|&a, &b| p[a].total_cmp(&p[b])).unwrap();
            brier += (0..3).map(|t| (p[t] - (t == truth) as u8 as f64).powi(2)).sum::<f64>();
            wrong += (top != truth) as usize;
            wrong_confident += (top != truth && p[top] >= 0.95) as usize;
            cuts += 1;
            let e = by_folder.entry(folder.clone()).or_default();
            e.0 += (top == truth) as usize;
            e.1 += 1;
            println!("{name:36} {:4} frames  P = [{:.2} {:.2} {:.2}] {}", k + 1, p[0], p[1], p[2], if top == truth { "ok" } else { "WRONG" });
        }
    }
    for (f, (r, t)) in &by_folder {
        println!("{f:16} {r}/{t} right");
    }
    let brier = brier / cuts as f64;
    println!("{cuts} shallow cuts: {} right, Brier {brier:.3}, wrong at P >= 0.95: {wrong_confident}", cuts - wrong);
    assert!(wrong_confident <= 1, "{wrong_confident} of {cuts} shallow real tracks called wrong at P >= 0.95");
    assert!(brier <= 0.33, "Brier score {brier:.3} over {cuts} shallow real tracks");
}
