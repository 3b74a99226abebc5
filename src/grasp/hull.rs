//! A convex hull whose support function climbs the vertex graph instead of scanning every
//! vertex (parry's `ConvexPolyhedron` scans them all: half of a decision's time went there).
//!
//! A linear function over a convex polytope has no local maximum on the edge graph that is not
//! global, so steepest ascent from the best of a few seed vertices finds the support point.
//! Ray casts and point queries are delegated to the polyhedron.

use parry3d::bounding_volume::{Aabb, BoundingSphere};
use parry3d::mass_properties::MassProperties;
use parry3d::math::{Real, Vector};
use parry3d::query::{PointProjection, PointQuery, Ray, RayCast, RayIntersection};
use parry3d::shape::{ConvexPolyhedron, FeatureId, Shape, ShapeType, SupportMap, TypedShape};

#[derive(Debug, Clone)]
pub struct ClimbingHull {
    poly: ConvexPolyhedron,
    points: Vec<Vector>,
    /// Neighbours of vertex `i`: `adjacency[offsets[i]..offsets[i + 1]]`.
    offsets: Vec<u32>,
    adjacency: Vec<u32>,
    /// Start vertices: the extremes along +-x, +-y, +-z.
    seeds: Vec<u32>,
}

impl ClimbingHull {
    pub fn new(poly: ConvexPolyhedron) -> Self {
        let (points, triangles) = poly.to_trimesh();
        let n = points.len();
        let mut nb: Vec<Vec<u32>> = vec![Vec::new(); n];
        for t in &triangles {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                if !nb[a as usize].contains(&b) {
                    nb[a as usize].push(b);
                }
                if !nb[b as usize].contains(&a) {
                    nb[b as usize].push(a);
                }
            }
        }
        let mut offsets = Vec::with_capacity(n + 1);
        let mut adjacency = Vec::new();
        offsets.push(0);
        for list in &nb {
            adjacency.extend_from_slice(list);
            offsets.push(adjacency.len() as u32);
        }
        // vertices on no face (left on an edge or inside a face by the hull) cannot lead
        // anywhere and never beat the face vertices: no seeds among them
        let mut seeds = Vec::new();
        for d in [Vector::X, -Vector::X, Vector::Y, -Vector::Y, Vector::Z, -Vector::Z] {
            let best = (0..n)
                .filter(|&i| !nb[i].is_empty())
                .max_by(|&a, &b| points[a].dot(d).total_cmp(&points[b].dot(d)))
                .unwrap_or(0) as u32;
            if !seeds.contains(&best) {
                seeds.push(best);
            }
        }
        Self {
            poly,
            points,
            offsets,
            adjacency,
            seeds,
        }
    }

    pub fn polyhedron(&self) -> &ConvexPolyhedron {
        &self.poly
    }
}

impl SupportMap for ClimbingHull {
    fn local_support_point(&self, dir: Vector) -> Vector {
        let dot = |i: u32| self.points[i as usize].dot(dir);
        let mut best = self.seeds[0];
        let mut best_dot = dot(best);
        for &s in &self.seeds[1..] {
            let d = dot(s);
            if d > best_dot {
                best = s;
                best_dot = d;
            }
        }
        loop {
            let (lo, hi) = (
                self.offsets[best as usize] as usize,
                self.offsets[best as usize + 1] as usize,
            );
            let mut next = best;
            for &m in &self.adjacency[lo..hi] {
                let d = dot(m);
                if d > best_dot {
                    best_dot = d;
                    next = m;
                }
            }
            if next == best {
                return self.points[best as usize];
            }
            best = next;
        }
    }
}

impl RayCast for ClimbingHull {
    fn cast_local_ray_and_get_normal(
        &self,
        ray: &Ray,
        max_time_of_impact: Real,
        solid: bool,
    ) -> Option<RayIntersection> {
        self.poly.cast_local_ray_and_get_normal(ray, max_time_of_impact, solid)
    }
}

impl PointQuery for ClimbingHull {
    fn project_local_point(&self, point: Vector, solid: bool) -> PointProjection {
        self.poly.project_local_point(point, solid)
    }

    fn project_local_point_and_get_feature(&self, point: Vector) -> (PointProjection, FeatureId) {
        self.poly.project_local_point_and_get_feature(point)
    }
}

impl Shape for ClimbingHull {
    fn compute_local_aabb(&self) -> Aabb {
        self.poly.compute_local_aabb()
    }
    fn compute_local_bounding_sphere(&self) -> BoundingSphere {
        self.poly.compute_local_bounding_sphere()
    }
    fn clone_dyn(&self) -> Box<dyn Shape> {
        Box::new(self.clone())
    }
    fn scale_dyn(&self, _scale: Vector, _num_subdivisions: u32) -> Option<Box<dyn Shape>> {
        None
    }
    fn mass_properties(&self, density: Real) -> MassProperties {
        self.poly.mass_properties(density)
    }
    fn shape_type(&self) -> ShapeType {
        ShapeType::Custom
    }
    fn as_typed_shape(&self) -> TypedShape<'_> {
        TypedShape::Custom(self)
    }
    fn ccd_thickness(&self) -> Real {
        self.poly.ccd_thickness()
    }
    fn ccd_angular_thickness(&self) -> Real {
        self.poly.ccd_angular_thickness()
    }
    fn is_convex(&self) -> bool {
        true
    }
    fn as_support_map(&self) -> Option<&dyn SupportMap> {
        Some(self as &dyn SupportMap)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn climbing_finds_the_same_support_as_the_scan() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let pts: Vec<Vector> = (0..500)
            .map(|_| {
                Vector::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-0.3..0.3),
                )
            })
            .collect();
        let poly = ConvexPolyhedron::from_convex_hull(&pts).unwrap();
        let hull = ClimbingHull::new(poly.clone());
        for _ in 0..2000 {
            let d = Vector::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            );
            let a = hull.local_support_point(d).dot(d);
            let b = poly.local_support_point(d).dot(d);
            assert!((a - b).abs() <= 1e-6 * (1.0 + b.abs()), "{a} vs {b} for {d:?}");
        }
    }
}
