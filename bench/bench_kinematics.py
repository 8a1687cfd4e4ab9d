"""Forward kinematics with all errors: time per pose, against the seed's 0.088 ms and a baseline.

Baseline, run side by side in this process: the same chain evaluated pose by pose with one
4×4 product per factor (how a straightforward implementation would loop). Goal: ≤ 0.005 ms/pose.

    python bench/bench_kinematics.py [--poses 300] [--repeats 50]
"""

from __future__ import annotations

import argparse

import numpy as np
from timing import best_of

from tasks.machine.description import load_machine
from tasks.machine.kinematics import forward
from tasks.simulation.campaign_plan import CampaignPlan, five_axis_poses
from tasks.simulation.prototype_errors import load_prototype_errors

SEED_MS_PER_POSE = 0.088


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--poses", type=int, default=300)
    ap.add_argument("--repeats", type=int, default=50)
    args = ap.parse_args()
    machine = load_machine("prototype")
    errors = load_prototype_errors()
    cmds = five_axis_poses(machine, args.poses, CampaignPlan(), np.random.default_rng(0))

    def batched():
        return forward(machine, cmds, errors).tool_in_workpiece()

    def pose_by_pose():
        return [forward(machine, c, errors).tool_in_workpiece() for c in cmds]

    assert np.allclose(np.concatenate(pose_by_pose()), batched(), atol=1e-12)
    t_batch, _ = best_of(batched, args.repeats)
    t_loop, _ = best_of(pose_by_pose, max(3, args.repeats // 10))
    per_pose = 1e3 * t_batch / args.poses
    print(f"forward kinematics, {args.poses} poses, all PIGEs and PDGEs")
    print(f"  batched local PoE : {1e3 * t_batch:8.3f} ms total, {per_pose:.5f} ms/pose")
    print(f"  pose-by-pose      : {1e3 * t_loop:8.3f} ms total, {1e3 * t_loop / args.poses:.5f} ms/pose")
    print(f"  speed-up of batching over pose-by-pose: {t_loop / t_batch:.1f}x")
    print(f"  against the seed's {SEED_MS_PER_POSE} ms/pose: {SEED_MS_PER_POSE / per_pose:.1f}x faster "
          f"(goal <= 0.005 ms/pose: {'met' if per_pose <= 0.005 else 'NOT met'})")


if __name__ == "__main__":
    main()
