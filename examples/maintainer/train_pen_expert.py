"""Trains the Adroit Pen expert with TorchRL's PPO and writes ``torchrl_dalir/experts/weights/pen_expert.pt``.

    OMP_NUM_THREADS=1 python examples/maintainer/train_pen_expert.py seed=0

Training matches our evaluation protocol: an episode terminates at its first success and earns a
success bonus, so PPO maximises the any-step success rate instead of learning to hover. The
per-step shaping (pen-to-target distance and orientation gap, a drop penalty and a small
action-rate penalty for smooth demonstrations) is non-positive, so ending early by succeeding is
always better than lingering. Episodes are truncated at 200 steps and bootstrapped there.

Checkpoints go to ``run_dir`` every ``checkpoint_every`` iterations and a rerun of the same
command resumes from the last one. Every ``eval_every`` iterations the deterministic policy
(mean action) is scored on ``eval_episodes`` training-seed episodes; the best one is exported.
Overrides are ``key=value`` (``total_frames=200000 run_dir=/tmp/pen_smoke``).
"""

from __future__ import annotations

import csv
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from tensordict.nn import AddStateIndependentNormalScale, TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers import SamplerWithoutReplacement
from torchrl.envs import GymWrapper, SerialEnv, TransformedEnv, VecNorm
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE
from tqdm import tqdm

from torchrl_dalir.allocator import reuse_freed_memory
from torchrl_dalir.checkpoints import safe_torch_load, save_checkpoint
from torchrl_dalir.config import config_dict, parse_config
from torchrl_dalir.experts.adroit_pen import DEFAULT_WEIGHTS, OBS_DIM, PenExpertPolicy, make_actor_mlp


@dataclass
class PenTrainConfig:
    seed: int = 0
    num_envs: int = 16
    steps_per_env: int = 250  # frames per iteration = num_envs * steps_per_env
    total_frames: int = 2_000_000
    epochs: int = 10
    minibatch_size: int = 500
    lr: float = 3e-4
    anneal_lr: bool = True  # linear decay to 0 over total_frames
    clip_epsilon: float = 0.2
    gamma: float = 0.99
    lmbda: float = 0.95
    max_grad_norm: float = 0.5
    init_log_std: float = -0.5
    entropy_coeff: float = 0.0
    # reward
    success_bonus: float = 500.0  # with 50 (reward_scale 0.1) training success fell to ~0 by 0.28M frames
    drop_penalty: float = 5.0
    action_rate_coef: float = 0.05  # times the mean squared change of the action
    reward_scale: float = 0.02
    # bookkeeping
    eval_every: int = 25
    eval_episodes: int = 50
    checkpoint_every: int = 5
    run_dir: str = "outputs/pen_expert"
    output: str = str(DEFAULT_WEIGHTS)


class PenTrainingTask(gym.Wrapper):
    """AdroitHandPen-v1 with the training reward; terminates at the first success."""

    def __init__(self, env: gym.Env, cfg: PenTrainConfig):
        super().__init__(env)
        self.cfg = cfg
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (OBS_DIM,), np.float32)
        self._prev_action = None

    def reset(self, *, seed=None, options=None):
        obs, info = self.env.reset(seed=seed, options=options)
        self._prev_action = None
        return obs.astype(np.float32), info

    def step(self, action):
        action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        obs, _, terminated, truncated, info = self.env.step(action)
        raw = self.env.unwrapped
        obj_pos = raw.data.xpos[raw.obj_body_id]
        goal_distance = np.linalg.norm(obj_pos - raw.data.site_xpos[raw.eps_ball_site_id])
        obj_orien = (raw.data.site_xpos[raw.obj_t_site_id] - raw.data.site_xpos[raw.obj_b_site_id]) / raw.pen_length
        tar_orien = (raw.data.site_xpos[raw.tar_t_site_id] - raw.data.site_xpos[raw.tar_b_site_id]) / raw.tar_length
        orien_similarity = float(np.dot(obj_orien, tar_orien))
        success = bool(info["success"])
        reward = -goal_distance + (orien_similarity - 1.0)
        if obj_pos[2] < 0.075:
            reward -= self.cfg.drop_penalty
        if self._prev_action is not None:
            reward -= self.cfg.action_rate_coef * float(np.mean((action - self._prev_action) ** 2))
        self._prev_action = action
        if success:
            reward += self.cfg.success_bonus
        return obs.astype(np.float32), reward * self.cfg.reward_scale, terminated or success, truncated, info


def make_raw_env(cfg: PenTrainConfig) -> gym.Env:
    import gymnasium_robotics

    gym.register_envs(gymnasium_robotics)
    return PenTrainingTask(gym.make("AdroitHandPen-v1", max_episode_steps=200), cfg)


def make_train_env(cfg: PenTrainConfig, seed: int) -> TransformedEnv:
    env = SerialEnv(cfg.num_envs, lambda: GymWrapper(make_raw_env(cfg)))
    env = TransformedEnv(env, VecNorm(in_keys=["observation"], new_api=True, decay=0.99999, reduce_batch_dims=True))
    env.set_seed(seed)
    return env


def make_modules(cfg: PenTrainConfig):
    actor_body = nn.Sequential(make_actor_mlp(), AddStateIndependentNormalScale(24, init_value=cfg.init_log_std))
    actor = ProbabilisticActor(
        TensorDictModule(actor_body, in_keys=["observation"], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"],
        distribution_class=TanhNormal,
        distribution_kwargs={"low": -1.0, "high": 1.0},
        return_log_prob=True,
    )
    critic = ValueOperator(
        MLP(in_features=OBS_DIM, out_features=1, num_cells=[256, 256], activation_class=nn.Tanh),
        in_keys=["observation"],
    )
    return actor, critic


def vecnorm_stats(env: TransformedEnv) -> tuple[torch.Tensor, torch.Tensor]:
    vn = env.transform
    return vn.loc["observation"].reshape(OBS_DIM).clone(), vn.scale["observation"].reshape(OBS_DIM).clone()


def export_policy(actor, loc, scale) -> PenExpertPolicy:
    policy = PenExpertPolicy()
    policy.net.load_state_dict(actor.module[0].module[0].state_dict())
    policy.obs_loc.copy_(loc)
    policy.obs_scale.copy_(scale)
    return policy.eval()


@torch.no_grad()
def evaluate_training_seeds(policy: PenExpertPolicy, cfg: PenTrainConfig, seeds) -> tuple[float, float]:
    """Deterministic success rate (any step) and mean episode length on raw envs, batched over episodes."""
    envs = [make_raw_env(cfg) for _ in seeds]
    obs = np.stack([e.reset(seed=int(s))[0] for e, s in zip(envs, seeds)])
    alive = np.ones(len(envs), bool)
    success = np.zeros(len(envs), bool)
    length = np.zeros(len(envs), int)
    for _ in range(200):
        state = torch.zeros(len(envs), 105)
        state[:, :OBS_DIM] = torch.as_tensor(obs)
        actions = policy(state).numpy()
        for i, env in enumerate(envs):
            if not alive[i]:
                continue
            obs[i], _, terminated, truncated, info = env.step(actions[i])
            length[i] += 1
            success[i] |= bool(info["success"])
            alive[i] = not (terminated or truncated)
        if not alive.any():
            break
    for env in envs:
        env.close()
    return float(success.mean()), float(length.mean())


def main(argv: list[str]) -> None:
    cfg = parse_config(PenTrainConfig, argv)
    torch.set_num_threads(1)
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    run_dir = Path(cfg.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    ckpt_path, csv_path = run_dir / "checkpoint.pt", run_dir / "train.csv"
    frames_per_batch = cfg.num_envs * cfg.steps_per_env
    num_iters = math.ceil(cfg.total_frames / frames_per_batch)

    actor, critic = make_modules(cfg)
    advantage = GAE(gamma=cfg.gamma, lmbda=cfg.lmbda, value_network=critic, average_gae=True)
    loss_module = ClipPPOLoss(
        actor,
        critic,
        clip_epsilon=cfg.clip_epsilon,
        entropy_bonus=cfg.entropy_coeff > 0,
        entropy_coeff=cfg.entropy_coeff,
        critic_coeff=0.5,
        loss_critic_type="l2",
        normalize_advantage=True,
    )
    optim = torch.optim.Adam(loss_module.parameters(), lr=cfg.lr, eps=1e-5)

    start_iter, best = 0, {"success": -1.0, "iteration": -1}
    ckpt = safe_torch_load(ckpt_path) if ckpt_path.exists() else None
    # A resumed run reseeds its envs with the iteration so it does not replay the same episodes.
    env_seed = cfg.seed * 1_000_003 + (ckpt["iteration"] if ckpt else 0)
    env = make_train_env(cfg, env_seed)
    env.reset()  # initialises VecNorm's statistics so that a checkpoint can overwrite them
    if ckpt is not None:
        loss_module.load_state_dict(ckpt["loss"])
        optim.load_state_dict(ckpt["optim"])
        env.transform.load_state_dict(ckpt["vecnorm"])
        torch.set_rng_state(ckpt["torch_rng"])
        start_iter, best = ckpt["iteration"], ckpt["best"]
        print(f"resumed from iteration {start_iter}", flush=True)
    elif csv_path.exists():
        csv_path.unlink()

    collector = Collector(
        env,
        actor,
        frames_per_batch=frames_per_batch,
        total_frames=(num_iters - start_iter) * frames_per_batch,
    )
    buffer = ReplayBuffer(
        storage=LazyTensorStorage(frames_per_batch), sampler=SamplerWithoutReplacement(), batch_size=cfg.minibatch_size
    )
    eval_seeds = [cfg.seed * 7919 + 10_000 + i for i in range(cfg.eval_episodes)]
    fields = [
        "iteration",
        "frames",
        "wall_s",
        "fps",
        "episodes",
        "train_success",
        "train_ep_len",
        "loss_objective",
        "loss_critic",
        "log_std",
        "lr",
        "eval_success",
        "eval_ep_len",
    ]
    new_csv = not csv_path.exists()
    csv_file = open(csv_path, "a", newline="")
    writer = csv.DictWriter(csv_file, fieldnames=fields)
    if new_csv:
        writer.writeheader()

    t0 = time.time() - (ckpt["wall_s"] if ckpt else 0.0)
    iteration = start_iter
    pbar = tqdm(total=num_iters, initial=start_iter, desc="pen PPO", mininterval=30)
    t_iter = time.time()
    for data in collector:
        iteration += 1
        frac = 1.0 - (iteration - 1) / num_iters
        lr = cfg.lr * frac if cfg.anneal_lr else cfg.lr
        for group in optim.param_groups:
            group["lr"] = lr
        done = data["next", "done"]
        episodes = int(done.sum())
        train_success = float(data["next", "terminated"][done].float().mean()) if episodes else float("nan")
        stats = {"loss_objective": 0.0, "loss_critic": 0.0}
        n_updates = 0
        for _ in range(cfg.epochs):
            with torch.no_grad():
                data = advantage(data)
            buffer.extend(data.reshape(-1))
            for _ in range(frames_per_batch // cfg.minibatch_size):
                batch = buffer.sample()
                loss = loss_module(batch)
                total = loss["loss_objective"] + loss["loss_critic"] + loss.get("loss_entropy", 0.0)
                optim.zero_grad()
                total.backward()
                nn.utils.clip_grad_norm_(loss_module.parameters(), cfg.max_grad_norm)
                optim.step()
                stats["loss_objective"] += float(loss["loss_objective"])
                stats["loss_critic"] += float(loss["loss_critic"])
                n_updates += 1
        collector.update_policy_weights_()
        now = time.time()
        row = {
            "iteration": iteration,
            "frames": iteration * frames_per_batch,
            "wall_s": round(now - t0, 1),
            "fps": round(frames_per_batch / (now - t_iter), 1),
            "episodes": episodes,
            "train_success": round(train_success, 4),
            "train_ep_len": round(frames_per_batch / max(episodes, 1), 1),
            "loss_objective": round(stats["loss_objective"] / n_updates, 5),
            "loss_critic": round(stats["loss_critic"] / n_updates, 5),
            "log_std": round(float(actor.module[0].module[1].state_independent_scale.mean()), 4),
            "lr": f"{lr:.2e}",
            "eval_success": "",
            "eval_ep_len": "",
        }
        if iteration % cfg.eval_every == 0 or iteration == num_iters:
            policy = export_policy(actor, *vecnorm_stats(env))
            success, ep_len = evaluate_training_seeds(policy, cfg, eval_seeds)
            row["eval_success"], row["eval_ep_len"] = success, ep_len
            if success >= best["success"]:
                best = {"success": success, "iteration": iteration}
                policy.save(
                    run_dir / "best_policy.pt",
                    {"iteration": iteration, "eval_success": success, "config": config_dict(cfg)},
                )
            policy.save(
                run_dir / "last_policy.pt",
                {"iteration": iteration, "eval_success": success, "config": config_dict(cfg)},
            )
        writer.writerow(row)
        csv_file.flush()
        pbar.update(1)
        pbar.set_postfix(success=row["train_success"], eval=row["eval_success"], fps=row["fps"])
        if iteration % cfg.checkpoint_every == 0 or iteration == num_iters:
            save_checkpoint(
                ckpt_path,
                {
                    "iteration": iteration,
                    "loss": loss_module.state_dict(),
                    "optim": optim.state_dict(),
                    "vecnorm": env.transform.state_dict(),
                    "torch_rng": torch.get_rng_state(),
                    "best": best,
                    "wall_s": now - t0,
                    "config": config_dict(cfg),
                },
            )
        t_iter = time.time()
    collector.shutdown()
    csv_file.close()
    pbar.close()
    best_path = run_dir / "best_policy.pt"
    if best_path.exists():
        policy = PenExpertPolicy.load(best_path)
        meta = safe_torch_load(best_path)["metadata"]
        policy.save(cfg.output, meta)
        print(
            f"exported iteration {best['iteration']} (training-seed success {best['success']:.2f}) to {cfg.output}",
            flush=True,
        )


if __name__ == "__main__":
    reuse_freed_memory(
        __file__
    )  # before any large tensor: re-executes under glibc malloc tunables (DALIR_MALLOC=system: not)
    main(sys.argv[1:])
