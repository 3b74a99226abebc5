//! pregrasp: multi-view 6D pose distribution tracking and grasp-or-observe decisions.
//!
//! See `ARCHITECTURE.md` for the modules and the data flow
//! (frame -> tracker -> decision -> API). Domain modules (`geometry`, `camera`, `mesh`,
//! `render`, `sensor`, `dataset`, `generate`, `tracker`, `eval`, `grasp`, `symmetry`) never
//! import axum or utoipa; `service` (the runtime: registry, ingest, the worker, decisions,
//! storage) takes domain types and knows no HTTP; `api` converts once at the edge; `tools`
//! talk to a server over the network.

pub mod api;
pub mod camera;
pub mod dataset;
pub mod eval;
pub mod generate;
pub mod geometry;
pub mod grasp;
pub mod mesh;
pub mod render;
pub mod sensor;
pub mod service;
pub mod symmetry;
pub mod tools;
pub mod tracker;

/// Helpers of the unit tests.
#[cfg(test)]
pub(crate) mod testing {
    use std::path::PathBuf;

    /// The shared data folder (`PREGRASP_SHARED`, else `../shared` beside the repository).
    pub fn shared_dir() -> PathBuf {
        std::env::var_os("PREGRASP_SHARED")
            .map(PathBuf::from)
            .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared"))
    }
}
