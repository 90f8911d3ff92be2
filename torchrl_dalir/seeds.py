"""Seed ranges: data generation and evaluation never share a seed.

Data-generation seeds lie in ``[0, EVAL_SEED_START)``; evaluation episode ``i`` of evaluation
seed ``s`` resets with ``EVAL_SEED_START + s * EVAL_EPISODES_PER_SEED + i``.
"""

EVAL_SEED_START = 1_000_000_000
EVAL_EPISODES_PER_SEED = 10_000


def check_data_seed(seed: int) -> int:
    if not 0 <= seed < EVAL_SEED_START:
        raise ValueError(f"data-generation seeds must lie in [0, {EVAL_SEED_START}); got {seed}")
    return seed


def check_eval_seed(seed: int, name: str = "evaluation seed") -> int:
    """Refuses a negative evaluation seed: its episodes would reset with data-generation seeds
    (below ``EVAL_SEED_START``), so a policy would be tested on the episodes it learned from."""
    if seed < 0:
        raise ValueError(
            f"{name} must be at least 0, got {seed}: evaluation seed {seed} resets its episodes with seeds below "
            f"{EVAL_SEED_START}, the data-generation seeds (use another non-negative seed for other episodes)"
        )
    return seed


def eval_episode_seed(seed: int, episode: int) -> int:
    """The reset seed of evaluation episode ``episode`` under evaluation seed ``seed``."""
    check_eval_seed(seed)
    if not 0 <= episode < EVAL_EPISODES_PER_SEED:
        raise ValueError(f"at most {EVAL_EPISODES_PER_SEED} evaluation episodes per seed")
    return EVAL_SEED_START + seed * EVAL_EPISODES_PER_SEED + episode
