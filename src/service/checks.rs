//! What the service checks on every input, whatever the transport brings it (HTTP today, a ROS
//! bridge tomorrow): ids and names usable as keys, poses within reach.

use super::error::ServiceError;
use crate::geometry::Pose;

/// Farthest position accepted anywhere (poses, planes), metres from the frame's origin.
pub const MAX_POSITION_M: f64 = 1_000.0;

/// At most 64 characters of `s` for an error message (a client's string is not echoed whole).
pub fn shorten(s: &str) -> String {
    let mut out: String = s.chars().take(64).filter(|c| !c.is_control()).collect();
    if s.chars().count() > 64 {
        out.push_str("...");
    }
    out
}

/// Checks a display name: at most `max_chars` characters, no control characters.
pub fn check_name(name: &str, max_chars: usize) -> Result<(), ServiceError> {
    if name.chars().count() > max_chars || name.chars().any(char::is_control) {
        return Err(ServiceError::Invalid(format!(
            "name '{}' must be at most {max_chars} characters without control characters",
            shorten(name)
        )));
    }
    Ok(())
}

/// Checks that an id is usable in a URL path and as a store key.
pub fn check_id(kind: &str, id: &str) -> Result<(), ServiceError> {
    let ok = !id.is_empty()
        && id.len() <= 64
        && id
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-' || c == '.');
    if ok {
        Ok(())
    } else {
        Err(ServiceError::Invalid(format!(
            "{kind} id '{}' must be 1-64 characters of A-Z, a-z, 0-9, '_', '-', '.'",
            shorten(id)
        )))
    }
}

/// Checks a pose from any transport: finite, and its position within [`MAX_POSITION_M`] of
/// the frame's origin (`what` names it in the error).
pub fn check_pose(what: &str, p: &Pose) -> Result<(), ServiceError> {
    let t = p.translation.vector;
    let finite = t.iter().chain(p.rotation.coords.iter()).all(|v| v.is_finite());
    if !finite || t.norm() > MAX_POSITION_M {
        return Err(ServiceError::Invalid(format!(
            "{what}: a pose needs finite numbers and a position within {MAX_POSITION_M} m of the origin"
        )));
    }
    Ok(())
}
