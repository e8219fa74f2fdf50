//! Decoding of segmented `sensor_msgs/PointCloud2` clouds (contract section 1).
//!
//! Handles any field order, extra fields, padding in `point_step` and `row_step`, organised clouds
//! (`height > 1`), NaN/Inf points (skipped), big-endian data, `x`/`y`/`z` as FLOAT32 or FLOAT64 and
//! `label` as any integer datatype or a FLOAT32 holding an integer value.

use crate::msgs::{PointCloud2, PointField};

/// The labelled points of one cloud, in the cloud's `header.frame_id`.
#[derive(Debug, Clone, Default)]
pub struct LabeledPoints {
    /// Point coordinates \[m\], in the cloud's frame; label-0 and non-finite points are dropped.
    pub points: Vec<[f64; 3]>,
    /// Part label of each point (>= 1).
    pub labels: Vec<u32>,
    /// Points skipped because a coordinate was NaN or infinite.
    pub nonfinite: usize,
    /// Points skipped because the label was not a non-negative integer (FLOAT32 labels only).
    pub bad_labels: usize,
    /// Points skipped because they lie farther than the plausible range from the frame's origin.
    pub out_of_range: usize,
}

/// Why a cloud could not be decoded; the whole cloud is then skipped.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CloudError {
    #[error("field '{0}' missing")]
    MissingField(&'static str),
    #[error("field '{name}' has unsupported datatype {datatype} ({why})")]
    UnsupportedDatatype { name: &'static str, datatype: u8, why: &'static str },
    #[error("field '{name}' at offset {offset} (+{size} bytes) overruns point_step {point_step}")]
    FieldOverrun { name: &'static str, offset: u32, size: u32, point_step: u32 },
    #[error("row_step {row_step} < width {width} x point_step {point_step}")]
    RowStepTooSmall { row_step: u32, width: u32, point_step: u32 },
    #[error("data is {actual} bytes, shorter than the declared {declared} (height {height} x row_step {row_step})")]
    DataTooShort { actual: usize, declared: u64, height: u32, row_step: u32 },
    #[error("{points} points (width {width} x height {height}) exceed input.max_cloud_points = {max}")]
    TooManyPoints { points: u64, width: u32, height: u32, max: u64 },
}

fn datatype_size(dt: u8) -> Option<u32> {
    Some(match dt {
        PointField::INT8 | PointField::UINT8 => 1,
        PointField::INT16 | PointField::UINT16 => 2,
        PointField::INT32 | PointField::UINT32 | PointField::FLOAT32 => 4,
        PointField::FLOAT64 => 8,
        _ => return None,
    })
}

#[derive(Clone, Copy)]
struct Field {
    offset: usize,
    datatype: u8,
}

fn find(cloud: &PointCloud2, name: &'static str) -> Result<Field, CloudError> {
    let f = cloud.fields.iter().find(|f| f.name == name).ok_or(CloudError::MissingField(name))?;
    let size = datatype_size(f.datatype).ok_or(CloudError::UnsupportedDatatype {
        name,
        datatype: f.datatype,
        why: "not a PointField datatype",
    })?;
    // In 64 bits: an offset near u32::MAX must not wrap past the check.
    if f.offset as u64 + size as u64 > cloud.point_step as u64 {
        return Err(CloudError::FieldOverrun { name, offset: f.offset, size, point_step: cloud.point_step });
    }
    Ok(Field { offset: f.offset as usize, datatype: f.datatype })
}

#[inline]
fn bytes<const N: usize>(b: &[u8], big: bool) -> [u8; N] {
    let mut a = [0u8; N];
    a.copy_from_slice(&b[..N]);
    if big {
        a.reverse();
    }
    a
}

/// Read a numeric field as f64 (little-endian bytes after `bytes` normalises the order).
#[inline]
fn read(p: &[u8], f: Field, big: bool) -> f64 {
    let b = &p[f.offset..];
    match f.datatype {
        PointField::INT8 => b[0] as i8 as f64,
        PointField::UINT8 => b[0] as f64,
        PointField::INT16 => i16::from_le_bytes(bytes::<2>(b, big)) as f64,
        PointField::UINT16 => u16::from_le_bytes(bytes::<2>(b, big)) as f64,
        PointField::INT32 => i32::from_le_bytes(bytes::<4>(b, big)) as f64,
        PointField::UINT32 => u32::from_le_bytes(bytes::<4>(b, big)) as f64,
        PointField::FLOAT32 => f32::from_le_bytes(bytes::<4>(b, big)) as f64,
        _ => f64::from_le_bytes(bytes::<8>(b, big)),
    }
}

/// Decode the labelled points of a segmented cloud: at most `max_points` points (`width x
/// height`); points farther than `max_range_m` from the frame's origin are skipped and counted.
///
/// Every size is checked in 64-bit arithmetic against `data` before anything is allocated or
/// sliced, so no field of a damaged cloud can make this panic or allocate beyond `max_points`.
///
/// # Errors
/// A [`CloudError`] when the cloud's layout is unusable: a missing `x`/`y`/`z`/`label` field, a
/// coordinate that is not FLOAT32/FLOAT64, a label that is FLOAT64 (or not a PointField datatype), a
/// field overrunning `point_step`, `data` shorter than `height x row_step`, or more points than
/// `max_points`.
pub fn decode(cloud: &PointCloud2, max_points: u64, max_range_m: f64) -> Result<LabeledPoints, CloudError> {
    let xyz = [find(cloud, "x")?, find(cloud, "y")?, find(cloud, "z")?];
    for (f, name) in xyz.iter().zip(["x", "y", "z"]) {
        if f.datatype != PointField::FLOAT32 && f.datatype != PointField::FLOAT64 {
            return Err(CloudError::UnsupportedDatatype { name, datatype: f.datatype, why: "coordinates must be FLOAT32 or FLOAT64" });
        }
    }
    let label_dt = cloud.fields.iter().find(|f| f.name == "label").map(|f| f.datatype);
    if label_dt == Some(PointField::FLOAT64) {
        return Err(CloudError::UnsupportedDatatype {
            name: "label",
            datatype: PointField::FLOAT64,
            why: "labels must be an integer datatype or FLOAT32",
        });
    }
    let label = find(cloud, "label")?;
    let (w, h, step) = (cloud.width, cloud.height, cloud.point_step);
    if (w as u64) * (step as u64) > cloud.row_step as u64 {
        return Err(CloudError::RowStepTooSmall { row_step: cloud.row_step, width: w, point_step: step });
    }
    let declared = h as u64 * cloud.row_step as u64;
    if (cloud.data.len() as u64) < declared {
        return Err(CloudError::DataTooShort { actual: cloud.data.len(), declared, height: h, row_step: cloud.row_step });
    }
    let n_points = w as u64 * h as u64;
    if n_points > max_points {
        return Err(CloudError::TooManyPoints { points: n_points, width: w, height: h, max: max_points });
    }
    if n_points == 0 {
        // Without this, width 0 and row_step 0 pass every check above and 4e9 empty rows take
        // seconds to walk (found by the `pointcloud` fuzz target).
        return Ok(LabeledPoints::default());
    }
    let big = cloud.is_bigendian;
    let float_label = label.datatype == PointField::FLOAT32;
    let max_r2 = max_range_m * max_range_m;
    let mut out = LabeledPoints::default();
    // point_step >= 1 here (every field fits in it), so the points are backed by data bytes.
    out.points.reserve(n_points as usize);
    for r in 0..h as usize {
        let row = &cloud.data[r * cloud.row_step as usize..];
        for c in 0..w as usize {
            let p = &row[c * step as usize..(c + 1) * step as usize];
            let lv = read(p, label, big);
            if float_label && (!lv.is_finite() || lv < 0.0 || lv.fract() != 0.0 || lv > u32::MAX as f64) {
                out.bad_labels += 1;
                continue;
            }
            if lv <= 0.0 {
                continue; // label 0 is "no part"; negative integer labels are treated the same
            }
            let x = [read(p, xyz[0], big), read(p, xyz[1], big), read(p, xyz[2], big)];
            if !x.iter().all(|v| v.is_finite()) {
                out.nonfinite += 1;
                continue;
            }
            if !(x[0] * x[0] + x[1] * x[1] + x[2] * x[2] <= max_r2) {
                out.out_of_range += 1;
                continue;
            }
            out.points.push(x);
            out.labels.push(lv as u32);
        }
    }
    Ok(out)
}

/// Build a dense, unorganised little-endian cloud with FLOAT32 `x`, `y`, `z` and UINT32 `label`.
/// Used by `bom import-tracks` and by tests.
pub fn encode_xyzl(header: crate::msgs::Header, points: &[[f64; 3]], labels: &[u32]) -> PointCloud2 {
    let mut data = Vec::with_capacity(points.len() * 16);
    for (p, l) in points.iter().zip(labels) {
        for v in p {
            data.extend_from_slice(&(*v as f32).to_le_bytes());
        }
        data.extend_from_slice(&l.to_le_bytes());
    }
    let field = |name: &str, offset, datatype| PointField { name: name.into(), offset, datatype, count: 1 };
    PointCloud2 {
        header,
        height: 1,
        width: points.len() as u32,
        fields: vec![
            field("x", 0, PointField::FLOAT32),
            field("y", 4, PointField::FLOAT32),
            field("z", 8, PointField::FLOAT32),
            field("label", 12, PointField::UINT32),
        ],
        is_bigendian: false,
        point_step: 16,
        row_step: 16 * points.len() as u32,
        data,
        is_dense: true,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::Header;

    fn field(name: &str, offset: u32, datatype: u8) -> PointField {
        PointField { name: name.into(), offset, datatype, count: 1 }
    }

    /// An organised 2x2 big-endian cloud, label first as INT16, FLOAT64 coordinates, padding in
    /// point_step and row_step, one NaN point and one label-0 point.
    #[test]
    fn decodes_big_endian_organised_padded_cloud() {
        let point_step = 2 + 6 + 24 + 4; // label, pad, xyz f64, trailing intensity
        let row_step = 2 * point_step + 8;
        let mut data = Vec::new();
        let pts = [([1.0, 2.0, 3.0], 2i16), ([f64::NAN, 0.0, 0.0], 2), ([4.0, 5.0, 6.0], 0), ([7.0, 8.0, 9.0], 3)];
        for row in pts.chunks(2) {
            for (p, l) in row {
                data.extend_from_slice(&l.to_be_bytes());
                data.extend_from_slice(&[0u8; 6]);
                for v in p {
                    data.extend_from_slice(&v.to_be_bytes());
                }
                data.extend_from_slice(&1.5f32.to_be_bytes());
            }
            data.extend_from_slice(&[0u8; 8]);
        }
        let cloud = PointCloud2 {
            header: Header::default(),
            height: 2,
            width: 2,
            fields: vec![field("intensity", 32, 7), field("z", 24, 8), field("label", 0, 3), field("x", 8, 8), field("y", 16, 8)],
            is_bigendian: true,
            point_step,
            row_step,
            data,
            is_dense: false,
        };
        let d = decode(&cloud, u64::MAX, f64::INFINITY).unwrap();
        assert_eq!(d.points, vec![[1.0, 2.0, 3.0], [7.0, 8.0, 9.0]]);
        assert_eq!(d.labels, vec![2, 3]);
        assert_eq!(d.nonfinite, 1);
    }

    #[test]
    fn float_labels_and_errors() {
        let mut c = encode_xyzl(Header::default(), &[[1.0, 2.0, 3.0], [0.0, 0.0, 1.0]], &[1, 2]);
        c.fields[3].datatype = PointField::FLOAT32;
        c.data[12..16].copy_from_slice(&4.0f32.to_le_bytes());
        c.data[28..32].copy_from_slice(&1.5f32.to_le_bytes());
        let d = decode(&c, u64::MAX, f64::INFINITY).unwrap();
        assert_eq!((d.labels.clone(), d.bad_labels), (vec![4], 1));

        let mut short = c.clone();
        short.data.truncate(20);
        assert!(matches!(decode(&short, u64::MAX, f64::INFINITY), Err(CloudError::DataTooShort { .. })));
        let mut f64_label = c.clone();
        f64_label.fields[3].datatype = PointField::FLOAT64;
        assert!(matches!(decode(&f64_label, u64::MAX, f64::INFINITY), Err(CloudError::UnsupportedDatatype { name: "label", .. })));
        let mut no_label = c.clone();
        no_label.fields.pop();
        assert_eq!(decode(&no_label, u64::MAX, f64::INFINITY).unwrap_err(), CloudError::MissingField("label"));

        // Sizes from a damaged header: checked in 64 bits, before any allocation or slicing.
        let mut wrapped = c.clone();
        wrapped.fields[3].offset = u32::MAX - 1; // offset + 4 wraps to 2 in 32 bits
        assert!(matches!(decode(&wrapped, u64::MAX, f64::INFINITY), Err(CloudError::FieldOverrun { name: "label", .. })));
        let mut huge = c.clone();
        (huge.width, huge.height, huge.row_step) = (u32::MAX, u32::MAX, u32::MAX);
        assert!(matches!(decode(&huge, u64::MAX, f64::INFINITY), Err(CloudError::RowStepTooSmall { .. })));
        let mut zero_step = c.clone();
        (zero_step.width, zero_step.point_step, zero_step.row_step) = (u32::MAX, 0, 0);
        assert!(matches!(decode(&zero_step, u64::MAX, f64::INFINITY), Err(CloudError::FieldOverrun { .. })));
        assert!(matches!(decode(&c, 1, f64::INFINITY), Err(CloudError::TooManyPoints { points: 2, .. })));
        let mut no_columns = c.clone();
        (no_columns.width, no_columns.height, no_columns.row_step) = (0, u32::MAX, 0);
        // 4e9 empty rows (once walked one by one: seconds per cloud); the fuzz target's inputs
        // that found it are in fuzz/corpus/pointcloud/slow-*, run by CI with a 10 s timeout.
        assert_eq!(decode(&no_columns, u64::MAX, f64::INFINITY).unwrap().points.len(), 0);
        let far = decode(&c, u64::MAX, 2.0).unwrap();
        assert_eq!((far.labels, far.out_of_range), (vec![], 1));
    }
}
