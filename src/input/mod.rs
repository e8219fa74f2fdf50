//! Input stage: ROS 2 MCAP bags (or, in the node, DDS topics) to decoded, validated clouds and
//! wrenches in the fixed frame.
//!
//! Bags are read with the `mcap` crate and messages decoded from CDR with serde (`cdr-encoding`).
//! Everything wrong with the input is reported through [`Diagnostics`] and skipped; only a bag
//! that cannot be opened at all is an error.

pub mod pointcloud;
pub mod stamps;
pub mod tf;

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use mcap::records::Record;
use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};
use nalgebra::{Point3, Vector3};
use serde::{Deserialize, Serialize};

use crate::diagnostics::Diagnostics;
use crate::msgs::{self, PointCloud2, TFMessage, WrenchStamped};
pub use pointcloud::LabeledPoints;
pub use stamps::{StampGuard, StampLimits};
pub use tf::TfBuffer;

/// Bounds on what the input stage accepts (issue 27). Every size read from input is checked
/// against the data actually present and against these caps before anything is allocated, so a
/// damaged bag or DDS sample gives a one-line error or warning, never an allocation abort; values
/// no real robot or camera produces are warned about, counted and dropped.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct InputLimits {
    /// Largest MCAP record, and largest chunk compressed or decompressed \[bytes\]. A larger
    /// declared size is damage: the bag is read up to it (as a truncated one). 128 MiB holds a
    /// 4-million-point cloud.
    pub max_record_bytes: usize,
    /// Most points (`width x height`) in one PointCloud2; a larger cloud is skipped.
    pub max_cloud_points: u64,
    /// Points farther than this from the origin of the cloud's frame are skipped and counted \[m\]
    /// (depth cameras see a few metres; 1e30 is a corrupted float, not a point).
    pub max_range_m: f64,
    /// Largest plausible applied force \[N\]; a manipulator pushing furniture stays far below.
    pub max_force_n: f64,
    /// Largest plausible applied torque \[N m\].
    pub max_torque_nm: f64,
    /// A header stamp more than this far ahead of its topic's clock waits for the next message to
    /// confirm it (a gap) or refute it (an outlier, dropped) \[s\] ([`stamps`]).
    pub stamp_jump_s: f64,
    /// This many consecutive messages behind a topic's clock, rising among themselves, reset it
    /// (a restarted publisher) instead of being dropped one by one.
    pub stamp_reset_messages: u32,
}

impl Default for InputLimits {
    fn default() -> Self {
        InputLimits {
            max_record_bytes: 128 << 20,
            max_cloud_points: 4_000_000,
            max_range_m: 1000.0,
            max_force_n: 2000.0,
            max_torque_nm: 500.0,
            stamp_jump_s: 1.0,
            stamp_reset_messages: 10,
        }
    }
}

impl InputLimits {
    /// The stamp checks' part of the limits.
    pub fn stamps(&self) -> StampLimits {
        StampLimits { jump_s: self.stamp_jump_s, reset_messages: self.stamp_reset_messages }
    }
}

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

/// Read every message and the `bom_ground_truth` metadata of an MCAP bag, with the default
/// [`InputLimits`]; see [`read_bag_with`].
///
/// # Errors
/// [`InputError`] when the file cannot be read, is not MCAP, or has invalid ground truth JSON.
pub fn read_bag(path: &Path, diag: &mut Diagnostics) -> Result<Bag, InputError> {
    read_bag_with(path, &InputLimits::default(), diag)
}

/// Read every message and the `bom_ground_truth` metadata of an MCAP bag.
///
/// A truncated or damaged bag is not an error: the messages before the damage are kept and the
/// damage is reported through `diag`. Messages are sorted by log time (chunks may interleave).
/// Memory is bounded by the file's size times [`MAX_INFLATION`] plus a few times
/// `limits.max_record_bytes`, whatever sizes the file declares ([`read_mcap`]).
///
/// # Errors
/// [`InputError`] when the file cannot be read, is not MCAP, or has invalid ground truth JSON.
pub fn read_bag_with(path: &Path, limits: &InputLimits, diag: &mut Diagnostics) -> Result<Bag, InputError> {
    let buf = std::fs::read(path).map_err(|e| InputError::Unreadable { path: path.into(), why: e.to_string() })?;
    let read = read_mcap(&buf, &path.display().to_string(), limits, diag)
        .map_err(|why| InputError::NotMcap { path: path.into(), why })?;
    let ground_truth = match read.ground_truth_json {
        Some(json) => Some(
            serde_json::from_str(&json).map_err(|e| InputError::GroundTruth { path: path.into(), why: e.to_string() })?,
        ),
        None => None,
    };
    Ok(Bag { path: path.into(), messages: read.messages, ground_truth })
}

/// What [`read_mcap`] found in an MCAP byte stream.
#[derive(Debug, Clone, Default)]
pub struct McapContents {
    /// Messages in log-time order.
    pub messages: Vec<BagMessage>,
    /// The `json` key of the `bom_ground_truth` metadata record, unparsed.
    pub ground_truth_json: Option<String>,
}

/// Decode the records of an MCAP file held in memory (chunks decompressed, each chunk's CRC
/// checked before its records are used).
///
/// Built on the `mcap` crate's sans-io [`LinearReader`] with `record_length_limit` set to
/// `limits.max_record_bytes`: the crate's whole-chunk readers trust a chunk's declared
/// uncompressed size and record lengths and allocate them (3e13 bytes in a damaged bag: an
/// abort, not an error). Here no declared size is allocated beyond what the file holds or the
/// limit, and the messages kept never exceed [`MAX_INFLATION`] times the file's size (or the
/// limit). A damaged chunk (bad CRC, bad compression, a record overrunning it) is skipped whole
/// with a warning and reading goes on with the next one; damage to the file's record framing
/// ends the reading, keeping what came before (a truncated bag). Warnings go through `diag`
/// under `src`, one line each.
///
/// # Errors
/// A one-line reason when not a single record could be read (not an MCAP file).
pub fn read_mcap(buf: &[u8], src: &str, limits: &InputLimits, diag: &mut Diagnostics) -> Result<McapContents, String> {
    let limit = limits.max_record_bytes.max(1);
    let mut reader = LinearReader::new_with_options(
        LinearReaderOptions::default().with_skip_end_magic(true).with_emit_chunks(true).with_record_length_limit(limit),
    );
    let mut state = McapState::default();
    let budget = buf.len().saturating_mul(MAX_INFLATION).max(limit);
    let mut records_ok = 0usize;
    let mut rest = buf;
    let mut trouble: Option<String> = None;
    while let Some(event) = reader.next_event() {
        match event {
            Ok(LinearReadEvent::ReadRequest(need)) => feed(&mut reader, &mut rest, need),
            Ok(LinearReadEvent::Record { data, opcode }) if opcode == mcap::records::op::CHUNK => {
                records_ok += 1;
                match read_chunk(data, limit) {
                    Ok(records) => {
                        for rec in records {
                            if let Err(e) = state.handle(rec) {
                                diag.warn(src, "invalid record", &e);
                            }
                        }
                    }
                    Err(why) => diag.warn(src, "damaged chunk", &format!("{why}; the chunk's records skipped")),
                }
                if state.bytes > budget {
                    trouble = Some(format!("messages inflate to more than {MAX_INFLATION} times the file's {} bytes", buf.len()));
                    break;
                }
            }
            Ok(LinearReadEvent::Record { data, opcode }) => match parse_used(opcode, data) {
                Ok(rec) => {
                    records_ok += 1;
                    if let Some(Err(e)) = rec.map(|r| state.handle(r)) {
                        diag.warn(src, "invalid record", &e);
                    }
                }
                Err(e) => {
                    trouble = Some(e);
                    break;
                }
            },
            Err(e) => {
                trouble = Some(e.to_string());
                break;
            }
        }
    }
    let mut out = state.out;
    if let Some(why) = trouble {
        if records_ok == 0 {
            return Err(why);
        }
        diag.warn(src, "truncated bag", &format!("{why}; using the {} messages before the damage", out.messages.len()));
    } else if records_ok == 0 {
        return Err("no MCAP record".into());
    }
    out.messages.sort_by_key(|m| m.log_time);
    Ok(out)
}

/// Parse a record of a kind bom reads (schema, channel, message, metadata); the others (indexes,
/// attachments, statistics, ...) are whole records left unparsed: `None`. Not parsing what is
/// not used keeps bom off `mcap` 0.26's attachment parser, which slices past a short record's end
/// and panics (found by the `mcap_bag` fuzz target).
fn parse_used(opcode: u8, data: &[u8]) -> Result<Option<Record<'_>>, String> {
    use mcap::records::op;
    if ![op::SCHEMA, op::CHANNEL, op::MESSAGE, op::METADATA].contains(&opcode) {
        return Ok(None);
    }
    strings_fit(opcode, data).map_err(|e| format!("record (opcode 0x{opcode:02x}): {e}"))?;
    mcap::parse_record(opcode, data).map(Some).map_err(|e| format!("record (opcode 0x{opcode:02x}): {e}"))
}

/// Whether every length-prefixed string and string map of a schema, channel or metadata record
/// fits in the record (MCAP spec field layouts). `mcap` 0.26 parses strings with binrw, which
/// reserves a string's declared `u32` length before reading it: a damaged length allocated up to
/// 4 GiB per record (found by the `mcap_bag` fuzz target under a malloc limit).
fn strings_fit(opcode: u8, data: &[u8]) -> Result<(), String> {
    use mcap::records::op;
    fn u32_at(b: &[u8], at: usize) -> Result<usize, String> {
        b.get(at..at + 4).map(|x| u32::from_le_bytes([x[0], x[1], x[2], x[3]]) as usize).ok_or_else(|| "record too short".into())
    }
    // One length-prefixed field at `at`; returns the offset after it.
    fn field(b: &[u8], at: usize, what: &str) -> Result<usize, String> {
        let len = u32_at(b, at)?;
        let end = (at + 4).checked_add(len).filter(|&e| e <= b.len());
        end.ok_or_else(|| format!("{what} of {len} bytes overruns the record ({} bytes)", b.len()))
    }
    // A string map: its byte length, then key/value strings within it.
    fn map(b: &[u8], at: usize, what: &str) -> Result<usize, String> {
        let end = field(b, at, what)?;
        let inner = &b[..end];
        let mut k = at + 4;
        while k < end {
            k = field(inner, k, what)?;
            k = field(inner, k, what)?;
        }
        Ok(end)
    }
    match opcode {
        op::SCHEMA => field(data, field(data, 2, "schema name")?, "schema encoding").map(drop),
        op::CHANNEL => map(data, field(data, field(data, 4, "channel topic")?, "message encoding")?, "channel metadata").map(drop),
        op::METADATA => map(data, field(data, 0, "metadata name")?, "metadata map").map(drop),
        _ => Ok(()),
    }
}

/// Hand a sans-io reader at most `need` bytes of `rest`: never more than the file still holds,
/// so a declared length is not an allocation.
fn feed(reader: &mut LinearReader, rest: &mut &[u8], need: usize) {
    let n = need.min(rest.len());
    reader.insert(n).copy_from_slice(&rest[..n]);
    reader.notify_read(n);
    *rest = &rest[n..];
}

/// Decode one chunk record's body in a reader of its own, CRC checked before any record is used
/// and every length bounded by `limit`: its records, when the whole chunk reads.
fn read_chunk(body: &[u8], limit: usize) -> Result<Vec<Record<'static>>, String> {
    let mut reader = LinearReader::new_with_options(
        LinearReaderOptions::default()
            .with_skip_start_magic(true)
            .with_skip_end_magic(true)
            .with_prevalidate_chunk_crcs(true)
            .with_record_length_limit(limit),
    );
    // The reader reads a chunk record: its opcode and length, then the body (fed in place).
    let mut head = [0u8; 9];
    head[0] = mcap::records::op::CHUNK;
    head[1..].copy_from_slice(&(body.len() as u64).to_le_bytes());
    let (mut head, mut rest) = (&head[..], body);
    let mut records = Vec::new();
    while let Some(event) = reader.next_event() {
        match event.map_err(|e| e.to_string())? {
            LinearReadEvent::ReadRequest(need) if !head.is_empty() => feed(&mut reader, &mut head, need),
            LinearReadEvent::ReadRequest(need) => feed(&mut reader, &mut rest, need),
            LinearReadEvent::Record { data, opcode } => records.extend(parse_used(opcode, data)?.map(|r| r.into_owned())),
        }
    }
    Ok(records)
}

/// Schemas and channels met so far, and what was read.
#[derive(Default)]
struct McapState {
    schemas: HashMap<u16, String>,
    channels: HashMap<u16, (String, u16, String)>,
    out: McapContents,
    /// Message bytes kept so far.
    bytes: usize,
}

/// Most message bytes kept per byte of file: sensor data compresses a few times; a bag whose
/// chunks inflate beyond this is a decompression bomb or damage, not a recording.
pub const MAX_INFLATION: usize = 64;

impl McapState {
    fn handle(&mut self, rec: Record<'_>) -> Result<(), String> {
        match rec {
            Record::Schema { header, .. } => {
                self.schemas.insert(header.id, header.name);
            }
            Record::Channel(c) => {
                self.channels.insert(c.id, (c.topic, c.schema_id, c.message_encoding));
            }
            Record::Message { header, data } => {
                let (topic, schema_id, encoding) =
                    self.channels.get(&header.channel_id).ok_or(format!("message on unknown channel {}", header.channel_id))?;
                self.bytes += data.len();
                self.out.messages.push(BagMessage {
                    topic: topic.clone(),
                    schema: self.schemas.get(schema_id).cloned().unwrap_or_default(),
                    encoding: encoding.clone(),
                    log_time: header.log_time,
                    data: data.into_owned(),
                });
            }
            Record::Metadata(m) if m.name == "bom_ground_truth" => {
                self.out.ground_truth_json =
                    Some(m.metadata.get("json").cloned().ok_or("metadata 'bom_ground_truth': no key 'json'")?);
            }
            _ => {}
        }
        Ok(())
    }
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
    /// Where the points were seen from \[m\], fixed frame: the origin of the cloud's
    /// `header.frame_id` (a depth camera's optical frame), or `None` when the cloud came in the
    /// fixed frame itself (its sensor is then unknown). Perception uses it to tell which of two
    /// neighbouring parts hides the other.
    pub viewpoint: Option<Point3<f64>>,
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

/// Decode the messages of bags into a [`Recording`] in `fixed_frame`, with the default
/// [`InputLimits`]; see [`decode_recording_with`].
pub fn decode_recording(bags: &[Bag], topics: &Topics, fixed_frame: &str, diag: &mut Diagnostics) -> Recording {
    decode_recording_with(bags, topics, fixed_frame, &InputLimits::default(), diag)
}

/// A cloud or a wrench in the fixed frame, on its way through its topic's [`StampGuard`] (replay
/// and the node's streaming pipeline alike).
pub enum Sample {
    Cloud(CloudFrame),
    Wrench(WrenchSample),
}

impl Recording {
    fn push(&mut self, item: Sample) {
        match item {
            Sample::Cloud(c) => self.clouds.push(c),
            Sample::Wrench(w) => self.wrenches.push(w),
        }
    }
}

/// Decode the messages of bags into a [`Recording`] in `fixed_frame`.
///
/// All `/tf` and `/tf_static` messages are buffered first, so a cloud can use a transform
/// recorded just after it (as a tf2 message filter would wait for it). Clouds that cannot be
/// decoded or transformed, wrenches that are not finite or not plausible (`limits`) or in unknown
/// frames, and messages whose header stamp goes backwards or jumps ahead alone on their topic
/// ([`stamps`]; each bag is a stream of its own) are reported through `diag` and skipped.
pub fn decode_recording_with(
    bags: &[Bag],
    topics: &Topics,
    fixed_frame: &str,
    limits: &InputLimits,
    diag: &mut Diagnostics,
) -> Recording {
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
    for bag in bags {
        let mut guards: HashMap<String, StampGuard<Sample>> = HashMap::new();
        for m in &bag.messages {
            let item = if m.topic == topics.points {
                let Some(cloud) = decode_or_warn::<PointCloud2>(m, diag) else { continue };
                let Some(c) = cloud_in_fixed_frame(&m.topic, &cloud, &tf, fixed_frame, limits, diag) else { continue };
                (c.stamp, Sample::Cloud(c))
            } else if m.topic == topics.wrench {
                let Some(w) = decode_or_warn::<WrenchStamped>(m, diag) else { continue };
                let Some(w) = wrench_in_fixed_frame(&m.topic, &w, &tf, fixed_frame, limits, diag) else { continue };
                (w.stamp, Sample::Wrench(w))
            } else {
                continue;
            };
            let guard = guards.entry(m.topic.clone()).or_insert_with(|| StampGuard::new(limits.stamps()));
            for (_, item) in guard.push(&m.topic, item.0, item.1, diag) {
                rec.push(item);
            }
        }
        for guard in guards.values_mut() {
            if let Some((_, item)) = guard.flush() {
                rec.push(item);
            }
        }
    }
    // Several bags are several interactions with one object: keep them in time order.
    rec.clouds.sort_by(|a, b| a.stamp.total_cmp(&b.stamp));
    rec.wrenches.sort_by(|a, b| a.stamp.total_cmp(&b.stamp));
    rec
}

/// Decode the labelled points of a cloud (in its own frame), reporting a malformed or oversized
/// cloud (then `None`), NaN/Inf points, points beyond `limits.max_range_m` and non-integer labels
/// (those points are skipped).
pub fn decode_cloud(topic: &str, cloud: &PointCloud2, limits: &InputLimits, diag: &mut Diagnostics) -> Option<LabeledPoints> {
    let lp = match pointcloud::decode(cloud, limits.max_cloud_points, limits.max_range_m) {
        Ok(lp) => lp,
        Err(e) => {
            diag.warn(topic, "malformed PointCloud2", &format!("{e}; cloud skipped"));
            return None;
        }
    };
    if lp.nonfinite > 0 {
        diag.warn(topic, "non-finite points", &format!("{} NaN/Inf points skipped", lp.nonfinite));
    }
    if lp.out_of_range > 0 {
        diag.warn(
            topic,
            "implausible points",
            &format!("{} points farther than input.max_range_m = {} m from the cloud's frame skipped", lp.out_of_range, limits.max_range_m),
        );
    }
    if lp.bad_labels > 0 {
        diag.warn(&format!("{topic}.label"), "non-integer label", &format!("{} points skipped", lp.bad_labels));
    }
    Some(lp)
}

/// A decoded cloud in the fixed frame: `iso` maps the cloud's frame into it; `stamp` in seconds.
/// The viewpoint is the cloud frame's origin, unless `iso` is the identity (a cloud published in
/// the fixed frame, whose sensor position is not known).
pub fn cloud_frame(lp: LabeledPoints, iso: &nalgebra::Isometry3<f64>, stamp: f64) -> CloudFrame {
    let points = lp.points.iter().map(|p| iso * Point3::new(p[0], p[1], p[2])).collect();
    let viewpoint = (*iso != nalgebra::Isometry3::identity()).then(|| iso * Point3::origin());
    CloudFrame { stamp, points, labels: lp.labels, viewpoint }
}

/// Whether every force and torque component is finite and the force and torque are within
/// `limits` (`max_force_n`, `max_torque_nm`); reports the wrench when not.
pub fn wrench_is_plausible(topic: &str, w: &WrenchStamped, limits: &InputLimits, diag: &mut Diagnostics) -> bool {
    let (f, t) = (w.wrench.force, w.wrench.torque);
    if ![f.x, f.y, f.z, t.x, t.y, t.z].iter().all(|x| x.is_finite()) {
        diag.warn(&format!("{topic}.wrench"), "non-finite wrench", "NaN or Inf in force/torque; message skipped");
        return false;
    }
    let norm = |v: crate::msgs::Vector3| (v.x * v.x + v.y * v.y + v.z * v.z).sqrt();
    let (fn_, tn) = (norm(f), norm(t));
    if !(fn_ <= limits.max_force_n && tn <= limits.max_torque_nm) {
        diag.warn(
            &format!("{topic}.wrench"),
            "implausible wrench",
            &format!(
                "|force| {fn_:.3e} N, |torque| {tn:.3e} N m beyond input.max_force_n = {} N / max_torque_nm = {} N m; message skipped",
                limits.max_force_n, limits.max_torque_nm
            ),
        );
        return false;
    }
    true
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
    limits: &InputLimits,
    diag: &mut Diagnostics,
) -> Option<CloudFrame> {
    let lp = decode_cloud(topic, cloud, limits, diag)?;
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
    limits: &InputLimits,
    diag: &mut Diagnostics,
) -> Option<WrenchSample> {
    if !wrench_is_plausible(topic, w, limits, diag) {
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
