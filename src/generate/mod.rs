//! (being built) The scene generator.

pub mod plan;
pub mod raster;

pub mod cli {
    /// Options of `pregrasp generate`.
    #[derive(Debug, clap::Args)]
    pub struct Args {}
    pub fn run(_args: Args) -> anyhow::Result<()> {
        anyhow::bail!("pregrasp generate is being built")
    }
}
