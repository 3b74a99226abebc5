//! `pregrasp serve`.

use super::{ApiConfig, AppState};
use crate::service::Limits;
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
    /// Bearer token required by every request that changes state (and with --protect-reads by
    /// every request but /healthz). Prefer PREGRASP_TOKEN or --token-file: a command-line
    /// argument shows in `ps`.
    #[arg(long, env = "PREGRASP_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// Read the bearer token from this file (its first line).
    #[arg(long, conflicts_with = "token")]
    pub token_file: Option<PathBuf>,
    /// Require the token for reads too (camera images, tracks, the dashboard).
    #[arg(long)]
    pub protect_reads: bool,
    /// Allow listening beyond the loopback interface without a token.
    #[arg(long)]
    pub insecure: bool,
    /// A host name (or name:port) requests may address besides the bound address and, when
    /// bound to loopback, localhost (repeatable; guards against DNS rebinding).
    #[arg(long = "allowed-host")]
    pub allowed_hosts: Vec<String>,
    /// Accept ground truth at POST /truth (for display; on with --demo).
    #[arg(long)]
    pub accept_truth: bool,
    /// Most cameras.
    #[arg(long, default_value_t = Limits::default().max_cameras)]
    pub max_cameras: usize,
    /// Most pixels of one camera image (width x height).
    #[arg(long, default_value_t = Limits::default().max_camera_pixels)]
    pub max_camera_pixels: u64,
    /// Most objects.
    #[arg(long, default_value_t = Limits::default().max_objects)]
    pub max_objects: usize,
    /// Most grippers.
    #[arg(long, default_value_t = Limits::default().max_grippers)]
    pub max_grippers: usize,
    /// Most tracks of one object a client may start with POST /tracks.
    #[arg(long, default_value_t = Limits::default().max_tracks_per_object)]
    pub max_tracks_per_object: usize,
    /// Most tracks in all a client may start with POST /tracks.
    #[arg(long, default_value_t = Limits::default().max_tracks)]
    pub max_tracks: usize,
    /// Longest object name, characters.
    #[arg(long, default_value_t = Limits::default().max_name_chars)]
    pub max_name_chars: usize,
    /// Most codebook files kept in the cache folder.
    #[arg(long, default_value_t = Limits::default().max_cached_codebooks)]
    pub max_cached_codebooks: usize,
    /// Longest time to answer a request, seconds (the event stream excepted).
    #[arg(long, default_value_t = 60)]
    pub request_timeout_s: u64,
    /// Longest time a client may take to send a request's headers, seconds.
    #[arg(long, default_value_t = 10)]
    pub header_read_timeout_s: u64,
    /// Most connections at once.
    #[arg(long, default_value_t = 256)]
    pub max_connections: usize,
    /// Built-in objects, gripper and a generated scene replayed into the server, looping.
    #[arg(long)]
    pub demo: bool,
    /// Fusion window and fixed lag, milliseconds.
    #[arg(long, default_value_t = 300)]
    pub window_ms: u64,
    /// Grid step (degrees) of the finer codebook built in the background after the coarse
    /// 10-degree one (5: the paper's grid; tracks carry over to it); 10 keeps the coarse one
    /// only. Must divide 180.
    #[arg(long, default_value_t = crate::service::codebooks::CodebookPlan::SERVE_FINE_STEP_DEG, value_parser = parse_grid_step)]
    pub codebook_step_deg: u32,
    /// The calibration map of `p_success` (JSON written by `pregrasp calibrate --fit`) instead
    /// of the one built into the binary; applied only where it was fitted for the running
    /// settings (a decision says `stale` otherwise).
    #[arg(long)]
    pub calibration_map: Option<PathBuf>,
}

fn parse_grid_step(s: &str) -> Result<u32, String> {
    let v: u32 = s.parse().map_err(|e| format!("{e}"))?;
    crate::geometry::RotationGrid::new(v).map_err(|e| e.to_string())?;
    if v > 10 {
        return Err(format!("{v} is coarser than the first (10-degree) codebook"));
    }
    Ok(v)
}

/// The default data folder.
pub fn default_data_dir() -> PathBuf {
    dirs::data_dir().unwrap_or_else(std::env::temp_dir).join("pregrasp")
}

/// Host names requests may address: the configured ones, plus the loopback names when bound to
/// loopback, else the bound address; empty (no check) when bound to every interface with no
/// name configured.
pub fn allowed_hosts(addr: &SocketAddr, configured: &[String]) -> Vec<String> {
    let mut hosts: Vec<String> = configured.iter().map(|h| h.to_ascii_lowercase()).collect();
    let ip = addr.ip();
    if ip.is_loopback() {
        hosts.extend(["localhost", "127.0.0.1", "[::1]"].map(String::from));
    } else if ip.is_unspecified() {
        if hosts.is_empty() {
            return hosts;
        }
        hosts.extend(["localhost", "127.0.0.1", "[::1]"].map(String::from));
    } else {
        hosts.push(match ip {
            std::net::IpAddr::V6(v6) => format!("[{v6}]"),
            std::net::IpAddr::V4(v4) => v4.to_string(),
        });
    }
    hosts
}

/// The server's settings from its options (reads `--token-file`; refuses to listen beyond
/// loopback without a token unless `--insecure`).
pub fn config_from(args: &ServeArgs) -> anyhow::Result<ApiConfig> {
    let mut config = ApiConfig::new(args.data_dir.clone().unwrap_or_else(default_data_dir));
    let token = match &args.token_file {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .map_err(|e| anyhow::anyhow!("reading --token-file {}: {e}", path.display()))?;
            Some(text.lines().next().unwrap_or("").trim().to_string())
        }
        None => args.token.clone(),
    };
    config.token = token.filter(|t| !t.is_empty());
    if !args.addr.ip().is_loopback() && config.token.is_none() {
        if !args.insecure {
            anyhow::bail!(
                "listening on {} (beyond loopback) without a token: set PREGRASP_TOKEN or --token-file, or pass --insecure",
                args.addr
            );
        }
        tracing::warn!(
            "listening on {} without a token (--insecure): anyone who can reach it can change its state",
            args.addr
        );
    }
    if args.protect_reads && config.token.is_none() {
        anyhow::bail!("--protect-reads needs a token (PREGRASP_TOKEN or --token-file)");
    }
    config.protect_reads = args.protect_reads;
    config.allowed_hosts = allowed_hosts(&args.addr, &args.allowed_hosts);
    if config.allowed_hosts.is_empty() {
        tracing::warn!("listening on every interface with no --allowed-host: the Host header is not checked");
    }
    config.service.accept_truth = args.accept_truth || args.demo;
    config.service.limits = Limits {
        max_cameras: args.max_cameras,
        max_camera_pixels: args.max_camera_pixels,
        max_objects: args.max_objects,
        max_grippers: args.max_grippers,
        max_tracks_per_object: args.max_tracks_per_object,
        max_tracks: args.max_tracks,
        max_name_chars: args.max_name_chars,
        max_cached_codebooks: args.max_cached_codebooks,
    };
    config.request_timeout = std::time::Duration::from_secs(args.request_timeout_s.max(1));
    config.header_read_timeout = std::time::Duration::from_secs(args.header_read_timeout_s.max(1));
    config.max_connections = args.max_connections.max(1);
    config.service.window_ns = i64::try_from(args.window_ms)
        .ok()
        .and_then(|ms| ms.checked_mul(1_000_000))
        .filter(|ns| *ns <= crate::service::ingest::MAX_STAMP_NS)
        .ok_or_else(|| anyhow::anyhow!("--window-ms {} is too large", args.window_ms))?;
    config.service.codebooks = crate::service::codebooks::CodebookPlan::with_fine_step(args.codebook_step_deg);
    if let Some(path) = &args.calibration_map {
        let text = std::fs::read_to_string(path)
            .map_err(|e| anyhow::anyhow!("reading --calibration-map {}: {e}", path.display()))?;
        let map = crate::grasp::CalibrationMap::from_json(&text)
            .map_err(|e| anyhow::anyhow!("--calibration-map {}: {e}", path.display()))?;
        config.service.calibration_map = Some(std::sync::Arc::new(map));
    }
    Ok(config)
}

pub fn serve(args: ServeArgs) -> anyhow::Result<()> {
    let config = config_from(&args)?;
    let rt = tokio::runtime::Runtime::new()?;
    rt.block_on(async move {
        let state = AppState::open(config.clone())?;
        let listener = tokio::net::TcpListener::bind(args.addr).await?;
        tracing::info!(
            "pregrasp listening on http://{} (data in {}, token {})",
            listener.local_addr()?,
            config.service.data_dir.display(),
            if config.token.is_some() { "required" } else { "off" }
        );
        let handle = super::start_background(&state);
        let demo = if args.demo {
            Some(crate::service::demo::start(state.service.clone())?)
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
/// Caps glibc's malloc arenas at one per core; every command calls it first, before any thread
/// starts. A long-running service allocates frames, crops and answers on many threads (tokio,
/// rayon, the worker); with glibc's default of eight arenas per core its resident memory crept
/// higher under the soak's steady load, and tracks updated side by side held their freed
/// matching buffers in more arenas (`docs/decisions.md`). Other platforms: nothing.
pub fn limit_malloc_arenas() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        let cores = std::thread::available_parallelism().map_or(2, |n| n.get()).max(2);
        let arenas = libc::c_int::try_from(cores).unwrap_or(libc::c_int::MAX);
        // SAFETY: mallopt only sets a tuning parameter of the allocator; called before the
        // runtime and every other thread of the service start.
        #[allow(unsafe_code)]
        let ok = unsafe { libc::mallopt(libc::M_ARENA_MAX, arenas) };
        if ok != 1 {
            tracing::warn!("cannot cap malloc's arenas at {arenas}");
        }
    }
}

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
