//! Configuration: one YAML file (`--config`, or the `bom: ros__parameters:` section of a ROS 2
//! parameters file) holding every stage's settings. Missing keys take the defaults below.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::criticism::CriticismConfig;
use crate::eval::tracking::TrackingConfig;
use crate::prediction::PredictConfig;
use crate::inference::nuts::NutsConfig;
use crate::inference::svi::SviConfig;
use crate::input::{InputLimits, Topics};
use crate::model::ModelConfig;
use crate::perception::PerceptionConfig;
use crate::windows::WindowConfig;

/// All settings of bom.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    /// The fixed frame, node 0 of every kinematic tree.
    pub fixed_frame: String,
    pub topics: Topics,
    /// Bounds on input sizes and plausible values (bad input is warned about, counted, dropped).
    pub input: InputLimits,
    pub perception: PerceptionConfig,
    pub windows: WindowConfig,
    pub model: ModelConfig,
    pub inference: SviConfig,
    /// BOM-NUTS after the last SVI posterior (`--inference nuts`; off by default).
    pub nuts: NutsConfig,
    pub criticism: CriticismConfig,
    /// The posterior predictive (`bom predict`, the node's predicted part poses, `--tracking`).
    pub prediction: PredictConfig,
    /// `bom eval --tracking`: the Kalman baselines' process noise.
    pub tracking: TrackingConfig,
}

impl Config {
    pub fn new() -> Self {
        Config { fixed_frame: "world".into(), ..Default::default() }
    }

    /// Load from YAML; accepts either the plain settings or a ROS 2 parameters file
    /// (`bom: ros__parameters: {...}`).
    ///
    /// # Errors
    /// A one-line description naming the file and the offending key.
    pub fn load(path: &Path) -> Result<Config, String> {
        let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
        Self::from_yaml(&text, &path.display().to_string())
    }

    /// Parse settings from YAML text, as [`Config::load`]; `source` names it in errors.
    ///
    /// # Errors
    /// A one-line description naming `source` and the offending key.
    pub fn from_yaml(text: &str, source: &str) -> Result<Config, String> {
        let value: serde_yaml::Value = serde_yaml::from_str(text).map_err(|e| format!("{source}: {e}"))?;
        let inner = value
            .get("bom")
            .and_then(|b| b.get("ros__parameters"))
            .cloned()
            .unwrap_or(value);
        let mut cfg: Config = serde_yaml::from_value(inner).map_err(|e| format!("{source}: {e}"))?;
        if cfg.fixed_frame.is_empty() {
            cfg.fixed_frame = "world".into();
        }
        // A rate of 0 or below would report every joint type as equally probable, NaN nothing.
        if !(cfg.inference.report_rate.is_finite() && cfg.inference.report_rate > 0.0) {
            return Err(format!("{source}: inference.report_rate must be a positive number, got {}", cfg.inference.report_rate));
        }
        // A negative or NaN discrepancy would make every reported axis spread NaN.
        for (name, v) in [("axis_discrepancy_deg", cfg.model.axis_discrepancy_deg), ("axis_point_discrepancy_m", cfg.model.axis_point_discrepancy_m)] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{source}: model.{name} must be a number >= 0, got {v}"));
            }
        }
        Ok(cfg)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The shipped parameters file states exactly the defaults.
    #[test]
    fn shipped_parameters_file_is_the_defaults() {
        let cfg = Config::load(Path::new("config/bom.yaml")).unwrap();
        assert_eq!(cfg, Config::new());
        let bad = std::env::temp_dir().join("bom_bad_config.yaml");
        std::fs::write(&bad, "bom:\n  ros__parameters:\n    windows: {force_open: 2}\n").unwrap();
        let e = Config::load(&bad).unwrap_err();
        assert!(e.contains("force_open"), "{e}");
        let e = Config::from_yaml("inference: {report_rate: -0.1}", "test").unwrap_err();
        assert!(e.contains("inference.report_rate"), "{e}");
        for (bad, key) in [("model: {axis_discrepancy_deg: -1}", "model.axis_discrepancy_deg"), ("model: {axis_point_discrepancy_m: .nan}", "model.axis_point_discrepancy_m")] {
            let e = Config::from_yaml(bad, "test").unwrap_err();
            assert!(e.contains(key), "{bad}: {e}");
        }
    }

    /// Every key path of a YAML mapping, `a.b.c`; sequences are values.
    fn key_paths(v: &serde_yaml::Value, prefix: &str, out: &mut std::collections::BTreeSet<String>) {
        if let serde_yaml::Value::Mapping(m) = v {
            for (k, v) in m {
                let k = k.as_str().expect("string keys");
                let path = if prefix.is_empty() { k.to_string() } else { format!("{prefix}.{k}") };
                key_paths(v, &path, out);
                out.insert(path);
            }
        }
    }

    /// The README says `config/bom.yaml` lists every key: it holds exactly the keys of the
    /// configuration structs (a key added to a struct and not to the file fails here).
    #[test]
    fn shipped_parameters_file_lists_every_key() {
        let text = std::fs::read_to_string("config/bom.yaml").unwrap();
        let file: serde_yaml::Value = serde_yaml::from_str(&text).unwrap();
        let mut listed = std::collections::BTreeSet::new();
        key_paths(&file["bom"]["ros__parameters"], "", &mut listed);
        let mut all = std::collections::BTreeSet::new();
        key_paths(&serde_yaml::to_value(Config::new()).unwrap(), "", &mut all);
        let missing: Vec<_> = all.difference(&listed).collect();
        let unknown: Vec<_> = listed.difference(&all).collect();
        assert!(missing.is_empty() && unknown.is_empty(), "missing from config/bom.yaml: {missing:?}; not a setting: {unknown:?}");
    }
}
