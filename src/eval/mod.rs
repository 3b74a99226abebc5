//! `pregrasp eval`: run the tracker over generated or recorded sequences and report the
//! paper's metrics (Table I), plots over time (Fig. 5) and, with `--decide`, the calibration
//! of the grasp decision.

pub mod calibration;
pub mod metrics;
pub mod plot;
pub mod report;
pub mod truth;

pub mod cli {
    /// Options of `pregrasp eval`.
    #[derive(Debug, clap::Args)]
    pub struct Args {}
    pub fn run(_args: Args) -> anyhow::Result<()> {
        anyhow::bail!("pregrasp eval is being built")
    }
}
