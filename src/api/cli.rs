//! `pregrasp serve` and `pregrasp replay`.

use super::{ApiConfig, AppState};
use std::net::SocketAddr;
use std::path::PathBuf;

/// Options of `pregrasp serve`.
#[derive(Debug, clap::Args)]
pub struct ServeArgs {
    /// Address to listen on.
    #[arg(long, default_value = "127.0.0.1:8080")]
    pub addr: SocketAddr,
    /// Data folder (store, codebook cache); default: <user data dir>/pregrasp.
    #[arg(long)]
    pub data_dir: Option<PathBuf>,
    /// Bearer token required by every request that changes state.
    #[arg(long, env = "PREGRASP_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// Built-in objects, gripper and a generated scene replayed into the server, looping.
    #[arg(long)]
    pub demo: bool,
    /// Fusion window and fixed lag, milliseconds.
    #[arg(long, default_value_t = 300)]
    pub window_ms: u64,
}

/// Options of `pregrasp replay`.
#[derive(Debug, Clone, clap::Args)]
pub struct ReplayArgs {
    /// A sequence folder (the generator's multi-view BOP format).
    #[arg(long)]
    pub data: PathBuf,
    /// Server base URL.
    #[arg(long, default_value = "http://127.0.0.1:8080")]
    pub server: String,
    /// Playback rate (1 = real time; 0 = as fast as the server takes it).
    #[arg(long, default_value_t = 1.0)]
    pub rate: f64,
    /// Bearer token.
    #[arg(long, env = "PREGRASP_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// Write the answers (per robot frame: time, estimate, decision) as JSON.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// The default data folder.
pub fn default_data_dir() -> PathBuf {
    dirs::data_dir().unwrap_or_else(std::env::temp_dir).join("pregrasp")
}

pub fn serve(args: ServeArgs) -> anyhow::Result<()> {
    let mut config = ApiConfig::new(args.data_dir.clone().unwrap_or_else(default_data_dir));
    config.token = args.token.clone().filter(|t| !t.is_empty());
    config.window_ns = args.window_ms as i64 * 1_000_000;
    let rt = tokio::runtime::Runtime::new()?;
    rt.block_on(async move {
        let state = AppState::open(config.clone())?;
        let listener = tokio::net::TcpListener::bind(args.addr).await?;
        tracing::info!(
            "pregrasp listening on http://{} (data in {}, token {})",
            listener.local_addr()?,
            config.data_dir.display(),
            if config.token.is_some() { "required" } else { "off" }
        );
        let handle = super::start_background(&state);
        let demo = if args.demo {
            Some(super::demo::start(state.clone())?)
        } else {
            None
        };
        super::serve_on(listener, state.clone(), shutdown_signal()).await?;
        if let Some(stop) = demo {
            stop.store(true, std::sync::atomic::Ordering::Relaxed);
        }
        handle.shutdown().await;
        tracing::info!("pregrasp stopped");
        anyhow::Ok(())
    })
}

/// Ctrl-C or SIGTERM.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! { _ = ctrl_c => {}, _ = term => {} }
}

pub fn replay(args: ReplayArgs) -> anyhow::Result<()> {
    let rt = tokio::runtime::Runtime::new()?;
    let summary = rt.block_on(super::replay::run(args))?;
    println!("{}", serde_json::to_string_pretty(&summary)?);
    Ok(())
}
