//! `/objects`: object models, registered by uploading a mesh (PLY, OBJ, STL; metres). The
//! codebook of each object builds in the background (status `pending`, `building`, `ready`,
//! `failed` with the reason and a progress fraction).

use super::AppState;
use super::error::ApiError;
use super::types::check_id;
use crate::mesh::{MAX_MESH_BYTES, Mesh, MeshFormat};
use crate::service;
use axum::Json;
use axum::body::Bytes;
use axum::extract::{Path, Query, State};
use axum::http::HeaderMap;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use utoipa::{IntoParams, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

/// Most triangles served for display by `/objects/{id}/mesh`.
pub const DISPLAY_MAX_TRIANGLES: usize = 2_000;

/// State of an object's codebook.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum CodebookState {
    Pending,
    Building,
    Ready,
    Failed,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct CodebookStatus {
    pub status: CodebookState,
    /// 0..=1.
    pub progress: f64,
    /// Rotation grid step of the codebook being built or ready (degrees).
    pub grid_step_deg: Option<u32>,
    /// Why the build failed.
    pub error: Option<String>,
}

/// A registered object.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct ObjectInfo {
    pub id: String,
    /// Display name.
    pub name: String,
    pub n_vertices: usize,
    pub n_triangles: usize,
    pub diameter_m: f64,
    /// SHA-256 of the geometry (the key of the codebook cache).
    pub content_hash: String,
    /// Whether the codebook uses the mesh's colours (false: depth alone, for a mesh whose
    /// colours do not match the cameras', such as an untextured CAD model or a scan under
    /// other light).
    pub use_color: bool,
    pub codebook: CodebookStatus,
}

impl From<service::registry::CodebookState> for CodebookState {
    fn from(s: service::registry::CodebookState) -> Self {
        use service::registry::CodebookState as S;
        match s {
            S::Pending => Self::Pending,
            S::Building => Self::Building,
            S::Ready => Self::Ready,
            S::Failed => Self::Failed,
        }
    }
}

impl From<&service::registry::ObjectInfo> for ObjectInfo {
    fn from(o: &service::registry::ObjectInfo) -> Self {
        Self {
            id: o.id.clone(),
            name: o.name.clone(),
            n_vertices: o.n_vertices,
            n_triangles: o.n_triangles,
            diameter_m: o.diameter_m,
            content_hash: o.content_hash.clone(),
            use_color: o.use_color,
            codebook: CodebookStatus {
                status: o.codebook.status.into(),
                progress: o.codebook.progress,
                grid_step_deg: o.codebook.grid_step_deg,
                error: o.codebook.error.clone(),
            },
        }
    }
}

/// A mesh reduced for display.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct DisplayMesh {
    pub vertices_m: Vec<[f32; 3]>,
    pub triangles: Vec<[u32; 3]>,
}

pub fn router() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(list_objects))
        .routes(routes!(get_object, put_object, delete_object))
        .routes(routes!(get_object_mesh))
}

#[utoipa::path(get, path = "/objects", tag = "objects",
    responses((status = 200, body = [ObjectInfo])))]
async fn list_objects(State(state): State<AppState>) -> Json<Vec<ObjectInfo>> {
    Json(
        state
            .registry()
            .objects
            .values()
            .map(|o| ObjectInfo::from(&o.info))
            .collect(),
    )
}

#[utoipa::path(get, path = "/objects/{id}", tag = "objects",
    params(("id" = String, Path, description = "Object id")),
    responses((status = 200, body = ObjectInfo), (status = 404, body = super::error::Problem)))]
async fn get_object(State(state): State<AppState>, Path(id): Path<String>) -> Result<Json<ObjectInfo>, ApiError> {
    state
        .registry()
        .objects
        .get(&id)
        .map(|o| Json(ObjectInfo::from(&o.info)))
        .ok_or_else(|| ApiError::not_found("object", id))
}

/// Query of an upload.
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct UploadQuery {
    /// Display name (default: the id).
    pub name: Option<String>,
    /// `ply`, `obj` or `stl` (default: from the Content-Type, else sniffed from the bytes).
    pub format: Option<String>,
    /// `false`: build the codebook from the mesh's depth alone, for a mesh whose colours do
    /// not match the cameras' (default `true`: depth and colour).
    pub use_color: Option<bool>,
}

fn format_of(q: &UploadQuery, headers: &HeaderMap, bytes: &[u8]) -> Result<MeshFormat, ApiError> {
    let ct = headers
        .get(axum::http::header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_ascii_lowercase();
    let named = q.format.as_deref().map(str::to_ascii_lowercase).or_else(|| {
        ["ply", "obj", "stl"]
            .into_iter()
            .find(|f| ct.contains(f))
            .map(String::from)
    });
    let allowed_ct = ct.is_empty()
        || ct.starts_with("application/octet-stream")
        || ct.starts_with("model/")
        || ct.starts_with("text/plain")
        || ct.starts_with("application/sla")
        || ct.starts_with("application/ply");
    if !allowed_ct {
        return Err(ApiError::UnsupportedMediaType(format!(
            "a mesh upload is the raw file (Content-Type application/octet-stream or model/ply, model/obj, model/stl), not '{ct}'"
        )));
    }
    match named.as_deref() {
        Some("ply") => Ok(MeshFormat::Ply),
        Some("obj") => Ok(MeshFormat::Obj),
        Some("stl") => Ok(MeshFormat::Stl),
        Some(other) => Err(ApiError::Malformed(format!(
            "unknown mesh format '{other}' (ply, obj or stl)"
        ))),
        None => MeshFormat::sniff(bytes)
            .ok_or_else(|| ApiError::Malformed("cannot tell the mesh format: pass ?format=ply|obj|stl".into())),
    }
}

#[utoipa::path(put, path = "/objects/{id}", tag = "objects",
    params(("id" = String, Path, description = "Object id"), UploadQuery),
    request_body(content = Vec<u8>, content_type = "application/octet-stream", description = "The mesh file (PLY, OBJ or STL, metres)"),
    responses((status = 200, body = ObjectInfo), (status = 400, body = super::error::Problem),
        (status = 409, description = "The object cap is reached", body = super::error::Problem),
        (status = 413, body = super::error::Problem), (status = 415, body = super::error::Problem),
        (status = 422, body = super::error::Problem)))]
async fn put_object(
    State(state): State<AppState>,
    Path(id): Path<String>,
    q: Result<Query<UploadQuery>, axum::extract::rejection::QueryRejection>,
    headers: HeaderMap,
    body: Result<Bytes, axum::extract::rejection::BytesRejection>,
) -> Result<Json<ObjectInfo>, ApiError> {
    let Query(q) = q?;
    let bytes = body?;
    check_id("object", &id)?;
    let name = q.name.clone().unwrap_or_else(|| id.clone());
    super::types::check_name(&name, state.config.service.limits.max_name_chars)?;
    if bytes.len() > MAX_MESH_BYTES {
        return Err(ApiError::TooLarge {
            limit_bytes: MAX_MESH_BYTES,
        });
    }
    let format = format_of(&q, &headers, &bytes)?;
    let mesh = tokio::task::spawn_blocking(move || Mesh::from_bytes(&bytes, format))
        .await
        .map_err(ApiError::internal)?
        .map_err(|e| ApiError::Invalid(format!("mesh: {e}")))?;
    let info = state.register_object(&id, &name, mesh, q.use_color.unwrap_or(true))?;
    Ok(Json(ObjectInfo::from(&info)))
}

#[utoipa::path(delete, path = "/objects/{id}", tag = "objects",
    params(("id" = String, Path, description = "Object id")),
    responses((status = 204), (status = 404, body = super::error::Problem)))]
async fn delete_object(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<super::error::Deleted, ApiError> {
    state.delete_object(&id)?;
    Ok(super::error::Deleted)
}

#[utoipa::path(get, path = "/objects/{id}/mesh", tag = "objects",
    params(("id" = String, Path, description = "Object id")),
    responses((status = 200, description = "The mesh decimated to at most 2,000 triangles for display", body = DisplayMesh),
        (status = 404, body = super::error::Problem)))]
async fn get_object_mesh(State(state): State<AppState>, Path(id): Path<String>) -> Result<Json<DisplayMesh>, ApiError> {
    let mesh = state
        .registry()
        .objects
        .get(&id)
        .map(|o| o.mesh.clone())
        .ok_or_else(|| ApiError::not_found("object", id))?;
    Ok(Json(decimate(&mesh, DISPLAY_MAX_TRIANGLES)))
}

/// Vertex clustering on a grid that coarsens until at most `max_triangles` remain.
pub fn decimate(mesh: &Mesh, max_triangles: usize) -> DisplayMesh {
    if mesh.triangles.len() <= max_triangles {
        return DisplayMesh {
            vertices_m: mesh.vertices_m.clone(),
            triangles: mesh.triangles.clone(),
        };
    }
    let diameter = mesh.diameter_m().max(1e-6) as f32;
    let mut cells = 64.0f32;
    loop {
        let cell = diameter / cells;
        let mut index: HashMap<[i32; 3], u32> = HashMap::new();
        let mut sums: Vec<([f32; 3], f32)> = Vec::new();
        let remap: Vec<u32> = mesh
            .vertices_m
            .iter()
            .map(|v| {
                let key = [
                    (v[0] / cell).floor() as i32,
                    (v[1] / cell).floor() as i32,
                    (v[2] / cell).floor() as i32,
                ];
                let i = *index.entry(key).or_insert_with(|| {
                    sums.push(([0.0; 3], 0.0));
                    (sums.len() - 1) as u32
                });
                let s = &mut sums[i as usize];
                for (acc, x) in s.0.iter_mut().zip(v) {
                    *acc += x;
                }
                s.1 += 1.0;
                i
            })
            .collect();
        let mut seen = std::collections::HashSet::new();
        let triangles: Vec<[u32; 3]> = mesh
            .triangles
            .iter()
            .map(|t| [remap[t[0] as usize], remap[t[1] as usize], remap[t[2] as usize]])
            .filter(|t| t[0] != t[1] && t[1] != t[2] && t[0] != t[2])
            .filter(|t| {
                let mut k = *t;
                k.sort_unstable();
                seen.insert(k)
            })
            .collect();
        if triangles.len() <= max_triangles || cells <= 2.0 {
            let vertices_m = sums.iter().map(|(s, n)| [s[0] / n, s[1] / n, s[2] / n]).collect();
            let mut triangles = triangles;
            triangles.truncate(max_triangles);
            return DisplayMesh { vertices_m, triangles };
        }
        cells *= 0.75;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn decimation_respects_the_limit_and_keeps_the_extent() {
        let mesh = crate::mesh::builtin_cylinder(0.05, 0.2, 2_000, [[1, 2, 3], [4, 5, 6]]);
        assert!(mesh.triangles.len() > DISPLAY_MAX_TRIANGLES);
        let d = decimate(&mesh, DISPLAY_MAX_TRIANGLES);
        assert!(d.triangles.len() <= DISPLAY_MAX_TRIANGLES && d.triangles.len() > 100);
        let max_z = d.vertices_m.iter().map(|v| v[2]).fold(f32::MIN, f32::max);
        let orig_max_z = mesh.vertices_m.iter().map(|v| v[2]).fold(f32::MIN, f32::max);
        assert!((max_z - orig_max_z).abs() < 0.02, "{max_z} vs {orig_max_z}");
        for t in &d.triangles {
            assert!(t.iter().all(|&i| (i as usize) < d.vertices_m.len()));
        }
    }
}
