//! The pipeline fed one message at a time (`bom node`): the same stages as [`replay`](super::replay)
//! — input decoding, perception, windows, evidence — with the state a live stream needs.
//!
//! Differences from the batch replay, each forced by not knowing the future:
//! - A message whose transform to the fixed frame is not buffered yet waits, as in a tf2 message
//!   filter, until the transform arrives, or `/tf` has moved [`TF_WAIT_S`] past its stamp, or any
//!   input topic has moved [`TF_WAIT_MAX_S`] past it ([`TF_LATE_MAX_S`] when its frame's
//!   transforms are merely late); it is then dropped with a warning.
//! - A window is *closed* once nothing later can change it: the data have moved past its end by
//!   the merge gap plus the margin before a following window. [`Online::flush`] closes the last
//!   one at the end of the stream as replay does at the end of a bag.
//! - In dynamic mode a cloud waits until the wrench samples up to its stamp are in (at most
//!   [`WRENCH_WAIT_S`] of stream time): the topics arrive in no fixed order (a reliable stream
//!   repairing a lost datagram falls seconds behind), and replay's push gate for a cloud sees
//!   every sample before it.
//! - Perception refines the poses (see [`Perception::refine`]) when windows close, with the part
//!   models as they are then, and keeps a bounded number of frames' points for that.
//! - Wrenches, part observations and transforms outside the closed windows and older than the
//!   open tail are dropped, so memory stays bounded on a node that runs for hours.
//!
//! What comes out is the same as replay's for the same messages: same windows, same pushed
//! parts, and evidence built by the same [`Evidence::new`](crate::model::likelihood::Evidence::new).

use std::collections::{BTreeMap, HashMap, VecDeque};

use nalgebra::Point3;

use crate::config::Config;
use crate::diagnostics::Diagnostics;
use crate::inference::svi;
use crate::criticism::Criticism;
use crate::model::likelihood::Evidence;
use crate::input::tf::TfBuffer;
use crate::input::{self, CloudFrame, LabeledPoints, Sample, StampGuard, WrenchSample};
use crate::msgs::{Header, PointCloud2, TFMessage, WrenchStamped};
use crate::perception::{self, PartGeometry, PartObservation, PartTracks, Perception};
use crate::windows::{self, Window};

/// How long a message may wait for its transform \[s\]: dropped once `/tf` has moved this far
/// past its stamp (tf2 message filters typically wait a fraction of a second) ...
pub const TF_WAIT_S: f64 = 0.5;
/// ... or once any input topic has moved this far past it (a frame that no `/tf` message will
/// ever bring, e.g. with only `/tf_static`, or `/tf` stopped).
pub const TF_WAIT_MAX_S: f64 = 3.0;
/// ... or, when its frame is on `/tf` and only its transform at that stamp has not come yet,
/// once any input topic has moved this far past it \[s\]. A reliable `/tf` stream that lost one
/// datagram delivers nothing more until the writer repairs it (a Fast DDS writer's heartbeat
/// period is 3 s by default), then its backlog at once; meanwhile the other topics run on. At
/// 3 s, wrenches whose transforms were in that backlog were dropped (stop 104: 138 to 419 of
/// 2,063 in four of fourteen interop runs, a window lost in three). Two repair periods.
pub const TF_LATE_MAX_S: f64 = 6.0;
/// How long a cloud waits for the wrench samples up to its stamp: until any input topic has
/// moved this far past it \[s\]. The wrench is a continuous stream (contract section 1: 100-1000
/// Hz), so a silent one is late, as a `/tf` in repair is ([`TF_LATE_MAX_S`]): 0.1 s (three
/// clouds at 30 Hz) gave the push gate and the pushed part's vote clouds whose wrench samples
/// were still in the writer's repair backlog (stop 104: a push given to the cabinet instead of
/// the drawer, in two of nineteen interop runs). A wrench stream that stops delays the clouds
/// by this much and no more.
pub const WRENCH_WAIT_S: f64 = TF_LATE_MAX_S;
/// Messages held waiting for transforms at most; beyond, the oldest is dropped with a warning.
pub const MAX_HELD: usize = 4096;
/// Registered frames per part kept for the refine pass when a window closes (30 s at 30 Hz).
pub const REFINE_FRAMES: usize = 900;
/// Least stream time between two searches for closed windows \[s\] (wrenches come at up to 1 kHz).
pub const CLOSE_CHECK_S: f64 = 0.02;
/// Transforms kept in the buffer, in stream time \[s\] (tf2's default cache is 10 s).
pub const TF_CACHE_S: f64 = 30.0;

/// Everything inference needs for one posterior update: a snapshot of the evidence so far.
#[derive(Debug, Clone)]
pub struct Job {
    /// `kinematic` or `dynamic`.
    pub mode: &'static str,
    pub tracks: PartTracks,
    pub geometry: BTreeMap<u32, PartGeometry>,
    /// Every window closed so far, in time order.
    pub windows: Vec<Window>,
    pub wrenches: Vec<WrenchSample>,
}

/// The newest stamp seen on some topics \[s\]; a jump of more than `jump_s` ahead moves it only
/// once a second stamp confirms it, so that one stamp far in the future cannot make every message
/// waiting for its transform look hopelessly late.
#[derive(Debug, Clone, Copy)]
struct Clock {
    now: f64,
    jump: Option<f64>,
}

impl Clock {
    const START: Clock = Clock { now: f64::NEG_INFINITY, jump: None };

    fn advance(&mut self, t: f64, jump_s: f64) {
        if !(t > self.now) {
            return;
        }
        let confirms = self.jump.is_some_and(|c| t >= c && t - c <= jump_s);
        if self.now == f64::NEG_INFINITY || t - self.now <= jump_s || confirms {
            self.now = t;
            self.jump = None;
        } else {
            self.jump = Some(t);
        }
    }
}

enum Held {
    Cloud { topic: String, header: Header, points: LabeledPoints },
    Wrench { topic: String, msg: WrenchStamped },
}

impl Held {
    fn topic(&self) -> &str {
        match self {
            Held::Cloud { topic, .. } | Held::Wrench { topic, .. } => topic,
        }
    }

    fn stamp(&self) -> f64 {
        match self {
            Held::Cloud { header, .. } => header.stamp.seconds(),
            Held::Wrench { msg, .. } => msg.header.stamp.seconds(),
        }
    }
}

/// How far any input topic may move past a message waiting for its transform before it is
/// dropped \[s\]: [`TF_LATE_MAX_S`] when the transform is merely late, else [`TF_WAIT_MAX_S`].
fn max_wait(e: &crate::input::tf::TfError) -> f64 {
    match e {
        crate::input::tf::TfError::Lookup { late: true, .. } => TF_LATE_MAX_S,
        _ => TF_WAIT_MAX_S,
    }
}

/// A rising edge of the applied force: the start of a push, and the part it pushes (contract
/// section 1: "the pushed part is the one whose points lie nearest to the contact point"): as in
/// replay, every cloud while the force stays above `force_close_n` votes
/// ([`perception::ContactVotes`]); a push no cloud falls in takes the part nearest its contact
/// point in the cloud nearest in time.
#[derive(Debug, Clone)]
struct Contact {
    stamp: f64,
    /// A rising edge above `force_open_n` (else above `force_close_n` alone: a light push).
    strong: bool,
    point: Point3<f64>,
    /// (|cloud stamp - contact stamp|, nearest label) of the best cloud so far.
    best: Option<(f64, u32)>,
    /// The clouds' votes while the push lasts.
    votes: perception::ContactVotes,
    /// Whether the force has stayed above `force_close_n` since the edge.
    pushing: bool,
}

impl Contact {
    /// The pushed part: the clouds' vote, else the nearest part in the cloud nearest in time.
    fn part(&self) -> Option<u32> {
        self.votes.part().or(self.best.map(|b| b.1))
    }
}

/// The streaming pipeline: feed it `/tf`, `/tf_static`, clouds and wrenches as they arrive.
pub struct Online {
    cfg: Config,
    tf: TfBuffer,
    perception: Perception,
    tracks: PartTracks,
    wrenches: Vec<WrenchSample>,
    closed: Vec<Window>,
    contacts: Vec<Contact>,
    last_cloud: Option<CloudFrame>,
    force_above: bool,
    force_above_close: bool,
    saw_wrench: bool,
    /// Whether a plausible wrench has arrived (it may still wait for its transform).
    wrench_heard: bool,
    held: VecDeque<Held>,
    /// Each input topic's clock (a stamp far ahead waits for the next message; see
    /// [`input::stamps`]).
    stamps: HashMap<String, StampGuard<Sample>>,
    /// Newest header stamp on any input topic \[s\].
    clock: Clock,
    /// Newest stamp of a dynamic transform \[s\].
    tf_clock: Clock,
    first_cloud: Option<f64>,
    last_cloud_stamp: f64,
    /// Data before this stamp lie in no window, closed or open \[s\] (a quiet stretch).
    quiet_until: f64,
    /// Stream time of the last search for a quiet stretch \[s\].
    quiet_checked: f64,
    /// Stream time of the last search for closed windows \[s\].
    close_checked: f64,
    /// Windows forgotten under `windows.node_max_windows_per_part`.
    forgotten: usize,
    /// Bad input, counted (contract: never silently dropped).
    pub diag: Diagnostics,
}

impl Online {
    pub fn new(cfg: &Config) -> Self {
        Online {
            cfg: cfg.clone(),
            tf: TfBuffer::with_cache(std::time::Duration::from_secs_f64(TF_CACHE_S)),
            perception: Perception::new(cfg.perception.clone()).with_frame_limit(REFINE_FRAMES),
            tracks: PartTracks::new(),
            wrenches: Vec::new(),
            closed: Vec::new(),
            contacts: Vec::new(),
            last_cloud: None,
            force_above: false,
            force_above_close: false,
            saw_wrench: false,
            wrench_heard: false,
            held: VecDeque::new(),
            stamps: HashMap::new(),
            clock: Clock::START,
            tf_clock: Clock::START,
            first_cloud: None,
            last_cloud_stamp: f64::NEG_INFINITY,
            quiet_until: f64::NEG_INFINITY,
            quiet_checked: f64::NEG_INFINITY,
            close_checked: f64::NEG_INFINITY,
            forgotten: 0,
            diag: Diagnostics::default(),
        }
    }

    /// `kinematic` until the first valid wrench, then `dynamic` (contract section 1).
    pub fn mode(&self) -> &'static str {
        if self.saw_wrench { "dynamic" } else { "kinematic" }
    }

    /// Windows closed so far whose evidence is kept (at most `windows.node_max_windows_per_part`
    /// per pushed part), in time order.
    pub fn windows(&self) -> &[Window] {
        &self.closed
    }

    /// Windows closed so far, kept or forgotten.
    pub fn windows_closed(&self) -> usize {
        self.closed.len() + self.forgotten
    }

    /// Windows forgotten under `windows.node_max_windows_per_part`.
    pub fn windows_forgotten(&self) -> usize {
        self.forgotten
    }

    /// The part tracks so far (in the fixed frame).
    pub fn tracks(&self) -> &PartTracks {
        &self.tracks
    }

    /// The measured wrenches kept (fixed frame, time order).
    pub fn wrenches(&self) -> &[WrenchSample] {
        &self.wrenches
    }

    /// The pushes so far, for prediction: the closed windows, then each rising edge of the force
    /// since the last of them as a window open until the next edge (the last one until `+inf`),
    /// with the part nearest its contact. A light push's edge (above `force_close_n`) that the
    /// same push follows with an edge above `force_open_n` counts once, as the latter.
    pub fn pushes(&self) -> Vec<Window> {
        let mut out = self.closed.clone();
        let after = self.closed.last().map_or(f64::NEG_INFINITY, |w| w.end);
        let recent: Vec<&Contact> = self.contacts.iter().filter(|c| c.stamp > after).collect();
        let open: Vec<&Contact> = recent
            .iter()
            .enumerate()
            .filter(|&(k, c)| c.strong || !recent.get(k + 1).is_some_and(|n| n.strong))
            .map(|(_, c)| *c)
            .collect();
        for (k, c) in open.iter().enumerate() {
            let end = open.get(k + 1).map_or(f64::INFINITY, |n| n.stamp);
            out.push(Window { start: c.stamp, end, pushed_part: c.part() });
        }
        out
    }

    /// Geometry of every part's model as it is now.
    pub fn geometry(&self) -> BTreeMap<u32, PartGeometry> {
        self.perception.geometry()
    }

    /// Buffer a `tf2_msgs/TFMessage` and release the messages that were waiting for it.
    /// Returns the perception results of released clouds, in order (see [`Online::cloud`]).
    pub fn tf(&mut self, topic: &str, msg: &TFMessage, is_static: bool) -> Vec<(f64, Vec<(u32, PartObservation)>)> {
        for e in self.tf.add(msg, is_static) {
            self.diag.warn(topic, "transform rejected", &e.to_string());
        }
        if let Some(t) = msg.transforms.iter().map(|t| t.header.stamp.seconds()).reduce(f64::max) {
            if !is_static {
                let jump = self.cfg.input.stamp_jump_s;
                self.clock.advance(t, jump);
                self.tf_clock.advance(t, jump);
            }
        }
        self.release()
    }

    /// One `sensor_msgs/PointCloud2`. Returns the perception results of every cloud this made
    /// ready (usually this one; none while it waits for its transform): its stamp \[s\] and the
    /// parts observed.
    pub fn cloud(&mut self, topic: &str, cloud: &PointCloud2) -> Vec<(f64, Vec<(u32, PartObservation)>)> {
        let Some(points) = input::decode_cloud(topic, cloud, &self.cfg.input, &mut self.diag) else { return Vec::new() };
        self.clock.advance(cloud.header.stamp.seconds(), self.cfg.input.stamp_jump_s);
        self.held.push_back(Held::Cloud { topic: topic.into(), header: cloud.header.clone(), points });
        self.release()
    }

    /// One `geometry_msgs/WrenchStamped`. Returns the perception results of clouds it released.
    pub fn wrench(&mut self, topic: &str, msg: &WrenchStamped) -> Vec<(f64, Vec<(u32, PartObservation)>)> {
        if !input::wrench_is_plausible(topic, msg, &self.cfg.input, &mut self.diag) {
            return Vec::new();
        }
        self.clock.advance(msg.header.stamp.seconds(), self.cfg.input.stamp_jump_s);
        self.wrench_heard = true;
        self.held.push_back(Held::Wrench { topic: topic.into(), msg: msg.clone() });
        self.release()
    }

    /// Process held messages in arrival order while their transforms are known; drop the head
    /// when it has waited too long.
    fn release(&mut self) -> Vec<(f64, Vec<(u32, PartObservation)>)> {
        let mut out = Vec::new();
        while self.held.len() > MAX_HELD {
            let h = self.held.pop_front().expect("non-empty");
            self.diag.warn(h.topic(), "waiting for transform", &format!("more than {MAX_HELD} messages held; oldest (t={:.3} s) dropped", h.stamp()));
        }
        loop {
            // A cloud waits for the wrench samples up to its stamp (perception's push gate and
            // the pushed part's vote read them); the wrenches behind it go first.
            let i = match self.held.front() {
                None => break,
                Some(Held::Cloud { header, .. }) if self.waits_for_wrench(header.stamp.seconds()) => {
                    match self.held.iter().position(|h| matches!(h, Held::Wrench { .. })) {
                        Some(i) => i,
                        None => break,
                    }
                }
                Some(_) => 0,
            };
            let (frame, stamp) = match &self.held[i] {
                Held::Cloud { header, .. } => (header.frame_id.clone(), header.stamp),
                Held::Wrench { msg, .. } => (msg.header.frame_id.clone(), msg.header.stamp),
            };
            match self.tf.lookup(&self.cfg.fixed_frame, &frame, stamp) {
                Ok(iso) => {
                    let h = self.held.remove(i).expect("in range");
                    let (topic, t, ready) = match h {
                        Held::Cloud { topic, header, points } => {
                            let t = header.stamp.seconds();
                            (topic, t, Sample::Cloud(input::cloud_frame(points, &iso, t)))
                        }
                        Held::Wrench { topic, msg } => {
                            let t = msg.header.stamp.seconds();
                            (topic, t, Sample::Wrench(input::wrench_sample(&msg, &iso)))
                        }
                    };
                    let limits = self.cfg.input.stamps();
                    let guard = self.stamps.entry(topic.clone()).or_insert_with(|| StampGuard::new(limits));
                    for (_, r) in guard.push(&topic, t, ready, &mut self.diag) {
                        self.take(r, &mut out);
                    }
                }
                Err(e) if self.tf_clock.now - stamp.seconds() > TF_WAIT_S || self.clock.now - stamp.seconds() > max_wait(&e) => {
                    let h = self.held.remove(i).expect("in range");
                    let what = if matches!(h, Held::Cloud { .. }) { "cloud" } else { "wrench" };
                    self.diag.warn(&format!("{}.header.frame_id", h.topic()), "unknown frame", &format!("{e}; {what} skipped"));
                }
                // Far ahead of the stream and not transformable: waiting for it would hold up
                // every message behind it (a stamp glitch on a cloud in a moving frame).
                Err(_) if stamp.seconds() - self.clock.now > self.cfg.input.stamp_jump_s => {
                    let h = self.held.remove(i).expect("in range");
                    let ahead = stamp.seconds() - self.clock.now;
                    self.diag.warn(
                        h.topic(),
                        "stamp outlier",
                        &format!("header.stamp {:.6} s is {ahead:.3} s ahead of the stream with no transform to the fixed frame yet; message skipped", stamp.seconds()),
                    );
                }
                Err(_) => break,
            }
        }
        out
    }

    /// Whether a cloud stamped `t` \[s\] waits for wrench samples: once the stream has any, until
    /// one at or after `t` is in, or the stream has moved [`WRENCH_WAIT_S`] past `t` (a wrench
    /// stream that stopped or lags). A stamp far ahead of the stream (`input.stamp_jump_s`) does
    /// not wait: no wrench may ever reach it, and its topic's stamp guard judges it. DDS
    /// delivers each topic in order but not the topics in step, and the node takes whichever is
    /// ready: without the wait a cloud could meet its push gate without the samples just before
    /// it, which replay always has.
    fn waits_for_wrench(&self, t: f64) -> bool {
        let far_ahead = t - self.clock.now > self.cfg.input.stamp_jump_s;
        self.wrench_heard && !far_ahead && self.wrenches.last().is_none_or(|w| w.stamp < t) && self.clock.now - t <= WRENCH_WAIT_S
    }

    /// Use a cloud or wrench whose stamp its topic's clock accepted.
    fn take(&mut self, r: Sample, out: &mut Vec<(f64, Vec<(u32, PartObservation)>)>) {
        match r {
            Sample::Cloud(c) => {
                let t = c.stamp;
                out.push((t, self.observe(c)));
            }
            Sample::Wrench(w) => self.add_wrench(w),
        }
    }

    fn observe(&mut self, cloud: CloudFrame) -> Vec<(u32, PartObservation)> {
        self.first_cloud.get_or_insert(cloud.stamp);
        self.last_cloud_stamp = cloud.stamp;
        let contact_now = self.wrenches.last().map(|w| w.point);
        for c in &mut self.contacts {
            if let (true, Some(p)) = (c.pushing && cloud.stamp >= c.stamp, contact_now) {
                c.votes.add(&cloud, &p);
            }
            let dt = (cloud.stamp - c.stamp).abs();
            if c.best.is_none_or(|(b, _)| dt < b) {
                if let Some((label, _)) = perception::nearest_part(&cloud, &c.point) {
                    c.best = Some((dt, label));
                }
            }
        }
        let push = super::push_gate(&self.cfg).push(&self.wrenches, cloud.stamp);
        let obs = self.perception.observe(&cloud, push.as_ref());
        for (label, o) in &obs {
            self.tracks.entry(*label).or_default().push(o.clone());
        }
        self.last_cloud = Some(cloud);
        obs
    }

    fn add_wrench(&mut self, w: WrenchSample) {
        let wc = &self.cfg.windows;
        let above = w.force.norm() > wc.force_open_n;
        let above_close = w.force.norm() > wc.force_close_n;
        // Replay's pushed part is the nearest one at the first sample above `force_open_n` in a
        // window, else at the first above `force_close_n` ([`crate::windows::force_windows`]).
        for (strong, rising) in [(true, above && !self.force_above), (false, above_close && !self.force_above_close)] {
            if rising {
                let mut c = Contact { stamp: w.stamp, strong, point: w.point, best: None, votes: Default::default(), pushing: true };
                if let Some(cloud) = &self.last_cloud {
                    c.best = perception::nearest_part(cloud, &w.point).map(|(l, _)| ((cloud.stamp - w.stamp).abs(), l));
                }
                self.contacts.push(c);
            }
        }
        if !above_close {
            // The push is over: later clouds no longer vote.
            for c in &mut self.contacts {
                c.pushing = false;
            }
        }
        self.force_above = above;
        self.force_above_close = above_close;
        self.saw_wrench = true;
        self.wrenches.push(w);
    }

    /// Start of the data not yet in a closed window.
    fn tail_start(&self) -> f64 {
        self.closed.last().map(|w| w.end).or(self.first_cloud).unwrap_or(f64::NEG_INFINITY).max(self.quiet_until)
    }

    /// Stream time up to which every input has arrived \[s\].
    fn now(&self) -> f64 {
        let t_max = self.last_cloud_stamp;
        if self.mode() == "dynamic" {
            self.wrenches.last().map_or(t_max, |w| w.stamp.min(t_max))
        } else {
            t_max
        }
    }

    /// Windows found in the data after the last closed window; with `at_end`, the open one is
    /// closed at the end of the data (as replay closes it at the end of a bag).
    fn candidate_windows(&self, at_end: bool) -> Vec<Window> {
        if self.first_cloud.is_none() {
            return Vec::new();
        }
        let t_min = self.tail_start();
        let t_max = self.last_cloud_stamp;
        // Each track from one speed span before `t_min`, so that speeds at `t_min` are measured.
        let span = self.cfg.windows.speed_span_s;
        let tails = self.tracks.values().map(|obs| &obs[obs.partition_point(|o| o.stamp < t_min - span)..]);
        let ws = if self.mode() == "dynamic" {
            let from = self.wrenches.partition_point(|w| w.stamp <= t_min);
            windows::force_windows(&self.wrenches[from..], tails, &self.cfg.windows, t_min, t_max)
        } else {
            windows::motion_windows(tails, &self.cfg.windows)
        };
        let wc = &self.cfg.windows;
        // Nothing after `now` can extend or merge into a window that ends this long before it.
        let now = self.now();
        ws.into_iter()
            .filter(|w| w.start >= t_min && w.end > w.start)
            .filter(|w| at_end || (w.end < t_max && w.end + wc.merge_gap_s + wc.margin_before_s < now))
            .collect()
    }

    /// Close the windows that nothing later can change; returns how many closed. Call after
    /// each message: it searches at most every [`CLOSE_CHECK_S`] of stream time, and only the
    /// data after the last closed window or quiet stretch.
    pub fn close_windows(&mut self) -> usize {
        let now = self.now();
        if now < self.close_checked + CLOSE_CHECK_S {
            return 0;
        }
        self.close_checked = now;
        self.close(false)
    }

    /// End of stream: close every open window (replay's rule at the end of a bag); when the
    /// whole stream had no window at all, use it whole, as replay does. Returns how many closed.
    pub fn flush(&mut self) -> usize {
        // Release what still waits for a transform, if it can be.
        self.clock.now = f64::INFINITY;
        self.tf_clock.now = f64::INFINITY;
        self.release();
        // ... and what waits for its stamp to be confirmed (nothing came to refute it).
        let held: Vec<Sample> = self.stamps.values_mut().filter_map(|g| g.flush()).map(|(_, r)| r).collect();
        let mut out = Vec::new();
        for r in held {
            self.take(r, &mut out);
        }
        let n = self.close(true);
        if self.closed.is_empty() {
            if let Some(first) = self.first_cloud {
                self.diag.warn(&self.cfg.topics.points, "no interaction window", "no motion or force period found; using the whole stream as one window");
                self.closed.push(Window { start: first, end: self.last_cloud_stamp, pushed_part: None });
                self.perception.refine(&mut self.tracks);
                return 1;
            }
        }
        n
    }

    fn close(&mut self, at_end: bool) -> usize {
        let mut new = self.candidate_windows(at_end);
        if new.is_empty() {
            self.mark_quiet();
            return 0;
        }
        let dynamic = self.mode() == "dynamic";
        for w in &mut new {
            if dynamic {
                let first = |strong: bool| self.contacts.iter().find(|c| c.strong == strong && w.contains(c.stamp));
                w.pushed_part = first(true).or_else(|| first(false)).and_then(Contact::part);
            }
        }
        let n = new.len();
        self.closed.extend(new);
        self.forget_old_windows();
        self.perception.refine(&mut self.tracks);
        self.prune();
        n
    }

    /// Keep the most recent `windows.node_max_windows_per_part` windows of each pushed part (the
    /// windows without a pushed part form one group); [`Online::prune`] then drops the evidence of
    /// the others. The tail (data after the last window) is untouched.
    fn forget_old_windows(&mut self) {
        let max = self.cfg.windows.node_max_windows_per_part.max(1);
        let mut seen: HashMap<Option<u32>, usize> = HashMap::new();
        let mut keep = vec![true; self.closed.len()];
        for (i, w) in self.closed.iter().enumerate().rev() {
            let n = seen.entry(w.pushed_part).or_insert(0);
            *n += 1;
            keep[i] = *n <= max;
        }
        // The last window marks where the tail starts: always kept (it is the newest of its group).
        let before = self.closed.len();
        let mut k = keep.into_iter();
        self.closed.retain(|_| k.next().unwrap_or(true));
        let dropped = before - self.closed.len();
        if dropped > 0 {
            self.forgotten += dropped;
            tracing::debug!("{dropped} old window(s) forgotten ({} so far; windows.node_max_windows_per_part = {max})", self.forgotten);
        }
    }

    /// Once a second of stream time: when the data after the last closed window hold no window at
    /// all, not even an open one, everything but the last few seconds is a quiet stretch that no
    /// window can reach; forget it, so that the search for windows stays short however long the
    /// robot waits between pushes.
    fn mark_quiet(&mut self) {
        let now = self.now();
        if !(now - self.quiet_checked >= 1.0) {
            return;
        }
        self.quiet_checked = now;
        if !self.candidate_windows(true).is_empty() {
            return;
        }
        let wc = &self.cfg.windows;
        let reach = wc.margin_before_s + wc.merge_gap_s + wc.hold_s + wc.speed_span_s + 1.0;
        if now - reach > self.quiet_until + 5.0 {
            self.quiet_until = now - reach;
            self.prune();
        }
    }

    /// Drop what no later window or update can use: wrenches, observations and contacts between
    /// closed windows (evidence only uses frames inside windows).
    fn prune(&mut self) {
        let tail = self.tail_start();
        let closed = &self.closed;
        let keep = |t: f64| t > tail - self.cfg.windows.margin_before_s - self.cfg.windows.speed_span_s || closed.iter().any(|w| w.contains(t));
        self.wrenches.retain(|w| keep(w.stamp));
        for obs in self.tracks.values_mut() {
            obs.retain(|o| keep(o.stamp));
        }
        self.contacts.retain(|c| c.stamp > tail - 1.0);
    }

    /// The evidence so far, for an inference run.
    pub fn job(&self) -> Job {
        Job {
            mode: self.mode(),
            tracks: self.tracks.clone(),
            geometry: self.geometry(),
            windows: self.closed.clone(),
            wrenches: self.wrenches.clone(),
        }
    }
}

impl Job {
    /// The evidence this job's update is built from.
    pub fn source(&self) -> super::EvidenceSource<'_> {
        super::EvidenceSource { tracks: &self.tracks, geometry: &self.geometry, windows: &self.windows, wrenches: &self.wrenches }
    }

    /// Update the posterior with this evidence: BOM-SVI warm-started from the previous update's
    /// guide when given, then model criticism, which may add effects to `effects` and refit
    /// ([`super::update`], as `bom replay`). `None` when no part was seen inside a window.
    pub fn update(&self, cfg: &Config, warm: Option<&svi::WarmStart>, effects: &mut super::Effects) -> Option<(svi::Fitted, Criticism)> {
        super::update(self.source(), effects, cfg, warm)
    }

    /// The first half of [`Job::update`] (the node publishes its result at once): BOM-SVI.
    pub fn fit(&self, cfg: &Config, warm: Option<&svi::WarmStart>, effects: &super::Effects) -> Option<(Evidence, svi::Fitted)> {
        super::fit_update(self.source(), effects, cfg, warm)
    }

    /// The evidence of the job's windows under `effects` (as [`Job::fit`] builds it).
    pub fn evidence(&self, cfg: &Config, effects: &super::Effects) -> Evidence {
        self.source().evidence(effects, cfg)
    }

    /// The second half: model criticism of `fitted`, and the refit when it adopts an effect.
    pub fn criticise(&self, ev: &Evidence, fitted: &svi::Fitted, cfg: &Config, effects: &mut super::Effects) -> (Criticism, Option<svi::Fitted>) {
        super::criticise_update(self.source(), ev, fitted, effects, cfg)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::input::pointcloud::encode_xyzl;
    use crate::msgs::{Time, Vector3, Wrench};

    fn wrench(t: f64, fx: f64) -> WrenchStamped {
        WrenchStamped {
            header: Header { stamp: Time::from_seconds(t), frame_id: "world".into() },
            wrench: Wrench { force: Vector3 { x: fx, y: 0.0, z: 0.0 }, torque: Vector3::default() },
        }
    }

    fn cloud(t: f64) -> PointCloud2 {
        let pts: Vec<[f64; 3]> = (0..27).map(|i| [(i % 3) as f64 * 0.02, (i / 3 % 3) as f64 * 0.02, (i / 9) as f64 * 0.02]).collect();
        encode_xyzl(Header { stamp: Time::from_seconds(t), frame_id: "world".into() }, &pts, &[1; 27])
    }

    #[test]
    fn a_long_quiet_stream_keeps_memory_bounded_and_a_push_still_closes_a_window() {
        let cfg = Config::new();
        let mut on = Online::new(&cfg);
        let push = |t: f64| if (100.0..101.0).contains(&t) { 5.0 } else { 0.0 };
        for k in 0..(110 * 1000) {
            let t = k as f64 * 1e-3;
            if k % 33 == 0 {
                on.cloud("/segmented_points", &cloud(t));
            }
            on.wrench("/applied_wrench", &wrench(t, push(t)));
            on.close_windows();
            if k == 99_000 {
                // 99 s of no force: only the last seconds are kept.
                assert!(on.wrenches.len() < 10_000, "{} wrenches kept", on.wrenches.len());
                assert!(on.tracks[&1].len() < 300, "{} observations kept", on.tracks[&1].len());
            }
        }
        assert_eq!(on.windows().len(), 1, "{:?}", on.windows());
        let w = &on.windows()[0];
        let wc = &cfg.windows;
        assert!((w.start - (100.0 - wc.margin_before_s)).abs() < 0.01 && (w.end - (101.0 + wc.margin_after_s)).abs() < 0.01, "{w:?}");
        assert_eq!(w.pushed_part, Some(1));
        assert_eq!(on.diag.total(), 0);
    }

    /// Pushes every 5 s for a minute: the node keeps the evidence of the last
    /// `node_max_windows_per_part` windows only, and counts the ones it forgot.
    #[test]
    fn old_windows_are_forgotten_and_counted() {
        let cfg = Config::new();
        let max = cfg.windows.node_max_windows_per_part;
        let mut on = Online::new(&cfg);
        let push = |t: f64| if t % 5.0 < 1.0 && t > 1.0 { 5.0 } else { 0.0 };
        for k in 0..(61 * 200) {
            let t = k as f64 / 200.0;
            if k % 7 == 0 {
                on.cloud("/segmented_points", &cloud(t));
            }
            on.wrench("/applied_wrench", &wrench(t, push(t)));
            on.close_windows();
        }
        on.flush();
        assert_eq!(on.windows_closed(), 12, "{:?}", on.windows());
        assert_eq!((on.windows().len(), on.windows_forgotten()), (max, 12 - max));
        // The kept windows are the last ones, and no evidence from before them is kept.
        let first_kept = on.windows()[0].start;
        assert!(first_kept > 60.0 - 5.0 * max as f64 - 1.0, "{first_kept}");
        assert!(on.tracks[&1].iter().all(|o| o.stamp >= first_kept - 1.0), "old observations kept");
        assert!(on.wrenches.iter().all(|w| w.stamp >= first_kept - 1.0), "old wrenches kept");
    }

    /// A cloud in a moving camera frame stamped 10^6 s ahead has no transform and never will:
    /// it is dropped as a stamp outlier instead of holding up every message behind it.
    #[test]
    fn a_future_cloud_in_a_moving_frame_does_not_hold_up_the_stream() {
        use crate::msgs::{Transform, TransformStamped};
        let cfg = Config::new();
        let mut on = Online::new(&cfg);
        let mut seen = 0;
        for k in 0..100 {
            let t = k as f64 / 30.0;
            let tf = TransformStamped {
                header: Header { stamp: Time::from_seconds(t), frame_id: "world".into() },
                child_frame_id: "camera".into(),
                transform: Transform { translation: Vector3 { x: 0.001 * k as f64, y: 0.0, z: 1.0 }, rotation: Default::default() },
            };
            seen += on.tf("/tf", &TFMessage { transforms: vec![tf] }, false).len();
            let mut c = cloud(if k == 50 { t + 1e6 } else { t });
            c.header.frame_id = "camera".into();
            seen += on.cloud("/segmented_points", &c).len();
        }
        // Every cloud but the outlier was used (each cloud's transform came just before it).
        assert_eq!(seen, 99, "{:?}", on.diag.counts());
        assert_eq!(on.diag.counts().get("/segmented_points: stamp outlier"), Some(&1), "{:?}", on.diag.counts());
        assert_eq!(on.diag.total(), 1);
    }
}
