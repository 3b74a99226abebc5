// Off-screen rendering of triangle meshes with pinhole intrinsics.
//
// One uniform record per draw (all records of a submit in one buffer, selected by a dynamic
// offset): the camera_from_object transform, the pinhole intrinsics of the view, its clip range
// and the instance id to write into the mask. A uniform (rather than a storage array indexed by
// the instance index) lets a software rasteriser load it once per draw instead of per vertex.
//
// Projection: pixel coordinates (u, v) (u right, v down, the centre of pixel (x, y) at (x, y),
// as BOP, OpenCV and ROS have them) of a point (x, y, z) in the optical frame (x right, y down,
// z forward) are u = fx x / z + cx, v = fy y / z + cy. The rasteriser samples pixel x at
// framebuffer coordinate x + 0.5, so framebuffer u_fb = u + 0.5; the viewport spans `width` x
// `height` pixels, so ndc_x = 2 u_fb / width - 1 and (wgpu's NDC is y up)
// ndc_y = 1 - 2 v_fb / height; multiplied by w = z this is linear in the point. The z-buffer holds reversed depth
// d = near (far - z) / ((far - near) z) (1 at near, 0 at far, compare Greater; with f32 this
// resolves about 1e-7 of the depth); it is read back and converted to metric z-depth on the
// CPU, so depth-only renders need no fragment shader.

struct Draw {
    // Column-major camera_from_object (rotation and translation), metres.
    camera_from_object: mat4x4<f32>,
    // fx, fy, cx, cy in pixels of the view.
    focal_principal: vec4<f32>,
    // width, height (pixels), near, far (metres).
    size_clip: vec4<f32>,
    // x: instance id for the mask; y, z, w unused.
    ids: vec4<u32>,
    // xyz: unit direction towards a directional light in the camera frame, w: 1 for that light,
    // 0 for a headlight (light at the camera centre).
    light: vec4<f32>,
};

@group(0) @binding(0) var<uniform> draw: Draw;

struct VertexIn {
    @location(0) position_m: vec3<f32>,
    @location(1) color: vec4<f32>,
};

struct VertexOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) point_in_camera_m: vec3<f32>,
    @location(1) color: vec3<f32>,
    @location(2) @interpolate(flat) instance_id: u32,
    @location(3) @interpolate(flat) light: vec4<f32>,
};

@vertex
fn vs_main(v: VertexIn) -> VertexOut {
    let d = draw;
    let p = (d.camera_from_object * vec4<f32>(v.position_m, 1.0)).xyz;
    let fx = d.focal_principal.x;
    let fy = d.focal_principal.y;
    // principal point in framebuffer coordinates (pixel centres at integer + 0.5 there)
    let cx = d.focal_principal.z + 0.5;
    let cy = d.focal_principal.w + 0.5;
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
    out.light = d.light;
    return out;
}

// Lambert shading, two-sided (the normal faces the camera), flat normals from screen-space
// derivatives of the camera-frame point: 20 % ambient plus 80 % Lambert, with a headlight
// (light at the camera centre: what codebook templates use) or a directional light.
fn shade(p: vec3<f32>, color: vec3<f32>, light: vec4<f32>) -> vec3<f32> {
    let n_raw = cross(dpdx(p), dpdy(p));
    let len = length(n_raw);
    let to_camera = -normalize(p);
    var lambert = 1.0;
    if (len > 0.0) {
        var n = n_raw / len;
        if (dot(n, to_camera) < 0.0) {
            n = -n;
        }
        var l = to_camera;
        if (light.w > 0.5) {
            l = light.xyz;
        }
        lambert = max(dot(n, l), 0.0);
    }
    return color * (0.2 + 0.8 * lambert);
}

struct SceneOut {
    @location(0) color: vec4<f32>,
    @location(1) instance_id: u32,
};

@fragment
fn fs_scene(f: VertexOut) -> SceneOut {
    var out: SceneOut;
    out.color = vec4<f32>(shade(f.point_in_camera_m, f.color, f.light), 1.0);
    out.instance_id = f.instance_id;
    return out;
}

@fragment
fn fs_view(f: VertexOut) -> @location(0) vec4<f32> {
    return vec4<f32>(shade(f.point_in_camera_m, f.color, f.light), 1.0);
}
