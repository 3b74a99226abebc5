//! `pregrasp replay`: streams a sequence into a running server over HTTP, as a robot would.

use super::cli::ReplayArgs;

pub async fn run(_args: ReplayArgs) -> anyhow::Result<serde_json::Value> {
    anyhow::bail!("replay needs the dataset reader (being merged)")
}
