//! Helpers shared by the integration tests: synthetic bags written through bom's own writer.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

use bom::input::pointcloud::encode_xyzl;
use bom::msgs::{Header, PointCloud2, Time};
use bom::output::BagWriter;
use rand::{Rng, SeedableRng};

/// Points of a 6 cm cube of `n^3` points centred at `c`, with Gaussian noise `sd`.
pub fn blob(c: [f64; 3], n: usize, sd: f64, rng: &mut impl Rng) -> Vec<[f64; 3]> {
    let mut pts = Vec::new();
    let normal = rand_distr::Normal::new(0.0, sd.max(1e-12)).unwrap();
    for a in 0..n {
        for b in 0..n {
            for k in 0..n {
                let f = |i: usize| (i as f64 / (n - 1) as f64 - 0.5) * 0.06;
                pts.push([c[0] + f(a) + rng.sample(normal), c[1] + f(b) + rng.sample(normal), c[2] + f(k) + rng.sample(normal)]);
            }
        }
    }
    pts
}

/// A cloud of one part (label 1) in frame `world` at time `t`.
pub fn cloud(t: f64, pts: &[[f64; 3]]) -> PointCloud2 {
    encode_xyzl(Header { stamp: Time::from_seconds(t), frame_id: "world".into() }, pts, &vec![1; pts.len()])
}

/// Write a bag of one part whose centre follows `path(t)` for `secs` at 30 Hz, after 1 s still
/// and followed by 1 s still, with `noise` m of per-point noise and 1 mm of per-frame jitter.
pub fn trajectory_bag(dir: &Path, name: &str, secs: f64, noise: f64, path: impl Fn(f64) -> [f64; 3]) -> PathBuf {
    let out = dir.join(format!("{name}.mcap"));
    let mut w = BagWriter::create(&out).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let jitter = rand_distr::Normal::new(0.0, 0.001).unwrap();
    let frames = ((secs + 2.0) * 30.0) as usize;
    for k in 0..frames {
        let t = k as f64 / 30.0;
        let s = ((t - 1.0) / secs).clamp(0.0, 1.0);
        let c = path(s);
        let c = [c[0] + rng.sample(jitter), c[1] + rng.sample(jitter), c[2] + rng.sample(jitter)];
        let msg = cloud(t, &blob(c, 4, noise, &mut rng));
        w.write("/segmented_points", "sensor_msgs/msg/PointCloud2", Time::from_seconds(t).nanos(), &msg).unwrap();
    }
    w.finish().unwrap();
    out
}

/// Run the `bom` binary; returns (exit code, stdout, stderr).
pub fn bom(args: &[&str]) -> (i32, String, String) {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_bom")).args(args).output().expect("bom runs");
    (out.status.code().unwrap_or(-1), String::from_utf8_lossy(&out.stdout).into(), String::from_utf8_lossy(&out.stderr).into())
}

/// Replay bags through the library with the default configuration.
pub fn replay(bags: &[PathBuf]) -> bom::pipeline::Run {
    bom::pipeline::replay(bags, &bom::config::Config::new()).expect("replay")
}

/// `P(type)` of the first joint, in rigid, prismatic, revolute order.
pub fn type_probs(run: &bom::pipeline::Run) -> [f64; 3] {
    run.posterior.as_ref().expect("a posterior").joints[0].type_probs
}

/// The project's shared folder (`../shared` beside the repository, or `$BOM_SHARED_DIR`).
pub fn shared_dir() -> PathBuf {
    let dir = std::env::var_os("BOM_SHARED_DIR").map(PathBuf::from).unwrap_or_else(|| PathBuf::from("../shared"));
    assert!(dir.join("data/sturm-articulation").is_dir(), "{}: no data/sturm-articulation (set BOM_SHARED_DIR)", dir.display());
    dir
}
