//! One submit per batch: draw records in one uniform buffer, one render pass over cached
//! targets, one copy of every target into its readback buffer, then the readback.

use super::readback::{Readback, read_f32_rows, read_rows, zbuffer_to_metric};
use super::{
    COLOR_FORMAT, ClipRange, DRAW_RECORD_BYTES, ErrorScopes, GpuMesh, INSTANCE_FORMAT, MAX_CACHED_TARGETS, MeshHandle,
    RenderError, Renderer, VERTEX_STRIDE, ZBUFFER_FORMAT,
};
use crate::camera::Intrinsics;
use crate::geometry::Pose;
use nalgebra::Vector3;
use wgpu::util::DeviceExt;

/// Which render targets a pass writes and reads back.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub(super) enum Outputs {
    /// Depth, colour and instance mask.
    Scene,
    /// Depth and colour.
    View,
    /// Depth only.
    Depth,
}

impl Outputs {
    pub(super) fn color(self) -> bool {
        matches!(self, Outputs::Scene | Outputs::View)
    }
    pub(super) fn instance(self) -> bool {
        matches!(self, Outputs::Scene)
    }
}

/// One render target with its readback buffer.
pub(super) struct Target {
    pub(super) texture: wgpu::Texture,
    pub(super) view: wgpu::TextureView,
    pub(super) aspect: wgpu::TextureAspect,
    pub(super) readback: wgpu::Buffer,
    pub(super) bytes_per_pixel: u32,
    pub(super) padded_bytes_per_row: u32,
}

/// Outputs and culled face of a pipeline.
pub(super) type PipelineKey = (Outputs, Option<wgpu::Face>);

/// Width, height and outputs of a set of render targets.
pub(super) type TargetKey = (u32, u32, Outputs);

/// The render targets of one size and kind.
pub(super) struct Targets {
    /// The reversed z-buffer, read back and converted to metric depth.
    zbuffer: Target,
    color: Option<Target>,
    instance: Option<Target>,
}

/// A draw: the mesh, its record (transform, intrinsics, clip, id) and its viewport.
pub(super) struct DrawCall<'a> {
    pub(super) mesh: &'a GpuMesh,
    pub(super) camera_from_object: Pose,
    pub(super) intrinsics: &'a Intrinsics,
    pub(super) clip: ClipRange,
    pub(super) instance_id: u16,
    /// x, y, width, height in pixels of the render target.
    pub(super) viewport: [u32; 4],
    /// Unit direction towards a directional light in the camera frame; `None`: a headlight.
    pub(super) light_in_camera: Option<Vector3<f64>>,
}

impl Renderer {
    /// Renders the views chunk by chunk; calls `tile(readback, x, y)` for every view in order.
    pub(super) fn render_views_each(
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

    /// Encodes all draws into one pass over `width` x `height` targets, submits once, reads the
    /// targets back.
    pub(super) fn render_batch(
        &self,
        outputs: Outputs,
        width: u32,
        height: u32,
        background_rgb: [u8; 3],
        draws: &[DrawCall],
    ) -> Result<Readback, RenderError> {
        let records = self.draw_records(draws)?;
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
        let targets = self.cached_targets(&mut cache, (width, height, outputs));
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("render") });
        self.encode_pass(&mut encoder, targets, outputs, background_rgb, draws, &bind_group)?;
        let all_targets: Vec<&Target> = std::iter::once(&targets.zbuffer)
            .chain(targets.color.as_ref())
            .chain(targets.instance.as_ref())
            .collect();
        for t in &all_targets {
            copy_to_readback(&mut encoder, t, width, height);
        }
        self.queue.submit(Some(encoder.finish()));
        scopes.pop()?;
        self.map_readbacks(&all_targets)?;

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
        debug_assert_eq!(depth_m.len(), (width * height) as usize);
        Ok(Readback {
            width,
            depth_m,
            color,
            instance,
        })
    }

    /// Every draw's record, each at a multiple of the uniform offset alignment (one empty record
    /// when there are no draws: a bind group needs a non-empty buffer).
    fn draw_records(&self, draws: &[DrawCall]) -> Result<Vec<u8>, RenderError> {
        let stride = self.record_stride as usize;
        let mut records = Vec::with_capacity(draws.len().max(1) * stride);
        for d in draws {
            write_draw_record(&mut records, d)?;
            records.resize(records.len().next_multiple_of(stride), 0);
        }
        if records.is_empty() {
            records.resize(stride, 0);
        }
        Ok(records)
    }

    /// The render targets of `key`, made on first use; the cache keeps the most recently used.
    fn cached_targets<'c>(&self, cache: &'c mut Vec<(TargetKey, Targets)>, key: TargetKey) -> &'c Targets {
        match cache.iter().position(|(k, _)| *k == key) {
            Some(p) => {
                let entry = cache.remove(p);
                cache.push(entry);
            }
            None => {
                if cache.len() >= MAX_CACHED_TARGETS {
                    cache.remove(0);
                }
                cache.push((key, self.make_targets(key.0, key.1, key.2)));
            }
        }
        &cache[cache.len() - 1].1
    }

    /// One render pass: clears the targets, then draws every call in its viewport.
    fn encode_pass(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        targets: &Targets,
        outputs: Outputs,
        background_rgb: [u8; 3],
        draws: &[DrawCall],
        bind_group: &wgpu::BindGroup,
    ) -> Result<(), RenderError> {
        let [r, g, b] = background_rgb.map(|c| c as f64 / 255.0);
        let mut attachments = Vec::new();
        if let Some(t) = &targets.color {
            attachments.push(Some(color_attachment(&t.view, wgpu::Color { r, g, b, a: 1.0 })));
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
            pass.set_bind_group(0, bind_group, &[i as u32 * self.record_stride]);
            pass.draw_indexed(0..d.mesh.index_count, 0, 0..1);
        }
        Ok(())
    }

    /// Maps every readback buffer and waits until all are mapped.
    fn map_readbacks(&self, targets: &[&Target]) -> Result<(), RenderError> {
        let (tx, rx) = std::sync::mpsc::channel();
        for (k, t) in targets.iter().enumerate() {
            let tx = tx.clone();
            t.readback.map_async(wgpu::MapMode::Read, .., move |r| {
                let _ = tx.send((k, r));
            });
        }
        drop(tx);
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| RenderError::Gpu(e.to_string()))?;
        for _ in 0..targets.len() {
            match rx.recv() {
                Ok((_, Ok(()))) => {}
                Ok((_, Err(e))) => return Err(RenderError::Readback(e.to_string())),
                Err(e) => return Err(RenderError::Readback(e.to_string())),
            }
        }
        Ok(())
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

/// Copies a whole target into its readback buffer (rows padded to the copy alignment).
fn copy_to_readback(encoder: &mut wgpu::CommandEncoder, t: &Target, width: u32, height: u32) {
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

pub(super) fn make_pipeline(
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
