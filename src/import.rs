//! `bom import-tracks`: articulation_models track logs to bags (contract section 4).
//!
//! Each line of a log is one observation: `x y z` (a tracked point), `x y z qx qy qz qw` (a pose)
//! or `x y z qx qy qz qw width height` (a tracked rectangle), metres, in the sensor frame, which
//! the bag calls the fixed frame `world`. Around each pose a cloud of the tracked part is
//! synthesised: a `grid x grid` lattice over the `width x height` rectangle in the pose's x-y
//! plane when given, else over a 5 cm square patch; for `x y z` lines, whose orientation is
//! unknown, points on a sphere of 2.5 cm radius (see [`synthesize`]). Blank lines and `#` comments are skipped.
//!
//! Several files become several parts of one bag, labels 1, 2, ... in the order given, all
//! starting at the same time (a part whose track is shorter is simply not seen afterwards).
//! Timestamps are `k / rate` seconds. `--joint` records the known joint type of every part as
//! `bom_ground_truth` (parent: the fixed frame); without it no ground truth is written.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use nalgebra::{Quaternion, UnitQuaternion, Vector3};

use crate::input::pointcloud::encode_xyzl;
use crate::input::{GroundTruth, GtPart};
use crate::model::JointType;
use crate::msgs::{Header, Time};
use crate::output::BagWriter;

/// One observation of a track.
#[derive(Debug, Clone, PartialEq)]
pub struct TrackPose {
    pub position: Vector3<f64>,
    pub orientation: Option<UnitQuaternion<f64>>,
    /// Width and height of the tracked rectangle \[m\].
    pub size: Option<(f64, f64)>,
}

/// Errors of `import-tracks`: bad input (exit 3) or an unwritable output.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    #[error("{path}:{line}: {why}")]
    BadLine { path: PathBuf, line: usize, why: String },
    #[error("{path}: {why}")]
    Unreadable { path: PathBuf, why: String },
    #[error("{path}: {why}")]
    Write { path: PathBuf, why: String },
}

/// Parse a track log.
///
/// # Errors
/// [`ImportError::BadLine`] naming the line for a wrong column count, a non-number, a
/// non-finite value or a zero quaternion; [`ImportError::Unreadable`] for an empty or unreadable file.
pub fn parse_track(path: &Path) -> Result<Vec<TrackPose>, ImportError> {
    let text = std::fs::read_to_string(path).map_err(|e| ImportError::Unreadable { path: path.into(), why: e.to_string() })?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let bad = |why: String| ImportError::BadLine { path: path.into(), line: i + 1, why };
        let v: Vec<f64> = line
            .split_whitespace()
            .map(|s| s.parse::<f64>().map_err(|_| bad(format!("'{s}' is not a number"))))
            .collect::<Result<_, _>>()?;
        if !v.iter().all(|x| x.is_finite()) {
            return Err(bad("non-finite value".into()));
        }
        if ![3, 7, 9].contains(&v.len()) {
            return Err(bad(format!("{} columns; expected 3 (x y z), 7 (+ qx qy qz qw) or 9 (+ width height)", v.len())));
        }
        let position = Vector3::new(v[0], v[1], v[2]);
        let pose = match v.len() {
            3 => TrackPose { position, orientation: None, size: None },
            7 | 9 => {
                let q = Quaternion::new(v[6], v[3], v[4], v[5]);
                if q.norm() < 1e-6 {
                    return Err(bad("zero quaternion".into()));
                }
                let size = (v.len() == 9).then(|| (v[7], v[8]));
                if let Some((w, h)) = size {
                    if w < 0.0 || h < 0.0 {
                        return Err(bad("negative width or height".into()));
                    }
                }
                TrackPose { position, orientation: Some(UnitQuaternion::from_quaternion(q)), size }
            }
            _ => unreachable!("column count checked above"),
        };
        out.push(pose);
    }
    if out.is_empty() {
        return Err(ImportError::Unreadable { path: path.into(), why: "no observations".into() });
    }
    Ok(out)
}

/// The synthesised cloud of one observation, fixed frame: a `grid x grid` lattice over the
/// rectangle (or 5 cm square) in the pose's x-y plane; for a bare point (`x y z`, no orientation
/// known) `grid^3` points on a sphere of 2.5 cm radius instead (a Fibonacci lattice), so that the
/// cloud implies no orientation — a flat patch in a fixed orientation would tell perception that
/// a rotating door does not rotate, and so would a cube's faces (a cube until stop 105).
pub fn synthesize(pose: &TrackPose, grid: usize) -> Vec<[f64; 3]> {
    let (w, h) = pose.size.unwrap_or((0.05, 0.05));
    let g = grid.max(2);
    let Some(rot) = pose.orientation else {
        // A sphere (Fibonacci lattice), which pins no rotation: a cube's faces would tell
        // perception's surface-normal test that this point never turns (stop 105).
        let n = g * g * g;
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        return (0..n)
            .map(|i| {
                let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
                let r = (1.0 - z * z).sqrt();
                let t = golden * i as f64;
                let p = pose.position + Vector3::new(r * t.cos(), r * t.sin(), z) * 0.025;
                [p.x, p.y, p.z]
            })
            .collect();
    };
    let mut pts = Vec::with_capacity(g * g);
    for a in 0..g {
        for b in 0..g {
            let u = (a as f64 / (g - 1) as f64 - 0.5) * w;
            let v = (b as f64 / (g - 1) as f64 - 0.5) * h;
            let p = pose.position + rot * Vector3::new(u, v, 0.0);
            pts.push([p.x, p.y, p.z]);
        }
    }
    pts
}

/// Write the bag. `rate` in Hz, `grid` points per side of each synthesised patch.
///
/// # Errors
/// See [`ImportError`].
pub fn import_tracks(files: &[PathBuf], out: &Path, joint: Option<JointType>, rate: f64, grid: usize) -> Result<usize, ImportError> {
    let tracks: Vec<Vec<TrackPose>> = files.iter().map(|f| parse_track(f)).collect::<Result<_, _>>()?;
    let werr = |e: crate::output::bag::WriteError| ImportError::Write { path: out.into(), why: e.to_string() };
    let mut w = BagWriter::create(out).map_err(werr)?;
    if let Some(joint) = joint {
        let gt = GroundTruth {
            fixed_frame: "world".into(),
            parts: files
                .iter()
                .enumerate()
                .map(|(i, f)| GtPart {
                    label: i as u32 + 1,
                    name: Some(f.display().to_string()),
                    parent: 0,
                    joint: joint.name().into(),
                    axis_direction: None,
                    axis_point: None,
                    damping: None,
                    friction: None,
                    mass: None,
                })
                .collect(),
            effects: Vec::new(),
        };
        let json = serde_json::to_string(&gt).expect("ground truth serialises");
        w.metadata("bom_ground_truth", BTreeMap::from([("json".to_string(), json)])).map_err(werr)?;
    }
    let frames = tracks.iter().map(|t| t.len()).max().unwrap_or(0);
    for k in 0..frames {
        let stamp = Time::from_seconds(k as f64 / rate);
        let (mut points, mut labels) = (Vec::new(), Vec::new());
        for (i, track) in tracks.iter().enumerate() {
            if let Some(pose) = track.get(k) {
                let pts = synthesize(pose, grid);
                labels.extend(std::iter::repeat_n(i as u32 + 1, pts.len()));
                points.extend(pts);
            }
        }
        let cloud = encode_xyzl(Header { stamp, frame_id: "world".into() }, &points, &labels);
        w.write("/segmented_points", "sensor_msgs/msg/PointCloud2", stamp.nanos(), &cloud).map_err(werr)?;
    }
    w.finish().map_err(werr)?;
    Ok(frames)
}
