#!/usr/bin/env python3
"""Pairs two `pregrasp eval` runs of the same sequences frame by frame (e.g. the dense reference
and the sparse step): the share of frames whose top mode differs, and the paired difference of
the truth's log-likelihood (B - A) with a bootstrap interval over sequences.

Usage: scripts/pair_runs.py A/frames.json B/frames.json [--baseline C/frames.json] [--mode-deg 15] [--boot 10000]

A frame's top modes "differ" when the two estimates are more than --mode-deg apart and not
both within --mode-deg of the truth modulo the object's symmetries (so a can's spin about its
axis is no difference); the test is conservative for symmetric objects. It is also reported
over the frames where A is confident (entropy under half of a uniform histogram's,
--uniform-entropy): where A is nearly flat its top mode is arbitrary; and over the frames
where either run is confident (a run that commits to an orientation the other does not share
is a different answer; two nearly flat histograms both answer "not known"). The differing
frames are split by which run is within --mode-deg of the truth (A only, B only, neither), and
`b_wrong_where_a_right_share` is the share of A's right frames where B is wrong: the loss a
replacement of A by B would cause.

With --baseline C/frames.json (A run again with another filter seed), the same figures of A
against C over the frames all three runs share, and the per-sequence differences (B against A)
- (C against A) of the differing share and of the share of A's right frames lost, with
bootstrap intervals over sequences: a particle filter moves its own top mode between seeds, and
B answers as A does when it differs from A no more than A differs from itself.
"""
import argparse
import json
import math
import random


def frames(path):
    out = {}
    for trace in json.load(open(path)):
        for f in trace["frames"]:
            e = f.get("errors")
            if e is None:
                continue
            out[(trace["sequence"], trace["object"], f["frame_id"])] = e
    return out


def angle_deg(q1, q2):
    d = abs(sum(a * b for a, b in zip(q1, q2)))
    return math.degrees(2 * math.acos(min(1.0, d)))


def boot_mean(values, rng, n):
    """Mean of `values` (one per sequence) and its 95 % bootstrap interval over sequences."""
    mean = sum(values) / len(values)
    boots = sorted(sum(rng.choice(values) for _ in values) / len(values) for _ in range(n))
    return mean, [boots[int(0.025 * n)], boots[int(0.975 * n) - 1]]


def compare(a, b, keys, args):
    """A against B over `keys`: the summary and, per sequence, (frames, differing frames, A's
    right frames, of those B wrong, mean log-likelihood difference B - A)."""
    differ = 0
    confident, differ_confident = 0, 0
    either, differ_either = 0, 0
    # of the differing frames: only A within --mode-deg of the truth, only B, neither
    only_a_right, only_b_right, neither_right = 0, 0, 0
    a_right = 0
    differ_by_object = {}
    per_seq = {}
    for k in keys:
        ea, eb = a[k], b[k]
        qa, qb = ea.get("estimate_xyzw"), eb.get("estimate_xyzw")
        both_right = ea["symmetric_error_deg"] < args.mode_deg and eb["symmetric_error_deg"] < args.mode_deg
        if qa is not None and qb is not None:
            apart = angle_deg(qa, qb) > args.mode_deg
        else:
            apart = abs(ea["symmetric_error_deg"] - eb["symmetric_error_deg"]) > args.mode_deg
        d = apart and not both_right
        differ += d
        ra, rb = (e["symmetric_error_deg"] < args.mode_deg for e in (ea, eb))
        a_right += ra
        if d:
            only_a_right += ra and not rb
            only_b_right += rb and not ra
            neither_right += not ra and not rb
        # A (the reference) confident: its entropy under half of uniform's
        sure = [e.get("rotation_entropy") is not None and e["rotation_entropy"] < 0.5 * args.uniform_entropy for e in (ea, eb)]
        if sure[0]:
            confident += 1
            differ_confident += d
        if sure[0] or sure[1]:
            either += 1
            differ_either += d
        o = differ_by_object.setdefault(k[1], [0, 0])
        o[0] += d
        o[1] += 1
        seq = per_seq.setdefault(k[0], {"frames": 0, "differ": 0, "a_right": 0, "lost": 0, "ll": []})
        seq["frames"] += 1
        seq["differ"] += d
        seq["a_right"] += ra
        seq["lost"] += ra and not rb
        la, lb = ea.get("gt_orientation_loglik"), eb.get("gt_orientation_loglik")
        if la is not None and lb is not None:
            seq["ll"].append(lb - la)
    rng = random.Random(args.seed)
    seq_means = [sum(v["ll"]) / len(v["ll"]) for v in per_seq.values() if v["ll"]]
    mean, ci = boot_mean(seq_means, rng, args.boot)
    summary = {
        "frames_paired": len(keys),
        "sequences": len(per_seq),
        "top_mode_differs_share": differ / len(keys),
        "a_confident_share": confident / len(keys),
        "top_mode_differs_where_a_confident_share": differ_confident / max(confident, 1),
        "either_confident_share": either / len(keys),
        "top_mode_differs_where_either_confident_share": differ_either / max(either, 1),
        "differing_frames_only_a_right_only_b_right_neither": [only_a_right, only_b_right, neither_right],
        "a_right_share": a_right / len(keys),
        "b_wrong_where_a_right_share": only_a_right / max(a_right, 1),
        "top_mode_differs_by_object": {o: v[0] / v[1] for o, v in sorted(differ_by_object.items())},
        "loglik_diff_b_minus_a_mean": mean,
        "loglik_diff_95ci": ci,
        "a_mean_symmetric_error_deg": sum(a[k]["symmetric_error_deg"] for k in keys) / len(keys),
        "b_mean_symmetric_error_deg": sum(b[k]["symmetric_error_deg"] for k in keys) / len(keys),
    }
    return summary, per_seq


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("--baseline", help="A run again with another filter seed (frames.json)")
    ap.add_argument("--mode-deg", type=float, default=15.0)
    ap.add_argument("--boot", type=int, default=10000)
    ap.add_argument("--seed", type=int, default=1)
    # entropy (nats) of a uniform histogram on the grid (RotationGrid::uniform_entropy; 5 deg)
    ap.add_argument("--uniform-entropy", type=float, default=11.9938)
    args = ap.parse_args()
    a, b = frames(args.a), frames(args.b)
    keys = sorted(set(a) & set(b))
    if not keys:
        raise SystemExit("no frame in common")
    summary, _ = compare(a, b, keys, args)
    out = {"b_against_a": summary}
    if args.baseline:
        c = frames(args.baseline)
        common = sorted(set(keys) & set(c))
        if not common:
            raise SystemExit("the baseline shares no frame with A and B")
        ab, ab_seq = compare(a, b, common, args)
        ac, ac_seq = compare(a, c, common, args)
        rng = random.Random(args.seed)
        seqs = sorted(ab_seq)
        diff_share = [ab_seq[q]["differ"] / ab_seq[q]["frames"] - ac_seq[q]["differ"] / ac_seq[q]["frames"] for q in seqs]
        lost = [(ab_seq[q]["lost"] - ac_seq[q]["lost"]) / ab_seq[q]["frames"] for q in seqs]
        d_mean, d_ci = boot_mean(diff_share, rng, args.boot)
        l_mean, l_ci = boot_mean(lost, rng, args.boot)
        out["on_the_baselines_frames"] = {
            "b_against_a": ab,
            "baseline_against_a": ac,
            "differs_share_b_minus_baseline": d_mean,
            "differs_share_b_minus_baseline_95ci": d_ci,
            "right_frames_lost_share_b_minus_baseline": l_mean,
            "right_frames_lost_share_b_minus_baseline_95ci": l_ci,
        }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
