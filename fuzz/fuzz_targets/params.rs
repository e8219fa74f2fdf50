//! A parameters file (`--config`, `--params-file`): YAML text through `Config::from_yaml`. Seeds:
//! `fuzz/corpus/params/` (config/bom.yaml and subsets).
#![no_main]

use bom::config::Config;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = Config::from_yaml(text, "fuzz.yaml");
    }
});
