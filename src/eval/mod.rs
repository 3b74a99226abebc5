//! `pregrasp eval`: run the tracker over generated or recorded sequences and report the
//! paper's metrics (Table I), plots over time (Fig. 5) and, with `--decide`, the calibration
//! of the grasp decision.
//!
//! Files: `metrics.rs` (per-frame errors, symmetries, ADD/ADD-S, AUC), `truth.rs` (ground
//! truth in the reference frame, for scoring only), `report.rs` (`results.json` and the
//! Markdown table beside the paper's), `plot.rs` (plots over time as SVG and PNG, the
//! reliability diagram; plotters), `calibration.rs` (scores of the grasp decision), `trust.rs` (the truth's place
//! in the tracked distribution: highest-density regions), `run.rs` (the runner), `cli.rs`
//! (`pregrasp eval`), `refit.rs` (`pregrasp calibrate`: the map of the calibrated `p_success`
//! and the rule chosen by its failures). Symmetries (shape, and shape with colour) live in `crate::symmetry`.

pub mod calibration;
pub mod cli;
pub mod metrics;
pub mod plot;
pub mod refit;
pub mod report;
pub mod run;
pub mod trust;
pub mod truth;

/// Errors of the evaluation.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error("data set: {0}")]
    Data(String),
    #[error("configuration: {0}")]
    Config(String),
    #[error("tracker: {0}")]
    Tracker(String),
    #[error("renderer: {0}")]
    Render(String),
    #[error("grasp decision: {0}")]
    Grasp(String),
    #[error("output: {0}")]
    Io(String),
}
