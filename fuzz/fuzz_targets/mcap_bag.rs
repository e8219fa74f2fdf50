//! An MCAP file, through bom's own reader and every decoder behind it: records and chunks
//! (`input::read_mcap`), then CDR, TF, PointCloud2 and wrench decoding into a recording in the
//! fixed frame (`input::decode_recording_with`). Nothing may panic, abort or allocate beyond the
//! limits. Seeds: `fuzz/corpus/mcap_bag/` (small bags from `bags/`).
#![no_main]

use bom::config::Config;
use bom::diagnostics::Diagnostics;
use bom::input::{self, Bag};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let mut cfg = Config::new();
    // The same code path as the default 128 MiB, with less memory per execution.
    cfg.input.max_record_bytes = 16 << 20;
    let mut diag = Diagnostics::default();
    let Ok(contents) = input::read_mcap(data, "fuzz", &cfg.input, &mut diag) else { return };
    if let Some(json) = &contents.ground_truth_json {
        let _ = serde_json::from_str::<input::GroundTruth>(json);
    }
    let bag = Bag { path: "fuzz".into(), messages: contents.messages, ground_truth: None };
    let _ = input::decode_recording_with(&[bag], &cfg.topics, &cfg.fixed_frame, &cfg.input, &mut diag);
});
