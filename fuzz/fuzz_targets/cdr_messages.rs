//! One CDR-encoded message of each input type, as a DDS sample reaches `bom node`: the first byte
//! picks the type (PointCloud2, WrenchStamped, TFMessage), the rest is the serialized message with
//! its 4-byte encapsulation header. Decoded with `msgs::decode_cdr`, then fed to the node's
//! streaming pipeline (`pipeline::online::Online`: cloud decoding, transforms, stamps, perception,
//! windows). Seeds: `fuzz/corpus/cdr_messages/` (messages from `bags/`).
#![no_main]

use bom::config::Config;
use bom::msgs::{decode_cdr, PointCloud2, TFMessage, WrenchStamped};
use bom::pipeline::online::Online;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&kind, msg)) = data.split_first() else { return };
    let cfg = Config::new();
    let mut on = Online::new(&cfg);
    match kind % 4 {
        0 => {
            if let Ok(c) = decode_cdr::<PointCloud2>(msg) {
                on.cloud("/segmented_points", &c);
            }
        }
        1 => {
            if let Ok(w) = decode_cdr::<WrenchStamped>(msg) {
                on.wrench("/applied_wrench", &w);
            }
        }
        2 => {
            if let Ok(t) = decode_cdr::<TFMessage>(msg) {
                on.tf("/tf", &t, false);
            }
        }
        _ => {
            if let Ok(t) = decode_cdr::<TFMessage>(msg) {
                on.tf("/tf_static", &t, true);
            }
        }
    }
    on.close_windows();
    on.flush();
});
