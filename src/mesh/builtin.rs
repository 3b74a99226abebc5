//! Procedural objects built into the binary, so the service runs without any file.

use super::Mesh;
use nalgebra::Vector3;

/// Names of the procedural objects built into the binary.
pub const BUILTIN_OBJECTS: [&str; 3] = ["box", "can", "mug"];

/// A procedural object by name (see [`BUILTIN_OBJECTS`]).
pub fn builtin(name: &str) -> Option<Mesh> {
    match name {
        "box" => Some(builtin_box([0.16, 0.06, 0.21], [[200, 40, 30], [240, 200, 40]])),
        "can" => Some(builtin_cylinder(0.051, 0.14, 48, [[40, 70, 160], [200, 200, 210]])),
        "mug" => Some(builtin_mug()),
        _ => None,
    }
}

/// A box centred at the origin with sides `size_m` (x, y, z); the +x half gets the second
/// colour so that the box is not colour-symmetric.
pub fn builtin_box(size_m: [f64; 3], colors: [[u8; 3]; 2]) -> Mesh {
    let mut b = Builder::default();
    b.add_box(Vector3::zeros(), Vector3::from(size_m) * 0.5, colors);
    b.finish()
}

/// A closed cylinder along z, centred at the origin; a stripe of the second colour on +x.
pub fn builtin_cylinder(radius_m: f64, height_m: f64, segments: usize, colors: [[u8; 3]; 2]) -> Mesh {
    let mut b = Builder::default();
    b.add_cylinder(Vector3::zeros(), radius_m, height_m, segments, colors, true);
    b.finish()
}

/// A cup with a handle on +x: an open cylinder (outer wall, inner wall, rim, bottom) plus a
/// box-shaped handle.
pub fn builtin_mug() -> Mesh {
    let mut b = Builder::default();
    let (r, h, wall) = (0.04, 0.09, 0.006);
    b.add_tube(r, r - wall, h, 40, [230, 230, 225]);
    b.add_box(
        Vector3::new(r + 0.014, 0.0, 0.0),
        Vector3::new(0.016, 0.006, 0.028),
        [[180, 40, 40], [180, 40, 40]],
    );
    b.finish()
}

#[derive(Default)]
struct Builder {
    v: Vec<[f32; 3]>,
    c: Vec<[u8; 3]>,
    t: Vec<[u32; 3]>,
}

impl Builder {
    fn push(&mut self, p: Vector3<f64>, c: [u8; 3]) -> u32 {
        self.v.push([p.x as f32, p.y as f32, p.z as f32]);
        self.c.push(c);
        self.v.len() as u32 - 1
    }
    fn quad(&mut self, a: u32, b: u32, c: u32, d: u32) {
        self.t.push([a, b, c]);
        self.t.push([a, c, d]);
    }
    fn add_box(&mut self, center: Vector3<f64>, half: Vector3<f64>, colors: [[u8; 3]; 2]) {
        // six faces, each with its own 4 vertices (flat colour), counter-clockwise from outside
        for axis in 0..3 {
            for sign in [-1.0, 1.0] {
                let n = Vector3::ith(axis, sign);
                let u = Vector3::ith((axis + 1) % 3, 1.0);
                let w = n.cross(&u);
                let col = if (center + n.component_mul(&half)).x > 1e-9 && axis == 0 {
                    colors[1]
                } else {
                    colors[0]
                };
                let corner = |su: f64, sw: f64| {
                    center + n.component_mul(&half) + (u * su).component_mul(&half) + (w * sw).component_mul(&half)
                };
                let a = self.push(corner(-1.0, -1.0), col);
                let b = self.push(corner(1.0, -1.0), col);
                let c = self.push(corner(1.0, 1.0), col);
                let d = self.push(corner(-1.0, 1.0), col);
                self.quad(a, b, c, d);
            }
        }
    }
    fn add_cylinder(&mut self, center: Vector3<f64>, r: f64, h: f64, n: usize, colors: [[u8; 3]; 2], caps: bool) {
        let ring = |k: usize, z: f64| {
            let a = k as f64 / n as f64 * std::f64::consts::TAU;
            center + Vector3::new(r * a.cos(), r * a.sin(), z)
        };
        let col = |k: usize| {
            if (k as f64 / n as f64) < 0.12 || (k as f64 / n as f64) > 0.88 {
                colors[1]
            } else {
                colors[0]
            }
        };
        let mut bottom = Vec::new();
        let mut top = Vec::new();
        for k in 0..n {
            bottom.push(self.push(ring(k, -h / 2.0), col(k)));
            top.push(self.push(ring(k, h / 2.0), col(k)));
        }
        for k in 0..n {
            let k2 = (k + 1) % n;
            self.quad(bottom[k], bottom[k2], top[k2], top[k]);
        }
        if caps {
            let cb = self.push(center - Vector3::new(0.0, 0.0, h / 2.0), colors[0]);
            let ct = self.push(center + Vector3::new(0.0, 0.0, h / 2.0), colors[0]);
            for k in 0..n {
                let k2 = (k + 1) % n;
                self.t.push([cb, bottom[k2], bottom[k]]);
                self.t.push([ct, top[k], top[k2]]);
            }
        }
    }
    fn add_tube(&mut self, r_out: f64, r_in: f64, h: f64, n: usize, color: [u8; 3]) {
        let ring = |k: usize, r: f64, z: f64| {
            let a = k as f64 / n as f64 * std::f64::consts::TAU;
            Vector3::new(r * a.cos(), r * a.sin(), z)
        };
        let (z0, z1, zb) = (-h / 2.0, h / 2.0, -h / 2.0 + 0.008);
        let mut ob = Vec::new();
        let mut ot = Vec::new();
        let mut ib = Vec::new();
        let mut it = Vec::new();
        for k in 0..n {
            ob.push(self.push(ring(k, r_out, z0), color));
            ot.push(self.push(ring(k, r_out, z1), color));
            ib.push(self.push(ring(k, r_in, zb), color));
            it.push(self.push(ring(k, r_in, z1), color));
        }
        let cb = self.push(Vector3::new(0.0, 0.0, z0), color);
        let ci = self.push(Vector3::new(0.0, 0.0, zb), color);
        for k in 0..n {
            let k2 = (k + 1) % n;
            self.quad(ob[k], ob[k2], ot[k2], ot[k]); // outer wall, outward
            self.quad(ib[k2], ib[k], it[k], it[k2]); // inner wall, facing the axis
            self.quad(ot[k], ot[k2], it[k2], it[k]); // rim
            self.t.push([cb, ob[k2], ob[k]]); // bottom, facing down
            self.t.push([ci, ib[k], ib[k2]]); // inside floor, facing up
        }
    }
    fn finish(self) -> Mesh {
        Mesh {
            vertices_m: self.v,
            colors: self.c,
            triangles: self.t,
        }
    }
}
