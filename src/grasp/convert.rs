//! The one place where nalgebra (f64, our maths) meets parry3d 0.31 (glam, f32).

use crate::geometry::Pose;
use nalgebra::{Point3, UnitQuaternion, Vector3};
use parry3d::math::{Pose as PPose, Rotation as PRotation, Vector as PVector};

/// nalgebra isometry -> parry pose.
pub fn pose_to_parry(pose: &Pose) -> PPose {
    let q = pose.rotation.quaternion();
    let t = pose.translation.vector;
    PPose::from_parts(
        PVector::new(t.x as f32, t.y as f32, t.z as f32),
        PRotation::from_xyzw(q.i as f32, q.j as f32, q.k as f32, q.w as f32).normalize(),
    )
}

/// parry pose -> nalgebra isometry.
pub fn pose_from_parry(pose: &PPose) -> Pose {
    let q = pose.rotation;
    Pose::from_parts(
        nalgebra::Translation3::new(
            pose.translation.x as f64,
            pose.translation.y as f64,
            pose.translation.z as f64,
        ),
        UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
            q.w as f64, q.x as f64, q.y as f64, q.z as f64,
        )),
    )
}

pub fn vector_to_parry(v: &Vector3<f64>) -> PVector {
    PVector::new(v.x as f32, v.y as f32, v.z as f32)
}

pub fn point_to_parry(p: &Point3<f64>) -> PVector {
    PVector::new(p.x as f32, p.y as f32, p.z as f32)
}

pub fn vector_from_parry(v: PVector) -> Vector3<f64> {
    Vector3::new(v.x as f64, v.y as f64, v.z as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    #[test]
    fn pose_round_trip_and_action_agree() {
        let pose = Pose::new(Vector3::new(0.1, -0.2, 0.3), Vector3::new(0.3, -0.5, 1.1));
        let p = pose_to_parry(&pose);
        let back = pose_from_parry(&p);
        assert_relative_eq!(back.to_homogeneous(), pose.to_homogeneous(), epsilon = 1e-6);
        let x = Point3::new(0.05, 0.02, -0.07);
        let a = pose * x;
        let b = vector_from_parry(p.transform_point(point_to_parry(&x)));
        assert_relative_eq!(a.coords, b, epsilon = 1e-6);
    }
}
