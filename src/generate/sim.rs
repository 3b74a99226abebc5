//! One scene simulator for the generator and the service's demo: meshes placed in the world
//! (tracked objects with instance ids from 1, props such as the table or the floor with 0),
//! lit from one direction or by a headlight, rendered from any camera pose with wgpu, or with
//! the CPU rasteriser when wgpu has no adapter (the demo only); each object's visible mask and
//! BOP box are read from the instance image.

use crate::camera::Intrinsics;
use crate::geometry::Pose;
use crate::mesh::Mesh;
use crate::render::{ClipRange, MeshHandle, RenderError, Renderer, SceneObject, SceneRender};
use nalgebra::Vector3;
use std::sync::{Arc, OnceLock};

/// One mesh placed in the world.
#[derive(Debug, Clone)]
pub struct Placed {
    /// Meshes shared between placements (floor tiles) are uploaded once.
    pub mesh: Arc<Mesh>,
    pub world_from_object: Pose,
}

/// A scene to render from any camera.
pub struct SceneSim {
    /// Tracked objects: instance id `i + 1`.
    objects: Vec<Placed>,
    /// Everything else (table, floor, occluders): instance id 0.
    props: Vec<Placed>,
    /// Direction towards the light (world frame); `None`: a headlight per camera.
    pub towards_light_in_world: Option<Vector3<f64>>,
    pub clip: ClipRange,
    pub background_rgb: [u8; 3],
    /// The scene on the GPU, uploaded on first use (or why the upload failed).
    gpu: OnceLock<Result<Vec<SceneObject>, String>>,
}

impl SceneSim {
    pub fn new(objects: Vec<Placed>, props: Vec<Placed>, clip: ClipRange, background_rgb: [u8; 3]) -> Self {
        Self {
            objects,
            props,
            towards_light_in_world: None,
            clip,
            background_rgb,
            gpu: OnceLock::new(),
        }
    }

    /// Tracked objects in instance order (instance id = index + 1).
    pub fn objects(&self) -> &[Placed] {
        &self.objects
    }

    /// Uploads the scene's meshes to `renderer` (once: a later call returns the first
    /// upload, or its error again).
    pub fn upload(&self, renderer: &Renderer) -> Result<&[SceneObject], RenderError> {
        let uploaded = self
            .gpu
            .get_or_init(|| self.upload_all(renderer).map_err(|e| e.to_string()));
        uploaded
            .as_deref()
            .map_err(|e| RenderError::Gpu(format!("uploading the scene: {e}")))
    }

    fn upload_all(&self, renderer: &Renderer) -> Result<Vec<SceneObject>, RenderError> {
        let mut handles: Vec<(*const Mesh, MeshHandle)> = Vec::new();
        let placements = self
            .objects
            .iter()
            .enumerate()
            .map(|(i, p)| (p, i as u16 + 1))
            .chain(self.props.iter().map(|p| (p, 0)));
        let mut scene = Vec::with_capacity(self.objects.len() + self.props.len());
        for (p, instance_id) in placements {
            let key = Arc::as_ptr(&p.mesh);
            let mesh = match handles.iter().find(|(k, _)| *k == key) {
                Some((_, h)) => h.clone(),
                None => {
                    let h = renderer.upload_mesh(&p.mesh)?;
                    handles.push((key, h.clone()));
                    h
                }
            };
            scene.push(SceneObject {
                mesh,
                world_from_object: p.world_from_object,
                instance_id,
            });
        }
        Ok(scene)
    }

    /// Renders the scene from `world_from_camera` with wgpu.
    pub fn render_gpu(
        &self,
        renderer: &Renderer,
        intrinsics: &Intrinsics,
        world_from_camera: &Pose,
    ) -> Result<SceneRender, RenderError> {
        let scene = self.upload(renderer)?;
        renderer.render_scene_lit(
            intrinsics,
            &world_from_camera.inverse(),
            scene,
            self.clip,
            self.background_rgb,
            self.towards_light_in_world,
        )
    }

    /// Renders the scene with wgpu when `renderer` is given and works, else with the CPU
    /// rasteriser (unlit colours; props get instance 0 as on the GPU).
    pub fn render(
        &self,
        renderer: Option<&Renderer>,
        intrinsics: &Intrinsics,
        world_from_camera: &Pose,
    ) -> SceneRender {
        if let Some(r) = renderer {
            match self.render_gpu(r, intrinsics, world_from_camera) {
                Ok(img) => return img,
                Err(e) => tracing::warn!("scene render failed ({e}); using the CPU rasteriser"),
            }
        }
        let camera_from_world = world_from_camera.inverse();
        let list: Vec<(&Mesh, Pose)> = self
            .objects
            .iter()
            .chain(&self.props)
            .map(|p| (&*p.mesh, camera_from_world * p.world_from_object))
            .collect();
        let r = crate::render::raster::render(intrinsics, &list, f64::from(self.clip.near_m), self.background_rgb);
        let n = self.objects.len() as u16;
        SceneRender {
            depth: r.depth,
            color: r.color,
            instance: r.instance.into_iter().map(|i| if i > n { 0 } else { i }).collect(),
        }
    }

    /// Each tracked object's visible pixels in a render of this scene, in instance order.
    pub fn visible_masks(&self, render: &SceneRender) -> Vec<Vec<bool>> {
        (1..=self.objects.len() as u16)
            .map(|id| render.instance.iter().map(|v| *v == id).collect())
            .collect()
    }
}

/// A tracked object's visible box: BOP's `bbox_visib` and its pixel count.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct VisibleBox {
    /// `[x, y, width, height]`; `[-1, -1, -1, -1]` when no pixel is visible.
    pub bbox_xywh_px: [i64; 4],
    pub px_count: u64,
}

/// The visible box of each mask (see [`SceneSim::visible_masks`]).
pub fn visible_boxes(masks: &[Vec<bool>], width: u32) -> Vec<VisibleBox> {
    masks
        .iter()
        .map(|m| VisibleBox {
            bbox_xywh_px: super::gt_info::bbox_of(m, width),
            px_count: m.iter().filter(|v| **v).count() as u64,
        })
        .collect()
}
