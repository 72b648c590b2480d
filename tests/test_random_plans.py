"""Random calibration plans (``identify.random_plans``) and their names (``named_plans``):
seeded, within the limits and speeds, admissible on the model, on built-in and generated arms.
"""

import math

import numpy as np
import pytest
from odd_arms import serial_arm

import jaxcomp
from jaxcomp.errors import InputError
from jaxcomp.identify.named_plans import check_plan_name, named_plan, plan_count, random_count
from jaxcomp.identify.plan import LIMIT_MARGIN, arm_pose
from jaxcomp.identify.plan_checks import plan_issues
from jaxcomp.identify.plan_design import inner_limits
from jaxcomp.identify.random_plans import HOLDS, plan_limits, plan_seed, random_plan
from jaxcomp.robot_params import arm_joint_indices
from jaxcomp.studies.calibration_settings import world_groups


@pytest.fixture(scope="module")
def odd_arm(tmp_path_factory):
    """A generated 5-joint arm with continuous joints 0 and 2."""
    path = tmp_path_factory.mktemp("odd") / "odd.xml"
    path.write_text(serial_arm(3, n=5, continuous=(0, 2)))
    return jaxcomp.load_robot(path)


@pytest.mark.parametrize("name", ["gen3_lite", "gen3", "wx250s", "odd"])
def test_random_plans_are_seeded_within_their_ranges_and_admissible(name, odd_arm):
    robot = odd_arm if name == "odd" else jaxcomp.load_robot(name)
    limits = plan_limits(robot)
    n = len(limits)
    raw = robot.joint_limits[arm_joint_indices(robot)]
    continuous = ~np.isfinite(raw).all(axis=1)
    assert continuous.any() == (name in ("gen3", "odd"))
    np.testing.assert_array_equal(
        limits[continuous], np.tile([-math.pi, math.pi], (continuous.sum(), 1))
    )
    inner = inner_limits(limits)
    mid, half = limits.mean(axis=1), 0.4 * (limits[:, 1] - limits[:, 0])
    plans = [random_plan(robot, seed) for seed in range(3)]
    assert random_plan(robot, 1) == plans[1]  # the same seed: the same plan
    assert plans[0] != plans[1] != plans[2]
    for plan in plans:
        assert plan.validate(robot) is plan
        joints = [s.joint for s in plan.sweeps]
        chosen = set(joints)
        assert math.ceil(n / 2) <= len(chosen) <= n
        assert all(joints.count(j) == HOLDS for j in chosen)  # each from HOLDS held poses
        holds = {j: [s.hold.tolist() for s in plan.sweeps if s.joint == j] for j in chosen}
        assert all(h[0] != h[1] for h in holds.values())
        assert plan.move_speed == pytest.approx(math.radians(55)) and plan.settle == 0.2
        assert plan.ramp == 0.25
        for s in plan.sweeps:
            assert math.radians(10) <= s.speed <= math.radians(40)
            lo, hi = inner[s.joint]
            assert lo <= s.lower < s.upper <= hi
            span = s.upper - s.lower
            assert min(math.radians(90), hi - lo) - 1e-12 <= span <= math.radians(200) + 1e-12
            held = np.arange(n) != s.joint
            assert np.all(np.abs(s.hold - mid)[held] <= half[held] + 1e-12)
            assert np.all(s.hold[held] > raw[held, 0] + LIMIT_MARGIN)
            assert np.all(s.hold[held] < raw[held, 1] - LIMIT_MARGIN)
        # the model finds nothing wrong with any sweep or transfer from the idle pose
        assert plan_issues(robot, plan, start=arm_pose(robot)) == []
    # over several seeds: subsets of different sizes, in random order
    more = plans + [random_plan(robot, seed) for seed in range(3, 8)]
    assert len({len(p) for p in more}) > 1
    assert any(p.joints != sorted(p.joints) for p in more)
    assert set().union(*(p.joints for p in more)) == set(range(n))


def test_random_plan_refuses_what_cannot_be_drawn():
    robot = jaxcomp.load_robot("gen3_lite")
    with pytest.raises(InputError, match=r"no admissible sweep of joint \d .* N m"):
        random_plan(robot, 0, effort_fraction=0.01, attempts=2)
    with pytest.raises(InputError, match="speeds must be"):
        random_plan(robot, 0, speeds=(0.0, 0.5))
    with pytest.raises(InputError, match="hold_fraction"):
        random_plan(robot, 0, hold_fraction=1.5)
    # unchecked, any draw within the limits will do
    plan = random_plan(robot, 0, check=False, speeds=(0.5, 0.5), spans=(1.0, 1.0))
    assert all(s.speed == 0.5 and s.upper - s.lower == pytest.approx(1.0) for s in plan.sweeps)


def test_random_plan_names():
    robot = jaxcomp.load_robot("gen3_lite")
    assert (random_count("random"), random_count("random:3"), random_count("short")) == (1, 3, None)
    assert plan_count("random:4") == 4 and plan_count("default") == 1
    for good in ("random", "random:1", "random:12"):
        check_plan_name(good)
    for bad in ("random:0", "random:x", "random:", "random:-1"):
        with pytest.raises(InputError, match="random:K needs an integer K >= 1"):
            check_plan_name(bad)
    with pytest.raises(InputError, match="--plan must be one of default, short, random"):
        check_plan_name("randomly")
    seeds = {plan_seed(5, g) for g in range(3)} | {plan_seed(6, 0)}
    assert len(seeds) == 4
    assert named_plan(robot, "random:2", seed=5, group=1) == random_plan(robot, plan_seed(5, 1))
    assert named_plan(robot, "random", seed=5) == random_plan(robot, plan_seed(5, 0))
    with pytest.raises(InputError, match="no group 2"):
        named_plan(robot, "random:2", group=2)
    assert world_groups(7, 3) == [range(0, 3), range(3, 5), range(5, 7)]
    assert world_groups(4, 4) == [range(k, k + 1) for k in range(4)]
