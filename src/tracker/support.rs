//! The support prior: an object on a table rests on a face, so its down direction (object
//! frame) is one of a few directions, whatever its turn about the vertical.
//!
//! A hull face is stable when the centroid projects inside it (the quasi-static rule of Wiegley
//! et al., "Computing a statistical distribution of stable poses of a polyhedron"); the faces
//! of the mesh's bounding box are added, since objects set down by hand (and by `pregrasp
//! generate`) stand upright, lie on a side or upside down whether or not a drop would have left
//! them so. Each step the matched bins' prior is multiplied by a factor that is 1 for an object
//! resting on any of those faces and falls to `(1 - share)^strength` for one tilted well off
//! them (a lobe of width `tilt_sigma_deg` about each face's normal). The factor carries no
//! face's probability: applied at every step, a preference between faces would compound while
//! the views are too far to object; what it holds back is the tilt that the views' noise and
//! the rotation blur add each step. It needs the table's normal in the world
//! (`Tracker::set_support_normal`, from the scene's support plane).

use crate::mesh::Mesh;
use crate::tracker::bins::GridTables;
use nalgebra::{Matrix3, Point3, Vector3};
use serde::{Deserialize, Serialize};

/// Settings of the support prior ([`crate::tracker::TrackerConfig::support`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SupportConfig {
    /// How much a pose off every face loses: its factor is `1 - share` before `strength`.
    pub share: f64,
    /// Standard deviation of a face's lobe, degrees: how far a resting object's down direction
    /// strays from the face's normal (a tilted table, a rounded face, a scan's facets).
    pub tilt_sigma_deg: f64,
    /// Exponent of the factor applied at every step.
    pub strength: f64,
    /// Whether the faces of the mesh's bounding box count beside the hull's stable faces.
    pub box_faces: bool,
}

impl Default for SupportConfig {
    fn default() -> Self {
        Self {
            share: 0.8,
            tilt_sigma_deg: 10.0,
            strength: 0.2,
            box_faces: true,
        }
    }
}

/// The faces an object may rest on: outward normals (object frame, unit), which point down
/// when it rests on them.
#[derive(Debug, Clone, PartialEq)]
pub struct RestingFaces {
    pub downs: Vec<Vector3<f64>>,
}

/// Edge-adjacent hull triangles whose normals differ by less than this form one face.
const FACE_MERGE_RAD: f64 = 5.0 * std::f64::consts::PI / 180.0;

impl RestingFaces {
    /// The stable faces of `mesh`'s convex hull; `None` for a flat or degenerate mesh.
    pub fn from_mesh(mesh: &Mesh) -> Option<Self> {
        let (pts, tris) = mesh.convex_hull()?.to_trimesh();
        let p: Vec<Point3<f64>> = pts
            .iter()
            .map(|v| Point3::new(f64::from(v.x), f64::from(v.y), f64::from(v.z)))
            .collect();
        Self::from_hull(&p, &tris)
    }

    /// [`Self::from_mesh`] and, with `box_faces`, the six faces of the mesh's bounding box.
    pub fn of_mesh(mesh: &Mesh, box_faces: bool) -> Option<Self> {
        let mut faces = Self::from_mesh(mesh)?;
        if box_faces {
            for axis in 0..3 {
                for sign in [1.0, -1.0] {
                    faces.downs.push(Vector3::ith(axis, sign));
                }
            }
        }
        Some(faces)
    }

    /// The stable faces of a convex hull given as triangles.
    pub fn from_hull(points: &[Point3<f64>], triangles: &[[u32; 3]]) -> Option<Self> {
        let centroid = hull_centroid(points, triangles)?;
        let mut normals: Vec<Vector3<f64>> = Vec::new();
        let mut areas: Vec<f64> = Vec::new();
        let mut corners: Vec<[Point3<f64>; 3]> = Vec::new();
        let mut ids: Vec<[u32; 3]> = Vec::new();
        for t in triangles {
            let [a, b, c] = t.map(|i| points[i as usize]);
            let cross = (b - a).cross(&(c - a));
            let Some(mut normal) = cross.try_normalize(1e-15) else {
                continue;
            };
            if normal.dot(&(a - centroid)) < 0.0 {
                normal = -normal;
            }
            normals.push(normal);
            areas.push(0.5 * cross.norm());
            corners.push([a, b, c]);
            ids.push(*t);
        }
        // faces: regions of edge-adjacent triangles whose normals differ by less than
        // FACE_MERGE_RAD (a scan's flat side is many slightly tilted facets)
        let mut parent: Vec<usize> = (0..normals.len()).collect();
        fn root(parent: &mut [usize], mut i: usize) -> usize {
            while parent[i] != i {
                parent[i] = parent[parent[i]];
                i = parent[i];
            }
            i
        }
        let mut edge_owner: std::collections::HashMap<(u32, u32), usize> = std::collections::HashMap::new();
        for (i, t) in ids.iter().enumerate() {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                match edge_owner.get(&(a.min(b), a.max(b))) {
                    Some(&j) if normals[i].angle(&normals[j]) < FACE_MERGE_RAD => {
                        let (ri, rj) = (root(&mut parent, i), root(&mut parent, j));
                        parent[ri] = rj;
                    }
                    Some(_) => {}
                    None => {
                        edge_owner.insert((a.min(b), a.max(b)), i);
                    }
                }
            }
        }
        let mut regions: std::collections::BTreeMap<usize, Vec<usize>> = std::collections::BTreeMap::new();
        for i in 0..normals.len() {
            let r = root(&mut parent, i);
            regions.entry(r).or_default().push(i);
        }
        let downs: Vec<Vector3<f64>> = regions
            .values()
            .filter_map(|f| {
                let normal = f
                    .iter()
                    .map(|&i| areas[i] * normals[i])
                    .sum::<Vector3<f64>>()
                    .try_normalize(1e-15)?;
                // resting on the face: the centroid projects inside it, seen along its normal
                f.iter()
                    .any(|&i| inside_triangle(&centroid, &corners[i], &normal))
                    .then_some(normal)
            })
            .collect();
        (!downs.is_empty()).then_some(Self { downs })
    }
}

/// The centroid of the solid a closed hull bounds.
fn hull_centroid(points: &[Point3<f64>], triangles: &[[u32; 3]]) -> Option<Point3<f64>> {
    if points.is_empty() {
        return None;
    }
    let o = points.iter().map(|p| p.coords).sum::<Vector3<f64>>() / points.len() as f64;
    let (mut vol, mut moment) = (0.0, Vector3::zeros());
    for t in triangles {
        let [a, b, c] = t.map(|i| points[i as usize].coords);
        let v = (a - o).dot(&(b - o).cross(&(c - o))).abs() / 6.0;
        vol += v;
        moment += v * (o + a + b + c) / 4.0;
    }
    (vol > 1e-12).then(|| Point3::from(moment / vol))
}

/// Whether `p` lies inside the triangle as seen along `normal`, up to a micrometre.
fn inside_triangle(p: &Point3<f64>, t: &[Point3<f64>; 3], normal: &Vector3<f64>) -> bool {
    (0..3).all(|k| {
        let (a, b) = (t[k], t[(k + 1) % 3]);
        (b - a).cross(&(p - a)).dot(normal) >= -1e-6 * (b - a).norm()
    })
}

/// The prior of one model: a lobe about each resting face's down, faces closer than half a
/// lobe's width merged (a cylinder's hull has a face every few degrees round its side).
#[derive(Debug, Clone, PartialEq)]
pub struct SupportPrior {
    downs: Vec<Vector3<f64>>,
    kappa: f64,
    share: f64,
    strength: f64,
}

impl SupportPrior {
    pub fn new(faces: &RestingFaces, config: &SupportConfig) -> Self {
        let sigma = config.tilt_sigma_deg.to_radians().max(1e-3);
        let mut downs: Vec<Vector3<f64>> = Vec::new();
        for d in &faces.downs {
            if downs.iter().all(|c| c.angle(d) >= 0.5 * sigma) {
                downs.push(*d);
            }
        }
        Self {
            downs,
            kappa: 1.0 / (sigma * sigma),
            share: config.share.clamp(0.0, 1.0),
            strength: config.strength.max(0.0),
        }
    }

    /// The step's factor, before `strength`, for an object whose down direction is `down`
    /// (object frame, unit): 1 resting on a face, `1 - share` far from every face.
    pub fn factor(&self, down: &Vector3<f64>) -> f64 {
        let best = self.downs.iter().map(|d| down.dot(d)).fold(-1.0, f64::max);
        (1.0 - self.share) + self.share * (self.kappa * (best - 1.0)).exp()
    }

    /// Per bin of `bins`, the factor the step multiplies its prior by (`factor` raised to
    /// `strength`), for the object's rotation `ray * matrix(bin)` in a frame whose down
    /// direction is `down_hist`, `ray` being the rotation of the track's ray there.
    pub fn factors(&self, tables: &GridTables, bins: &[u32], ray: &Matrix3<f64>, down_hist: &Vector3<f64>) -> Vec<f32> {
        let d = ray.transpose() * down_hist;
        bins.iter()
            .map(|b| {
                let down = tables.matrix(*b as usize).transpose() * d;
                self.factor(&down).powf(self.strength) as f32
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::RotationGrid;
    use approx::assert_relative_eq;

    fn box_hull(ext: [f64; 3]) -> (Vec<Point3<f64>>, Vec<[u32; 3]>) {
        let mesh = crate::mesh::builtin_box(ext, [[200, 0, 0], [0, 0, 200]]);
        let p = mesh
            .vertices_m
            .iter()
            .map(|v| Point3::new(f64::from(v[0]), f64::from(v[1]), f64::from(v[2])))
            .collect();
        (p, mesh.triangles.clone())
    }

    #[test]
    fn a_box_rests_on_its_six_faces() {
        let (p, t) = box_hull([0.2, 0.1, 0.03]);
        let faces = RestingFaces::from_hull(&p, &t).expect("box");
        assert_eq!(faces.downs.len(), 6, "{faces:?}");
        for axis in 0..3 {
            for sign in [1.0, -1.0] {
                let d = Vector3::ith(axis, sign);
                assert!(faces.downs.iter().any(|f| f.angle(&d) < 1e-6), "{d:?}: {faces:?}");
            }
        }
    }

    #[test]
    fn a_face_the_centroid_does_not_project_into_is_not_stable() {
        // a prism over the triangle (0, 0), (0.3, 0), (0.35, 0.05) in x, z, 0.1 deep in y: the
        // centroid (x 0.22, z 0.017) projects onto the bottom and the long top face, but past
        // the short slanted face between (0.3, 0) and (0.35, 0.05), whose normal is (1, 0, -1)
        let corners = [[0.0, 0.0], [0.3, 0.0], [0.35, 0.05]];
        let vertices = [0.0f32, 0.1]
            .iter()
            .flat_map(|y| corners.iter().map(move |[x, z]| [*x as f32, *y, *z as f32]))
            .collect();
        // the hull is all that counts: the vertices, triangulated by the hull
        let mesh = Mesh::new(vertices, None, vec![[0, 1, 2]]).expect("mesh");
        let faces = RestingFaces::from_mesh(&mesh).expect("prism");
        assert!(faces.downs.iter().any(|d| d.z < -0.99), "the bottom: {faces:?}");
        assert!(faces.downs.iter().any(|d| d.z > 0.98), "the long top face: {faces:?}");
        assert!(
            !faces.downs.iter().any(|d| d.x > 0.6 && d.z < -0.6),
            "the short face: {faces:?}"
        );
    }

    /// The factor of a bin reads the object's down direction through the track's ray: the bin
    /// of a box standing on its bottom, seen from a camera looking down at it off its axis,
    /// carries the prior's peak, and the bin of the box tipped by 40 degrees a small share.
    #[test]
    fn a_bin_s_factor_follows_the_object_s_rotation_through_the_ray() {
        let (p, t) = box_hull([0.2, 0.1, 0.03]);
        let faces = RestingFaces::from_hull(&p, &t).expect("box");
        let cfg = SupportConfig {
            strength: 1.0,
            box_faces: false,
            ..SupportConfig::default()
        };
        let prior = SupportPrior::new(&faces, &cfg);
        let tables = GridTables::new(RotationGrid::new(5).expect("grid"));
        // camera frame: the world's down seen from a camera pitched 35 degrees down
        let down_hist = nalgebra::Rotation3::from_axis_angle(&Vector3::x_axis(), 0.6) * Vector3::y();
        let position = Vector3::new(0.3, -0.1, 1.5);
        let ray = crate::geometry::ray_rotation(&position)
            .to_rotation_matrix()
            .into_inner();
        let factor_of = |object: &nalgebra::UnitQuaternion<f64>| {
            let allocentric = ray.transpose() * object.to_rotation_matrix().into_inner();
            let b = crate::tracker::bins::flat_of_matrix(&tables.grid, &allocentric) as u32;
            prior.factors(&tables, &[b], &ray, &down_hist)[0]
        };
        let spin = nalgebra::UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 1.1);
        let upright = nalgebra::UnitQuaternion::rotation_between(&-Vector3::z(), &down_hist).expect("turn") * spin;
        let tipped = upright * nalgebra::UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 40f64.to_radians());
        assert!(factor_of(&upright) > 0.9, "{}", factor_of(&upright));
        assert!(factor_of(&tipped) < 0.25, "{}", factor_of(&tipped));
    }

    #[test]
    fn the_factor_is_one_on_every_face_and_falls_off_them() {
        let (p, t) = box_hull([0.2, 0.1, 0.03]);
        let faces = RestingFaces::from_hull(&p, &t).expect("box");
        let prior = SupportPrior::new(&faces, &SupportConfig::default());
        for d in &faces.downs {
            assert_relative_eq!(prior.factor(d), 1.0, epsilon = 1e-9);
        }
        let tilted = nalgebra::Rotation3::from_axis_angle(&Vector3::x_axis(), 0.6) * -Vector3::z();
        assert_relative_eq!(prior.factor(&tilted), 0.2, epsilon = 0.01);
    }
}
