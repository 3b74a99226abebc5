//! Grasp now or observe more? Draws poses from a track's distribution (from the worker's bank
//! when one is fresh, else from the tracker) and calls [`crate::grasp::decide`].

use super::ServiceState;
use super::decisions::{DecisionParams, DecisionRecord, Drawn, MAX_DECISION_SAMPLES};
use super::error::ServiceError;
use super::events::ServiceEvent;
use crate::grasp::{self, DecisionQuery, Grasp};
use std::sync::Arc;
use std::sync::atomic::Ordering;

impl ServiceState {
    /// Runs a decision for a track (blocking: call from a blocking context). The query is
    /// checked before the track is looked up.
    pub fn decide(&self, track_id: u64, params: &DecisionParams) -> Result<Arc<DecisionRecord>, ServiceError> {
        let gripper = self.gripper(&params.gripper)?;
        let n = params.n_samples;
        if n == 0 || n > MAX_DECISION_SAMPLES {
            return Err(ServiceError::Invalid(format!(
                "n_samples must be in 1..={MAX_DECISION_SAMPLES}, got {n}"
            )));
        }
        let threshold = params.threshold;
        if !(threshold > 0.0 && threshold <= 1.0) {
            return Err(ServiceError::Invalid(format!(
                "threshold must be in (0, 1], got {threshold}"
            )));
        }
        let plane_world = match &params.support_plane_world {
            Some(p) => Some(super::scene::validate_plane(p)?),
            None => self.support_plane(),
        };
        if !self.tracking.board().views.contains_key(&track_id) {
            return Err(ServiceError::not_found("track", track_id.to_string()));
        }
        self.decision_cache.note_interest(track_id, n);
        let bank = self.decision_cache.bank(track_id, n);
        // identical queries within one step share one answer (the samples are the same)
        let key = serde_json::to_string(&(params, &gripper)).unwrap_or_default();
        if let Some(b) = &bank
            && let Some(v) = self.decision_cache.answer(track_id, b.generation, &key)
        {
            self.metrics.decisions.fetch_add(1, Ordering::Relaxed);
            self.metrics.decisions_from_bank.fetch_add(1, Ordering::Relaxed);
            self.metrics.decisions_shared.fetch_add(1, Ordering::Relaxed);
            return Ok(v);
        }
        let drawn = match &bank {
            Some(b) => {
                self.metrics.decisions_from_bank.fetch_add(1, Ordering::Relaxed);
                let mut d = b.drawn.clone();
                d.samples.poses.truncate(n);
                d.samples.effective_sample_size = d.samples.effective_sample_size.min(n as f64);
                d
            }
            None => super::worker::draw_samples(self, track_id, n)?,
        };
        let object = self.grasp_objects.get_or_build(self, &drawn.object_id)?;
        let support_plane = plane_world.map(|p| p.transformed(&drawn.world_from_reference.inverse()));
        let query = DecisionQuery {
            n_samples: n,
            threshold,
            grasp: params
                .object_from_gripper
                .map(|p| Grasp::from_pose(&object, p, "client")),
            support_plane,
        };
        let d = grasp::decide(&object, &gripper, &drawn.reference_from_object, &drawn.samples, &query)?;
        let record = Arc::new(DecisionRecord {
            decision: d,
            stamp_ns: drawn.stamp_ns,
            world_from_reference: drawn.world_from_reference,
            base_from_reference: drawn.base_from_reference,
        });
        if let Some(b) = &bank {
            self.decision_cache
                .store_answer(track_id, b.generation, key, record.clone());
        }
        self.metrics.decisions.fetch_add(1, Ordering::Relaxed);
        self.tracking.set_decision(track_id, record.clone());
        self.publish(ServiceEvent::Decision {
            track_id,
            decision: record.clone(),
        });
        Ok(record)
    }

    /// Draws `n` poses from a track's distribution (blocking).
    pub fn draw_samples(&self, track_id: u64, n: usize) -> Result<Drawn, ServiceError> {
        if n == 0 || n > MAX_DECISION_SAMPLES {
            return Err(ServiceError::Invalid(format!(
                "n must be in 1..={MAX_DECISION_SAMPLES}, got {n}"
            )));
        }
        super::worker::draw_samples(self, track_id, n)
    }
}
