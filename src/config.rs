//! Configuration: one YAML file (`--config`, or the `bom: ros__parameters:` section of a ROS 2
//! parameters file) holding every stage's settings. Missing keys take the defaults below.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::criticism::CriticismConfig;
use crate::inference::svi::SviConfig;
use crate::input::Topics;
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
    pub perception: PerceptionConfig,
    pub windows: WindowConfig,
    pub model: ModelConfig,
    pub inference: SviConfig,
    pub criticism: CriticismConfig,
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
        let value: serde_yaml::Value = serde_yaml::from_str(&text).map_err(|e| format!("{}: {e}", path.display()))?;
        let inner = value
            .get("bom")
            .and_then(|b| b.get("ros__parameters"))
            .cloned()
            .unwrap_or(value);
        let mut cfg: Config = serde_yaml::from_value(inner).map_err(|e| format!("{}: {e}", path.display()))?;
        if cfg.fixed_frame.is_empty() {
            cfg.fixed_frame = "world".into();
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
    }
}
