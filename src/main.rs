//! The `bom` command line (contract section 4).

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

use bom::config::Config;
use bom::model::JointType;
use bom::{eval, import, node, output, pipeline};

#[derive(Parser)]
#[command(name = "bom", version, about = "Bayesian Object Models for ROS 2: articulated-object posteriors from segmented clouds")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// The bags and settings of a replay (shared by `replay` and `eval`).
#[derive(clap::Args)]
struct ReplayInput {
    /// Bags of one object (several bags = several interactions with it).
    #[arg(required = true)]
    bags: Vec<PathBuf>,
    /// Settings (YAML, or a ROS 2 parameters file with a `bom: ros__parameters:` section).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Inference: svi (BOM-SVI), or nuts (BOM-NUTS after SVI, on the last update's evidence).
    #[arg(long, value_enum, default_value = "svi")]
    inference: InferenceArg,
}

#[derive(Subcommand)]
enum Command {
    /// Run the node's whole pipeline on recorded bags (several bags = several interactions with one object).
    Replay {
        #[command(flatten)]
        input: ReplayInput,
        /// Write the JSON summary here.
        #[arg(long)]
        json: Option<PathBuf>,
        /// Write an MCAP bag of the output topics here.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Print the wall time of every stage.
        #[arg(long)]
        timing: bool,
        /// Write SVG figures of model criticism here (observed vs predicted, before and after).
        #[arg(long)]
        plot: Option<PathBuf>,
    },
    /// Replay, then the metrics of contract section 6 against the bags' bom_ground_truth; with
    /// --corpus, over every object of a corpus, with the calibration of the joint-type posterior.
    Eval {
        /// Bags of one object (several bags = several interactions with it).
        #[arg(required_unless_present = "corpus", conflicts_with = "corpus")]
        bags: Vec<PathBuf>,
        /// Settings (YAML, or a ROS 2 parameters file with a `bom: ros__parameters:` section).
        #[arg(long)]
        config: Option<PathBuf>,
        /// Inference: svi (BOM-SVI), or nuts (BOM-NUTS after SVI, on the last update's evidence).
        #[arg(long, value_enum, default_value = "svi")]
        inference: InferenceArg,
        /// Write the metrics (JSON) here.
        #[arg(long)]
        json: Option<PathBuf>,
        /// Add the paper's baselines: Disconnected, Clique, and (dynamic mode) differentiable
        /// simulation with the true structure and axes, from the priors' medians and 1% tails.
        #[arg(long)]
        baselines: bool,
        /// Add `tracking`: leave each interaction out, fit on the others, predict it open loop
        /// (from its first 0.1 s) and one cloud ahead, against Kalman filters.
        #[arg(long, conflicts_with = "corpus")]
        tracking: bool,
        /// A corpus: a manifest (bags/generate/corpus.py), a folder holding manifest.json, or a
        /// folder of objects, each a folder of bags.
        #[arg(long)]
        corpus: Option<PathBuf>,
        /// Corpus objects of this split only (tune, validation; all: every object).
        #[arg(long, default_value = "all", requires = "corpus")]
        split: String,
        /// Which recordings of each corpus object (both: each, and their agreement).
        #[arg(long, value_enum, default_value = "continuous", requires = "corpus")]
        layout: LayoutArg,
        /// Corpus objects replayed at a time.
        #[arg(long, default_value_t = 1, requires = "corpus")]
        jobs: usize,
    },
    /// The live ROS 2 node (contract sections 1-2). Honours ROS_DOMAIN_ID and
    /// ROS_AUTOMATIC_DISCOVERY_RANGE; stops on SIGINT/SIGTERM after publishing the last model.
    Node {
        /// ROS 2 parameters file (`bom: ros__parameters: ...`), e.g. config/bom.yaml.
        #[arg(long)]
        params_file: Option<PathBuf>,
        /// ROS arguments as `ros2 run`/launch pass them: `--ros-args [-r FROM:=TO]...
        /// [--params-file FILE] [-r __node:=NAME]`.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true, value_name = "--ros-args ...")]
        ros_args: Vec<String>,
    },
    /// Posterior predictive part poses (median and 90% band) under a bag's wrench, from its state
    /// at --from (contract section 4).
    Predict {
        /// A replay's JSON summary (`bom replay ... --json`): the posterior to predict with.
        #[arg(long)]
        model: PathBuf,
        /// A bag of the same object with the wrench (`/applied_wrench`) and clouds that give the
        /// parts' state.
        #[arg(long)]
        wrench: PathBuf,
        /// Predict from this header stamp [s] (default: the start of the bag's first interaction
        /// window).
        #[arg(long)]
        from: Option<f64>,
        /// Predict up to this stamp [s] (default: the bag's last cloud).
        #[arg(long)]
        to: Option<f64>,
        /// Write the prediction (JSON) here.
        #[arg(long)]
        json: Option<PathBuf>,
        /// Settings (YAML or ROS 2 parameters file): topics, perception and the physics' step.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Posterior draws for the 90% band (0: the medians only; default: the configuration's
        /// `prediction.draws`, 100).
        #[arg(long)]
        draws: Option<usize>,
        /// Seed of the draws (default: `prediction.seed`).
        #[arg(long)]
        seed: Option<u64>,
    },
    /// Convert articulation_models track logs into a bag.
    ImportTracks {
        #[arg(required = true)]
        files: Vec<PathBuf>,
        #[arg(long)]
        out: PathBuf,
        /// Known joint type, recorded as ground truth (rigid|fixed, prismatic, revolute).
        #[arg(long, value_parser = parse_joint)]
        joint: Option<JointType>,
        /// Observation rate [Hz].
        #[arg(long, default_value_t = 30.0)]
        rate: f64,
        /// Points per side of each synthesised patch.
        #[arg(long, default_value_t = 4)]
        grid: usize,
    },
}

#[derive(Clone, Copy, PartialEq, clap::ValueEnum)]
enum InferenceArg {
    Svi,
    Nuts,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum LayoutArg {
    Continuous,
    Episodes,
    Both,
}

fn parse_joint(s: &str) -> Result<JointType, String> {
    JointType::parse(s).ok_or_else(|| format!("unknown joint type '{s}' (rigid, fixed, prismatic, revolute)"))
}

const EXIT_ARGS: u8 = 2;
const EXIT_INPUT: u8 = 3;

/// Load the settings (`None`: the defaults); a bad configuration exits 2.
fn load_config(path: Option<&PathBuf>) -> Result<Config, ExitCode> {
    match path {
        Some(path) => Config::load(path).map_err(|e| {
            eprintln!("error: config {e}");
            ExitCode::from(EXIT_ARGS)
        }),
        None => Ok(Config::new()),
    }
}

/// `bom eval --corpus`: the aggregate table on stdout, the report as JSON.
#[allow(clippy::too_many_arguments)]
fn eval_corpus(
    corpus: &std::path::Path,
    split: &str,
    layout: LayoutArg,
    jobs: usize,
    config: Option<&PathBuf>,
    json: Option<&PathBuf>,
    inference: InferenceArg,
    baselines: bool,
) -> ExitCode {
    use bom::eval::corpus::{self, Layout};
    let mut cfg = match load_config(config) {
        Ok(c) => c,
        Err(code) => return code,
    };
    if inference == InferenceArg::Nuts {
        cfg.nuts.enabled = true;
    }
    let layouts = match layout {
        LayoutArg::Continuous => vec![Layout::Continuous],
        LayoutArg::Episodes => vec![Layout::Episodes],
        LayoutArg::Both => vec![Layout::Continuous, Layout::Episodes],
    };
    let report = match corpus::run(corpus, split, &layouts, &cfg, jobs, baselines) {
        Ok(r) => r,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(EXIT_INPUT);
        }
    };
    print!("{}", corpus::render(&report));
    if let Some(path) = json {
        let text = serde_json::to_string_pretty(&report).expect("report serialises");
        if let Err(e) = std::fs::write(path, text + "\n") {
            eprintln!("error: {}: {e}", path.display());
            return ExitCode::from(EXIT_ARGS);
        }
    }
    if report.scored == 0 {
        eprintln!("error: {}: no object could be scored", corpus.display());
        return ExitCode::from(EXIT_INPUT);
    }
    ExitCode::SUCCESS
}

/// `bom predict`: bad arguments exit 2; an unreadable model or bag, a bag without a wrench, or a
/// model of another object exit 3.
#[allow(clippy::too_many_arguments)]
fn predict(model: &PathBuf, wrench: &PathBuf, from: Option<f64>, to: Option<f64>, json: Option<&PathBuf>, config: Option<&PathBuf>, draws: Option<usize>, seed: Option<u64>) -> ExitCode {
    use bom::prediction::{self, PredictiveModel, Scene};
    let cfg = match load_config(config) {
        Ok(c) => c,
        Err(code) => return code,
    };
    if from.is_some_and(|x| !x.is_finite()) || to.is_some_and(|x| !x.is_finite()) {
        eprintln!("error: --from and --to must be finite stamps in seconds");
        return ExitCode::from(EXIT_ARGS);
    }
    // A summary is kilobytes; bound what is read before it is allocated.
    const MAX_SUMMARY_BYTES: u64 = 64 << 20;
    if let Ok(m) = std::fs::metadata(model) {
        if m.len() > MAX_SUMMARY_BYTES {
            eprintln!("error: {}: {} bytes is not a JSON summary (at most {MAX_SUMMARY_BYTES})", model.display(), m.len());
            return ExitCode::from(EXIT_INPUT);
        }
    }
    let text = match std::fs::read_to_string(model) {
        Ok(t) => t,
        Err(e) => {
            eprintln!("error: {}: {e}", model.display());
            return ExitCode::from(EXIT_INPUT);
        }
    };
    let parsed = serde_json::from_str::<serde_json::Value>(&text).map_err(|e| e.to_string()).and_then(|v| PredictiveModel::from_summary_json(&v).map_err(|e| e.to_string()));
    let pm = match parsed {
        Ok(m) => m,
        Err(e) => {
            eprintln!("error: {}: {e}", model.display());
            return ExitCode::from(EXIT_INPUT);
        }
    };
    let mut diag = bom::diagnostics::Diagnostics::default();
    let obs = match pipeline::observe(std::slice::from_ref(wrench), &cfg, &mut diag) {
        Ok(o) => o,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(EXIT_INPUT);
        }
    };
    if obs.recording.wrenches.is_empty() {
        eprintln!("error: {}: no geometry_msgs/msg/WrenchStamped on '{}': nothing to predict under", wrench.display(), cfg.topics.wrench);
        return ExitCode::from(EXIT_INPUT);
    }
    let scene = Scene { tracks: &obs.tracks, geometry: &obs.geometry, wrenches: &obs.recording.wrenches, windows: &obs.windows };
    // The contract: a model of another object (labels that do not match) exits 3.
    let (labels, seen): (Vec<u32>, Vec<u32>) = (pm.labels(), obs.tracks.keys().copied().collect());
    if labels.len() != seen.len() || labels.iter().any(|l| !seen.contains(l)) {
        eprintln!("error: {} with {}: {}", model.display(), wrench.display(), prediction::PredictError::Labels { model: labels, recording: seen });
        return ExitCode::from(EXIT_INPUT);
    }
    if pm.joints.iter().any(|j| j.axis.is_some() && j.damping.is_none()) {
        eprintln!("warning: {}: a kinematic-mode posterior (no damping, friction or mass): its joints keep their velocity at --from instead of following the wrench", model.display());
    }
    let all = scene.stamps();
    let (first, last) = (all.first().copied().unwrap_or(0.0), all.last().copied().unwrap_or(0.0));
    let from = from.unwrap_or_else(|| obs.windows.first().map_or(first, |w| w.start.max(first)));
    let to = to.unwrap_or(last);
    if from < first || from > last || to < from {
        eprintln!("error: --from {from:.3} / --to {to:.3}: outside {}'s clouds ({first:.3} to {last:.3} s)", wrench.display());
        return ExitCode::from(EXIT_ARGS);
    }
    let stamps: Vec<f64> = all.into_iter().filter(|&t| t >= from && t <= to).collect();
    let pcfg = bom::prediction::PredictConfig { draws: draws.unwrap_or(cfg.prediction.draws), seed: seed.unwrap_or(cfg.prediction.seed), ..cfg.prediction };
    let pred = match prediction::predict(&pm, &scene, from, &stamps, &pcfg, &cfg.model) {
        Ok(p) => p,
        Err(e) => {
            eprintln!("error: {} with {}: {e}", model.display(), wrench.display());
            return ExitCode::from(EXIT_INPUT);
        }
    };
    let out = output::json::prediction_json(&model.display().to_string(), &wrench.display().to_string(), &pred, &scene);
    print!("{}", output::table::render_prediction(&out));
    if let Some(path) = json {
        let text = serde_json::to_string_pretty(&out).expect("prediction serialises");
        if let Err(e) = std::fs::write(path, text + "\n") {
            eprintln!("error: {}: {e}", path.display());
            return ExitCode::from(EXIT_ARGS);
        }
    }
    ExitCode::SUCCESS
}

/// Load the settings and run the pipeline; a bad configuration exits 2, unusable bags 3.
fn replay(input: &ReplayInput) -> Result<(pipeline::Run, Config), ExitCode> {
    let mut cfg = load_config(input.config.as_ref())?;
    if input.inference == InferenceArg::Nuts {
        cfg.nuts.enabled = true;
    }
    let run = pipeline::replay(&input.bags, &cfg).map_err(|e| {
        eprintln!("error: {e}");
        ExitCode::from(EXIT_INPUT)
    })?;
    Ok((run, cfg))
}

/// Parse the `--ros-args` section of a node command line (ROS 2 conventions): `-r`/`--remap
/// FROM:=TO` (`__node:=NAME` renames the node), `--params-file FILE`; other ROS arguments are
/// reported and ignored.
fn parse_ros_args(args: &[String], params_file: &mut Option<PathBuf>) -> Result<(String, Vec<(String, String)>), String> {
    let mut name = "bom".to_string();
    let mut remaps = Vec::new();
    let mut it = args.iter();
    let mut in_ros = false;
    while let Some(a) = it.next() {
        match a.as_str() {
            "--ros-args" => in_ros = true,
            "--" => in_ros = false,
            _ if !in_ros => return Err(format!("unexpected argument '{a}' (ROS arguments follow --ros-args)")),
            "-r" | "--remap" => {
                let r = it.next().ok_or("-r needs FROM:=TO")?;
                let (from, to) = r.split_once(":=").ok_or_else(|| format!("remapping '{r}' is not FROM:=TO"))?;
                if from == "__node" || from == "__name" {
                    name = to.to_string();
                } else {
                    remaps.push((from.to_string(), to.to_string()));
                }
            }
            "--params-file" => *params_file = Some(it.next().ok_or("--params-file needs a FILE")?.into()),
            "-p" | "--param" | "--log-level" | "-e" | "--enclave" => {
                let v = it.next().map(String::as_str).unwrap_or("");
                eprintln!("warning: ROS argument '{a} {v}' is not supported by bom node; ignored");
            }
            other => eprintln!("warning: ROS argument '{other}' is not supported by bom node; ignored"),
        }
    }
    Ok((name, remaps))
}

fn run_node(mut params_file: Option<PathBuf>, ros_args: &[String]) -> ExitCode {
    let (node_name, remaps) = match parse_ros_args(ros_args, &mut params_file) {
        Ok(x) => x,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(EXIT_ARGS);
        }
    };
    let config = match &params_file {
        Some(path) => match Config::load(path) {
            Ok(c) => c,
            Err(e) => {
                eprintln!("error: params file {e}");
                return ExitCode::from(EXIT_ARGS);
            }
        },
        None => Config::new(),
    };
    match node::run(node::NodeOptionsBom { config, node_name, remaps }) {
        Ok(report) => {
            eprint!("{}", node::render_report(&report));
            ExitCode::SUCCESS
        }
        Err(e @ node::NodeError::Settings(_)) => {
            eprintln!("error: {e}");
            ExitCode::from(EXIT_ARGS)
        }
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(EXIT_INPUT)
        }
    }
}

fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_env("BOM_LOG").unwrap_or_else(|_| "info,rustdds=error,ros2_client=warn".into()))
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_target(false)
        .without_time()
        .init();
    let cli = Cli::parse();
    match cli.command {
        Command::Eval { bags, config, inference, json, baselines, tracking, corpus, split, layout, jobs } => {
            if let Some(corpus) = corpus {
                return eval_corpus(&corpus, &split, layout, jobs, config.as_ref(), json.as_ref(), inference, baselines);
            }
            let input = ReplayInput { bags, config, inference };
            let (run, cfg) = match replay(&input) {
                Ok(r) => r,
                Err(code) => return code,
            };
            let Some(gt) = run.ground_truth.as_ref() else {
                let names: Vec<String> = input.bags.iter().map(|b| b.display().to_string()).collect();
                eprintln!("error: {}: no 'bom_ground_truth' metadata record to evaluate against", names.join(", "));
                return ExitCode::from(EXIT_INPUT);
            };
            let Some(post) = run.posterior.as_ref() else {
                eprintln!("error: no posterior: no part was observed inside an interaction window");
                return ExitCode::from(EXIT_INPUT);
            };
            let mut metrics = eval::evaluate(gt, post, baselines);
            eval::add_diff_sim(&mut metrics, &run, gt, &cfg);
            if tracking {
                metrics.tracking = Some(eval::tracking::evaluate(&run, &cfg));
            }
            print!("{}", output::table::render(&run));
            print!("{}", eval::render(&metrics));
            if let Some(t) = &metrics.tracking {
                print!("{}", eval::render_tracking(t));
            }
            if let Some(path) = json {
                let text = serde_json::to_string_pretty(&metrics).expect("metrics serialise");
                if let Err(e) = std::fs::write(&path, text + "\n") {
                    eprintln!("error: {}: {e}", path.display());
                    return ExitCode::from(EXIT_ARGS);
                }
            }
            ExitCode::SUCCESS
        }
        Command::Replay { input, json, out, timing, plot } => {
            let (run, cfg) = match replay(&input) {
                Ok(r) => r,
                Err(code) => return code,
            };
            print!("{}", output::table::render(&run));
            if let Some(path) = json {
                let text = serde_json::to_string_pretty(&output::json::summary(&run)).expect("summary serialises");
                if let Err(e) = std::fs::write(&path, text + "\n") {
                    eprintln!("error: {}: {e}", path.display());
                    return ExitCode::from(EXIT_ARGS);
                }
            }
            if let Some(path) = out {
                if let Err(e) = output::write_replay_bag(&run, &path, &cfg) {
                    eprintln!("error: {e}");
                    return ExitCode::from(EXIT_ARGS);
                }
            }
            if let Some(dir) = plot {
                match output::plot::write_criticism_plots(&run, &dir) {
                    Ok(files) => eprintln!("wrote {} figure(s) to {}", files.len(), dir.display()),
                    Err(e) => {
                        eprintln!("error: {e}");
                        return ExitCode::from(EXIT_ARGS);
                    }
                }
            }
            if timing {
                let t = &run.timing;
                println!("timing [s]: read {:.3}  decode {:.3}  perception {:.3}  windows {:.3}  inference {:.3}  criticism {:.3}  total {:.3}",
                    t.read.as_secs_f64(), t.decode.as_secs_f64(), t.perception.as_secs_f64(), t.windows.as_secs_f64(),
                    t.inference.as_secs_f64(), t.criticism.as_secs_f64(), t.total.as_secs_f64());
            }
            ExitCode::SUCCESS
        }
        Command::Node { params_file, ros_args } => run_node(params_file, &ros_args),
        Command::Predict { model, wrench, from, to, json, config, draws, seed } => predict(&model, &wrench, from, to, json.as_ref(), config.as_ref(), draws, seed),
        Command::ImportTracks { files, out, joint, rate, grid } => {
            if !(rate.is_finite() && rate > 0.0) {
                eprintln!("error: --rate must be a positive number of Hz, got {rate}");
                return ExitCode::from(EXIT_ARGS);
            }
            match import::import_tracks(&files, &out, joint, rate, grid) {
                Ok(n) => {
                    eprintln!("wrote {} ({} frames, {} part(s))", out.display(), n, files.len());
                    ExitCode::SUCCESS
                }
                Err(e @ import::ImportError::Write { .. }) => {
                    eprintln!("error: {e}");
                    ExitCode::from(EXIT_ARGS)
                }
                Err(e) => {
                    eprintln!("error: {e}");
                    ExitCode::from(EXIT_INPUT)
                }
            }
        }
    }
}
