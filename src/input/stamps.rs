//! Header stamps checked against the stream's own clock, one clock per topic (issue 27).
//!
//! A stream's stamps should rise. Two kinds of damage break that, and they must be told apart so
//! that one bad stamp cannot poison a stream:
//! - **one stamp far ahead** (a clock glitch, a corrupted field): if it were taken as the new
//!   clock, every later message would look like "time going backwards" and be dropped. A jump of
//!   more than [`StampLimits::jump_s`] is therefore held until the next message on the topic
//!   confirms it (a stamp at or after it: a real gap) or refutes it (a stamp between the old clock
//!   and the jump: the jump was an outlier, dropped with a warning);
//! - **the clock going back for good** (a publisher restarted with its clock reset, a bag whose
//!   first stamp was the outlier): [`StampLimits::reset_messages`] consecutive messages behind the
//!   clock, rising among themselves, reset the topic's clock to them.
//!
//! Single messages behind the clock are dropped as before ("time went backwards"). Everything
//! dropped is warned about and counted through [`Diagnostics`].

use crate::diagnostics::Diagnostics;

/// When a stamp is suspect (part of [`super::InputLimits`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StampLimits {
    /// A stamp more than this far ahead of the topic's clock waits for the next message \[s\].
    pub jump_s: f64,
    /// This many consecutive messages behind the clock, rising among themselves, reset it.
    pub reset_messages: u32,
}

/// The clock of one topic and the one message, if any, whose jump ahead awaits confirmation.
#[derive(Debug, Clone)]
pub struct StampGuard<T> {
    limits: StampLimits,
    /// Stamp of the last accepted message \[s\].
    clock: Option<f64>,
    /// A message whose stamp jumped ahead, waiting for the next one.
    suspect: Option<(f64, T)>,
    /// Consecutive messages behind the clock, and the last of their stamps.
    behind: (u32, f64),
}

impl<T> StampGuard<T> {
    pub fn new(limits: StampLimits) -> Self {
        StampGuard { limits, clock: None, suspect: None, behind: (0, f64::NEG_INFINITY) }
    }

    /// Offer the message `item` stamped `t` \[s\] on `topic`; returns the messages released, in
    /// order: this one, a confirmed earlier one, both, or none (this one held for its jump, or
    /// dropped and counted).
    pub fn push(&mut self, topic: &str, t: f64, item: T, diag: &mut Diagnostics) -> Vec<(f64, T)> {
        let mut out = Vec::new();
        if let Some((ts, held)) = self.suspect.take() {
            let clock = self.clock.unwrap_or(f64::NEG_INFINITY);
            if t >= ts {
                // The stream carried on from the jump: a real gap.
                self.clock = Some(ts);
                out.push((ts, held));
            } else if t >= clock {
                diag.warn(
                    topic,
                    "stamp outlier",
                    &format!(
                        "header.stamp {ts:.6} s jumped {:.3} s ahead of the stream and the next message ({t:.6} s) is back; that message skipped",
                        ts - clock
                    ),
                );
            } else {
                // Behind both: it says nothing about the jump, which keeps waiting.
                self.suspect = Some((ts, held));
            }
        }
        self.offer(topic, t, item, &mut out, diag);
        out
    }

    fn offer(&mut self, topic: &str, t: f64, item: T, out: &mut Vec<(f64, T)>, diag: &mut Diagnostics) {
        let Some(clock) = self.clock else {
            self.clock = Some(t);
            out.push((t, item));
            return;
        };
        if t < clock {
            let (n, last) = self.behind;
            let n = if n > 0 && t >= last { n + 1 } else { 1 };
            self.behind = (n, t);
            if n >= self.limits.reset_messages.max(1) {
                diag.warn(
                    topic,
                    "clock reset",
                    &format!("{n} messages in a row behind the stream's clock ({clock:.6} s); its clock restarts at {t:.6} s"),
                );
                self.behind = (0, f64::NEG_INFINITY);
                if let Some((ts, _)) = self.suspect.take() {
                    diag.warn(topic, "stamp outlier", &format!("header.stamp {ts:.6} s held for its jump ahead; dropped at the clock reset"));
                }
                self.clock = Some(t);
                out.push((t, item));
                return;
            }
            diag.warn(topic, "time went backwards", &format!("header.stamp {t:.6} s after {clock:.6} s; message skipped"));
            return;
        }
        self.behind = (0, f64::NEG_INFINITY);
        if self.suspect.is_none() && t - clock > self.limits.jump_s {
            self.suspect = Some((t, item));
            return;
        }
        self.clock = Some(t);
        out.push((t, item));
    }

    /// End of the stream: a message still held is released (nothing refuted its jump).
    pub fn flush(&mut self) -> Option<(f64, T)> {
        let s = self.suspect.take();
        if let Some((t, _)) = &s {
            self.clock = Some(*t);
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(stamps: &[f64]) -> (Vec<f64>, Diagnostics) {
        let mut g = StampGuard::new(StampLimits { jump_s: 1.0, reset_messages: 5 });
        let mut diag = Diagnostics::default();
        let mut got = Vec::new();
        for (i, &t) in stamps.iter().enumerate() {
            got.extend(g.push("/t", t, i, &mut diag).into_iter().map(|(t, _)| t));
        }
        got.extend(g.flush().map(|(t, _)| t));
        (got, diag)
    }

    #[test]
    fn one_stamp_far_ahead_is_dropped_and_the_stream_goes_on() {
        let mut s: Vec<f64> = (0..30).map(|k| k as f64 / 30.0).collect();
        s.insert(10, 1e6);
        let (got, diag) = run(&s);
        assert_eq!(got.len(), 30, "{got:?}");
        assert!(got.iter().all(|t| *t < 1.0));
        assert_eq!(diag.counts().get("/t: stamp outlier"), Some(&1));
        assert_eq!(diag.total(), 1);
    }

    #[test]
    fn a_real_gap_is_kept_whole() {
        let s: Vec<f64> = (0..10).map(|k| k as f64 * 0.1).chain((0..10).map(|k| 300.0 + k as f64 * 0.1)).collect();
        let (got, diag) = run(&s);
        assert_eq!(got, s);
        assert_eq!(diag.total(), 0);
        // A jump at the very end has nothing to refute it: released by flush.
        let (got, _) = run(&[0.0, 0.1, 50.0]);
        assert_eq!(got, vec![0.0, 0.1, 50.0]);
    }

    #[test]
    fn a_single_backward_stamp_is_dropped_and_a_restarted_clock_is_followed() {
        let (got, diag) = run(&[1.0, 1.1, 0.5, 1.2]);
        assert_eq!(got, vec![1.0, 1.1, 1.2]);
        assert_eq!(diag.counts().get("/t: time went backwards"), Some(&1));
        // The first stamp was the outlier: five rising stamps behind it reset the clock.
        let mut s = vec![1e6];
        s.extend((0..20).map(|k| k as f64 * 0.1));
        let (got, diag) = run(&s);
        assert_eq!(got.len(), 1 + 16, "{got:?}");
        assert_eq!(diag.counts().get("/t: clock reset"), Some(&1));
        assert_eq!(diag.counts().get("/t: time went backwards"), Some(&4));
    }
}
