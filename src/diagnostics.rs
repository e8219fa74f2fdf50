//! Counting and logging of bad input.
//!
//! Every stage that meets bad input (a malformed cloud, a NaN, an unknown frame, a truncated bag,
//! time going backwards) reports it here: one line naming the topic or field and why, logged as a
//! warning the first [`WARN_LIMIT`] times per kind (later repeats at debug level, so a bad stream
//! cannot flood the log), and counted. The counts go into the summary so nothing disappears
//! silently.

use std::collections::BTreeMap;

/// Warnings logged per `topic: kind` before later ones go to debug level.
pub const WARN_LIMIT: u64 = 5;

/// Counts of bad-input events by `topic: kind`.
#[derive(Debug, Default, Clone, serde::Serialize)]
pub struct Diagnostics {
    counts: BTreeMap<String, u64>,
}

impl Diagnostics {
    /// Record one event: `source` is the topic, file or field at fault, `kind` a short stable
    /// category (e.g. `data shorter than declared`), `detail` the specifics for the log line.
    pub fn warn(&mut self, source: &str, kind: &str, detail: &str) {
        let key = format!("{source}: {kind}");
        let n = self.counts.entry(key).or_insert(0);
        *n += 1;
        if *n <= WARN_LIMIT {
            tracing::warn!("{source}: {kind}: {detail}");
            if *n == WARN_LIMIT {
                tracing::warn!("{source}: {kind}: further ones are counted and logged at debug level");
            }
        } else {
            tracing::debug!("{source}: {kind}: {detail} (seen {n} times)");
        }
    }

    /// All counts, `topic: kind` -> number of events.
    pub fn counts(&self) -> &BTreeMap<String, u64> {
        &self.counts
    }

    /// Total number of bad-input events.
    pub fn total(&self) -> u64 {
        self.counts.values().sum()
    }
}
