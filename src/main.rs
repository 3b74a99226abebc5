//! The `pregrasp` command line: `generate`, `eval`, `calibrate`, `serve`, `replay`, `demo-loops`.

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "pregrasp",
    version,
    about = "Multi-view 6D pose distribution tracking and grasp-or-observe decisions"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Generate multi-view sequences (BOP format, see shared/design/multiview-bop.md).
    Generate(pregrasp::generate::cli::Args),
    /// Track every object of a data set and report the paper's metrics.
    Eval(pregrasp::eval::cli::Args),
    /// Fit the calibrated p_success and choose the grasp rule on eval's decisions.json (or
    /// report a map on other runs').
    Calibrate(pregrasp::eval::refit::Args),
    /// Run the HTTP service (with --demo: the built-in demo scene, dashboard included).
    Serve(pregrasp::api::cli::ServeArgs),
    /// Stream a sequence into a running server as a robot would.
    Replay(pregrasp::tools::replay::ReplayArgs),
    /// Run the built-in demo's loops headless (simulated time, no server) and print per loop
    /// when the can first got `grasp` and whether that grasp works on the true pose.
    DemoLoops(pregrasp::service::demo::HeadlessArgs),
}

fn main() -> anyhow::Result<()> {
    pregrasp::api::cli::limit_malloc_arenas();
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()))
        .with_writer(std::io::stderr)
        .init();
    match Cli::parse().command {
        Command::Generate(a) => pregrasp::generate::cli::run(a),
        Command::Eval(a) => pregrasp::eval::cli::run(a),
        Command::Calibrate(a) => pregrasp::eval::refit::run(a),
        Command::Serve(a) => pregrasp::api::cli::serve(a),
        Command::Replay(a) => pregrasp::tools::replay::cli(a),
        Command::DemoLoops(a) => pregrasp::service::demo::run_headless(&a).map(|_| ()),
    }
}
