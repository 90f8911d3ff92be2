"""Data-parallel training (issue 19, item 2): two CPU processes with gloo train like one on the
same global batch, only rank 0 writes, and an interrupted two-process run resumes exactly."""

import os
import socket
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import NestedKey, TensorDict

from torchrl_dalir.checkpoints import load_policy
from torchrl_dalir.checkpoints.files import safe_torch_load
from torchrl_dalir.objectives.common import KeyedLossModule
from torchrl_dalir.training import distributed
from torchrl_dalir.training.loop import OptimConfig, fit
from torchrl_dalir.utils import weights_digest

REPO = Path(__file__).resolve().parents[1]
BATCH = 8  # the global batch
STEPS = 6
OPTIM = OptimConfig(lr=0.05, warmup_steps=0)
# Features and targets of a linear regression with a known answer.
X = torch.linspace(-1, 1, 64 * 3).reshape(64, 3).sin()
DATA = TensorDict({"x": X, "y": X @ torch.tensor([[1.0], [-2.0], [0.5]]) + 0.3}, [64])


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class RegressionLoss(KeyedLossModule):
    """Mean squared error of a linear model; with ``noise``, its inputs are jittered by torch's
    global generator (a loss with internal random draws, like flow matching's)."""

    @dataclass
    class _AcceptedKeys:
        x: NestedKey = "x"
        y: NestedKey = "y"

    default_keys = _AcceptedKeys
    out_keys = ["loss_mse"]

    def __init__(self, model: torch.nn.Module, noise: float = 0.0):
        super().__init__()
        self.model, self.noise, self.rows_seen = model, noise, 0

    def forward(self, td):
        self.rows_seen += td.shape[0]
        x = td[self.tensor_keys.x]
        x = x + self.noise * torch.randn_like(x)
        return TensorDict({"loss_mse": ((self.model(x) - td[self.tensor_keys.y]) ** 2).mean()}, [])


class Interrupted(Exception):
    pass


def _train(path: Path, noise: float = 0.0, stop_at: int | None = None) -> None:
    """``STEPS`` steps of :func:`fit` on a linear model (the same initial weights every time),
    checkpointing every 3 steps (with the rows the writing rank's loss has seen); with ``stop_at``,
    the batch draw of that step raises (a crash)."""
    torch.manual_seed(0)
    model = torch.nn.Linear(3, 1)
    loss = RegressionLoss(model, noise)
    draws = 0

    def next_batch(generator):
        nonlocal draws
        draws += 1
        if draws == stop_at:
            raise Interrupted
        return DATA[torch.randint(len(DATA), (BATCH,), generator=generator)]

    try:
        fit(
            loss,
            model,
            next_batch,
            STEPS,
            OPTIM,
            path,
            lambda ema: {"rows_seen": loss.rows_seen},
            seed=3,
            checkpoint_every=3,
            progress=False,
        )
    except Interrupted:
        pass


def _two_rank_runs(rank: int, port: int, folder: Path) -> None:
    """One of two gloo processes, joined as torchrun would join them: every 2-rank training of the tests."""
    os.environ.update(
        MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), LOCAL_RANK=str(rank), WORLD_SIZE="2"
    )
    torch.set_num_threads(1)
    distributed.setup("cpu")
    _train(folder / "deterministic.pt")
    _train(folder / "noisy.pt", noise=0.1)
    _train(folder / "resumed.pt", noise=0.1, stop_at=5)  # crashes after the step-3 checkpoint...
    _train(folder / "resumed.pt", noise=0.1)  # ... and resumes from it
    distributed.teardown()


@pytest.fixture(scope="module")
def two_ranks(tmp_path_factory):
    """The checkpoints of the 2-process trainings (one spawn of two processes for all of them)."""
    folder = tmp_path_factory.mktemp("two_ranks")
    torch.multiprocessing.spawn(_two_rank_runs, args=(_free_port(), folder), nprocs=2)
    return folder


def test_two_ranks_at_half_the_batch_take_the_steps_of_one_rank(two_ranks, tmp_path):
    _train(tmp_path / "one_rank.pt")  # this process: no torchrun, one rank on the whole batch
    one, two = safe_torch_load(tmp_path / "one_rank.pt"), safe_torch_load(two_ranks / "deterministic.pt")
    torch.manual_seed(0)
    initial = torch.nn.Linear(3, 1).state_dict()
    for name, value in one["model"].items():
        assert not torch.allclose(value, initial[name])  # the steps moved the weights...
        torch.testing.assert_close(two["model"][name], value, rtol=0, atol=1e-6)  # ... the same way on 2 ranks
    assert one["step"] == two["step"] == STEPS
    assert torch.equal(one["generator"], two["generator"])  # the same global batches were drawn...
    assert one["rows_seen"] == 2 * two["rows_seen"] == STEPS * BATCH  # ... and each rank trained on half of each


def test_interrupted_two_ranks_resume_exactly(two_ranks):
    straight, resumed = safe_torch_load(two_ranks / "noisy.pt"), safe_torch_load(two_ranks / "resumed.pt")
    ranks = straight["rank_torch_rng"]
    assert len(ranks) == 2 and not torch.equal(ranks[0], ranks[1])  # each rank draws its own noise
    for entry in ("model", "ema"):
        for name, value in straight[entry].items():
            assert torch.equal(resumed[entry][name], value), (entry, name)
    for a, b in zip(straight["rank_torch_rng"], resumed["rank_torch_rng"]):
        assert torch.equal(a, b)


def _smoke_demos(root: Path) -> Path:
    """A small reach dataset (4-D actions, as the task's) written without a simulator, through DP3's
    zarr layout: four episodes of the same smooth actions, in noisy point clouds."""
    rng = np.random.default_rng(0)
    episodes = []
    for _ in range(4):
        t = np.linspace(0, 1, 20, dtype=np.float32)[:, None]
        offset = rng.uniform(-1, 1, (1, 4)).astype(np.float32)
        cloud = rng.normal(size=(20, 64, 3)).astype(np.float32) + t[:, :, None]
        episodes.append(
            {
                "point_cloud": cloud,
                "state": np.concatenate([t, offset.repeat(20, 0)], 1),
                "action": np.sin(3 * t + np.arange(4, dtype=np.float32)),
            }
        )
    from torchrl_dalir.data import import_dp3_zarr, write_dp3_zarr

    import_dp3_zarr(
        write_dp3_zarr(root / "store.zarr", episodes), root / "data" / "reach" / "demos", task="reach", num_points=64
    )
    return root / "data"


def test_torchrun_two_processes_train_a_smoke_policy(tmp_path):
    pytest.importorskip("zarr")
    data, out = _smoke_demos(tmp_path), tmp_path / "out"
    command = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--nproc_per_node=2",
        f"--master_port={_free_port()}",
        str(REPO / "examples" / "train_policy.py"),
        "preset=smoke",
        "task=reach",
        f"data={data}",
        f"out={out}",
        "progress=false",
        "log_every=1",
    ]
    env = {
        **os.environ,
        "OMP_NUM_THREADS": "1",
        "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
    }
    done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.count("trained fm on reach") == 1  # only rank 0 reports
    run = out / "reach" / "fm_seed0"
    state = safe_torch_load(run / "checkpoint.pt")
    assert state["step"] == 30 and len(state["rank_torch_rng"]) == 2  # written by a 2-rank training
    policy = load_policy(run / "checkpoint.pt", task="reach")
    assert weights_digest(policy) == weights_digest(load_policy(run / "checkpoint.pt", task="reach"))
    [log_dir] = (run / "logs").iterdir()  # one logger: rank 0's
    losses = [
        float(line.split(",")[1]) for line in (log_dir / "scalars" / "loss_flow_matching.csv").read_text().split()
    ]
    assert len(losses) == 30 and np.mean(losses[-10:]) < 0.85 * np.mean(losses[:3]), losses  # 1.73 -> 1.33 here


def test_a_global_batch_that_does_not_split_over_the_ranks_is_refused(monkeypatch):
    from torchrl_dalir.config import parse_config
    from torchrl_dalir.training import POLICY_PRESETS, PolicyTrainingConfig

    monkeypatch.setenv("WORLD_SIZE", "3")
    with pytest.raises(ValueError, match="batch_size=8 is the global batch and cannot be split over 3 processes"):
        parse_config(PolicyTrainingConfig, ["preset=smoke", "task=reach"], POLICY_PRESETS)
