//! `bom node`: the live ROS 2 node. The same stages as `bom replay` ([`crate::pipeline::online`]) fed by
//! DDS instead of a bag, on `ros2-client` (native Rust DDS) and `tokio`.
//!
//! Tasks:
//! - the **receive loop** takes `/tf`, `/tf_static`, the wrench and the clouds as they arrive,
//!   runs perception on every cloud, publishes predicted part poses at the cloud rate from the
//!   current posterior, and closes windows;
//! - the **worker** runs BOM-SVI (a blocking task) on the evidence of all windows closed so far and
//!   hands the posterior back to be published at once; then model criticism, whose findings go
//!   out on `/bom/model_criticism` (and, when it adopts an effect, the refitted posterior, and the
//!   effect stays in the model for every later job);
//! - with `nuts.enabled`, **BOM-NUTS** after each job's final SVI fit, in a task of its own so the
//!   worker goes on: its posterior follows SVI's on `/bom/object_model` (`inference: "nuts"`),
//!   unless a newer SVI posterior went out meanwhile (one run at a time).
//!
//! Queue policy (bounded, nothing dropped silently): the worker has one pending slot. A window
//! closing while the worker is busy replaces the pending job by one holding every window so far,
//! so windows are *merged* into the next run, never dropped; each merge is counted and logged.
//! DDS reader histories are bounded (clouds keep the last 10, wrenches and `/tf` the last 1000):
//! a node that cannot keep up with perception loses the oldest samples there, as any ROS 2
//! subscriber does.
//!
//! Network: `ROS_DOMAIN_ID` picks the DDS domain (default 0) and
//! `ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST` (or `OFF`) keeps every packet on loopback, as in
//! every ROS 2 Jazzy node. SIGINT and SIGTERM end the stream: open windows are closed, the last
//! model is computed and published, and the node exits.

use std::net::Ipv4Addr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use futures::StreamExt;
use nalgebra::Isometry3;
use ros2_client::dds::rustdds;
use ros2_client::qos::{Durability, History, QosProfile};
use ros2_client::{Context, MessageTypeName, Name, Node, NodeName, NodeOptions, Publisher};
use tokio::sync::{mpsc, Notify};

use crate::config::Config;
use crate::inference::Posterior;
use crate::msgs::{MarkerArray, ModelCriticism, ObjectModel, PointCloud2, PoseArray, TFMessage, Time, WrenchStamped};
use crate::output::messages;
use crate::perception::PartObservation;
use crate::pipeline::online::{Job, Online};
use crate::prediction::{PredictConfig, PredictiveModel, Scene};

/// Output topics (contract section 2); remappable like the inputs.
#[derive(Debug, Clone)]
pub struct OutputTopics {
    pub object_model: String,
    pub predicted_part_poses: String,
    pub markers: String,
    pub model_criticism: String,
}

impl Default for OutputTopics {
    fn default() -> Self {
        OutputTopics {
            object_model: "/bom/object_model".into(),
            predicted_part_poses: "/bom/predicted_part_poses".into(),
            markers: "/bom/markers".into(),
            model_criticism: "/bom/model_criticism".into(),
        }
    }
}

/// How the node was started: settings, node name and topic remappings (`--ros-args -r a:=b`).
#[derive(Debug, Clone)]
pub struct NodeOptionsBom {
    pub config: Config,
    pub node_name: String,
    /// `(from, to)` topic remappings, applied to every input and output topic.
    pub remaps: Vec<(String, String)>,
}

/// Why the node could not start (exit code 2 for settings, 3 for the middleware).
#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    #[error("{0}")]
    Settings(String),
    #[error("ROS 2 middleware: {0}")]
    Middleware(String),
}

/// What the node did, printed when it stops.
#[derive(Debug, Default)]
pub struct NodeReport {
    pub clouds: u64,
    pub wrenches: u64,
    pub windows: usize,
    /// Windows whose evidence was forgotten (`windows.node_max_windows_per_part`).
    pub windows_forgotten: usize,
    pub updates: u64,
    /// Windows merged into a later inference run because the worker was busy.
    pub merged: u64,
    /// Perception CPU time per cloud \[s\].
    pub perception_s: Vec<f64>,
    /// Wall time from a window closing to its posterior being published \[s\].
    pub latency_s: Vec<f64>,
    /// Stream time covered by clouds \[s\].
    pub stream_s: f64,
    /// Panics caught in pose prediction and in the inference and criticism worker (each logged;
    /// the node went on). Panics in perception are counted in `diagnostics` under the topic.
    pub other_panics: u64,
    pub diagnostics: crate::diagnostics::Diagnostics,
}

/// The DDS domain and network settings from the environment, as a ROS 2 Jazzy node reads them.
///
/// # Errors
/// A one-line message naming the variable when `ROS_DOMAIN_ID` is not an integer in 0..=232 or
/// `ROS_AUTOMATIC_DISCOVERY_RANGE` is not one of `SUBNET`, `LOCALHOST`, `OFF`, `SYSTEM_DEFAULT`.
pub fn participant_from_env() -> Result<rustdds::DomainParticipant, NodeError> {
    let domain = match std::env::var("ROS_DOMAIN_ID") {
        Ok(s) if !s.trim().is_empty() => match s.trim().parse::<u16>() {
            Ok(d) if d <= 232 => d,
            _ => return Err(NodeError::Settings(format!("ROS_DOMAIN_ID: '{s}' is not a domain id (0-232)"))),
        },
        _ => 0,
    };
    let range = std::env::var("ROS_AUTOMATIC_DISCOVERY_RANGE").unwrap_or_default();
    let mut builder = rustdds::DomainParticipantBuilder::new(domain);
    match range.trim().to_ascii_uppercase().as_str() {
        "" | "SUBNET" | "SYSTEM_DEFAULT" => {}
        "LOCALHOST" => builder = builder.with_only_networks([Ipv4Addr::LOCALHOST]),
        "OFF" => {
            // RustDDS cannot switch discovery off; loopback only is the nearest safe behaviour.
            tracing::warn!("ROS_AUTOMATIC_DISCOVERY_RANGE=OFF: discovery limited to loopback (same as LOCALHOST)");
            builder = builder.with_only_networks([Ipv4Addr::LOCALHOST]);
        }
        other => {
            return Err(NodeError::Settings(format!(
                "ROS_AUTOMATIC_DISCOVERY_RANGE: '{other}' (expected SUBNET, LOCALHOST, OFF or SYSTEM_DEFAULT)"
            )))
        }
    }
    if std::env::var("ROS_STATIC_PEERS").is_ok_and(|s| !s.trim().is_empty()) {
        tracing::warn!("ROS_STATIC_PEERS is not supported by bom's DDS layer; ignored");
    }
    tracing::info!("DDS domain {domain}, discovery range {}", if range.is_empty() { "SUBNET" } else { &range });
    builder.build().map_err(|e| NodeError::Middleware(format!("DDS participant: {e:?}")))
}

fn remap(name: &str, remaps: &[(String, String)]) -> String {
    remaps.iter().find(|(from, _)| from == name).map(|(_, to)| to.clone()).unwrap_or_else(|| name.to_string())
}

fn topic_name(name: &str) -> Result<Name, NodeError> {
    Name::parse(name).map_err(|e| NodeError::Settings(format!("topic '{name}': {e:?}")))
}

fn qos(reliable: bool, transient_local: bool, depth: usize) -> QosProfile {
    let base = if reliable { QosProfile::publisher_default() } else { QosProfile::subscription_default() };
    base.durability(if transient_local { Durability::TransientLocal } else { Durability::Volatile })
        .history(History::KeepLast { depth })
}

/// The posterior the node predicts part poses from (contract section 2,
/// `/bom/predicted_part_poses`): for each cloud, the poses predicted for its stamp plus the
/// look-ahead from the posterior, the state observed up to the cloud before it and the wrench
/// measured since ([`crate::prediction`]) — never the cloud's own observation.
struct Predictor {
    model: PredictiveModel,
    /// Part geometry of the job the posterior was fitted on (the reference centres of mass).
    geometry: std::collections::BTreeMap<u32, crate::perception::PartGeometry>,
    /// Stamp of the previous cloud \[s\]: the state predictions start from.
    prev: Option<f64>,
}

impl Predictor {
    fn new(posterior: &Posterior, findings: &[crate::criticism::Finding], job: &Job, prev: Option<f64>) -> Self {
        Predictor { model: PredictiveModel::from_posterior(posterior, findings), geometry: job.geometry.clone(), prev }
    }

    /// Poses for the cloud at `stamp`, one per part in the posterior's order, or `None` when
    /// there is no state to predict from (the first cloud, a part not seen yet, a cloud stamped
    /// before the previous one, as after a clock reset).
    fn predict(&mut self, stamp: f64, on: &Online, cfg: &Config) -> Option<Vec<Isometry3<f64>>> {
        let prev = self.prev.replace(stamp)?;
        let pushes = on.pushes();
        let scene = Scene { tracks: on.tracks(), geometry: &self.geometry, wrenches: on.wrenches(), windows: &pushes };
        let pcfg = PredictConfig { draws: 0, ..cfg.prediction };
        match crate::prediction::predict(&self.model, &scene, prev, &[stamp + cfg.prediction.look_ahead_s], &pcfg, &cfg.model) {
            Ok(p) if !p.stamps.is_empty() => Some(p.poses(0)),
            // Prediction keeps only stamps from the state's on: this cloud is before the previous one.
            Ok(_) => {
                tracing::debug!("no predicted part poses at {stamp:.3} s: the previous cloud is later ({prev:.3} s)");
                None
            }
            Err(e) => {
                tracing::debug!("no predicted part poses at {stamp:.3} s: {e}");
                None
            }
        }
    }
}

/// One finished inference run.
/// What the worker sends back: first the posterior of a job, then its model criticism (with the
/// refit, when criticism adopted an effect).
struct Update {
    posterior: Option<Posterior>,
    /// The sampler's diagnostics when `posterior` is BOM-NUTS's.
    sampler: Option<crate::inference::nuts::SamplerReport>,
    criticism: Option<crate::criticism::Criticism>,
    job: Arc<Job>,
    closed_at: Instant,
}

/// The worker's single pending slot (see the module docs for the policy).
#[derive(Default)]
struct Slot {
    job: Option<(Job, Instant)>,
    busy: bool,
}

struct Publishers {
    model: Publisher<ObjectModel>,
    poses: Publisher<PoseArray>,
    markers: Publisher<MarkerArray>,
    criticism: Publisher<ModelCriticism>,
}

/// Publish what an update carries: the model and markers of a posterior (the first posterior of a
/// job records its delay in the report), and model criticism when it has findings.
fn publish_update(p: &Publishers, u: &Update, cfg: &Config, report: &mut NodeReport) {
    let stamp = Time::from_seconds(u.job.windows.last().map(|w| w.end).unwrap_or(0.0));
    if let Some(posterior) = &u.posterior {
        if u.criticism.is_none() && u.sampler.is_none() {
            report.updates += 1;
            report.latency_s.push(u.closed_at.elapsed().as_secs_f64());
        }
        let inference = if u.sampler.is_some() { "nuts" } else { "svi" };
        let model = messages::object_model(posterior, stamp, &cfg.fixed_frame, u.job.mode, u.job.windows.len() as u32, inference);
        if let Err(e) = p.model.publish(model) {
            tracing::warn!("publishing the object model failed: {e:?}");
        }
        if let Err(e) = p.markers.publish(messages::markers(posterior, stamp, &cfg.fixed_frame)) {
            tracing::warn!("publishing markers failed: {e:?}");
        }
    }
    // Model criticism whenever it has something to say (the topic is latched: a late subscriber
    // gets the last findings).
    if let Some(c) = u.criticism.as_ref().filter(|c| !c.findings.is_empty()) {
        for f in &c.findings {
            tracing::info!("model criticism: {}", crate::output::table::finding_line(f));
        }
        if let Err(e) = p.criticism.publish(messages::model_criticism(&c.findings, stamp, &cfg.fixed_frame)) {
            tracing::warn!("publishing model criticism failed: {e:?}");
        }
    }
}

/// The message of a caught panic.
fn panic_text(p: &(dyn std::any::Any + Send)) -> String {
    p.downcast_ref::<&str>().map(|s| s.to_string()).or_else(|| p.downcast_ref::<String>().cloned()).unwrap_or_else(|| "non-text panic".into())
}

/// Run `f` on the streaming pipeline; a panic inside (a defect met by some input) is caught,
/// warned about and counted under `topic`, and the node goes on with the next message.
fn guarded<R: Default>(on: &mut Online, topic: &str, f: impl FnOnce(&mut Online) -> R) -> R {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| f(on))) {
        Ok(r) => r,
        Err(p) => {
            on.diag.warn(topic, "panic in perception", &format!("{}; message dropped, node goes on", panic_text(&*p)));
            R::default()
        }
    }
}

/// Shared state of the node's BOM-NUTS runs.
#[derive(Clone)]
struct NutsRuns {
    /// Number of the latest SVI posterior published.
    latest: Arc<std::sync::atomic::AtomicU64>,
    /// Whether a NUTS run is in flight (one at a time).
    busy: Arc<std::sync::atomic::AtomicBool>,
    panics: Arc<std::sync::atomic::AtomicU64>,
}

/// BOM-NUTS on a job's final SVI fit (after model criticism), in its own task so that the SVI
/// worker goes on with the next window: its posterior is published (inference `nuts`) only while
/// no newer SVI posterior has been (`seq`, the number of the SVI posterior it starts from), so
/// that a planner never gets an older model after a newer one. One run at a time; a job whose
/// windows close while one runs keeps SVI's posterior only (said in the log). The sampler's
/// chains share the cores with the SVI worker.
#[allow(clippy::too_many_arguments)]
fn start_nuts(cfg: &Config, job: Arc<Job>, fitted: crate::inference::svi::Fitted, effects: crate::pipeline::Effects, closed_at: Instant, seq: u64, runs: &NutsRuns, tx: &mpsc::Sender<Update>) {
    use std::sync::atomic::Ordering;
    if runs.busy.swap(true, Ordering::SeqCst) {
        tracing::info!("NUTS busy with an earlier posterior: SVI's posterior {seq} stays unsampled");
        return;
    }
    let (cfg, runs, tx) = (cfg.clone(), runs.clone(), tx.clone());
    tokio::spawn(async move {
        let j = job.clone();
        let res = tokio::task::spawn_blocking(move || {
            below_io(move || {
                let ev = j.evidence(&cfg, &effects);
                crate::inference::nuts::sample(&ev, &cfg.model, &fitted, &cfg.nuts)
            })
        })
        .await;
        let update = match res {
            Ok(Ok((posterior, report))) => {
                for w in &report.warnings {
                    tracing::warn!("{w}");
                }
                if runs.latest.load(Ordering::SeqCst) == seq {
                    tracing::info!(
                        "NUTS posterior: R-hat {:.3}, bulk ESS {:.0}, tail ESS {:.0}, {} divergent, {:.1} s",
                        report.r_hat_max,
                        report.ess_bulk_min,
                        report.ess_tail_min,
                        report.divergences,
                        report.runtime_s
                    );
                    Some(Update { posterior: Some(posterior), sampler: Some(report), criticism: None, job, closed_at })
                } else {
                    tracing::info!("NUTS posterior of SVI posterior {seq} superseded by a newer SVI posterior: not published");
                    None
                }
            }
            Ok(Err(e)) => {
                tracing::warn!("NUTS failed: {e}; the posterior stays SVI's");
                None
            }
            Err(e) => {
                runs.panics.fetch_add(1, Ordering::Relaxed);
                tracing::error!("NUTS task failed: {e}; the posterior stays SVI's");
                None
            }
        };
        if let Some(u) = update {
            let _ = tx.send(u).await;
        }
        // Cleared after the send: the end of the stream waits for both.
        runs.busy.store(false, Ordering::SeqCst);
    });
}

/// Run the node until SIGINT or SIGTERM.
///
/// # Errors
/// [`NodeError`] when the settings are invalid or DDS cannot start.
pub fn run(opts: NodeOptionsBom) -> Result<NodeReport, NodeError> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(|e| NodeError::Middleware(format!("tokio runtime: {e}")))?;
    let report = rt.block_on(run_async(opts));
    // A sampler run abandoned by a second SIGINT must not hold the process.
    rt.shutdown_timeout(Duration::from_secs(1));
    report
}

async fn run_async(opts: NodeOptionsBom) -> Result<NodeReport, NodeError> {
    let cfg = opts.config.clone();
    if cfg.nuts.enabled {
        tracing::info!("parameter nuts.enabled: BOM-NUTS runs after each SVI posterior and its posterior follows it on the object model topic (inference \"nuts\")");
    }
    let mw = |e: &dyn std::fmt::Debug| NodeError::Middleware(format!("{e:?}"));
    let context = Context::from_domain_participant(participant_from_env()?).map_err(|e| mw(&e))?;
    let node_name = NodeName::new("/", &opts.node_name).map_err(|e| NodeError::Settings(format!("node name '{}': {e:?}", opts.node_name)))?;
    let mut node: Node = context.new_node(node_name, NodeOptions::new().enable_rosout(true)).map_err(|e| mw(&e))?;
    let spinner = node.spinner().map_err(|e| mw(&e))?;
    let spin = tokio::spawn(spinner.spin());

    let r = |n: &str| remap(n, &opts.remaps);
    let t = &cfg.topics;
    let (points_topic, wrench_topic, tf_topic, tf_static_topic) = (r(&t.points), r(&t.wrench), r(&t.tf), r(&t.tf_static));
    let outputs = OutputTopics::default();
    let mk_topic = |node: &mut Node, name: &str, pkg: &str, ty: &str, q: &QosProfile| {
        node.create_topic(&topic_name(name)?, MessageTypeName::new(pkg, ty), q).map_err(|e| mw(&e))
    };
    // Inputs: clouds best effort (sensor data: matches best-effort and reliable publishers);
    // wrenches and /tf reliable like tf2's listener; /tf_static transient local.
    let q_points = qos(false, false, 10);
    let q_wrench = qos(true, false, 1000);
    let q_tf = qos(true, false, 1000);
    let q_tf_static = qos(true, true, 100);
    let topic = mk_topic(&mut node, &points_topic, "sensor_msgs", "PointCloud2", &q_points)?;
    let sub_points = node.create_subscription::<PointCloud2>(&topic, Some(q_points.clone())).map_err(|e| mw(&e))?;
    let topic = mk_topic(&mut node, &wrench_topic, "geometry_msgs", "WrenchStamped", &q_wrench)?;
    let sub_wrench = node.create_subscription::<WrenchStamped>(&topic, Some(q_wrench.clone())).map_err(|e| mw(&e))?;
    let topic = mk_topic(&mut node, &tf_topic, "tf2_msgs", "TFMessage", &q_tf)?;
    let sub_tf = node.create_subscription::<TFMessage>(&topic, Some(q_tf.clone())).map_err(|e| mw(&e))?;
    let topic = mk_topic(&mut node, &tf_static_topic, "tf2_msgs", "TFMessage", &q_tf_static)?;
    let sub_tf_static = node.create_subscription::<TFMessage>(&topic, Some(q_tf_static.clone())).map_err(|e| mw(&e))?;

    // Outputs, with the contract's QoS (section 2).
    let q_model = qos(true, true, 1);
    let q_poses = qos(true, false, 10);
    let q_markers = qos(true, false, 1);
    let topic = mk_topic(&mut node, &r(&outputs.object_model), "bom_msgs", "ObjectModel", &q_model)?;
    let model = node.create_publisher::<ObjectModel>(&topic, Some(q_model.clone())).map_err(|e| mw(&e))?;
    let topic = mk_topic(&mut node, &r(&outputs.predicted_part_poses), "geometry_msgs", "PoseArray", &q_poses)?;
    let poses = node.create_publisher::<PoseArray>(&topic, Some(q_poses.clone())).map_err(|e| mw(&e))?;
    let topic = mk_topic(&mut node, &r(&outputs.markers), "visualization_msgs", "MarkerArray", &q_markers)?;
    let markers = node.create_publisher::<MarkerArray>(&topic, Some(q_markers.clone())).map_err(|e| mw(&e))?;
    let topic = mk_topic(&mut node, &r(&outputs.model_criticism), "bom_msgs", "ModelCriticism", &q_model)?;
    let criticism = node.create_publisher::<ModelCriticism>(&topic, Some(q_model.clone())).map_err(|e| mw(&e))?;
    let pubs = Publishers { model, poses, markers, criticism };
    tracing::info!(
        "node '{}' up: clouds '{points_topic}', wrench '{wrench_topic}', tf '{tf_topic}', '{tf_static_topic}'; fixed frame '{}'",
        opts.node_name,
        cfg.fixed_frame
    );

    // Worker: one pending slot, one run at a time.
    let slot = Arc::new(Mutex::new(Slot::default()));
    let wake = Arc::new(Notify::new());
    let (done_tx, mut done_rx) = mpsc::channel::<Update>(4);
    let worker_panics = Arc::new(std::sync::atomic::AtomicU64::new(0));
    let nuts_busy = Arc::new(std::sync::atomic::AtomicBool::new(false));
    {
        let (slot, wake, cfg, panics) = (slot.clone(), wake.clone(), cfg.clone(), worker_panics.clone());
        let c_nuts = cfg.clone();
        // The number of the latest SVI posterior, and whether a NUTS run is in flight.
        let latest = Arc::new(std::sync::atomic::AtomicU64::new(0));
        let nuts_runs = NutsRuns { latest: latest.clone(), busy: nuts_busy.clone(), panics: panics.clone() };
        tokio::spawn(async move {
            let mut warm: Option<crate::inference::svi::WarmStart> = None;
            // Effects model criticism adopted, kept for every later update.
            let mut effects = crate::pipeline::Effects::default();
            loop {
                let next = {
                    let mut s = slot.lock().expect("slot lock");
                    let j = s.job.take();
                    s.busy = j.is_some();
                    j
                };
                let Some((job, closed_at)) = next else {
                    wake.notified().await;
                    continue;
                };
                // Stage 1: BOM-SVI; its posterior is published at once.
                let job = Arc::new(job);
                let (c, w, fx, j) = (cfg.clone(), warm.take(), effects.clone(), job.clone());
                let fitted = match tokio::task::spawn_blocking(move || below_io(|| j.fit(&c, w.as_ref(), &fx))).await {
                    Ok(Some(f)) => f,
                    Ok(None) => {
                        tracing::warn!("inference: no part was observed inside a window; no posterior");
                        slot.lock().expect("slot lock").busy = false;
                        continue;
                    }
                    Err(e) => {
                        panics.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        tracing::error!("inference task failed: {e}; the node goes on with the next window");
                        slot.lock().expect("slot lock").busy = false;
                        continue;
                    }
                };
                let seq = latest.fetch_add(1, std::sync::atomic::Ordering::SeqCst) + 1;
                let first = Update { posterior: Some(fitted.1.posterior.clone()), sampler: None, criticism: None, job: job.clone(), closed_at };
                if done_tx.send(first).await.is_err() {
                    break;
                }
                // Stage 2: model criticism, and the refit when it adopts an effect.
                let (c, mut fx, j) = (cfg.clone(), effects.clone(), job.clone());
                let res = tokio::task::spawn_blocking(move || {
                    below_io(move || {
                        let (criticism, refit) = j.criticise(&fitted.0, &fitted.1, &c, &mut fx);
                        (fitted.1, criticism, refit, fx)
                    })
                })
                .await;
                let update = match res {
                    Ok((fitted, criticism, refit, fx)) => {
                        let posterior = refit.as_ref().map(|r| r.posterior.clone());
                        let fitted = refit.unwrap_or(fitted);
                        if c_nuts.nuts.enabled {
                            start_nuts(&c_nuts, job.clone(), fitted.clone(), fx.clone(), closed_at, seq, &nuts_runs, &done_tx);
                        }
                        effects = fx;
                        warm = Some(fitted.warm);
                        Some(Update { posterior, sampler: None, criticism: Some(criticism), job, closed_at })
                    }
                    Err(e) => {
                        panics.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        tracing::error!("model criticism task failed: {e}; the node goes on with the next window");
                        None
                    }
                };
                if let Some(u) = update {
                    if done_tx.send(u).await.is_err() {
                        break;
                    }
                }
                slot.lock().expect("slot lock").busy = false;
            }
        });
    }
    let submit = |on: &Online, report: &mut NodeReport| {
        let mut s = slot.lock().expect("slot lock");
        if s.job.is_some() {
            report.merged += 1;
            tracing::info!("inference busy: window merged into the next run ({} merged so far)", report.merged);
        }
        s.job = Some((on.job(), Instant::now()));
        drop(s);
        wake.notify_one();
    };

    let mut on = Online::new(&cfg);
    let mut report = NodeReport::default();
    let mut predictor: Option<Predictor> = None;
    // Model criticism's latest findings (their adopted effects join the predictions).
    let mut findings: Vec<crate::criticism::Finding> = Vec::new();
    let mut first_stamp: Option<f64> = None;
    let mut points = Box::pin(sub_points.async_stream());
    let mut wrench = Box::pin(sub_wrench.async_stream());
    let mut tf = Box::pin(sub_tf.async_stream());
    let mut tf_static = Box::pin(sub_tf_static.async_stream());
    let mut sigterm = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .map_err(|e| NodeError::Middleware(format!("SIGTERM handler: {e}")))?;

    let handle_frames = |frames: Vec<(f64, Vec<(u32, PartObservation)>)>,
                         on: &Online,
                         predictor: &mut Option<Predictor>,
                         first_stamp: &mut Option<f64>,
                         report: &mut NodeReport| {
        for (stamp, _) in frames {
            first_stamp.get_or_insert(stamp);
            report.stream_s = stamp - first_stamp.unwrap_or(stamp);
            if let Some(p) = predictor.as_mut() {
                match std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| p.predict(stamp, on, &cfg))) {
                    Ok(None) => {}
                    Ok(Some(poses)) => {
                        let msg = messages::pose_array(&poses, Time::from_seconds(stamp + cfg.prediction.look_ahead_s), &cfg.fixed_frame);
                        if let Err(e) = pubs.poses.publish(msg) {
                            tracing::warn!("publishing predicted part poses failed: {e:?}");
                        }
                    }
                    Err(e) => {
                        report.other_panics += 1;
                        tracing::error!("predicting part poses panicked: {}; poses of this cloud skipped", panic_text(&*e));
                    }
                }
            }
            report.clouds += 1;
        }
    };

    loop {
        tokio::select! {
            Some(m) = points.next() => {
                match m {
                    Ok((cloud, _)) => {
                        let t0 = cpu_time();
                        let frames = guarded(&mut on, &points_topic, |on| on.cloud(&points_topic, &cloud));
                        report.perception_s.push(cpu_time() - t0);
                        handle_frames(frames, &on, &mut predictor, &mut first_stamp, &mut report);
                    }
                    Err(e) => on.diag.warn(&points_topic, "undecodable message", &format!("{e:?}; message skipped")),
                }
                let closed = guarded(&mut on, &points_topic, |on| on.close_windows());
                if closed > 0 {
                    log_closed(&on, closed);
                    submit(&on, &mut report);
                }
            }
            Some(m) = wrench.next() => {
                match m {
                    Ok((w, _)) => {
                        report.wrenches += 1;
                        let frames = guarded(&mut on, &wrench_topic, |on| on.wrench(&wrench_topic, &w));
                        handle_frames(frames, &on, &mut predictor, &mut first_stamp, &mut report);
                    }
                    Err(e) => on.diag.warn(&wrench_topic, "undecodable message", &format!("{e:?}; message skipped")),
                }
                let closed = guarded(&mut on, &wrench_topic, |on| on.close_windows());
                if closed > 0 {
                    log_closed(&on, closed);
                    submit(&on, &mut report);
                }
            }
            Some(m) = tf.next() => match m {
                Ok((msg, _)) => {
                    let frames = guarded(&mut on, &tf_topic, |on| on.tf(&tf_topic, &msg, false));
                    handle_frames(frames, &on, &mut predictor, &mut first_stamp, &mut report)
                }
                Err(e) => on.diag.warn(&tf_topic, "undecodable message", &format!("{e:?}; message skipped")),
            },
            Some(m) = tf_static.next() => match m {
                Ok((msg, _)) => {
                    let frames = guarded(&mut on, &tf_static_topic, |on| on.tf(&tf_static_topic, &msg, true));
                    handle_frames(frames, &on, &mut predictor, &mut first_stamp, &mut report)
                }
                Err(e) => on.diag.warn(&tf_static_topic, "undecodable message", &format!("{e:?}; message skipped")),
            },
            Some(u) = done_rx.recv() => {
                publish_update(&pubs, &u, &cfg, &mut report);
                if let Some(posterior) = u.posterior {
                    // A posterior that comes with criticism is the refit after an adopted effect.
                    let what = if u.criticism.is_some() { "refitted posterior (effects changed by criticism)" } else { "posterior" };
                    tracing::info!(
                        "{what} after {} window(s) published {:.2} s after the window closed (ELBO {:.1})",
                        u.job.windows.len(), u.closed_at.elapsed().as_secs_f64(), posterior.elbo
                    );
                    if let Some(c) = &u.criticism {
                        findings = c.findings.clone();
                    }
                    predictor = Some(Predictor::new(&posterior, &findings, &u.job, predictor.as_ref().and_then(|p| p.prev)));
                }
            }
            _ = tokio::signal::ctrl_c() => { tracing::info!("SIGINT: finishing"); break; }
            _ = sigterm.recv() => { tracing::info!("SIGTERM: finishing"); break; }
        }
    }

    // End of stream: close open windows, let the worker finish, publish the last model.
    let closed = guarded(&mut on, &points_topic, |on| on.flush());
    if closed > 0 {
        log_closed(&on, closed);
        submit(&on, &mut report);
    }
    loop {
        // The last model includes a BOM-NUTS run in flight (a second SIGINT abandons it).
        let idle = {
            let s = slot.lock().expect("slot lock");
            s.job.is_none() && !s.busy && !nuts_busy.load(std::sync::atomic::Ordering::SeqCst)
        };
        if idle && done_rx.is_empty() {
            break;
        }
        tokio::select! {
            Some(u) = done_rx.recv() => {
                publish_update(&pubs, &u, &cfg, &mut report);
                if u.posterior.is_some() {
                    tracing::info!("last posterior ({} window(s)) published", u.job.windows.len());
                }
            }
            _ = tokio::time::sleep(Duration::from_millis(50)) => {}
            _ = tokio::signal::ctrl_c() => { tracing::warn!("second SIGINT: exiting without the last model"); break; }
        }
    }
    // Give reliable readers time to acknowledge the last samples before the participant goes.
    tokio::time::sleep(Duration::from_millis(500)).await;
    report.windows = on.windows_closed();
    report.windows_forgotten = on.windows_forgotten();
    report.diagnostics = on.diag.clone();
    report.other_panics += worker_panics.load(std::sync::atomic::Ordering::Relaxed);
    // Tear down in order: spinner, endpoints, node, then the participant, so that DDS can tell
    // its peers that the endpoints are gone.
    drop((points, wrench, tf, tf_static));
    drop((sub_points, sub_wrench, sub_tf, sub_tf_static, pubs));
    drop(node); // stops the spinner
    if tokio::time::timeout(Duration::from_secs(2), spin).await.is_err() {
        tracing::warn!("ROS 2 spinner did not stop within 2 s");
    }
    drop(context);
    Ok(report)
}

/// The nice value (Linux, 0-19) of the threads that run BOM-SVI, model criticism and BOM-NUTS;
/// the receive loop and the DDS threads keep the node's own (0). Inference fills every core for
/// seconds at a time, while the sensor streams cannot wait: a DDS receive thread that does not
/// get the CPU loses datagrams (on loopback the kernel drops them when a socket's buffer is full),
/// and a reliable stream then stalls until the writer repairs it. Inference can wait. (Not enough
/// alone: with it, two of eleven interop runs at stop 104 still saw `/tf` seconds late; the waits
/// of [`crate::pipeline::online`] are what keep the node's evidence equal to replay's.)
pub const WORKER_NICE: i32 = 10;

/// Run `f` on a thread of its own at [`WORKER_NICE`] (threads it starts inherit the priority);
/// a panic in `f` resumes on the caller. Raising a thread's nice value needs no privilege; it
/// could not be lowered again, hence a fresh thread rather than tokio's pooled one.
fn below_io<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    std::thread::scope(|s| {
        s.spawn(|| {
            // SAFETY: setpriority on this thread's own id (Linux: PRIO_PROCESS with a thread id
            // sets that thread's nice value); no memory is passed.
            let r = unsafe { libc::setpriority(libc::PRIO_PROCESS, libc::syscall(libc::SYS_gettid) as libc::id_t, WORKER_NICE) };
            if r != 0 {
                tracing::debug!("inference threads keep the node's priority: setpriority failed ({})", std::io::Error::last_os_error());
            }
            f()
        })
        .join()
        .unwrap_or_else(|e| std::panic::resume_unwind(e))
    })
}

/// One info line per window of the `n` that just closed (stream time, the pushed part): what a
/// comparison with `bom replay`'s `windows` needs when the node's model differs from it.
fn log_closed(on: &Online, n: usize) {
    let all = on.windows();
    for (k, w) in all.iter().enumerate().skip(all.len().saturating_sub(n)) {
        let part = w.pushed_part.map_or("none".to_string(), |p| p.to_string());
        tracing::info!("window {} closed: [{:.3}, {:.3}] s, pushed part {part}", k + 1 + on.windows_forgotten(), w.start, w.end);
    }
}

/// CPU time of this thread \[s\] (perception cost, independent of the other threads' load).
fn cpu_time() -> f64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: clock_gettime only writes the timespec it is given.
    unsafe {
        libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts);
    }
    ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9
}

/// Render the report printed when the node stops.
pub fn render_report(r: &NodeReport) -> String {
    let mut s = String::new();
    let med = |v: &[f64]| {
        let mut v = v.to_vec();
        v.sort_by(|a, b| a.total_cmp(b));
        match v.len() {
            0 => f64::NAN,
            n if n % 2 == 1 => v[n / 2],
            n => 0.5 * (v[n / 2 - 1] + v[n / 2]),
        }
    };
    let per_cloud = r.perception_s.iter().sum::<f64>() / r.perception_s.len().max(1) as f64;
    let rate = if r.stream_s > 0.0 { r.clouds as f64 / r.stream_s } else { 0.0 };
    s += &format!(
        "bom node: {} clouds, {} wrenches, {} window(s) ({} old ones forgotten), {} posterior update(s), {} window(s) merged into later runs\n",
        r.clouds, r.wrenches, r.windows, r.windows_forgotten, r.updates, r.merged
    );
    s += &format!(
        "  perception: {:.1} ms CPU per cloud (median {:.1}), {:.0}% of one core at the stream's {:.1} Hz\n",
        per_cloud * 1e3,
        med(&r.perception_s) * 1e3,
        per_cloud * rate * 100.0,
        rate
    );
    if !r.latency_s.is_empty() {
        s += &format!("  window closed -> posterior published: median {:.2} s, max {:.2} s\n", med(&r.latency_s), r.latency_s.iter().cloned().fold(0.0, f64::max));
    }
    if r.other_panics > 0 {
        s += &format!("  panics caught in prediction, inference or criticism: {}\n", r.other_panics);
    }
    if r.diagnostics.total() > 0 {
        s += &format!("  bad input: {} event(s)\n", r.diagnostics.total());
        for (k, n) in r.diagnostics.counts() {
            s += &format!("    {k}: {n}\n");
        }
    }
    s
}
