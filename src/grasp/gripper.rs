//! The parallel-jaw gripper: palm, two fingers, pads with a capture funnel; JSON in and out.
//!
//! Gripper frame (all dimensions below are in it): origin at the tool centre point (TCP), the
//! middle between the two pad centres; x is the closing axis (the fingers move along +-x),
//! z the approach axis (from the palm towards the finger tips), y = z x x. The finger tips lie
//! at `z = pad.length_m / 2`, the pads cover the last `pad.length_m` of each finger's inner
//! face, and the palm sits behind the finger roots.
//!
//! The alignment capability is geometry: each pad carries a V-groove running along the
//! approach axis (mouth half-width `pad.groove_half_width_m`, wall angle
//! `pad.capture_angle_deg`). A contact inside the groove mouth whose surface normal is within
//! the wall angle of the closing axis is pushed to the groove's centre when the fingers close;
//! a flat face lying on the pad is squared by it. Contacts outside the funnel slip or pivot.

use super::GraspError;
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Finger pad geometry and its capture funnel.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PadGeometry {
    /// Length of the pad along the approach axis, measured from the finger tip.
    pub length_m: f64,
    /// Thickness of the pad slab on the finger's inner face (its collision volume).
    pub thickness_m: f64,
    /// Half-width of the V-groove's mouth across the pad (along gripper y).
    pub groove_half_width_m: f64,
    /// Angle of the groove walls (and tip chamfer) from the pad plane: a contact whose surface
    /// normal is tilted by more than this from the closing axis is not pushed into the groove.
    pub capture_angle_deg: f64,
}

/// A parallel-jaw gripper (see the module docs for the frame).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Gripper {
    pub name: String,
    /// Palm box size (x, y, z).
    pub palm_size_m: [f64; 3],
    /// Finger box: thickness (x), width (y), length (z).
    pub finger_size_m: [f64; 3],
    /// Largest distance between the pads (the stroke).
    pub max_opening_m: f64,
    /// Smallest distance between the pads (fully closed).
    pub min_opening_m: f64,
    pub pad: PadGeometry,
    /// Distance of the pre-grasp pose before the grasp pose along the approach axis; the
    /// approach sweep covers it.
    pub approach_distance_m: f64,
    /// Least distance between any gripper part and the support plane.
    pub table_clearance_m: f64,
}

impl Gripper {
    /// A two-finger gripper of about the size of a Robotiq 2F-140: 140 mm stroke (the 102 mm
    /// YCB can fits), 60 mm fingers, 35 mm pads with a 9 mm V-groove mouth.
    pub fn default_parallel_jaw() -> Self {
        Self {
            name: "parallel_jaw_140".to_string(),
            palm_size_m: [0.19, 0.06, 0.08],
            finger_size_m: [0.012, 0.024, 0.06],
            max_opening_m: 0.14,
            min_opening_m: 0.0,
            pad: PadGeometry {
                length_m: 0.035,
                thickness_m: 0.002,
                groove_half_width_m: 0.009,
                capture_angle_deg: 30.0,
            },
            approach_distance_m: 0.10,
            table_clearance_m: 0.002,
        }
    }

    /// Parses and validates a gripper from JSON.
    pub fn from_json(text: &str) -> Result<Self, GraspError> {
        let g: Gripper = serde_json::from_str(text)?;
        g.validate()?;
        Ok(g)
    }

    /// Reads and validates a gripper JSON file.
    pub fn from_file(path: &Path) -> Result<Self, GraspError> {
        let text = std::fs::read_to_string(path).map_err(|source| GraspError::GripperFile {
            path: path.display().to_string(),
            source,
        })?;
        Self::from_json(&text)
    }

    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).unwrap_or_default()
    }

    /// Checks that every size is finite and positive and that the parts fit together.
    pub fn validate(&self) -> Result<(), GraspError> {
        let bad = |msg: String| Err(GraspError::InvalidGripper(msg));
        let positive = [
            ("palm_size_m[0]", self.palm_size_m[0]),
            ("palm_size_m[1]", self.palm_size_m[1]),
            ("palm_size_m[2]", self.palm_size_m[2]),
            ("finger_size_m[0] (thickness)", self.finger_size_m[0]),
            ("finger_size_m[1] (width)", self.finger_size_m[1]),
            ("finger_size_m[2] (length)", self.finger_size_m[2]),
            ("max_opening_m", self.max_opening_m),
            ("pad.length_m", self.pad.length_m),
            ("pad.thickness_m", self.pad.thickness_m),
            ("pad.groove_half_width_m", self.pad.groove_half_width_m),
            ("pad.capture_angle_deg", self.pad.capture_angle_deg),
        ];
        for (name, v) in positive {
            if !v.is_finite() {
                return bad(format!("{name} must be finite, got {v}"));
            }
            if v <= 0.0 {
                return bad(format!("{name} must be positive, got {v}"));
            }
        }
        let non_negative = [
            ("min_opening_m", self.min_opening_m),
            ("approach_distance_m", self.approach_distance_m),
            ("table_clearance_m", self.table_clearance_m),
        ];
        for (name, v) in non_negative {
            if !v.is_finite() || v < 0.0 {
                return bad(format!("{name} must be finite and >= 0, got {v}"));
            }
        }
        if self.min_opening_m >= self.max_opening_m {
            return bad(format!(
                "min_opening_m ({}) must be below max_opening_m ({})",
                self.min_opening_m, self.max_opening_m
            ));
        }
        if self.pad.length_m > self.finger_size_m[2] {
            return bad(format!(
                "pad.length_m ({}) exceeds the finger length ({})",
                self.pad.length_m, self.finger_size_m[2]
            ));
        }
        if self.pad.thickness_m > self.finger_size_m[0] {
            return bad(format!(
                "pad.thickness_m ({}) exceeds the finger thickness ({})",
                self.pad.thickness_m, self.finger_size_m[0]
            ));
        }
        if self.pad.groove_half_width_m > self.finger_size_m[1] * 0.5 {
            return bad(format!(
                "pad.groove_half_width_m ({}) exceeds half the finger width ({})",
                self.pad.groove_half_width_m,
                self.finger_size_m[1] * 0.5
            ));
        }
        if self.pad.capture_angle_deg >= 90.0 {
            return bad(format!(
                "pad.capture_angle_deg must be below 90, got {}",
                self.pad.capture_angle_deg
            ));
        }
        let span = self.max_opening_m + 2.0 * self.finger_size_m[0];
        if self.palm_size_m[0] + 1e-9 < span {
            return bad(format!(
                "palm_size_m[0] ({}) must carry the open fingers ({span} m across)",
                self.palm_size_m[0]
            ));
        }
        if self.name.trim().is_empty() {
            return bad("name must not be empty".to_string());
        }
        Ok(())
    }

    /// z of the finger tips.
    pub fn tip_z_m(&self) -> f64 {
        self.pad.length_m * 0.5
    }

    /// z of the finger roots (the palm's front face).
    pub fn root_z_m(&self) -> f64 {
        self.tip_z_m() - self.finger_size_m[2]
    }

    /// Greatest depth of the TCP below an object surface facing the palm: the finger length
    /// from the palm face to the pad centre.
    pub fn reach_m(&self) -> f64 {
        self.finger_size_m[2] - self.pad.length_m * 0.5
    }

    pub fn palm_half_extents(&self) -> Vector3<f64> {
        Vector3::from(self.palm_size_m) * 0.5
    }

    pub fn palm_center(&self) -> Vector3<f64> {
        Vector3::new(0.0, 0.0, self.root_z_m() - self.palm_size_m[2] * 0.5)
    }

    pub fn finger_half_extents(&self) -> Vector3<f64> {
        Vector3::from(self.finger_size_m) * 0.5
    }

    /// Centre of a finger (`side` = +1 for +x, -1 for -x) when the pads are `opening_m` apart.
    pub fn finger_center(&self, side: f64, opening_m: f64) -> Vector3<f64> {
        Vector3::new(
            side * (opening_m * 0.5 + self.finger_size_m[0] * 0.5),
            0.0,
            self.tip_z_m() - self.finger_size_m[2] * 0.5,
        )
    }

    /// The pad slab: (half extents, centre) for `side` when the pads are `opening_m` apart.
    /// The slab lies inside the finger, against its inner face.
    pub fn pad_box(&self, side: f64, opening_m: f64) -> (Vector3<f64>, Vector3<f64>) {
        let half = Vector3::new(
            self.pad.thickness_m * 0.5,
            self.finger_size_m[1] * 0.5,
            self.pad.length_m * 0.5,
        );
        let center = Vector3::new(side * (opening_m * 0.5 + self.pad.thickness_m * 0.5), 0.0, 0.0);
        (half, center)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_is_valid_and_round_trips_through_json() {
        let g = Gripper::default_parallel_jaw();
        g.validate().unwrap();
        let back = Gripper::from_json(&g.to_json()).unwrap();
        assert_eq!(back, g);
        assert!(g.max_opening_m > 0.103, "the 102 mm can must fit");
    }

    #[test]
    fn rejects_bad_values_with_the_field_name() {
        let g = Gripper::default_parallel_jaw();
        let mut v: serde_json::Value = serde_json::from_str(&g.to_json()).unwrap();
        v["finger_size_m"][2] = serde_json::json!(-0.06);
        let err = Gripper::from_json(&v.to_string()).unwrap_err().to_string();
        assert!(err.contains("finger_size_m[2]") && err.contains("positive"), "{err}");

        let mut bad = g.clone();
        bad.max_opening_m = f64::NAN;
        let err = bad.validate().unwrap_err().to_string();
        assert!(err.contains("max_opening_m") && err.contains("finite"), "{err}");

        let mut bad = g.clone();
        bad.pad.length_m = 0.2;
        assert!(bad.validate().unwrap_err().to_string().contains("pad.length_m"));

        let mut bad = g.clone();
        bad.palm_size_m[0] = 0.1;
        assert!(bad.validate().unwrap_err().to_string().contains("palm_size_m[0]"));

        let err = Gripper::from_json(r#"{"name": "x"}"#).unwrap_err().to_string();
        assert!(err.contains("missing field"), "{err}");
        let mut v: serde_json::Value = serde_json::from_str(&g.to_json()).unwrap();
        v["stroke"] = serde_json::json!(1.0);
        assert!(Gripper::from_json(&v.to_string()).is_err(), "unknown fields are rejected");
    }

    #[test]
    fn parts_are_where_the_frame_says() {
        let g = Gripper::default_parallel_jaw();
        // finger inner faces at +-opening/2, tips at the pad's far end
        let c = g.finger_center(1.0, 0.1);
        assert!((c.x - g.finger_half_extents().x - 0.05).abs() < 1e-12);
        assert!((c.z + g.finger_half_extents().z - g.tip_z_m()).abs() < 1e-12);
        // palm front face at the finger roots
        assert!((g.palm_center().z + g.palm_half_extents().z - g.root_z_m()).abs() < 1e-12);
        assert!((g.reach_m() - (g.tip_z_m() - g.root_z_m() - g.pad.length_m * 0.5)).abs() < 1e-12);
    }
}
