//! Off-screen rendering with wgpu: metric z-depth, shaded colour and instance masks of meshes.
//!
//! - [`Renderer::render_scene`]: several meshes seen by one camera with any pinhole intrinsics
//!   (depth, colour, per-object instance mask).
//! - [`Renderer::render_views`] / [`Renderer::render_view_depths`]: many small views of one mesh
//!   (codebooks), batched into an atlas texture: one viewport and one draw per view, one submit
//!   per atlas, the atlas chunked to stay within the device's texture limits.
//!
//! Conventions: optical frames (x right, y down, z forward); pixel `(u, v)` of a camera-frame
//! point is `u = fx x / z + cx`, `v = fy y / z + cy` with pixel centres at integer + 0.5 (exactly
//! as [`Intrinsics::project`]). Depth images hold z-depth in metres, 0 where nothing was hit or
//! outside the clip range. The shader (`mesh.wgsl`) documents the projection.
//!
//! Adapter: a real GPU when there is one, else a software adapter (Mesa's lavapipe on Vulkan).
//! `WGPU_BACKEND` (e.g. `vulkan`) restricts the backends; without it we try the primary
//! backends (Vulkan, Metal, DX12) first, then all. wgpu's GL backend cannot copy depth
//! textures to buffers, so it is refused with a clear error.
//!
//! The renderer is `Send + Sync`: share it with `Arc`. GPU work is serialised by an internal
//! mutex (which also guards the cached render targets and readback buffers).
//!
//! # Speed (see `benches/render.rs`)
//! On the 2-core machine without a GPU (lavapipe), batched 64x64 depth views of a
//! 5,000-triangle mesh cost about 0.25 ms of CPU each (about 4,000 views per CPU-second); per
//! triangle set-up and rasterisation dominate. What keeps it there: one submit per atlas (a
//! submit costs about 13 ms on lavapipe); all per-draw records in one uniform buffer, selected
//! by a dynamic offset (lavapipe then loads a record once per draw; a storage array indexed by
//! the instance index was loaded per vertex and made vertex work twice as expensive); culling
//! the invisible faces of closed meshes ([`invisible_faces`]), which halves the triangles the
//! rasteriser sets up (1.8x faster); depth read back from the reversed f32 z-buffer and
//! converted to metres on the CPU (resolution about 1e-7 of the depth), so depth-only renders
//! run no fragment shader at all (10 % faster than writing an `R32Float` target); render
//! targets and readback buffers cached per size. Views with colour ([`Renderer::render_views`]) cost about 30 % more
//! than depth only. For whole codebooks use [`Renderer::for_each_view_depth`], which streams
//! one atlas at a time.
//!
//! # What a real GPU changes
//! Not measured here (no GPU on this machine); what follows is the expected shift. Triangle
//! work becomes nearly free (microseconds per view), so the cost moves to reading the atlas
//! back (16 KiB per 64x64 depth view; tens of GB/s over PCIe, i.e. hundreds of thousands of
//! views per second) and to cutting tiles on the CPU. Worth doing then: a larger atlas
//! ([`MAX_ATLAS_SIDE_PX`] could follow the device limit, 8192 or more), double-buffered
//! readback (map atlas k while atlas k+1 renders), and matching codebooks on the GPU in a
//! compute pass instead of reading views back at all (on lavapipe compute is about 250x slower
//! than the CPU, so matching stays on the CPU there). Depth precision is unchanged (the
//! reversed `Depth32Float` z-buffer).

use crate::camera::{ColorImage, DepthImage, Intrinsics};
use crate::geometry::Pose;
use crate::mesh::Mesh;
use nalgebra::Vector3;
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use wgpu::util::DeviceExt;

/// The WGSL source of the mesh shader (validated with naga in the tests).
pub const MESH_SHADER_WGSL: &str = include_str!("mesh.wgsl");

/// Every WGSL shader of this module, by file name (for validation).
pub const SHADERS: &[(&str, &str)] = &[("mesh.wgsl", MESH_SHADER_WGSL)];

/// Largest atlas side used for batched views (pixels); smaller if the device allows less.
pub const MAX_ATLAS_SIDE_PX: u32 = 2048;

const COLOR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
const INSTANCE_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::R16Uint;
const ZBUFFER_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;
/// Bytes of one vertex: position f32x3, colour unorm8x4.
const VERTEX_STRIDE: u64 = 16;
/// Bytes of one draw record in the uniform buffer (see `Draw` in mesh.wgsl).
const DRAW_RECORD_BYTES: usize = 128;
/// Meshes with at most this fraction of flawed edges (holes, non-manifold) count as closed and
/// consistently oriented for culling.
pub const MAX_FLAWED_EDGE_FRACTION: f64 = 0.01;
/// Cached render-target sets kept at most.
const MAX_CACHED_TARGETS: usize = 6;

static NEXT_RENDERER_ID: AtomicU64 = AtomicU64::new(1);

#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    #[error(
        "no graphics adapter found ({0}); without a GPU install Mesa's software Vulkan driver \
         (Debian: apt-get install -y mesa-vulkan-drivers libvulkan1) and set WGPU_BACKEND=vulkan"
    )]
    NoAdapter(String),
    #[error("cannot open the graphics device on adapter {adapter}: {reason}")]
    Device { adapter: String, reason: String },
    #[error("invalid mesh for rendering: {0}")]
    Mesh(#[from] crate::mesh::MeshError),
    #[error("clip range must satisfy 0 < near_m < far_m (finite); got near {near_m} m, far {far_m} m")]
    BadClip { near_m: f32, far_m: f32 },
    #[error("image {width}x{height} exceeds the device's texture limit of {max} pixels per side")]
    TooLarge { width: u32, height: u32, max: u32 },
    #[error("mesh handle belongs to another renderer")]
    ForeignMesh,
    #[error("pose is not finite")]
    NonFinitePose,
    #[error("reading back the rendered images failed: {0}")]
    Readback(String),
    #[error("GPU error: {0}")]
    Gpu(String),
}

/// Near and far clip distances along the optical axis, metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClipRange {
    pub near_m: f32,
    pub far_m: f32,
}

impl ClipRange {
    pub fn new(near_m: f32, far_m: f32) -> Result<Self, RenderError> {
        let c = Self { near_m, far_m };
        c.validate()?;
        Ok(c)
    }

    fn validate(&self) -> Result<(), RenderError> {
        if self.near_m.is_finite() && self.far_m.is_finite() && self.near_m > 0.0 && self.far_m > self.near_m {
            Ok(())
        } else {
            Err(RenderError::BadClip {
                near_m: self.near_m,
                far_m: self.far_m,
            })
        }
    }
}

impl Default for ClipRange {
    /// 5 cm to 20 m.
    fn default() -> Self {
        Self {
            near_m: 0.05,
            far_m: 20.0,
        }
    }
}

/// A mesh uploaded to one renderer; cheap to clone.
#[derive(Clone)]
pub struct MeshHandle {
    inner: Arc<GpuMesh>,
}

struct GpuMesh {
    renderer_id: u64,
    /// Faces that can never be visible (closed, consistently oriented meshes): culled before
    /// rasterisation, which halves the triangles a software rasteriser sets up.
    cull: Option<wgpu::Face>,
    vertices: wgpu::Buffer,
    indices: wgpu::Buffer,
    index_count: u32,
}

impl MeshHandle {
    pub fn n_triangles(&self) -> usize {
        self.inner.index_count as usize / 3
    }

    /// True when the mesh is closed and consistently oriented, so its invisible faces are culled
    /// (see [`invisible_faces`]).
    pub fn culls_back_faces(&self) -> bool {
        self.inner.cull.is_some()
    }
}

impl std::fmt::Debug for MeshHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MeshHandle")
            .field("n_triangles", &self.n_triangles())
            .field("cull", &self.inner.cull)
            .finish()
    }
}

/// One object of a scene.
#[derive(Debug, Clone)]
pub struct SceneObject {
    pub mesh: MeshHandle,
    pub world_from_object: Pose,
    /// Written into [`SceneRender::instance`] where this object is visible; 0 means none, so
    /// use ids from 1.
    pub instance_id: u16,
}

/// A rendered scene: z-depth (0 = nothing), shaded colour, instance ids (0 = none), row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneRender {
    pub depth: DepthImage,
    pub color: ColorImage,
    pub instance: Vec<u16>,
}

/// One rendered view of a mesh.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewRender {
    pub depth: DepthImage,
    pub color: ColorImage,
}

/// Which render targets a pass writes and reads back.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum Outputs {
    /// Depth, colour and instance mask.
    Scene,
    /// Depth and colour.
    View,
    /// Depth only.
    Depth,
}

impl Outputs {
    fn color(self) -> bool {
        matches!(self, Outputs::Scene | Outputs::View)
    }
    fn instance(self) -> bool {
        matches!(self, Outputs::Scene)
    }
}

/// One render target with its readback buffer.
struct Target {
    texture: wgpu::Texture,
    view: wgpu::TextureView,
    aspect: wgpu::TextureAspect,
    readback: wgpu::Buffer,
    bytes_per_pixel: u32,
    padded_bytes_per_row: u32,
}

/// Outputs and culled face of a pipeline.
type PipelineKey = (Outputs, Option<wgpu::Face>);

/// Width, height and outputs of a set of render targets.
type TargetKey = (u32, u32, Outputs);

/// The render targets of one size and kind.
struct Targets {
    /// The reversed z-buffer, read back and converted to metric depth.
    zbuffer: Target,
    color: Option<Target>,
    instance: Option<Target>,
}

/// A draw: the mesh, its record (transform, intrinsics, clip, id) and its viewport.
struct DrawCall<'a> {
    mesh: &'a GpuMesh,
    camera_from_object: Pose,
    intrinsics: &'a Intrinsics,
    clip: ClipRange,
    instance_id: u16,
    /// x, y, width, height in pixels of the render target.
    viewport: [u32; 4],
    /// Unit direction towards a directional light in the camera frame; `None`: a headlight.
    light_in_camera: Option<Vector3<f64>>,
}

/// Whole render targets read back into memory (row padding removed).
struct Readback {
    width: u32,
    depth_m: Vec<f32>,
    color: Vec<[u8; 3]>,
    instance: Vec<u16>,
}

impl Readback {
    fn depth_tile(&self, x0: u32, y0: u32, w: u32, h: u32) -> Vec<f32> {
        tile(&self.depth_m, self.width, x0, y0, w, h)
    }
    fn color_tile(&self, x0: u32, y0: u32, w: u32, h: u32) -> Vec<[u8; 3]> {
        tile(&self.color, self.width, x0, y0, w, h)
    }
}

fn tile<T: Copy>(data: &[T], width: u32, x0: u32, y0: u32, w: u32, h: u32) -> Vec<T> {
    let mut out = Vec::with_capacity((w * h) as usize);
    for y in y0..y0 + h {
        let start = (y * width + x0) as usize;
        out.extend_from_slice(&data[start..start + w as usize]);
    }
    out
}

/// The wgpu renderer. `Send + Sync`; share it with `Arc`.
pub struct Renderer {
    id: u64,
    device: wgpu::Device,
    queue: wgpu::Queue,
    info: wgpu::AdapterInfo,
    max_side_px: u32,
    bind_group_layout: wgpu::BindGroupLayout,
    /// Bytes between draw records: the record rounded up to the uniform offset alignment.
    record_stride: u32,
    pipeline_layout: wgpu::PipelineLayout,
    shader: wgpu::ShaderModule,
    /// Pipelines by outputs and culled face, created on first use.
    pipelines: Mutex<HashMap<PipelineKey, wgpu::RenderPipeline>>,
    /// Serialises GPU work and caches render targets by (width, height, outputs).
    targets: Mutex<Vec<(TargetKey, Targets)>>,
}

impl std::fmt::Debug for Renderer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Renderer")
            .field("adapter", &self.info.name)
            .field("backend", &self.info.backend)
            .finish()
    }
}

impl Renderer {
    /// Opens a device: a high-performance adapter if there is one, else any (software) adapter.
    pub fn new() -> Result<Renderer, RenderError> {
        let adapter = find_adapter()?;
        let info = adapter.get_info();
        let limits = adapter.limits();
        let unfit = |reason: String| RenderError::Device {
            adapter: format!("{} ({:?})", info.name, info.backend),
            reason: format!("{reason} (wgpu's GL backend cannot; use Vulkan: WGPU_BACKEND=vulkan)"),
        };
        let downlevel = adapter.get_downlevel_capabilities();
        if !downlevel
            .flags
            .contains(wgpu::DownlevelFlags::DEPTH_TEXTURE_AND_BUFFER_COPIES)
        {
            return Err(unfit("cannot copy depth textures to buffers".into()));
        }
        for format in [COLOR_FORMAT, INSTANCE_FORMAT] {
            let features = adapter.get_texture_format_features(format);
            if !features.allowed_usages.contains(wgpu::TextureUsages::RENDER_ATTACHMENT) {
                return Err(unfit(format!("cannot render to {format:?}")));
            }
        }
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("pregrasp renderer"),
            required_features: wgpu::Features::empty(),
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| RenderError::Device {
            adapter: info.name.clone(),
            reason: e.to_string(),
        })?;
        device.on_uncaptured_error(Arc::new(|e| {
            tracing::error!("wgpu error: {e}");
        }));
        let scopes = ErrorScopes::push(&device);
        let bind_group_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("draws"),
            entries: &[wgpu::BindGroupLayoutEntry {
                binding: 0,
                visibility: wgpu::ShaderStages::VERTEX,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Uniform,
                    has_dynamic_offset: true,
                    min_binding_size: wgpu::BufferSize::new(DRAW_RECORD_BYTES as u64),
                },
                count: None,
            }],
        });
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("mesh.wgsl"),
            source: wgpu::ShaderSource::Wgsl(MESH_SHADER_WGSL.into()),
        });
        let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("mesh"),
            bind_group_layouts: &[Some(&bind_group_layout)],
            immediate_size: 0,
        });
        scopes.pop()?;
        let max_side_px = limits.max_texture_dimension_2d;
        Ok(Renderer {
            id: NEXT_RENDERER_ID.fetch_add(1, Ordering::Relaxed),
            device,
            queue,
            info,
            max_side_px,
            bind_group_layout,
            record_stride: (DRAW_RECORD_BYTES as u32).next_multiple_of(limits.min_uniform_buffer_offset_alignment),
            pipeline_layout: layout,
            shader: module,
            pipelines: Mutex::new(HashMap::new()),
            targets: Mutex::new(Vec::new()),
        })
    }

    /// The adapter's name and backend, e.g. `llvmpipe (LLVM 19.1.7, 256 bits) (Vulkan)`.
    pub fn adapter_name(&self) -> String {
        format!("{} ({:?})", self.info.name, self.info.backend)
    }

    /// True for a software (CPU) adapter such as lavapipe.
    pub fn is_software(&self) -> bool {
        self.info.device_type == wgpu::DeviceType::Cpu
    }

    /// Largest image side the device renders (pixels).
    pub fn max_image_side_px(&self) -> u32 {
        self.max_side_px
    }

    /// Copies a mesh to the device (validates it first). Closed, consistently oriented meshes
    /// get their invisible faces culled ([`invisible_faces`]): correct for cameras outside the
    /// mesh; for a camera inside a closed mesh (a room) use [`Self::upload_mesh_two_sided`].
    pub fn upload_mesh(&self, mesh: &Mesh) -> Result<MeshHandle, RenderError> {
        self.upload(mesh, invisible_faces(mesh))
    }

    /// Like [`Self::upload_mesh`] but never culls faces (slower on software adapters).
    pub fn upload_mesh_two_sided(&self, mesh: &Mesh) -> Result<MeshHandle, RenderError> {
        self.upload(mesh, None)
    }

    fn upload(&self, mesh: &Mesh, cull: Option<wgpu::Face>) -> Result<MeshHandle, RenderError> {
        mesh.validate()?;
        let mut vertex_bytes = Vec::with_capacity(mesh.vertices_m.len() * VERTEX_STRIDE as usize);
        for (i, v) in mesh.vertices_m.iter().enumerate() {
            for c in v {
                vertex_bytes.extend_from_slice(&c.to_le_bytes());
            }
            let rgb = mesh.colors.get(i).copied().unwrap_or([160, 160, 160]);
            vertex_bytes.extend_from_slice(&[rgb[0], rgb[1], rgb[2], 255]);
        }
        let index_bytes: Vec<u8> = mesh.triangles.iter().flatten().flat_map(|i| i.to_le_bytes()).collect();
        let vertices = self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("mesh vertices"),
            contents: &vertex_bytes,
            usage: wgpu::BufferUsages::VERTEX,
        });
        let indices = self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("mesh indices"),
            contents: &index_bytes,
            usage: wgpu::BufferUsages::INDEX,
        });
        Ok(MeshHandle {
            inner: Arc::new(GpuMesh {
                renderer_id: self.id,
                vertices,
                indices,
                index_count: (mesh.triangles.len() * 3) as u32,
                cull,
            }),
        })
    }

    /// Renders several objects seen from one camera, on a black background.
    pub fn render_scene(
        &self,
        intrinsics: &Intrinsics,
        camera_from_world: &Pose,
        objects: &[SceneObject],
        clip: ClipRange,
    ) -> Result<SceneRender, RenderError> {
        self.render_scene_lit(intrinsics, camera_from_world, objects, clip, [0, 0, 0], None)
    }

    /// [`Self::render_scene`] with a background colour (RGB) for pixels where nothing was hit,
    /// lit by a directional light shining from `towards_light_in_world` (a direction, world
    /// frame; `None`: a headlight at the camera, as codebook templates are rendered). A scene
    /// lit from elsewhere than the camera is what real cameras see: its shading is not the
    /// templates'.
    pub fn render_scene_lit(
        &self,
        intrinsics: &Intrinsics,
        camera_from_world: &Pose,
        objects: &[SceneObject],
        clip: ClipRange,
        background_rgb: [u8; 3],
        towards_light_in_world: Option<Vector3<f64>>,
    ) -> Result<SceneRender, RenderError> {
        clip.validate()?;
        let (w, h) = (intrinsics.width, intrinsics.height);
        self.check_size(w, h)?;
        let mut draws = Vec::with_capacity(objects.len());
        for o in objects {
            self.check_mesh(&o.mesh)?;
            draws.push(DrawCall {
                mesh: &o.mesh.inner,
                camera_from_object: camera_from_world * o.world_from_object,
                intrinsics,
                clip,
                instance_id: o.instance_id,
                viewport: [0, 0, w, h],
                light_in_camera: towards_light_in_world.map(|l| camera_from_world.rotation * l),
            });
        }
        let rb = self.render_batch(Outputs::Scene, w, h, background_rgb, &draws)?;
        Ok(SceneRender {
            depth: DepthImage {
                width: w,
                height: h,
                data_m: rb.depth_m,
            },
            color: ColorImage {
                width: w,
                height: h,
                data: rb.color,
            },
            instance: rb.instance,
        })
    }

    /// Many views of one mesh, each at `camera_from_object[i]` with `intrinsics` (the view's
    /// size and focal length), batched into atlases. Black background.
    pub fn render_views(
        &self,
        mesh: &MeshHandle,
        intrinsics: &Intrinsics,
        camera_from_object: &[Pose],
        clip: ClipRange,
    ) -> Result<Vec<ViewRender>, RenderError> {
        let mut out = Vec::with_capacity(camera_from_object.len());
        self.for_each_view(mesh, intrinsics, camera_from_object, clip, |_, v| out.push(v))?;
        Ok(out)
    }

    /// Streams the views of [`Self::render_views`] to `f(index, view)` in order, one atlas at a
    /// time, so that callers rendering very many views need not hold them all.
    pub fn for_each_view(
        &self,
        mesh: &MeshHandle,
        intrinsics: &Intrinsics,
        camera_from_object: &[Pose],
        clip: ClipRange,
        mut f: impl FnMut(usize, ViewRender),
    ) -> Result<(), RenderError> {
        let (w, h) = (intrinsics.width, intrinsics.height);
        let mut index = 0;
        self.render_views_each(mesh, intrinsics, camera_from_object, clip, Outputs::View, |rb, x, y| {
            f(
                index,
                ViewRender {
                    depth: DepthImage {
                        width: w,
                        height: h,
                        data_m: rb.depth_tile(x, y, w, h),
                    },
                    color: ColorImage {
                        width: w,
                        height: h,
                        data: rb.color_tile(x, y, w, h),
                    },
                },
            );
            index += 1;
        })
    }

    /// Like [`Self::render_views`] but depth only (faster: no colour target, less readback).
    pub fn render_view_depths(
        &self,
        mesh: &MeshHandle,
        intrinsics: &Intrinsics,
        camera_from_object: &[Pose],
        clip: ClipRange,
    ) -> Result<Vec<DepthImage>, RenderError> {
        let mut out = Vec::with_capacity(camera_from_object.len());
        self.for_each_view_depth(mesh, intrinsics, camera_from_object, clip, |_, d| out.push(d))?;
        Ok(out)
    }

    /// Streams depth-only views to `f(index, depth)` in order, one atlas at a time, so that
    /// callers rendering very many views (a full codebook) need not hold them all.
    pub fn for_each_view_depth(
        &self,
        mesh: &MeshHandle,
        intrinsics: &Intrinsics,
        camera_from_object: &[Pose],
        clip: ClipRange,
        mut f: impl FnMut(usize, DepthImage),
    ) -> Result<(), RenderError> {
        let (w, h) = (intrinsics.width, intrinsics.height);
        let mut index = 0;
        self.render_views_each(
            mesh,
            intrinsics,
            camera_from_object,
            clip,
            Outputs::Depth,
            |rb, x, y| {
                f(
                    index,
                    DepthImage {
                        width: w,
                        height: h,
                        data_m: rb.depth_tile(x, y, w, h),
                    },
                );
                index += 1;
            },
        )
    }

    /// Views per atlas for views of `width` x `height` pixels.
    pub fn views_per_atlas(&self, width: u32, height: u32) -> usize {
        let (cols, rows) = self.atlas_grid(width, height);
        (cols * rows) as usize
    }

    /// Columns and rows of views in an atlas (at least one view, even if larger than
    /// [`MAX_ATLAS_SIDE_PX`]; sizes are checked against the device limit separately).
    fn atlas_grid(&self, width: u32, height: u32) -> (u32, u32) {
        let side = self.atlas_side();
        ((side / width.max(1)).max(1), (side / height.max(1)).max(1))
    }

    fn atlas_side(&self) -> u32 {
        self.max_side_px.min(MAX_ATLAS_SIDE_PX)
    }

    /// Renders the views chunk by chunk; calls `tile(readback, x, y)` for every view in order.
    fn render_views_each(
        &self,
        mesh: &MeshHandle,
        intrinsics: &Intrinsics,
        camera_from_object: &[Pose],
        clip: ClipRange,
        outputs: Outputs,
        mut tile: impl FnMut(&Readback, u32, u32),
    ) -> Result<(), RenderError> {
        clip.validate()?;
        self.check_mesh(mesh)?;
        let (w, h) = (intrinsics.width, intrinsics.height);
        self.check_size(w, h)?;
        let (cols, rows) = self.atlas_grid(w, h);
        let per_atlas = self.views_per_atlas(w, h);
        for chunk in camera_from_object.chunks(per_atlas.max(1)) {
            // Atlas sizes rounded up to powers of two of views, so that calls with varying
            // numbers of views reuse a few cached render targets.
            let n = chunk.len() as u32;
            let used_rows = n.div_ceil(cols);
            let (atlas_cols, atlas_rows) = if used_rows > 1 {
                (cols, used_rows.next_power_of_two().min(rows))
            } else {
                (n.next_power_of_two().min(cols), 1)
            };
            let (atlas_w, atlas_h) = (atlas_cols * w, atlas_rows * h);
            let draws: Vec<DrawCall> = chunk
                .iter()
                .enumerate()
                .map(|(i, pose)| {
                    let i = i as u32;
                    DrawCall {
                        mesh: &mesh.inner,
                        camera_from_object: *pose,
                        intrinsics,
                        clip,
                        instance_id: 0,
                        viewport: [(i % cols) * w, (i / cols) * h, w, h],
                        light_in_camera: None,
                    }
                })
                .collect();
            let rb = self.render_batch(outputs, atlas_w, atlas_h, [0, 0, 0], &draws)?;
            for d in &draws {
                tile(&rb, d.viewport[0], d.viewport[1]);
            }
        }
        Ok(())
    }

    fn check_size(&self, width: u32, height: u32) -> Result<(), RenderError> {
        if width == 0 || height == 0 || width > self.max_side_px || height > self.max_side_px {
            return Err(RenderError::TooLarge {
                width,
                height,
                max: self.max_side_px,
            });
        }
        Ok(())
    }

    fn check_mesh(&self, mesh: &MeshHandle) -> Result<(), RenderError> {
        if mesh.inner.renderer_id != self.id {
            return Err(RenderError::ForeignMesh);
        }
        Ok(())
    }

    /// Encodes all draws into one pass over `width` x `height` targets, submits once, reads the
    /// targets back.
    fn render_batch(
        &self,
        outputs: Outputs,
        width: u32,
        height: u32,
        background_rgb: [u8; 3],
        draws: &[DrawCall],
    ) -> Result<Readback, RenderError> {
        let stride = self.record_stride as usize;
        let mut records = Vec::with_capacity(draws.len().max(1) * stride);
        for d in draws {
            write_draw_record(&mut records, d)?;
            records.resize(records.len().next_multiple_of(stride), 0);
        }
        if records.is_empty() {
            records.resize(stride, 0);
        }
        let mut cache = self
            .targets
            .lock()
            .map_err(|_| RenderError::Gpu("renderer mutex poisoned by a panic".into()))?;
        let scopes = ErrorScopes::push(&self.device);
        let draw_buffer = self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("draw records"),
            contents: &records,
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let bind_group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("draw records"),
            layout: &self.bind_group_layout,
            entries: &[wgpu::BindGroupEntry {
                binding: 0,
                resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                    buffer: &draw_buffer,
                    offset: 0,
                    size: wgpu::BufferSize::new(DRAW_RECORD_BYTES as u64),
                }),
            }],
        });

        // Least recently used first.
        let key = (width, height, outputs);
        match cache.iter().position(|(k, _)| *k == key) {
            Some(p) => {
                let entry = cache.remove(p);
                cache.push(entry);
            }
            None => {
                if cache.len() >= MAX_CACHED_TARGETS {
                    cache.remove(0);
                }
                cache.push((key, self.make_targets(width, height, outputs)));
            }
        }
        let targets = &cache[cache.len() - 1].1;

        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("render") });
        {
            let bg = [
                background_rgb[0] as f64 / 255.0,
                background_rgb[1] as f64 / 255.0,
                background_rgb[2] as f64 / 255.0,
            ];
            let mut attachments = Vec::new();
            if let Some(t) = &targets.color {
                attachments.push(Some(color_attachment(
                    &t.view,
                    wgpu::Color {
                        r: bg[0],
                        g: bg[1],
                        b: bg[2],
                        a: 1.0,
                    },
                )));
            }
            if let Some(t) = &targets.instance {
                attachments.push(Some(color_attachment(&t.view, wgpu::Color::TRANSPARENT)));
            }
            let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("render"),
                color_attachments: &attachments,
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    view: &targets.zbuffer.view,
                    depth_ops: Some(wgpu::Operations {
                        load: wgpu::LoadOp::Clear(0.0),
                        store: wgpu::StoreOp::Store,
                    }),
                    stencil_ops: None,
                }),
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            let mut bound: Option<&GpuMesh> = None;
            let mut bound_cull = None;
            for (i, d) in draws.iter().enumerate() {
                if bound_cull != Some(d.mesh.cull) {
                    pass.set_pipeline(&self.pipeline(outputs, d.mesh.cull)?);
                    bound_cull = Some(d.mesh.cull);
                }
                if !bound.is_some_and(|b| std::ptr::eq(b, d.mesh)) {
                    pass.set_vertex_buffer(0, d.mesh.vertices.slice(..));
                    pass.set_index_buffer(d.mesh.indices.slice(..), wgpu::IndexFormat::Uint32);
                    bound = Some(d.mesh);
                }
                let [x, y, w, h] = d.viewport;
                pass.set_viewport(x as f32, y as f32, w as f32, h as f32, 0.0, 1.0);
                pass.set_scissor_rect(x, y, w, h);
                pass.set_bind_group(0, &bind_group, &[i as u32 * self.record_stride]);
                pass.draw_indexed(0..d.mesh.index_count, 0, 0..1);
            }
        }
        let all_targets: Vec<&Target> = std::iter::once(&targets.zbuffer)
            .chain(targets.color.as_ref())
            .chain(targets.instance.as_ref())
            .collect();
        for t in &all_targets {
            encoder.copy_texture_to_buffer(
                wgpu::TexelCopyTextureInfo {
                    texture: &t.texture,
                    mip_level: 0,
                    origin: wgpu::Origin3d::ZERO,
                    aspect: t.aspect,
                },
                wgpu::TexelCopyBufferInfo {
                    buffer: &t.readback,
                    layout: wgpu::TexelCopyBufferLayout {
                        offset: 0,
                        bytes_per_row: Some(t.padded_bytes_per_row),
                        rows_per_image: Some(height),
                    },
                },
                wgpu::Extent3d {
                    width,
                    height,
                    depth_or_array_layers: 1,
                },
            );
        }
        self.queue.submit(Some(encoder.finish()));
        scopes.pop()?;

        let (tx, rx) = std::sync::mpsc::channel();
        for (k, t) in all_targets.iter().enumerate() {
            let tx = tx.clone();
            t.readback.map_async(wgpu::MapMode::Read, .., move |r| {
                let _ = tx.send((k, r));
            });
        }
        drop(tx);
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| RenderError::Gpu(e.to_string()))?;
        for _ in 0..all_targets.len() {
            match rx.recv() {
                Ok((_, Ok(()))) => {}
                Ok((_, Err(e))) => return Err(RenderError::Readback(e.to_string())),
                Err(e) => return Err(RenderError::Readback(e.to_string())),
            }
        }

        let n = (width * height) as usize;
        let mut depth_m = read_f32_rows(&targets.zbuffer, width, height)?;
        if let Some(d) = draws.first() {
            // One clip range per batch (the z-buffer encoding depends on it).
            debug_assert!(draws.iter().all(|o| o.clip == d.clip));
            zbuffer_to_metric(&mut depth_m, d.clip);
        }
        let color = match &targets.color {
            Some(t) => read_rows(t, width, height, |b| [b[0], b[1], b[2]])?,
            None => Vec::new(),
        };
        let instance = match &targets.instance {
            Some(t) => read_rows(t, width, height, |b| u16::from_le_bytes([b[0], b[1]]))?,
            None => Vec::new(),
        };
        debug_assert_eq!(depth_m.len(), n);
        Ok(Readback {
            width,
            depth_m,
            color,
            instance,
        })
    }

    fn pipeline(&self, outputs: Outputs, cull: Option<wgpu::Face>) -> Result<wgpu::RenderPipeline, RenderError> {
        let mut pipelines = self
            .pipelines
            .lock()
            .map_err(|_| RenderError::Gpu("renderer mutex poisoned by a panic".into()))?;
        Ok(pipelines
            .entry((outputs, cull))
            .or_insert_with(|| make_pipeline(&self.device, &self.pipeline_layout, &self.shader, outputs, cull))
            .clone())
    }

    fn make_targets(&self, width: u32, height: u32, outputs: Outputs) -> Targets {
        let make = |format: wgpu::TextureFormat, bytes_per_pixel: u32, label: &str, aspect| {
            let texture = self.device.create_texture(&wgpu::TextureDescriptor {
                label: Some(label),
                size: wgpu::Extent3d {
                    width,
                    height,
                    depth_or_array_layers: 1,
                },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format,
                usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
                view_formats: &[],
            });
            let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
            let padded_bytes_per_row = (width * bytes_per_pixel).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT)
                * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
            let readback = self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: padded_bytes_per_row as u64 * height as u64,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            Target {
                texture,
                view,
                aspect,
                readback,
                bytes_per_pixel,
                padded_bytes_per_row,
            }
        };
        let all = wgpu::TextureAspect::All;
        Targets {
            zbuffer: make(ZBUFFER_FORMAT, 4, "z-buffer", wgpu::TextureAspect::DepthOnly),
            color: outputs.color().then(|| make(COLOR_FORMAT, 4, "color", all)),
            instance: outputs.instance().then(|| make(INSTANCE_FORMAT, 2, "instance", all)),
        }
    }
}

/// Captures validation and out-of-memory errors of the calls between `push` and `pop` (on this
/// thread) and turns them into [`RenderError::Gpu`].
struct ErrorScopes {
    // Fields drop in declaration order: the inner scope (pushed last) must be popped first.
    validation: wgpu::ErrorScopeGuard,
    out_of_memory: wgpu::ErrorScopeGuard,
}

impl ErrorScopes {
    fn push(device: &wgpu::Device) -> Self {
        let out_of_memory = device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let validation = device.push_error_scope(wgpu::ErrorFilter::Validation);
        Self {
            validation,
            out_of_memory,
        }
    }

    fn pop(self) -> Result<(), RenderError> {
        let validation = pollster::block_on(self.validation.pop());
        let out_of_memory = pollster::block_on(self.out_of_memory.pop());
        match validation.or(out_of_memory) {
            Some(e) => Err(RenderError::Gpu(e.to_string())),
            None => Ok(()),
        }
    }
}

/// Turns reversed z-buffer values (`d = near (far - z) / ((far - near) z)`, see mesh.wgsl;
/// 0 = cleared, nothing drawn) into metric z-depth. In f32 the z-buffer resolves about 1e-7 of
/// the depth (0.1 micrometre at 1 m).
fn zbuffer_to_metric(values: &mut [f32], clip: ClipRange) {
    let (near, far) = (clip.near_m as f64, clip.far_m as f64);
    for v in values.iter_mut() {
        if *v > 0.0 {
            *v = (near * far / (*v as f64 * (far - near) + near)) as f32;
        }
    }
}

/// [`read_rows`] for `f32` targets: whole rows at once where the mapping is aligned (it is: rows
/// start at multiples of 256 bytes), value by value otherwise.
fn read_f32_rows(t: &Target, width: u32, height: u32) -> Result<Vec<f32>, RenderError> {
    let mut out = Vec::with_capacity((width * height) as usize);
    {
        let mapped = t
            .readback
            .get_mapped_range(..)
            .map_err(|e| RenderError::Readback(e.to_string()))?;
        for y in 0..height as usize {
            let row = &mapped[y * t.padded_bytes_per_row as usize..][..width as usize * 4];
            match bytemuck::try_cast_slice::<u8, f32>(row) {
                Ok(values) if cfg!(target_endian = "little") => out.extend_from_slice(values),
                _ => out.extend(
                    row.chunks_exact(4)
                        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                ),
            }
        }
    }
    t.readback.unmap();
    Ok(out)
}

/// Reads a mapped readback buffer row by row (dropping the row padding), then unmaps it.
fn read_rows<T>(t: &Target, width: u32, height: u32, convert: impl Fn(&[u8]) -> T) -> Result<Vec<T>, RenderError> {
    let mut out = Vec::with_capacity((width * height) as usize);
    {
        let mapped = t
            .readback
            .get_mapped_range(..)
            .map_err(|e| RenderError::Readback(e.to_string()))?;
        let bpp = t.bytes_per_pixel as usize;
        for y in 0..height as usize {
            let row = &mapped[y * t.padded_bytes_per_row as usize..][..width as usize * bpp];
            out.extend(row.chunks_exact(bpp).map(&convert));
        }
    }
    t.readback.unmap();
    Ok(out)
}

fn color_attachment(view: &wgpu::TextureView, clear: wgpu::Color) -> wgpu::RenderPassColorAttachment<'_> {
    wgpu::RenderPassColorAttachment {
        view,
        depth_slice: None,
        resolve_target: None,
        ops: wgpu::Operations {
            load: wgpu::LoadOp::Clear(clear),
            store: wgpu::StoreOp::Store,
        },
    }
}

/// Appends the `Draw` record of mesh.wgsl (128 bytes, little-endian).
fn write_draw_record(out: &mut Vec<u8>, d: &DrawCall) -> Result<(), RenderError> {
    let m = d.camera_from_object.to_homogeneous();
    if m.iter().any(|v| !v.is_finite()) {
        return Err(RenderError::NonFinitePose);
    }
    // nalgebra matrices are column-major, like WGSL's mat4x4.
    for v in m.as_slice() {
        out.extend_from_slice(&(*v as f32).to_le_bytes());
    }
    let k = d.intrinsics;
    for v in [
        k.fx() as f32,
        k.fy() as f32,
        k.cx() as f32,
        k.cy() as f32,
        d.viewport[2] as f32,
        d.viewport[3] as f32,
        d.clip.near_m,
        d.clip.far_m,
    ] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    for v in [d.instance_id as u32, 0, 0, 0] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    let light = match d.light_in_camera {
        Some(l) if l.iter().all(|v| v.is_finite()) && l.norm() > 0.0 => {
            let l = l.normalize();
            [l.x as f32, l.y as f32, l.z as f32, 1.0]
        }
        Some(_) => return Err(RenderError::NonFinitePose),
        None => [0.0; 4],
    };
    for v in light {
        out.extend_from_slice(&v.to_le_bytes());
    }
    Ok(())
}

fn make_pipeline(
    device: &wgpu::Device,
    layout: &wgpu::PipelineLayout,
    module: &wgpu::ShaderModule,
    outputs: Outputs,
    cull: Option<wgpu::Face>,
) -> wgpu::RenderPipeline {
    let target = |format| {
        Some(wgpu::ColorTargetState {
            format,
            blend: None,
            write_mask: wgpu::ColorWrites::ALL,
        })
    };
    let mut targets = Vec::new();
    if outputs.color() {
        targets.push(target(COLOR_FORMAT));
    }
    if outputs.instance() {
        targets.push(target(INSTANCE_FORMAT));
    }
    // Depth comes from the z-buffer; depth-only renders need no fragment shader at all.
    let fragment_entry = match outputs {
        Outputs::Scene => Some("fs_scene"),
        Outputs::View => Some("fs_view"),
        Outputs::Depth => None,
    };
    let attributes = [
        wgpu::VertexAttribute {
            format: wgpu::VertexFormat::Float32x3,
            offset: 0,
            shader_location: 0,
        },
        wgpu::VertexAttribute {
            format: wgpu::VertexFormat::Unorm8x4,
            offset: 12,
            shader_location: 1,
        },
    ];
    device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some(fragment_entry.unwrap_or("depth only")),
        layout: Some(layout),
        vertex: wgpu::VertexState {
            module,
            entry_point: Some("vs_main"),
            compilation_options: Default::default(),
            buffers: &[Some(wgpu::VertexBufferLayout {
                array_stride: VERTEX_STRIDE,
                step_mode: wgpu::VertexStepMode::Vertex,
                attributes: &attributes,
            })],
        },
        primitive: wgpu::PrimitiveState {
            topology: wgpu::PrimitiveTopology::TriangleList,
            // Counter-clockwise in wgpu's y-up NDC is counter-clockwise seen from the camera in
            // the object's right-handed frame (the y flip and the optical frame's y-down cancel).
            front_face: wgpu::FrontFace::Ccw,
            cull_mode: cull,
            ..Default::default()
        },
        depth_stencil: Some(wgpu::DepthStencilState {
            format: ZBUFFER_FORMAT,
            depth_write_enabled: Some(true),
            depth_compare: Some(wgpu::CompareFunction::Greater),
            stencil: wgpu::StencilState::default(),
            bias: wgpu::DepthBiasState::default(),
        }),
        multisample: wgpu::MultisampleState::default(),
        fragment: fragment_entry.map(|entry| wgpu::FragmentState {
            module,
            entry_point: Some(entry),
            compilation_options: Default::default(),
            targets: &targets,
        }),
        multiview_mask: None,
        cache: None,
    })
}

/// The faces that can be culled without changing any render: back faces (`Face::Back`) of a
/// closed mesh whose triangles are all counter-clockwise seen from outside, front faces of one
/// that is all clockwise; `None` (no culling) for open, non-manifold or inconsistently oriented
/// meshes. Vertices are welded by exact position first (scans duplicate vertices along seams).
/// Decimated scans often have a few flaws (YCB's mug: 14 hole edges of 13,468; the drill: 2
/// non-manifold ones): up to [`MAX_FLAWED_EDGE_FRACTION`] of flawed edges still count as closed,
/// so that only through those tiny holes could a render differ (background or a far front face
/// instead of an inner wall). YCB's master chef can (about 3 % flawed) is rendered unculled.
pub fn invisible_faces(mesh: &Mesh) -> Option<wgpu::Face> {
    let mut weld: HashMap<[u32; 3], u32> = HashMap::with_capacity(mesh.vertices_m.len());
    let ids: Vec<u32> = mesh
        .vertices_m
        .iter()
        .map(|v| {
            let key = v.map(|c| (c + 0.0).to_bits()); // + 0.0 maps -0.0 to 0.0
            let next = weld.len() as u32;
            *weld.entry(key).or_insert(next)
        })
        .collect();
    // Every directed edge exactly once, and its reverse exactly once.
    let mut edges: HashMap<(u32, u32), u32> = HashMap::with_capacity(mesh.triangles.len() * 3);
    let mut volume6 = 0.0f64;
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| ids[i as usize]);
        if a == b || b == c || a == c {
            // Degenerate after welding (e.g. at the poles of a sphere): covers no pixel.
            continue;
        }
        for e in [(a, b), (b, c), (c, a)] {
            *edges.entry(e).or_insert(0) += 1;
        }
        let [p, q, r] = t.map(|i| mesh.vertices_m[i as usize].map(f64::from));
        volume6 += p[0] * (q[1] * r[2] - q[2] * r[1]) - p[1] * (q[0] * r[2] - q[2] * r[0])
            + p[2] * (q[0] * r[1] - q[1] * r[0]);
    }
    // Edges in the same direction twice (non-manifold, or neighbours wound oppositely) or
    // without their reverse (holes).
    let flawed = edges
        .iter()
        .filter(|&(&(a, b), &n)| n != 1 || !edges.contains_key(&(b, a)))
        .count();
    if flawed as f64 > MAX_FLAWED_EDGE_FRACTION * edges.len() as f64 || volume6 == 0.0 {
        return None;
    }
    Some(if volume6 > 0.0 {
        wgpu::Face::Back
    } else {
        wgpu::Face::Front
    })
}

/// A high-performance adapter on the requested (or primary) backends, else any adapter there,
/// else any adapter on any backend.
fn find_adapter() -> Result<wgpu::Adapter, RenderError> {
    let from_env = wgpu::Backends::from_env();
    let mut tried = Vec::new();
    let candidates = match from_env {
        Some(b) => vec![b],
        None => vec![wgpu::Backends::PRIMARY, wgpu::Backends::all()],
    };
    for backends in candidates {
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle_from_env();
        desc.backends = backends;
        let instance = wgpu::Instance::new(desc);
        let request = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            force_fallback_adapter: false,
            compatible_surface: None,
            ..Default::default()
        }));
        match request {
            Ok(a) => return Ok(a),
            Err(e) => tried.push(format!("{backends:?}: {e}")),
        }
        let mut all = pollster::block_on(instance.enumerate_adapters(backends));
        // Prefer real GPUs, then software adapters; GL cannot copy depth to buffers.
        all.sort_by_key(|a| {
            let i = a.get_info();
            (i.backend == wgpu::Backend::Gl, i.device_type == wgpu::DeviceType::Cpu)
        });
        if let Some(a) = all.into_iter().next() {
            return Ok(a);
        }
    }
    Err(RenderError::NoAdapter(tried.join("; ")))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every WGSL shader parses and validates with naga (CPU only, no adapter needed).
    #[test]
    fn shaders_validate_with_naga() {
        for (name, source) in SHADERS {
            let module = naga::front::wgsl::parse_str(source)
                .unwrap_or_else(|e| panic!("{name} does not parse:\n{}", e.emit_to_string(source)));
            naga::valid::Validator::new(naga::valid::ValidationFlags::all(), naga::valid::Capabilities::empty())
                .validate(&module)
                .unwrap_or_else(|e| panic!("{name} does not validate: {e:?}"));
            for entry in ["vs_main", "fs_scene", "fs_view"] {
                assert!(
                    module.entry_points.iter().any(|ep| ep.name == entry),
                    "{name} lacks entry point {entry}"
                );
            }
        }
    }

    #[test]
    fn clip_range_is_checked() {
        assert!(ClipRange::new(0.1, 10.0).is_ok());
        assert!(ClipRange::new(0.0, 10.0).is_err());
        assert!(ClipRange::new(1.0, 0.5).is_err());
        assert!(ClipRange::new(0.1, f32::INFINITY).is_err());
    }

    #[test]
    fn tiles_are_cut_from_the_atlas() {
        let data: Vec<u32> = (0..12).collect(); // 4 x 3
        assert_eq!(tile(&data, 4, 1, 1, 2, 2), vec![5, 6, 9, 10]);
    }

    #[test]
    fn closed_oriented_meshes_cull_back_faces() {
        let mut mesh = crate::mesh::builtin("box").expect("box");
        assert_eq!(invisible_faces(&mesh), Some(wgpu::Face::Back));
        for name in ["can", "mug"] {
            assert_eq!(
                invisible_faces(&crate::mesh::builtin(name).expect("mesh")),
                Some(wgpu::Face::Back)
            );
        }
        // All windings flipped: the front faces are the invisible ones.
        let mut flipped = mesh.clone();
        flipped.triangles.iter_mut().for_each(|t| t.swap(1, 2));
        assert_eq!(invisible_faces(&flipped), Some(wgpu::Face::Front));
        // Inconsistent windings or holes: no culling.
        let mut mixed = mesh.clone();
        mixed.triangles[0].swap(1, 2);
        mixed.triangles[5].swap(1, 2);
        assert_eq!(invisible_faces(&mixed), None);
        mesh.triangles.truncate(10);
        assert_eq!(invisible_faces(&mesh), None);
    }

    #[test]
    fn renderer_is_send_and_sync() {
        fn check<T: Send + Sync>() {}
        check::<Renderer>();
        check::<MeshHandle>();
    }
}
