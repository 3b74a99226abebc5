// Off-screen rendering of triangle meshes with pinhole intrinsics.
//
// One storage-buffer record per draw (selected by the instance index, so one bind group serves
// every draw of a submit): the camera_from_object transform, the pinhole intrinsics of the
// view, its clip range and the instance id to write into the mask.
//
// Projection: pixel (u, v) (u right, v down, pixel centres at integer + 0.5) of a point
// (x, y, z) in the optical frame (x right, y down, z forward) is u = fx x / z + cx,
// v = fy y / z + cy. The viewport of a view spans its `width` x `height` pixels, so
// ndc_x = 2 u / width - 1 and (wgpu's NDC is y up) ndc_y = 1 - 2 v / height; multiplied by
// w = z this is linear in the point. Depth in the z-buffer is reversed (1 at near, 0 at far,
// compare Greater) for precision; the metric z-depth itself is written to an R32Float target
// from the perspective-correct interpolated camera-frame point.

struct Draw {
    // Column-major camera_from_object (rotation and translation), metres.
    camera_from_object: mat4x4<f32>,
    // fx, fy, cx, cy in pixels of the view.
    focal_principal: vec4<f32>,
    // width, height (pixels), near, far (metres).
    size_clip: vec4<f32>,
    // x: instance id for the mask; y, z, w unused.
    ids: vec4<u32>,
};

@group(0) @binding(0) var<storage, read> draws: array<Draw>;

struct VertexIn {
    @location(0) position_m: vec3<f32>,
    @location(1) color: vec4<f32>,
};

struct VertexOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) point_in_camera_m: vec3<f32>,
    @location(1) color: vec3<f32>,
    @location(2) @interpolate(flat) instance_id: u32,
};

@vertex
fn vs_main(v: VertexIn, @builtin(instance_index) draw_index: u32) -> VertexOut {
    let d = draws[draw_index];
    let p = (d.camera_from_object * vec4<f32>(v.position_m, 1.0)).xyz;
    let fx = d.focal_principal.x;
    let fy = d.focal_principal.y;
    let cx = d.focal_principal.z;
    let cy = d.focal_principal.w;
    let width = d.size_clip.x;
    let height = d.size_clip.y;
    let near = d.size_clip.z;
    let far = d.size_clip.w;
    var out: VertexOut;
    out.clip = vec4<f32>(
        2.0 * (fx * p.x + cx * p.z) / width - p.z,
        p.z - 2.0 * (fy * p.y + cy * p.z) / height,
        near * (far - p.z) / (far - near),
        p.z,
    );
    out.point_in_camera_m = p;
    out.color = v.color.rgb;
    out.instance_id = d.ids.x;
    return out;
}

// Lambert shading with a headlight (light at the camera centre), two-sided, flat normals from
// screen-space derivatives of the camera-frame point.
fn shade(p: vec3<f32>, color: vec3<f32>) -> vec3<f32> {
    let n_raw = cross(dpdx(p), dpdy(p));
    let len = length(n_raw);
    var lambert = 1.0;
    if (len > 0.0) {
        lambert = abs(dot(n_raw / len, normalize(p)));
    }
    return color * (0.2 + 0.8 * lambert);
}

struct SceneOut {
    @location(0) depth_m: f32,
    @location(1) color: vec4<f32>,
    @location(2) instance_id: u32,
};

@fragment
fn fs_scene(f: VertexOut) -> SceneOut {
    var out: SceneOut;
    out.depth_m = f.point_in_camera_m.z;
    out.color = vec4<f32>(shade(f.point_in_camera_m, f.color), 1.0);
    out.instance_id = f.instance_id;
    return out;
}

struct ViewOut {
    @location(0) depth_m: f32,
    @location(1) color: vec4<f32>,
};

@fragment
fn fs_view(f: VertexOut) -> ViewOut {
    var out: ViewOut;
    out.depth_m = f.point_in_camera_m.z;
    out.color = vec4<f32>(shade(f.point_in_camera_m, f.color), 1.0);
    return out;
}

@fragment
fn fs_depth(f: VertexOut) -> @location(0) f32 {
    return f.point_in_camera_m.z;
}
