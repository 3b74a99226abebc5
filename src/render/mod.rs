//! Off-screen rendering with wgpu: metric z-depth, shaded colour and instance masks of meshes.
//!
//! - [`Renderer::render_scene`]: several meshes seen by one camera with any pinhole intrinsics
//!   (depth, colour, per-object instance mask).
//! - [`Renderer::render_views`] / [`Renderer::render_view_depths`]: many small views of one mesh
//!   (codebooks), batched into an atlas texture: one viewport and one draw per view, one submit
//!   per atlas, the atlas chunked to stay within the device's texture limits.
//!
//! Conventions: optical frames (x right, y down, z forward); pixel `(u, v)` of a camera-frame
//! point is `u = fx x / z + cx`, `v = fy y / z + cy` with the centre of pixel `(x, y)` at `(x, y)`
//! (BOP, OpenCV, ROS; exactly as [`Intrinsics::project`]). Depth images hold z-depth in metres, 0 where nothing was hit or
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
//! # Speed
//! On a software adapter a submit is expensive and triangle set-up dominates, so views are
//! batched into atlases with one submit each, invisible faces of closed meshes are culled, and
//! depth-only renders run no fragment shader; `benches/render.rs` measures it and
//! `docs/decisions.md` has the figures. For whole codebooks use
//! [`Renderer::for_each_view_depth`], which streams one atlas at a time.

mod adapter;
mod batch;
mod cull;
pub mod raster;
mod readback;

pub use cull::invisible_faces;

use crate::camera::{ColorImage, DepthImage, Intrinsics};
use crate::geometry::Pose;
use crate::mesh::Mesh;
use adapter::find_adapter;
use batch::{DrawCall, Outputs, PipelineKey, TargetKey, Targets};
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
