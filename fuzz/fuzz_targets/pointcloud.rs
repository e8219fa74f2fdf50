//! PointCloud2 layouts built field by field from the fuzzer's bytes (sizes, steps, offsets,
//! datatypes, byte order, data), through `input::pointcloud::decode`: every size a sender can
//! declare, against the data actually present. Then an encode -> decode round trip of the
//! points that decoded.
#![no_main]

use arbitrary::Arbitrary;
use bom::input::pointcloud::{decode, encode_xyzl};
use bom::msgs::{Header, PointCloud2, PointField};
use libfuzzer_sys::fuzz_target;

#[derive(Arbitrary, Debug)]
struct Field {
    name: u8,
    offset: u32,
    datatype: u8,
}

#[derive(Arbitrary, Debug)]
struct Cloud {
    height: u32,
    width: u32,
    fields: Vec<Field>,
    is_bigendian: bool,
    point_step: u32,
    row_step: u32,
    max_points: u32,
    data: Vec<u8>,
}

fuzz_target!(|c: Cloud| {
    const NAMES: [&str; 5] = ["x", "y", "z", "label", "rgb"];
    let cloud = PointCloud2 {
        header: Header::default(),
        height: c.height,
        width: c.width,
        fields: c
            .fields
            .iter()
            .map(|f| PointField { name: NAMES[f.name as usize % NAMES.len()].into(), offset: f.offset, datatype: f.datatype, count: 1 })
            .collect(),
        is_bigendian: c.is_bigendian,
        point_step: c.point_step,
        row_step: c.row_step,
        data: c.data,
        is_dense: false,
    };
    if let Ok(lp) = decode(&cloud, c.max_points as u64, 1e3) {
        assert_eq!(lp.points.len(), lp.labels.len());
        assert!(lp.points.len() as u64 <= cloud.width as u64 * cloud.height as u64);
        // What decoded encodes and decodes to the same points (as f32) and labels.
        let again = decode(&encode_xyzl(Header::default(), &lp.points, &lp.labels), u64::MAX, 1e3).expect("own encoding");
        assert_eq!(again.labels, lp.labels);
        for (a, b) in again.points.iter().zip(&lp.points) {
            for k in 0..3 {
                assert_eq!(a[k], b[k] as f32 as f64);
            }
        }
    }
});
