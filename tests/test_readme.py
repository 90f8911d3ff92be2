"""The README's python blocks marked ``<!-- tested -->`` run as written (on a smoke-size run)."""

import re
from pathlib import Path

import torch

from torchrl_dalir import keys
from torchrl_dalir.reranking import CANDIDATE_SCORES, CHOSEN_CANDIDATE

README = Path(__file__).resolve().parent.parent / "README.md"


def _tested_blocks() -> list[str]:
    return re.findall(r"<!-- tested -->\n```python\n(.*?)```", README.read_text(), flags=re.S)


@torch.no_grad()
def test_readme_torchrl_loop_runs(trained_world_model):
    _, world_model_checkpoint, policy_checkpoint = trained_world_model
    (block,) = _tested_blocks()
    namespace = {"policy_checkpoint": policy_checkpoint, "world_model_checkpoint": world_model_checkpoint}
    exec(compile(block, str(README), "exec"), namespace)
    rollout, td, loss = namespace["rollout"], namespace["td"], namespace["loss"]
    namespace["env"].close()
    assert rollout[keys.ACTION].shape == (16, 4) and rollout[CANDIDATE_SCORES].shape == (16, 8)
    # the imagined outcome of the first 8 executed actions is the score the actor gave the chunk it chose
    chosen = rollout[CHOSEN_CANDIDATE][0]
    torch.testing.assert_close(
        torch.sigmoid(td[keys.COMPLETION_LOGIT][0]), rollout[CANDIDATE_SCORES][0, chosen], atol=1e-5, rtol=0
    )
    assert loss.in_keys == [keys.POINT_CLOUD, keys.AGENT_POS, "dense_reward_target"]
    batch = namespace["batch"]
    assert batch[keys.ACTION].shape == (2, 16, 4) and batch[CANDIDATE_SCORES].shape == (2, 16, 8)
