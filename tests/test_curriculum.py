"""The tolerance curriculum: levels, graduation, and a window free of the episode-length bias."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from train.curriculum import GRADUATION_RATE, LEVELS, WINDOW, Curriculum


def test_levels_follow_the_paper_table():
    assert len(LEVELS) == 22
    np.testing.assert_allclose(LEVELS[0], (0.10, 0.20))
    np.testing.assert_allclose(LEVELS[-1], (0.01, 0.05))
    assert np.all(np.diff(LEVELS[:, 0]) < 0) and np.all(np.diff(LEVELS[:, 1]) <= 0)


def _run(curriculum, outcomes_per_step):
    record = jax.jit(Curriculum.record)
    for ended, success in outcomes_per_step:
        curriculum = record(curriculum, np.asarray(ended), np.asarray(success))
    return curriculum


@pytest.mark.parametrize("num_envs", [1, 4, 64, 256])
def test_graduates_after_a_full_window_at_the_rate(num_envs):
    """Every environment fills ceil(100 / E) episodes: at >= 70% success the level rises
    (and the window restarts); below it, or before the window is full, it does not."""
    per_env = -(-WINDOW // num_envs)
    all_end = np.ones(num_envs, bool)
    good = [(all_end, np.arange(num_envs) % 10 < 8)] * per_env  # 80% success
    bad = [(all_end, np.arange(num_envs) % 10 < 5)] * per_env  # 50% success (where E >= 10)
    promoted = _run(Curriculum.start(num_envs), good)
    assert int(promoted.level) == 1 and int(promoted.count.sum()) == 0
    almost = _run(Curriculum.start(num_envs), good[:-1])
    assert int(almost.level) == 0
    if num_envs >= 10:
        assert int(_run(Curriculum.start(num_envs), bad).level) == 0
    top = _run(Curriculum.start(num_envs, level=len(LEVELS) - 1), good)
    assert int(top.level) == len(LEVELS) - 1  # the last level stays


def test_window_is_free_of_the_episode_length_bias():
    """64 environments at a new level, each mid-episode; every episode is a success with
    probability 0.5 that ends after 14 steps, or a failure that times out after 200. Among
    the first 100 episodes to end ~78% are successes (a shared window of the latest
    episodes graduates a policy that succeeds half the time); the per-environment window
    waits for every environment's share, measures ~50% and does not graduate."""
    rng = np.random.default_rng(0)
    num_envs = 64
    new_success = rng.random(num_envs) < 0.5
    remaining, outcome = (rng.random(num_envs) * np.where(new_success, 14, 200)).astype(int) + 1, new_success
    curriculum, record = Curriculum.start(num_envs), jax.jit(Curriculum.record)
    ended_order = []
    for _ in range(3000):
        remaining = remaining - 1
        ended = remaining == 0
        curriculum = record(curriculum, ended, outcome & ended)
        ended_order += outcome[ended].tolist()
        if len(ended_order) >= WINDOW and len(ended_order) - ended.sum() < WINDOW:
            assert np.mean(ended_order[:WINDOW]) > GRADUATION_RATE  # what the shared window would see
            assert not bool(np.all(curriculum.count >= curriculum.outcomes.shape[1]))  # ours: not full yet
        new_success = rng.random(num_envs) < 0.5
        outcome = np.where(ended, new_success, outcome)
        remaining = np.where(ended, np.where(new_success, 14, 200), remaining)
    assert int(curriculum.level) == 0
    assert abs(float(curriculum.success_rate) - 0.5) < 0.12


def test_rejects_bad_levels_and_sizes():
    with pytest.raises(ValueError, match="level"):
        Curriculum.start(4, level=22)
    with pytest.raises(ValueError, match="environment"):
        Curriculum.start(0)


def test_grouped_curriculum_graduates_each_group_on_its_own_episodes():
    """Two groups (e.g. one- and two-arm tasks) in 10 environments: the first succeeds on 80 %
    of its episodes and graduates, the second on 20 % and stays; one group of the same
    episodes (the paper's single curriculum) sees 50 % and does not graduate."""
    from train.curriculum import GroupedCurriculum

    num_envs = 10
    per_env = -(-WINDOW // num_envs)
    group = np.arange(num_envs) % 2  # even environments run group 0, odd ones group 1
    success = np.where(group == 0, np.arange(num_envs) % 10 < 8, np.arange(num_envs) % 10 < 3)  # 0,2,4,6 / 1 of 1,3,5,7,9
    record = jax.jit(GroupedCurriculum.record)
    grouped, single = GroupedCurriculum.start(num_envs, 2), GroupedCurriculum.start(num_envs, 1)
    for _ in range(2 * per_env):  # each environment records its share of its own group twice over
        grouped = record(grouped, np.ones(num_envs, bool), success, group)
        single = record(single, np.ones(num_envs, bool), success, np.zeros(num_envs, int))
    assert grouped.level.tolist() == [0, 0]  # odd environments never record group 0 episodes: not full
    grouped = GroupedCurriculum.start(num_envs, 2)
    for step in range(2 * per_env):  # environments alternate groups: every one fills both windows
        alternating = (group + step) % 2
        grouped = record(grouped, np.ones(num_envs, bool), np.where(alternating == 0, True, np.arange(num_envs) < 2), alternating)
    assert grouped.level.tolist() == [1, 0]
    np.testing.assert_allclose(np.asarray(grouped.tolerance), LEVELS[[1, 0]])
    assert int(single.level[0]) == 0 and abs(float(single.success_rate[0]) - 0.5) < 1e-6
    with pytest.raises(ValueError, match="group"):
        GroupedCurriculum.start(4, 0)
