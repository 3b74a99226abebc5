//! Background codebook builds: one low-priority builder thread (a bounded pool of one, so that
//! builds never take more than one of the machine's cores from tracking), coarse codebooks
//! first so that tracking starts quickly, then (optionally) the fine grid. Built codebooks are
//! cached on disk under `<data dir>/codebooks` (keyed by mesh content, grid and config), so a
//! restart loads them instead of rebuilding.

use super::AppState;
use super::objects::{CodebookState, CodebookStatus, set_codebook_status};
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

impl Default for CodebookPlan {
    fn default() -> Self {
        Self {
            coarse_step_deg: 10,
            coarse: CodebookConfig::coarse(),
            fine: None,
        }
    }
}

fn build(state: &AppState, object_id: &str, step_deg: u32, config: &CodebookConfig) -> Result<(), String> {
    let (mesh, hash, use_color) = {
        let reg = state.registry();
        let o = reg.objects.get(object_id).ok_or("object was deleted")?;
        (o.mesh.clone(), o.info.content_hash.clone(), o.info.use_color)
    };
    let config = &CodebookConfig {
        use_color: config.use_color && use_color,
        ..config.clone()
    };
    let grid = RotationGrid::new(step_deg).map_err(|e| e.to_string())?;
    let cache = state.config.data_dir.join("codebooks");
    // Templates come from the wgpu renderer (a real GPU, or lavapipe without one); the CPU
    // rasteriser is the fallback for machines where wgpu finds no usable adapter at all.
    let gpu_views = template_renderer().and_then(|r| match RendererViews::new(r, &mesh) {
        Ok(v) => Some(v),
        Err(e) => {
            tracing::warn!("cannot upload {object_id} to the renderer ({e}); using the CPU rasteriser");
            None
        }
    });
    let cpu_views = CpuViews(&mesh);
    let source: &dyn ViewSource = match &gpu_views {
        Some(v) => v,
        None => &cpu_views,
    };
    let cb = Codebook::load_or_build_with(source, &mesh, grid, config, Some(&cache)).map_err(|e| e.to_string())?;
    tracing::info!(
        "codebook of {object_id}: {step_deg} deg grid, {} bins, {:.1} s{}",
        cb.n_bins(),
        cb.build_seconds,
        if cb.from_cache { " (from cache)" } else { "" }
    );
    state.codebooks.put(object_id, &hash, Arc::new(cb));
    Ok(())
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
pub fn spawn_builder(state: AppState, stop: Arc<AtomicBool>) -> Option<std::thread::JoinHandle<()>> {
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
                let status = |status, stages_done: usize, error| CodebookStatus {
                    status,
                    progress: stages_done as f64 / n as f64,
                    grid_step_deg: Some(*step),
                    error,
                };
                // a later stage keeps the earlier codebook in use: the object stays ready
                let before = if i == 0 {
                    CodebookState::Building
                } else {
                    CodebookState::Ready
                };
                set_codebook_status(&state, &id, status(before, i, None));
                let built = match &pool {
                    Some(p) => p.install(|| build(&state, &id, *step, config)),
                    None => build(&state, &id, *step, config),
                };
                let after = match built {
                    Ok(()) => status(CodebookState::Ready, i + 1, None),
                    Err(e) => {
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
                set_codebook_status(&state, &id, after);
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
            let info = crate::api::objects::ObjectInfo {
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
            (id.to_string(), crate::api::objects::ObjectEntry { info, mesh })
        };
        let mut reg = crate::api::Registry::default();
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
