//! ROS 2 message types that bom reads and writes, as serde structs for CDR, and their `ros2msg`
//! schema texts for MCAP.
//!
//! The standard messages (sensor_msgs, geometry_msgs, std_msgs, tf2_msgs, visualization_msgs) are
//! written here rather than taken from `ros2-interfaces-jazzy-serde` because that crate declares
//! `PointCloud2.data` as a plain `Vec<u8>`, which serde decodes one byte at a time; with
//! `serde_bytes` a 20,000-point cloud decodes in one copy. The field layouts follow ROS 2 Jazzy
//! (`common_interfaces` 5.5); the `.msg` texts in `defs/` are the upstream files, embedded verbatim
//! so that bags written by bom carry exact schemas.

use serde::{Deserialize, Serialize};

/// `builtin_interfaces/msg/Time`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

impl Time {
    /// Seconds as f64 (header stamps are reported in seconds everywhere in bom).
    pub fn seconds(&self) -> f64 {
        self.sec as f64 + self.nanosec as f64 * 1e-9
    }
    /// Nanoseconds since the clock's epoch; negative stamps clamp to 0.
    pub fn nanos(&self) -> u64 {
        (self.sec.max(0) as u64) * 1_000_000_000 + self.nanosec as u64
    }
    /// From nanoseconds since the clock's epoch.
    pub fn from_nanos(ns: u64) -> Self {
        Time { sec: (ns / 1_000_000_000) as i32, nanosec: (ns % 1_000_000_000) as u32 }
    }
    /// From seconds (>= 0).
    pub fn from_seconds(s: f64) -> Self {
        Self::from_nanos((s.max(0.0) * 1e9).round() as u64)
    }
}

/// `builtin_interfaces/msg/Duration`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Duration {
    pub sec: i32,
    pub nanosec: u32,
}

/// `std_msgs/msg/Header`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

/// `std_msgs/msg/ColorRGBA`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct ColorRGBA {
    pub r: f32,
    pub g: f32,
    pub b: f32,
    pub a: f32,
}

/// `geometry_msgs/msg/Vector3`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

/// `geometry_msgs/msg/Point`.
pub type Point = Vector3;

/// `geometry_msgs/msg/Quaternion` (x, y, z, w).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub w: f64,
}

impl Default for Quaternion {
    fn default() -> Self {
        Quaternion { x: 0.0, y: 0.0, z: 0.0, w: 1.0 }
    }
}

/// `geometry_msgs/msg/Pose`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    pub position: Point,
    pub orientation: Quaternion,
}

/// `geometry_msgs/msg/PoseArray`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseArray {
    pub header: Header,
    pub poses: Vec<Pose>,
}

/// `geometry_msgs/msg/Transform`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Transform {
    pub translation: Vector3,
    pub rotation: Quaternion,
}

/// `geometry_msgs/msg/TransformStamped`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TransformStamped {
    pub header: Header,
    pub child_frame_id: String,
    pub transform: Transform,
}

/// `tf2_msgs/msg/TFMessage`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TFMessage {
    pub transforms: Vec<TransformStamped>,
}

/// `geometry_msgs/msg/Wrench`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Wrench {
    pub force: Vector3,
    pub torque: Vector3,
}

/// `geometry_msgs/msg/WrenchStamped`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct WrenchStamped {
    pub header: Header,
    pub wrench: Wrench,
}

/// `sensor_msgs/msg/PointField`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PointField {
    pub name: String,
    pub offset: u32,
    pub datatype: u8,
    pub count: u32,
}

impl PointField {
    pub const INT8: u8 = 1;
    pub const UINT8: u8 = 2;
    pub const INT16: u8 = 3;
    pub const UINT16: u8 = 4;
    pub const INT32: u8 = 5;
    pub const UINT32: u8 = 6;
    pub const FLOAT32: u8 = 7;
    pub const FLOAT64: u8 = 8;
}

/// `sensor_msgs/msg/PointCloud2`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PointCloud2 {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub fields: Vec<PointField>,
    pub is_bigendian: bool,
    pub point_step: u32,
    pub row_step: u32,
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
    pub is_dense: bool,
}

/// `sensor_msgs/msg/CompressedImage`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CompressedImage {
    pub header: Header,
    pub format: String,
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// `visualization_msgs/msg/UVCoordinate`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct UVCoordinate {
    pub u: f32,
    pub v: f32,
}

/// `visualization_msgs/msg/MeshFile`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MeshFile {
    pub filename: String,
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// `visualization_msgs/msg/Marker` (Jazzy layout).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Marker {
    pub header: Header,
    pub ns: String,
    pub id: i32,
    #[serde(rename = "type")]
    pub type_: i32,
    pub action: i32,
    pub pose: Pose,
    pub scale: Vector3,
    pub color: ColorRGBA,
    pub lifetime: Duration,
    pub frame_locked: bool,
    pub points: Vec<Point>,
    pub colors: Vec<ColorRGBA>,
    pub texture_resource: String,
    pub texture: CompressedImage,
    pub uv_coordinates: Vec<UVCoordinate>,
    pub text: String,
    pub mesh_resource: String,
    pub mesh_file: MeshFile,
    pub mesh_use_embedded_materials: bool,
}

impl Marker {
    pub const ARROW: i32 = 0;
    pub const SPHERE: i32 = 2;
    pub const TEXT_VIEW_FACING: i32 = 9;
    pub const ADD: i32 = 0;
    pub const DELETEALL: i32 = 3;
}

/// `visualization_msgs/msg/MarkerArray`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MarkerArray {
    pub markers: Vec<Marker>,
}

/// `bom_msgs/msg/ParameterEstimate` (see `msg/msg/ParameterEstimate.msg`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct ParameterEstimate {
    pub known: bool,
    pub median: f64,
    pub sd: f64,
    pub q05: f64,
    pub q95: f64,
}

/// `bom_msgs/msg/JointPosterior` (see `msg/msg/JointPosterior.msg`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct JointPosterior {
    pub child: i32,
    pub parent: i32,
    pub parent_candidates: Vec<i32>,
    pub parent_probs: Vec<f64>,
    pub most_probable_type: String,
    pub p_rigid: f64,
    pub p_prismatic: f64,
    pub p_revolute: f64,
    pub axis_direction: Vector3,
    pub axis_direction_sd_deg: f64,
    pub axis_direction_q90_deg: f64,
    pub has_axis_point: bool,
    pub axis_point: Point,
    pub axis_point_sd_m: f64,
    pub damping: ParameterEstimate,
    pub friction: ParameterEstimate,
    pub mass: ParameterEstimate,
}

/// `bom_msgs/msg/ObjectModel` (see `msg/msg/ObjectModel.msg`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ObjectModel {
    pub header: Header,
    pub mode: String,
    pub inference: String,
    pub runtime_s: f64,
    pub elbo: f64,
    pub num_windows: u32,
    pub part_labels: Vec<i32>,
    pub joints: Vec<JointPosterior>,
}

/// `bom_msgs/msg/EffectFinding`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct EffectFinding {
    pub part: i32,
    pub effect: String,
    pub param_names: Vec<String>,
    pub param_values: Vec<f64>,
    pub rmse_before_m: f64,
    pub rmse_after_m: f64,
}

/// `bom_msgs/msg/ModelCriticism`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ModelCriticism {
    pub header: Header,
    pub findings: Vec<EffectFinding>,
}

/// The `.msg` text of a type named `pkg/Type` or `pkg/msg/Type`, if bom knows it.
fn msg_text(name: &str) -> Option<&'static str> {
    let short = name.replace("/msg/", "/");
    Some(match short.as_str() {
        "builtin_interfaces/Time" => include_str!("defs/builtin_interfaces/Time.msg"),
        "builtin_interfaces/Duration" => include_str!("defs/builtin_interfaces/Duration.msg"),
        "std_msgs/Header" => include_str!("defs/std_msgs/Header.msg"),
        "std_msgs/ColorRGBA" => include_str!("defs/std_msgs/ColorRGBA.msg"),
        "geometry_msgs/Vector3" => include_str!("defs/geometry_msgs/Vector3.msg"),
        "geometry_msgs/Point" => include_str!("defs/geometry_msgs/Point.msg"),
        "geometry_msgs/Quaternion" => include_str!("defs/geometry_msgs/Quaternion.msg"),
        "geometry_msgs/Pose" => include_str!("defs/geometry_msgs/Pose.msg"),
        "geometry_msgs/PoseArray" => include_str!("defs/geometry_msgs/PoseArray.msg"),
        "geometry_msgs/Transform" => include_str!("defs/geometry_msgs/Transform.msg"),
        "geometry_msgs/TransformStamped" => include_str!("defs/geometry_msgs/TransformStamped.msg"),
        "geometry_msgs/Wrench" => include_str!("defs/geometry_msgs/Wrench.msg"),
        "geometry_msgs/WrenchStamped" => include_str!("defs/geometry_msgs/WrenchStamped.msg"),
        "sensor_msgs/PointCloud2" => include_str!("defs/sensor_msgs/PointCloud2.msg"),
        "sensor_msgs/PointField" => include_str!("defs/sensor_msgs/PointField.msg"),
        "sensor_msgs/CompressedImage" => include_str!("defs/sensor_msgs/CompressedImage.msg"),
        "visualization_msgs/Marker" => include_str!("defs/visualization_msgs/Marker.msg"),
        "visualization_msgs/MarkerArray" => include_str!("defs/visualization_msgs/MarkerArray.msg"),
        "visualization_msgs/UVCoordinate" => include_str!("defs/visualization_msgs/UVCoordinate.msg"),
        "visualization_msgs/MeshFile" => include_str!("defs/visualization_msgs/MeshFile.msg"),
        "tf2_msgs/TFMessage" => "geometry_msgs/TransformStamped[] transforms\n",
        "bom_msgs/ParameterEstimate" => include_str!("../../msg/msg/ParameterEstimate.msg"),
        "bom_msgs/JointPosterior" => include_str!("../../msg/msg/JointPosterior.msg"),
        "bom_msgs/ObjectModel" => include_str!("../../msg/msg/ObjectModel.msg"),
        "bom_msgs/EffectFinding" => include_str!("../../msg/msg/EffectFinding.msg"),
        "bom_msgs/ModelCriticism" => include_str!("../../msg/msg/ModelCriticism.msg"),
        _ => return None,
    })
}

const PRIMITIVES: &[&str] = &[
    "bool", "byte", "char", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64",
    "float32", "float64", "string", "wstring",
];

/// Complex field types used by a `.msg` text, resolved to `pkg/Type` (a bare name refers to `pkg`).
fn dependencies(pkg: &str, text: &str) -> Vec<String> {
    let mut out = Vec::new();
    for line in text.lines() {
        let line = line.split('#').next().unwrap_or("").trim();
        let Some(ty) = line.split_whitespace().next() else { continue };
        if line.contains('=') && !line.contains(' ') {
            continue;
        }
        // Constants have the form `TYPE NAME=VALUE`; they are always primitive.
        let base = ty.split('[').next().unwrap_or(ty);
        let base = base.split("<=").next().unwrap_or(base);
        if PRIMITIVES.contains(&base) {
            continue;
        }
        let full = if base.contains('/') { base.replace("/msg/", "/") } else { format!("{pkg}/{base}") };
        if !out.contains(&full) {
            out.push(full);
        }
    }
    out
}

/// The `ros2msg` schema text of `name` (e.g. `sensor_msgs/msg/PointCloud2`) as rosbag2 writes it:
/// the type's own `.msg` text followed by one `MSG: pkg/Type` section per nested type.
///
/// # Panics
/// Never for the types this module defines; an unknown name gives `None`.
pub fn ros2msg_schema(name: &str) -> Option<String> {
    let root = name.replace("/msg/", "/");
    let mut text = msg_text(&root)?.to_string();
    let mut seen = vec![root.clone()];
    let mut queue = dependencies(root.split('/').next().unwrap_or(""), msg_text(&root)?);
    while let Some(dep) = queue.first().cloned() {
        queue.remove(0);
        if seen.contains(&dep) {
            continue;
        }
        let body = msg_text(&dep)?;
        text.push_str("\n================================================================================\nMSG: ");
        text.push_str(&dep);
        text.push('\n');
        text.push_str(body);
        let pkg = dep.split('/').next().unwrap_or("").to_string();
        queue.extend(dependencies(&pkg, body));
        seen.push(dep);
    }
    Some(text)
}

/// Errors of CDR (de)serialisation.
#[derive(Debug, thiserror::Error)]
pub enum CdrError {
    #[error("message shorter than its 4-byte CDR encapsulation header")]
    NoHeader,
    #[error("unknown CDR encapsulation kind {0:#04x}")]
    Encapsulation(u8),
    #[error("{0}")]
    Decode(#[from] cdr_encoding::Error),
}

/// Decode a CDR message as stored in ROS 2 MCAP (`cdr` message encoding): a 4-byte encapsulation
/// header (0x00 0x00 = big endian, 0x00 0x01 = little endian) then the plain CDR body.
pub fn decode_cdr<T: serde::de::DeserializeOwned>(bytes: &[u8]) -> Result<T, CdrError> {
    if bytes.len() < 4 {
        return Err(CdrError::NoHeader);
    }
    let body = &bytes[4..];
    let v = match bytes[1] {
        0x00 => cdr_encoding::from_bytes::<T, byteorder::BigEndian>(body)?.0,
        0x01 => cdr_encoding::from_bytes::<T, byteorder::LittleEndian>(body)?.0,
        k => return Err(CdrError::Encapsulation(k)),
    };
    Ok(v)
}

/// Encode a message as little-endian CDR with its encapsulation header, as rosbag2 writes it.
pub fn encode_cdr<T: Serialize>(msg: &T) -> Result<Vec<u8>, CdrError> {
    let mut out = vec![0x00, 0x01, 0x00, 0x00];
    out.extend(cdr_encoding::to_vec::<T, byteorder::LittleEndian>(msg)?);
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn schemas_resolve_every_nested_type() {
        let s = ros2msg_schema("visualization_msgs/msg/MarkerArray").unwrap();
        for dep in ["MSG: visualization_msgs/Marker", "MSG: std_msgs/Header", "MSG: builtin_interfaces/Time",
            "MSG: sensor_msgs/CompressedImage", "MSG: visualization_msgs/MeshFile", "MSG: geometry_msgs/Pose"] {
            assert!(s.contains(dep), "missing {dep}");
        }
        let s = ros2msg_schema("bom_msgs/msg/ObjectModel").unwrap();
        assert!(s.contains("MSG: bom_msgs/JointPosterior") && s.contains("MSG: bom_msgs/ParameterEstimate"));
        assert!(ros2msg_schema("nope/msg/Nope").is_none());
    }

    #[test]
    fn cdr_round_trip_both_byte_orders() {
        let m = WrenchStamped {
            header: Header { stamp: Time { sec: 3, nanosec: 5 }, frame_id: "contact".into() },
            wrench: Wrench { force: Vector3 { x: 1.0, y: -2.0, z: 3.5 }, torque: Vector3::default() },
        };
        let bytes = encode_cdr(&m).unwrap();
        assert_eq!(decode_cdr::<WrenchStamped>(&bytes).unwrap(), m);
        let mut be = vec![0x00, 0x00, 0x00, 0x00];
        be.extend(cdr_encoding::to_vec::<_, byteorder::BigEndian>(&m).unwrap());
        assert_eq!(decode_cdr::<WrenchStamped>(&be).unwrap(), m);
        assert!(decode_cdr::<WrenchStamped>(&bytes[..bytes.len() - 3]).is_err());
    }
}
