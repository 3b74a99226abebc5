//! Background codebook builds: one low-priority builder thread (a bounded pool of one, so that
//! builds never take more than one of the machine's cores from tracking), coarse codebooks
//! first so that tracking starts quickly, then (optionally) the fine grid. Built codebooks are
//! cached on disk under `<data dir>/codebooks` (keyed by mesh content, grid and config), so a
//! restart loads them instead of rebuilding.

use super::registry::{CodebookState, CodebookStatus};
use super::{Service, ServiceState};
use crate::geometry::RotationGrid;
use crate::render::Renderer;
use crate::tracker::Codebook;
use crate::tracker::codebook::{CodebookConfig, CpuViews, RendererViews, ViewSource};
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Duration;

/// Ready codebooks per object id, with the content hash they were built for.
#[derive(Default)]
pub struct Codebooks {
    ready: Mutex<HashMap<String, (String, Arc<Codebook>)>>,
}

impl Codebooks {
    /// The ready codebook of an object whose mesh has `content_hash`, with or without colour.
    pub fn get(&self, object_id: &str, content_hash: &str, use_color: bool) -> Option<Arc<Codebook>> {
        let ready = self.ready.lock().unwrap_or_else(|p| p.into_inner());
        ready
            .get(object_id)
            .filter(|(h, c)| h == content_hash && c.config.use_color == use_color)
            .map(|(_, c)| c.clone())
    }
    /// Drops an object's codebook (the object was deleted).
    pub fn forget(&self, object_id: &str) {
        self.ready.lock().unwrap_or_else(|p| p.into_inner()).remove(object_id);
    }
    fn put(&self, object_id: &str, content_hash: &str, cb: Arc<Codebook>) {
        self.ready
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .insert(object_id.to_string(), (content_hash.to_string(), cb));
    }
}

/// The codebook settings of a server.
#[derive(Debug, Clone)]
pub struct CodebookPlan {
    /// The first codebook of every object (fast).
    pub coarse_step_deg: u32,
    pub coarse: CodebookConfig,
    /// The codebook built after the coarse one (`None`: keep the coarse one).
    pub fine: Option<(u32, CodebookConfig)>,
}

impl CodebookPlan {
    /// The grid step of `serve`'s finer codebook by default (the paper's grid).
    pub const SERVE_FINE_STEP_DEG: u32 = crate::eval::calibration::SERVICE_GRID_STEP_DEG;

    /// The coarse codebook first, then a finer one on the `fine_step_deg` grid when that is
    /// finer than the coarse one (as `serve --codebook-step-deg` and `demo-loops` build them).
    pub fn with_fine_step(fine_step_deg: u32) -> Self {
        let mut plan = Self::default();
        if fine_step_deg < plan.coarse_step_deg {
            plan.fine = Some((fine_step_deg, CodebookConfig::default()));
        }
        plan
    }

    /// The codebook an object tracks with once every stage is built, and its grid step.
    pub fn last_stage(&self) -> (&CodebookConfig, u32) {
        match &self.fine {
            Some((step, config)) => (config, *step),
            None => (&self.coarse, self.coarse_step_deg),
        }
    }
}

impl Default for CodebookPlan {
    fn default() -> Self {
        Self {
            coarse_step_deg: 10,
            coarse: CodebookConfig::coarse(),
            fine: None,
        }
    }
}

/// What a build is for: an object with one mesh and one colour choice. A build whose object
/// no longer matches is stale: it stops at its next batch of views and its result is dropped.
#[derive(Debug, Clone, PartialEq, Eq)]
struct BuildTag {
    object_id: String,
    content_hash: String,
    use_color: bool,
}

impl BuildTag {
    fn is_current(&self, state: &ServiceState) -> bool {
        state
            .registry()
            .objects
            .get(&self.object_id)
            .is_some_and(|o| o.info.content_hash == self.content_hash && o.info.use_color == self.use_color)
    }
}

/// A view source that fails once its build is stale, so that a replaced or deleted object's
/// build ends early instead of running to completion.
struct Cancellable<'a> {
    inner: &'a dyn ViewSource,
    tag: &'a BuildTag,
    state: &'a ServiceState,
}

impl ViewSource for Cancellable<'_> {
    fn render(
        &self,
        intrinsics: &crate::camera::Intrinsics,
        camera_from_object: &[crate::geometry::Pose],
    ) -> Result<Vec<(crate::camera::DepthImage, Option<crate::camera::ColorImage>)>, crate::tracker::TrackerError> {
        if !self.tag.is_current(self.state) {
            return Err(crate::tracker::TrackerError::Config(STALE_BUILD.into()));
        }
        self.inner.render(intrinsics, camera_from_object)
    }
}

/// The error text of a build stopped because its object changed.
const STALE_BUILD: &str = "the object's mesh changed during the build";

/// Why a build produced no codebook.
enum BuildError {
    /// The object was replaced or deleted meanwhile (not a failure of the object).
    Stale,
    Failed(String),
}

fn build(
    state: &ServiceState,
    tag: &BuildTag,
    mesh: &crate::mesh::Mesh,
    step_deg: u32,
    config: &CodebookConfig,
) -> Result<(), BuildError> {
    let object_id = &tag.object_id;
    let config = &CodebookConfig {
        use_color: config.use_color && tag.use_color,
        ..state.config.tracker.codebook_config(config)
    };
    let grid = RotationGrid::new(step_deg).map_err(|e| BuildError::Failed(e.to_string()))?;
    let cache = state.config.data_dir.join("codebooks");
    // Templates come from the wgpu renderer (a real GPU, or lavapipe without one); the CPU
    // rasteriser is the fallback for machines where wgpu finds no usable adapter at all.
    let gpu_views = template_renderer().and_then(|r| match RendererViews::new(r, mesh) {
        Ok(v) => Some(v),
        Err(e) => {
            tracing::warn!("cannot upload {object_id} to the renderer ({e}); using the CPU rasteriser");
            None
        }
    });
    let cpu_views = CpuViews(mesh);
    let source: &dyn ViewSource = match &gpu_views {
        Some(v) => v,
        None => &cpu_views,
    };
    let source = Cancellable {
        inner: source,
        tag,
        state,
    };
    let built = Codebook::load_or_build_with(&source, mesh, grid, config, Some(&cache));
    if !tag.is_current(state) {
        return Err(BuildError::Stale);
    }
    let cb = built.map_err(|e| BuildError::Failed(e.to_string()))?;
    tracing::info!(
        "codebook of {object_id}: {step_deg} deg grid, {} bins, {:.1} s{}",
        cb.n_bins(),
        cb.build_seconds,
        if cb.from_cache { " (from cache)" } else { "" }
    );
    if !cb.from_cache {
        prune_cache(&cache, state.config.limits.max_cached_codebooks);
    }
    state.codebooks.put(object_id, &tag.content_hash, Arc::new(cb));
    Ok(())
}

/// Keeps at most `max_files` codebook files in the cache folder, deleting the least recently
/// written first.
pub fn prune_cache(dir: &std::path::Path, max_files: usize) {
    let Ok(entries) = std::fs::read_dir(dir) else { return };
    let mut files: Vec<(std::time::SystemTime, std::path::PathBuf)> = entries
        .filter_map(Result::ok)
        .filter(|e| {
            let name = e.file_name();
            let name = name.to_string_lossy();
            name.starts_with("codebook-") && name.ends_with(".bin")
        })
        .filter_map(|e| Some((e.metadata().ok()?.modified().ok()?, e.path())))
        .collect();
    if files.len() <= max_files {
        return;
    }
    files.sort();
    let excess = files.len() - max_files;
    for (_, path) in files.into_iter().take(excess) {
        if let Err(e) = std::fs::remove_file(&path) {
            tracing::warn!("cannot remove cached codebook {}: {e}", path.display());
        }
    }
}

/// The process's wgpu renderer (codebook templates, demo cameras), created on first use;
/// `None` when wgpu has no adapter.
pub(crate) fn template_renderer() -> Option<&'static Renderer> {
    static RENDERER: OnceLock<Option<Renderer>> = OnceLock::new();
    RENDERER
        .get_or_init(|| match Renderer::new() {
            Ok(r) => {
                tracing::info!("codebook templates rendered with wgpu on {}", r.adapter_name());
                Some(r)
            }
            Err(e) => {
                tracing::warn!("no wgpu adapter ({e}); codebook templates use the CPU rasteriser");
                None
            }
        })
        .as_ref()
}

/// Nice value of the codebook builder's threads (the tracker runs at the default 0).
pub const BUILDER_NICE: i32 = 10;

/// Lowers the calling thread's OS priority to [`BUILDER_NICE`] (Linux: the nice value is per
/// thread); elsewhere a no-op.
fn lower_thread_priority() {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: setpriority only reads its integer arguments; `who = 0` is the calling thread.
        #[allow(unsafe_code)]
        let rc = unsafe { libc::setpriority(libc::PRIO_PROCESS, 0, BUILDER_NICE) };
        if rc != 0 {
            tracing::warn!(
                "cannot lower the codebook builder's priority: {}",
                std::io::Error::last_os_error()
            );
        }
    }
}

/// The builder's own thread pool: all cores but one (at least one), every thread at lower OS
/// priority, so that a codebook build (the encoder's training and matrix products run on
/// rayon) never competes with the tracker's steps on equal terms.
fn builder_pool() -> Option<rayon::ThreadPool> {
    let cores = std::thread::available_parallelism().map_or(2, |n| n.get());
    rayon::ThreadPoolBuilder::new()
        .num_threads(cores.saturating_sub(1).max(1))
        .thread_name(|i| format!("pregrasp-codebook-{i}"))
        .start_handler(|_| lower_thread_priority())
        .build()
        .map_err(|e| tracing::warn!("codebook pool: {e}; building on the global pool"))
        .ok()
}

/// The next build, as (object, stage): every object's first (coarse) stage before any
/// object's later stage, so that all objects become trackable before a fine grid starts (a
/// full codebook takes 15-30 s on 2 cores). An object whose stage failed gets no later stage.
fn next_stage(reg: &super::Registry, n_stages: usize) -> Option<(String, usize)> {
    let pending = reg
        .objects
        .values()
        .find(|o| o.info.codebook.status == CodebookState::Pending)
        .map(|o| (o.info.id.clone(), 0));
    pending.or_else(|| {
        reg.objects.values().find_map(|o| {
            let c = &o.info.codebook;
            let done = (c.progress * n_stages as f64).round() as usize;
            (c.status == CodebookState::Ready && c.error.is_none() && (1..n_stages).contains(&done))
                .then(|| (o.info.id.clone(), done))
        })
    })
}

/// Starts the builder thread; it stops when `stop` is set.
pub fn spawn_builder(state: Service, stop: Arc<AtomicBool>) -> Option<std::thread::JoinHandle<()>> {
    std::thread::Builder::new()
        .name("pregrasp-codebooks".into())
        .spawn(move || {
            lower_thread_priority();
            let pool = builder_pool();
            while !stop.load(Ordering::Relaxed) {
                let plan = state.config.codebooks.clone();
                let stages: Vec<(u32, CodebookConfig)> = std::iter::once((plan.coarse_step_deg, plan.coarse.clone()))
                    .chain(plan.fine.clone())
                    .collect();
                let n = stages.len();
                let next = next_stage(&state.registry(), n);
                let Some((id, i)) = next else {
                    std::thread::sleep(Duration::from_millis(100));
                    continue;
                };
                let (step, config) = &stages[i];
                let (tag, mesh) = {
                    let reg = state.registry();
                    let Some(o) = reg.objects.get(&id) else { continue };
                    let tag = BuildTag {
                        object_id: id.clone(),
                        content_hash: o.info.content_hash.clone(),
                        use_color: o.info.use_color,
                    };
                    (tag, o.mesh.clone())
                };
                let status = |status, stages_done: usize, error| CodebookStatus {
                    status,
                    progress: stages_done as f64 / n as f64,
                    grid_step_deg: Some(*step),
                    error,
                };
                let set = |s: CodebookStatus| state.set_codebook_status(&id, &tag.content_hash, tag.use_color, s);
                // a later stage keeps the earlier codebook in use: the object stays ready
                let before = if i == 0 {
                    CodebookState::Building
                } else {
                    CodebookState::Ready
                };
                if !set(status(before, i, None)) {
                    continue;
                }
                let built = match &pool {
                    Some(p) => p.install(|| build(&state, &tag, &mesh, *step, config)),
                    None => build(&state, &tag, &mesh, *step, config),
                };
                let after = match built {
                    Ok(()) => status(CodebookState::Ready, i + 1, None),
                    Err(BuildError::Stale) => {
                        // the new mesh is pending: its own build comes next
                        tracing::info!("codebook build of {id} abandoned: {STALE_BUILD}");
                        state.metrics.codebook_builds_cancelled.fetch_add(1, Ordering::Relaxed);
                        continue;
                    }
                    Err(BuildError::Failed(e)) => {
                        tracing::warn!("codebook of {id} failed: {e}");
                        let state_now = if i == 0 {
                            CodebookState::Failed
                        } else {
                            CodebookState::Ready
                        };
                        // the error stops later stages (see `next_stage`)
                        status(state_now, i, Some(e))
                    }
                };
                // only the status of the mesh this build was for (see `set_codebook_status`)
                let trackable = i == 0 && after.status == CodebookState::Ready;
                if set(after) && trackable {
                    // the object can be tracked now: get its grasps ready before a decision
                    // asks, on the builders' low-priority pool
                    match &pool {
                        Some(p) => p.install(|| state.warm_grasps(&id)),
                        None => state.warm_grasps(&id),
                    }
                }
            }
        })
        .ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_coarse_codebook_is_built_before_any_fine_one() {
        let object = |id: &str, status: CodebookState, stages_done: usize, error: Option<&str>| {
            let info = crate::service::registry::ObjectInfo {
                id: id.into(),
                name: id.into(),
                n_vertices: 8,
                n_triangles: 12,
                diameter_m: 0.1,
                content_hash: "h".into(),
                use_color: true,
                codebook: CodebookStatus {
                    status,
                    progress: stages_done as f64 / 2.0,
                    grid_step_deg: Some(10),
                    error: error.map(String::from),
                },
            };
            let mesh = Arc::new(crate::mesh::builtin("box").expect("builtin"));
            (id.to_string(), crate::service::registry::ObjectEntry { info, mesh })
        };
        let mut reg = crate::service::Registry::default();
        // "a" has its coarse codebook, "b" and "c" none yet: "b" (then "c") first
        reg.objects.extend([
            object("a", CodebookState::Ready, 1, None),
            object("b", CodebookState::Pending, 0, None),
            object("c", CodebookState::Pending, 0, None),
        ]);
        assert_eq!(next_stage(&reg, 2), Some(("b".into(), 0)));
        reg.objects.extend([
            object("b", CodebookState::Ready, 1, None),
            object("c", CodebookState::Ready, 1, None),
        ]);
        // all coarse: now the fine stage, of the first object that still needs it
        assert_eq!(next_stage(&reg, 2), Some(("a".into(), 1)));
        reg.objects.extend([
            object("a", CodebookState::Ready, 2, None),
            object("b", CodebookState::Ready, 1, Some("render failed")),
        ]);
        assert_eq!(next_stage(&reg, 2), Some(("c".into(), 1)));
        reg.objects.extend([object("c", CodebookState::Ready, 2, None)]);
        // nothing left (a failed stage is not retried); one stage only: nothing after coarse
        assert_eq!(next_stage(&reg, 2), None);
        assert_eq!(next_stage(&reg, 1), None);
    }

    #[test]
    fn the_cache_keeps_the_newest_codebooks() {
        let dir = tempfile::tempdir().expect("tempdir");
        for i in 0..5 {
            std::fs::write(dir.path().join(format!("codebook-{i}.bin")), b"x").expect("write");
            // distinct modification times
            std::thread::sleep(Duration::from_millis(20));
        }
        std::fs::write(dir.path().join("other.txt"), b"x").expect("write");
        prune_cache(dir.path(), 2);
        let mut left: Vec<String> = std::fs::read_dir(dir.path())
            .expect("read")
            .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
            .collect();
        left.sort();
        assert_eq!(left, ["codebook-3.bin", "codebook-4.bin", "other.txt"]);
    }

    #[test]
    #[cfg(target_os = "linux")]
    fn builder_pool_threads_run_at_lower_priority() {
        let pool = builder_pool().expect("pool");
        let nices: Vec<i32> = pool.install(|| {
            use rayon::prelude::*;
            (0..64)
                .into_par_iter()
                // SAFETY: getpriority only reads its integer arguments.
                .map(|_| {
                    #[allow(unsafe_code)]
                    unsafe {
                        libc::getpriority(libc::PRIO_PROCESS, 0)
                    }
                })
                .collect()
        });
        assert!(nices.iter().all(|n| *n >= BUILDER_NICE), "{nices:?}");
        // ... and the caller's thread is untouched
        // SAFETY: as above.
        #[allow(unsafe_code)]
        let here = unsafe { libc::getpriority(libc::PRIO_PROCESS, 0) };
        assert!(here < BUILDER_NICE);
    }
}
