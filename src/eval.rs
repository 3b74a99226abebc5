//! (being built) The evaluation.

pub mod cli {
    /// Options of `pregrasp eval`.
    #[derive(Debug, clap::Args)]
    pub struct Args {}
    pub fn run(_args: Args) -> anyhow::Result<()> {
        anyhow::bail!("pregrasp eval is being built")
    }
}
