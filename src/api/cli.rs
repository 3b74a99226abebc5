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
    /// Grid step (degrees) of a finer codebook built in the background after the coarse
    /// 10-degree one (e.g. 5, the paper's grid; tracks carry over to it); 10 keeps the coarse
    /// one only. Must divide 180. Default 10: measured in the demo (3 objects, 2 cores), the
    /// 5-degree grid makes a step take about 0.7 s and the process 1.45 GB.
    #[arg(long, default_value_t = 10, value_parser = parse_grid_step)]
    pub codebook_step_deg: u32,
}

fn parse_grid_step(s: &str) -> Result<u32, String> {
    let v: u32 = s.parse().map_err(|e| format!("{e}"))?;
    crate::geometry::RotationGrid::new(v).map_err(|e| e.to_string())?;
    if v > 10 {
        return Err(format!("{v} is coarser than the first (10-degree) codebook"));
    }
    Ok(v)
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
    if args.codebook_step_deg < config.codebooks.coarse_step_deg {
        config.codebooks.fine = Some((args.codebook_step_deg, crate::tracker::CodebookConfig::default()));
    }
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

#[cfg(test)]
mod tests {
    use super::parse_grid_step;

    #[test]
    fn codebook_step_must_divide_180_and_be_finer_than_the_coarse_grid() {
        assert_eq!(parse_grid_step("5"), Ok(5));
        assert_eq!(parse_grid_step("10"), Ok(10));
        assert!(parse_grid_step("7").is_err(), "does not divide 180");
        assert!(parse_grid_step("15").is_err(), "coarser than the first codebook");
        assert!(parse_grid_step("five").is_err());
    }
}
