//! (being built) The HTTP service.

pub mod cli {
    /// Options of `pregrasp serve`.
    #[derive(Debug, clap::Args)]
    pub struct ServeArgs {}
    /// Options of `pregrasp replay`.
    #[derive(Debug, clap::Args)]
    pub struct ReplayArgs {}
    pub fn serve(_args: ServeArgs) -> anyhow::Result<()> {
        anyhow::bail!("pregrasp serve is being built")
    }
    pub fn replay(_args: ReplayArgs) -> anyhow::Result<()> {
        anyhow::bail!("pregrasp replay is being built")
    }
}
