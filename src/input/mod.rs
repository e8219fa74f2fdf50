//! Input stage: ROS 2 MCAP bags (or, in the node, DDS topics) to decoded, validated clouds and
//! wrenches in the fixed frame.
//!
//! Bags are read with the `mcap` crate and messages decoded from CDR with serde (`cdr-encoding`).
//! Everything wrong with the input is reported through [`Diagnostics`] and skipped; only a bag
//! that cannot be opened at all is an error.

pub mod pointcloud;
pub mod tf;

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use mcap::read::{ChunkReader, LinearReader, Options};
use mcap::records::Record;
use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};

use crate::diagnostics::Diagnostics;
use crate::msgs::{self, PointCloud2, TFMessage, WrenchStamped};
pub use pointcloud::LabeledPoints;
pub use tf::TfBuffer;

/// A bag that cannot be used at all (exit code 3).
#[derive(Debug, thiserror::Error)]
pub enum InputError {
    #[error("{path}: cannot read: {why}")]
    Unreadable { path: PathBuf, why: String },
    #[error("{path}: not an MCAP file: {why}")]
    NotMcap { path: PathBuf, why: String },
    #[error("{path}: metadata 'bom_ground_truth': {why}")]
    GroundTruth { path: PathBuf, why: String },
}

/// One raw message of a bag.
#[derive(Debug, Clone)]
pub struct BagMessage {
    pub topic: String,
    /// Schema name, e.g. `sensor_msgs/msg/PointCloud2`.
    pub schema: String,
    /// Channel message encoding, `cdr` for ROS 2.
    pub encoding: String,
    /// Log time \[ns\].
    pub log_time: u64,
    pub data: Vec<u8>,
}

/// Ground truth of one part (contract section 3).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct GtPart {
    pub label: u32,
    #[serde(default)]
    pub name: Option<String>,
    pub parent: u32,
    pub joint: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub axis_direction: Option<[f64; 3]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub axis_point: Option<[f64; 3]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub damping: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub friction: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mass: Option<f64>,
}

/// The `bom_ground_truth` metadata record of a bag (contract section 3).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct GroundTruth {
    #[serde(default = "default_fixed_frame")]
    pub fixed_frame: String,
    pub parts: Vec<GtPart>,
    #[serde(default)]
    pub effects: Vec<serde_json::Value>,
}

fn default_fixed_frame() -> String {
    "world".into()
}

/// A bag's messages in log-time order and its ground truth, if any.
#[derive(Debug, Clone)]
pub struct Bag {
    pub path: PathBuf,
    pub messages: Vec<BagMessage>,
    pub ground_truth: Option<GroundTruth>,
}

/// Read every message and the `bom_ground_truth` metadata of an MCAP bag.
///
/// A truncated bag is not an error: the messages before the damage are kept and the truncation
/// is reported through `diag`. Messages are sorted by log time (chunks may interleave).
///
/// # Errors
/// [`InputError`] when the file cannot be read, is not MCAP, or has invalid ground truth JSON.
pub fn read_bag(path: &Path, diag: &mut Diagnostics) -> Result<Bag, InputError> {
    let buf = std::fs::read(path).map_err(|e| InputError::Unreadable { path: path.into(), why: e.to_string() })?;
    let src = path.display().to_string();
    let reader = LinearReader::new_with_options(&buf, Options::IgnoreEndMagic.into())
        .map_err(|e| InputError::NotMcap { path: path.into(), why: e.to_string() })?;
    let mut schemas: HashMap<u16, String> = HashMap::new();
    let mut channels: HashMap<u16, (String, u16, String)> = HashMap::new();
    let mut messages = Vec::new();
    let mut ground_truth = None;
    let mut records_ok = 0usize;

    fn handle(
        rec: Record<'_>,
        schemas: &mut HashMap<u16, String>,
        channels: &mut HashMap<u16, (String, u16, String)>,
        messages: &mut Vec<BagMessage>,
        gt: &mut Option<String>,
    ) -> Result<(), String> {
        match rec {
            Record::Schema { header, .. } => {
                schemas.insert(header.id, header.name);
            }
            Record::Channel(c) => {
                channels.insert(c.id, (c.topic, c.schema_id, c.message_encoding));
            }
            Record::Message { header, data } => {
                let (topic, schema_id, encoding) =
                    channels.get(&header.channel_id).ok_or(format!("message on unknown channel {}", header.channel_id))?;
                messages.push(BagMessage {
                    topic: topic.clone(),
                    schema: schemas.get(schema_id).cloned().unwrap_or_default(),
                    encoding: encoding.clone(),
                    log_time: header.log_time,
                    data: data.into_owned(),
                });
            }
            Record::Metadata(m) if m.name == "bom_ground_truth" => {
                *gt = Some(m.metadata.get("json").cloned().ok_or("no key 'json'")?);
            }
            _ => {}
        }
        Ok(())
    }

    let mut gt_json = None;
    let mut trouble: Option<String> = None;
    'outer: for rec in reader {
        let rec = match rec {
            Ok(r) => r,
            Err(e) => {
                trouble = Some(e.to_string());
                break;
            }
        };
        records_ok += 1;
        if let Record::Chunk { header, data } = rec {
            let chunk = match ChunkReader::new(header, &data) {
                Ok(c) => c,
                Err(e) => {
                    trouble = Some(format!("bad chunk: {e}"));
                    break;
                }
            };
            for r in chunk {
                match r {
                    Ok(r) => {
                        if let Err(e) = handle(r, &mut schemas, &mut channels, &mut messages, &mut gt_json) {
                            diag.warn(&src, "invalid record", &e);
                        }
                    }
                    Err(e) => {
                        trouble = Some(format!("bad chunk: {e}"));
                        break 'outer;
                    }
                }
            }
        } else if let Err(e) = handle(rec, &mut schemas, &mut channels, &mut messages, &mut gt_json) {
            diag.warn(&src, "invalid record", &e);
        }
    }
    if let Some(why) = trouble {
        if records_ok == 0 {
            return Err(InputError::NotMcap { path: path.into(), why });
        }
        diag.warn(&src, "truncated bag", &format!("{why}; using the {} messages before the damage", messages.len()));
    }
    if let Some(json) = gt_json {
        let gt: GroundTruth =
            serde_json::from_str(&json).map_err(|e| InputError::GroundTruth { path: path.into(), why: e.to_string() })?;
        ground_truth = Some(gt);
    }
    messages.sort_by_key(|m| m.log_time);
    Ok(Bag { path: path.into(), messages, ground_truth })
}

/// Topic names and the fixed frame that the input stage listens to (contract section 1).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct Topics {
    pub points: String,
    pub wrench: String,
    pub tf: String,
    pub tf_static: String,
}

impl Default for Topics {
    fn default() -> Self {
        Topics {
            points: "/segmented_points".into(),
            wrench: "/applied_wrench".into(),
            tf: "/tf".into(),
            tf_static: "/tf_static".into(),
        }
    }
}

/// One segmented cloud, in the fixed frame.
#[derive(Debug, Clone)]
pub struct CloudFrame {
    /// Header stamp \[s\].
    pub stamp: f64,
    /// Points \[m\], fixed frame.
    pub points: Vec<Point3<f64>>,
    /// Part label of each point (>= 1).
    pub labels: Vec<u32>,
}

/// One applied wrench, in the fixed frame.
#[derive(Debug, Clone)]
pub struct WrenchSample {
    /// Header stamp \[s\].
    pub stamp: f64,
    /// Point of application (the contact frame's origin) \[m\], fixed frame.
    pub point: Point3<f64>,
    /// Force \[N\], fixed frame.
    pub force: Vector3<f64>,
    /// Torque [N m], fixed frame.
    pub torque: Vector3<f64>,
}

/// Everything the later stages need from a set of bags: clouds and wrenches in the fixed frame,
/// in time order.
#[derive(Debug, Clone, Default)]
pub struct Recording {
    pub clouds: Vec<CloudFrame>,
    pub wrenches: Vec<WrenchSample>,
}

fn decode_or_warn<T: serde::de::DeserializeOwned>(m: &BagMessage, diag: &mut Diagnostics) -> Option<T> {
    if m.encoding != "cdr" {
        diag.warn(&m.topic, "unsupported message encoding", &format!("'{}' (expected cdr); message skipped", m.encoding));
        return None;
    }
    match msgs::decode_cdr::<T>(&m.data) {
        Ok(v) => Some(v),
        Err(e) => {
            diag.warn(&m.topic, "undecodable message", &format!("{e}; message skipped"));
            None
        }
    }
}

/// Decode the messages of bags into a [`Recording`] in `fixed_frame`.
///
/// All `/tf` and `/tf_static` messages are buffered first, so a cloud can use a transform
/// recorded just after it (as a tf2 message filter would wait for it). Clouds that cannot be
/// decoded or transformed, wrenches with non-finite values or unknown frames, and messages whose
/// header stamp goes backwards on their topic are reported through `diag` and skipped.
pub fn decode_recording(bags: &[Bag], topics: &Topics, fixed_frame: &str, diag: &mut Diagnostics) -> Recording {
    let mut tf = TfBuffer::new();
    for bag in bags {
        for m in &bag.messages {
            let is_static = m.topic == topics.tf_static;
            if m.topic == topics.tf || is_static {
                if let Some(msg) = decode_or_warn::<TFMessage>(m, diag) {
                    for e in tf.add(&msg, is_static) {
                        diag.warn(&m.topic, "transform rejected", &e.to_string());
                    }
                }
            }
        }
    }
    let mut rec = Recording::default();
    let mut last_stamp: HashMap<String, f64> = HashMap::new();
    for bag in bags {
        for m in &bag.messages {
            if m.topic == topics.points {
                let Some(cloud) = decode_or_warn::<PointCloud2>(m, diag) else { continue };
                if let Some(c) = cloud_in_fixed_frame(&m.topic, &cloud, &tf, fixed_frame, diag) {
                    if check_monotonic(&mut last_stamp, &m.topic, c.stamp, diag) {
                        rec.clouds.push(c);
                    }
                }
            } else if m.topic == topics.wrench {
                let Some(w) = decode_or_warn::<WrenchStamped>(m, diag) else { continue };
                if let Some(w) = wrench_in_fixed_frame(&m.topic, &w, &tf, fixed_frame, diag) {
                    if check_monotonic(&mut last_stamp, &m.topic, w.stamp, diag) {
                        rec.wrenches.push(w);
                    }
                }
            }
        }
    }
    // Several bags are several interactions with one object: keep them in time order.
    rec.clouds.sort_by(|a, b| a.stamp.total_cmp(&b.stamp));
    rec.wrenches.sort_by(|a, b| a.stamp.total_cmp(&b.stamp));
    rec
}

/// Whether `stamp` is not earlier than the previous header stamp on `topic` (then it becomes the
/// previous one); a stamp going backwards is reported and the message is to be skipped.
pub fn check_monotonic(last: &mut HashMap<String, f64>, topic: &str, stamp: f64, diag: &mut Diagnostics) -> bool {
    match last.get_mut(topic) {
        Some(prev) if stamp < *prev => {
            diag.warn(topic, "time went backwards", &format!("header.stamp {stamp:.6} s after {prev:.6} s; message skipped"));
            false
        }
        Some(prev) => {
            *prev = stamp;
            true
        }
        None => {
            last.insert(topic.to_string(), stamp);
            true
        }
    }
}

/// Decode the labelled points of a cloud (in its own frame), reporting a malformed cloud (then
/// `None`), NaN/Inf points and non-integer labels (those points are skipped).
pub fn decode_cloud(topic: &str, cloud: &PointCloud2, diag: &mut Diagnostics) -> Option<LabeledPoints> {
    let lp = match pointcloud::decode(cloud) {
        Ok(lp) => lp,
        Err(e) => {
            diag.warn(topic, "malformed PointCloud2", &format!("{e}; cloud skipped"));
            return None;
        }
    };
    if lp.nonfinite > 0 {
        diag.warn(topic, "non-finite points", &format!("{} NaN/Inf points skipped", lp.nonfinite));
    }
    if lp.bad_labels > 0 {
        diag.warn(&format!("{topic}.label"), "non-integer label", &format!("{} points skipped", lp.bad_labels));
    }
    Some(lp)
}

/// A decoded cloud in the fixed frame: `iso` maps the cloud's frame into it; `stamp` in seconds.
pub fn cloud_frame(lp: LabeledPoints, iso: &nalgebra::Isometry3<f64>, stamp: f64) -> CloudFrame {
    let points = lp.points.iter().map(|p| iso * Point3::new(p[0], p[1], p[2])).collect();
    CloudFrame { stamp, points, labels: lp.labels }
}

/// Whether every force and torque component is finite; reports the wrench when not.
pub fn wrench_is_finite(topic: &str, w: &WrenchStamped, diag: &mut Diagnostics) -> bool {
    let (f, t) = (w.wrench.force, w.wrench.torque);
    let ok = [f.x, f.y, f.z, t.x, t.y, t.z].iter().all(|x| x.is_finite());
    if !ok {
        diag.warn(&format!("{topic}.wrench"), "non-finite wrench", "NaN or Inf in force/torque; message skipped");
    }
    ok
}

/// A wrench in the fixed frame: `iso` maps the wrench's frame into it; force and torque rotated,
/// the point of application at the frame's origin.
pub fn wrench_sample(w: &WrenchStamped, iso: &nalgebra::Isometry3<f64>) -> WrenchSample {
    let (f, t) = (w.wrench.force, w.wrench.torque);
    WrenchSample {
        stamp: w.header.stamp.seconds(),
        point: iso * Point3::origin(),
        force: iso.rotation * Vector3::new(f.x, f.y, f.z),
        torque: iso.rotation * Vector3::new(t.x, t.y, t.z),
    }
}

/// Decode one cloud and express its labelled points in the fixed frame.
pub fn cloud_in_fixed_frame(
    topic: &str,
    cloud: &PointCloud2,
    tf: &TfBuffer,
    fixed_frame: &str,
    diag: &mut Diagnostics,
) -> Option<CloudFrame> {
    let lp = decode_cloud(topic, cloud, diag)?;
    let iso = match tf.lookup(fixed_frame, &cloud.header.frame_id, cloud.header.stamp) {
        Ok(iso) => iso,
        Err(e) => {
            diag.warn(&format!("{topic}.header.frame_id"), "unknown frame", &format!("{e}; cloud skipped"));
            return None;
        }
    };
    Some(cloud_frame(lp, &iso, cloud.header.stamp.seconds()))
}

/// Express one wrench in the fixed frame: the force and torque rotated, the point of application
/// at the origin of the wrench's frame.
pub fn wrench_in_fixed_frame(
    topic: &str,
    w: &WrenchStamped,
    tf: &TfBuffer,
    fixed_frame: &str,
    diag: &mut Diagnostics,
) -> Option<WrenchSample> {
    if !wrench_is_finite(topic, w, diag) {
        return None;
    }
    let iso = match tf.lookup(fixed_frame, &w.header.frame_id, w.header.stamp) {
        Ok(iso) => iso,
        Err(e) => {
            diag.warn(&format!("{topic}.header.frame_id"), "unknown frame", &format!("{e}; wrench skipped"));
            return None;
        }
    };
    Some(wrench_sample(w, &iso))
}
