"""Per-episode seeds (lq_ros/core/seeding.py)."""

from __future__ import annotations

from lq_ros.core.seeding import LEROBOT_SEED_TAG, episode_seed, policy_seed


def test_each_episode_of_a_cell_gets_its_own_seed_and_a_rerun_the_same():
    cell = {(task, init): episode_seed(7, "libero_spatial", task, init, LEROBOT_SEED_TAG)
            for task in range(10) for init in range(50)}  # fmt: skip
    assert len(set(cell.values())) == len(cell)  # 500 episodes, 500 seeds
    assert all(0 <= seed < 2**32 for seed in cell.values())
    assert episode_seed(7, "libero_spatial", 3, 4, LEROBOT_SEED_TAG) == cell[3, 4]
    assert episode_seed(8, "libero_spatial", 3, 4, LEROBOT_SEED_TAG) != cell[3, 4]  # the run seed counts
    assert episode_seed(7, "libero_object", 3, 4, LEROBOT_SEED_TAG) != cell[3, 4]  # and the suite


def test_the_row_records_the_seed_only_for_a_policy_seeded_per_episode():
    config = {"seed": 7, "suite": "libero_goal", "task": 2, "init": 9}
    assert policy_seed(config, {"seeding": "episode"}) == episode_seed(7, "libero_goal", 2, 9, LEROBOT_SEED_TAG)
    assert policy_seed(config, {}) is None
