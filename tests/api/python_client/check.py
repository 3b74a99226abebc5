"""Calls a running pregrasp server through the client generated from openapi/openapi.json.

Run by tests/api/python_client.rs: `python check.py BASE_URL OBJECT_ID WORLD_FROM_OBJECT_JSON`.
Every call goes through the generated, typed functions; each answer must parse into its
model (never None, never a raw dict). Prints a JSON summary for the Rust side to compare with
what it reads over plain HTTP.
"""

import json
import sys

from pregrasp_client import Client
from pregrasp_client.api.cameras import list_cameras
from pregrasp_client.api.decisions import post_decision
from pregrasp_client.api.grippers import get_gripper
from pregrasp_client.api.health import healthz
from pregrasp_client.api.objects import get_object
from pregrasp_client.api.scene import get_scene
from pregrasp_client.api.tracks import get_track, start_track
from pregrasp_client.models import (
    DecisionRequest,
    DecisionView,
    GripperRecord,
    Health,
    ObjectInfo,
    PoseDto,
    Problem,
    Scene,
    StartTrackRequest,
    TrackView,
    Verdict,
)


def expect(value, model, what):
    if not isinstance(value, model):
        raise SystemExit(f"{what}: expected {model.__name__}, got {value!r}")
    return value


def main():
    base, object_id, prior = sys.argv[1], sys.argv[2], json.loads(sys.argv[3])
    client = Client(base_url=base, raise_on_unexpected_status=True, timeout=60.0)
    with client as c:
        health = expect(healthz.sync(client=c), Health, "healthz")
        cameras = list_cameras.sync(client=c)
        obj = expect(get_object.sync(client=c, id=object_id), ObjectInfo, "object")
        gripper = expect(get_gripper.sync(client=c, id="default"), GripperRecord, "gripper")
        scene = expect(get_scene.sync(client=c), Scene, "scene")
        started = expect(
            start_track.sync(
                client=c,
                body=StartTrackRequest(
                    object_id=object_id,
                    world_from_object=PoseDto.from_dict(prior),
                    translation_std_m=0.02,
                    rotation_std_deg=20.0,
                ),
            ),
            TrackView,
            "start_track",
        )
        track = expect(get_track.sync(client=c, id=started.id), TrackView, "get_track")
        decision = expect(
            post_decision.sync(client=c, id=track.id, body=DecisionRequest(n_samples=200, threshold=0.8)),
            DecisionView,
            "decision",
        )
        if decision.decision not in (Verdict.GRASP, Verdict.OBSERVE):
            raise SystemExit(f"verdict {decision.decision!r}")
        # errors parse into the Problem model with their status
        missing = expect(get_track.sync(client=c, id=999_999), Problem, "unknown track")
        bad = expect(
            post_decision.sync(client=c, id=track.id, body=DecisionRequest(threshold=1.5)),
            Problem,
            "bad threshold",
        )
        # the track now carries its decision, typed
        track = expect(get_track.sync(client=c, id=started.id), TrackView, "get_track after the decision")
        carried = expect(track.decision, DecisionView, "track.decision")
    summary = {
        "health_status": health.status,
        "cameras": sorted(cam.id for cam in cameras),
        "object_hash": obj.content_hash,
        "gripper_max_opening_m": gripper.gripper.max_opening_m,
        "scene_cameras": len(scene.cameras),
        "track_id": track.id,
        "track_object": track.object_id,
        "verdict": decision.decision.value,
        "p_success": decision.p_success,
        "stamp_ns": decision.stamp_ns,
        "reference_from_gripper": decision.reference_from_gripper.to_dict(),
        "base_from_gripper": decision.base_from_gripper.to_dict(),
        "world_from_gripper": decision.world_from_gripper.to_dict(),
        "n_candidates": len(decision.candidates),
        "carried_p_success": carried.p_success,
        # the calibration behind p_success and the rule, as typed enums
        "calibration_state": decision.calibration.state.value,
        "running_settings_hash": decision.calibration.running_settings_hash,
        "rule_quantity": decision.rule.quantity.value,
        "rule_threshold": decision.rule.threshold,
        "p_success_raw": decision.p_success_raw,
        "missing_status": missing.status,
        "bad_status": bad.status,
    }
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
