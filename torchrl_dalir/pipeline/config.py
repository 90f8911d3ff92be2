"""Configuration of the end-to-end job, ``examples/train_dp3_wm.py``: one task, every stage.

The stage configurations of the collection, policy and world-model jobs are nested here; the
job's ``preset`` selects the matching preset of each, and its ``task``, ``seed``, ``device``,
``wandb`` and ``out`` are passed down, so one command line sets the whole run.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

from torchrl_dalir.config import check_at_least, check_choice
from torchrl_dalir.data.collection import SEEDS_PER_DATASET
from torchrl_dalir.data.config import PRESETS as COLLECTION_PRESETS
from torchrl_dalir.data.config import CollectionConfig
from torchrl_dalir.envs.tasks import get_task
from torchrl_dalir.evaluation.calibration import ALPHA, DESIGNS, FAILURES, GRIDS
from torchrl_dalir.evaluation.compare import METHODS, check_evaluation_settings, evaluation_reranking
from torchrl_dalir.modules.config import POLICY_KINDS
from torchrl_dalir.reranking.config import RerankingConfig
from torchrl_dalir.seeds import check_eval_seed
from torchrl_dalir.training.logging import wandb_mode
from torchrl_dalir.training.policy import PRESETS as POLICY_PRESETS
from torchrl_dalir.training.policy import PolicyTrainingConfig
from torchrl_dalir.training.world_model import PRESETS as WORLD_MODEL_PRESETS
from torchrl_dalir.training.world_model import WorldModelTrainingConfig

#: The job's setting that each derived stage setting comes from (the others share their name).
DERIVED_FROM = {"data": "out", "mixed_name": "policy and seed", "policy_checkpoint": "out, policy and seed"}

#: The main job's stages, in the order they run (``until=<stage>``, ``redo=[<stage>]``).
STAGES = ("demos", "policy", "mixed", "exploration", "branched", "world_model", "calibration", "evaluation")
# Branched episodes of training seed s reset with data seeds BASE + 1000 s + i: dataset seed 900's range, which
# no collection of the main job reaches (its datasets use seeds 2 s + 1 and 2 s + 2).
BRANCHED_SEED_BASE = 900 * SEEDS_PER_DATASET
MAX_BRANCHED_EPISODES = 1000
STAGE_LOG = "stages"  # under out: <task>/<run name>.jsonl, a line per finished stage (wall time, peak memory)


@dataclass
class PipelineConfig:
    """The main job's configuration (``examples/train_dp3_wm.py``): its own settings and each stage's,
    nested (``collection``, ``policy_training``, ``world_model``; ``preset`` picks :data:`PRESETS`).

    Args:
        task, seed, device, out: passed to every stage; artifacts go under ``out``.
        demo_seed: the data seed of the task's demos, which every training seed shares (the demos
            live in ``<out>/data/<task>/demos``; ``seed`` varies the policy, mixed data and world model).
        policy: the base policy's backbone (``fm`` or ``dp``).
        base_policy_rollouts: trajectories of the trained base policy added to the mixed data.
        exploration_rollouts: trajectories of the base policy acting on point-dropout views (one of
            DALI-R's candidates at random per decision), collected as ``explore_<policy>_seed<seed>``
            and added to the world model's data (0: none, the paper's data; the ``cpu`` preset: 60).
        branched_episodes, branched_stride, branched_candidates, branched_decisions: branched outcomes
            (:mod:`~torchrl_dalir.branching.outcomes`): at every ``branched_stride``-th decision of
            ``branched_episodes`` base-policy episodes on data seeds (before decision ``branched_decisions``,
            if not 0), ``branched_candidates`` of DALI-R's
            candidates are each executed from the saved state and continued with the base policy, in
            ``<out>/data/<task>/branched_<policy>_seed<seed>``, with the within-decision AUC of a scorer
            trained on them (``ranking.json`` there). 0 episodes (the default): no branched outcomes.
        eval_episodes, eval_seed: the test episodes, shared by every method (``eval_methods``: the
            base policy, DALI-R with the calibrated rule, with the paper's arg-max, and the
            random-candidate control; ``dropout`` adds the point-dropout policy; see
            :func:`~torchrl_dalir.evaluation.compare.evaluate_checkpoints`).
        calibration_episodes, calibration_seed: the validation episodes on which the selection
            rule's setting is chosen (:mod:`torchrl_dalir.evaluation.calibration`); never the test seed.
            ``calibration_episodes=0`` keeps the paper's arg-max.
        calibration_alpha: the evidence a setting needs to be chosen over the base policy (one-sided
            sign-test p-value on the validation episodes; 1: the setting with the most successes).
        calibration_confirm_episodes: with ``n > 0``, a chosen setting other than the base policy must
            win again on ``n`` fresh validation episodes (evaluation seed ``calibration_seed + 1``)
            to be kept (:func:`~torchrl_dalir.evaluation.calibration.calibrate`); 0 skips it. A grid of
            several alternatives needs it (30): the best of nine clears the bar by luck (warned).
        calibration_grid: the settings compared with the base policy (``GRIDS``): ``argmax``, the
            default, the ensemble arg-max alone (one comparison named in advance, so its p-value
            holds as it is); ``all``, nine settings of four rules; ``margin``, the margin rule's;
            ``critic``, the arg-max of the chunk critic that the branched stage trains (needs
            ``branched_episodes >= 2``; the evaluation's DALI-R methods then carry that critic).
        calibration_design: ``fixed``, every setting on ``calibration_episodes`` episodes (then the
            confirmation above), or ``failures``, sized by the base policy's failures: the settings are
            screened on ``calibration_failures`` episodes it failed and as many it solved, and the most
            promising one is confirmed on as many fresh episodes of ``calibration_seed + 1`` as the
            screen took (:func:`~torchrl_dalir.evaluation.calibration.calibrate_on_failures`; ``calibration_episodes``
            and ``calibration_confirm_episodes`` then only say whether to calibrate at all).
        num_candidates, dropout: DALI-R's candidates per decision and point-dropout probability (the
            defaults of :class:`~torchrl_dalir.reranking.RerankingConfig`; :meth:`reranking` gives the record).
        rerank_decisions: DALI-R reranks only each episode's first ``n`` decisions in calibration and
            evaluation, the base policy acting alone afterwards (0, the default: every decision;
            ``RerankingConfig.decisions``).
        redo: stages to run again from scratch even if their artifact exists
            (``redo=[world_model]``); later stages are redone too, and each previous run's
            directory is kept aside.
        until: the last stage to run (``until=mixed`` makes the policy and its data, then stops).
        wandb: ``off`` (the default: CSV logs only), ``offline`` or ``online`` (``wandb login`` first):
            passed to the policy and world-model trainings, and the calibration and evaluation results
            are logged to wandb runs of their own (:mod:`torchrl_dalir.training.logging`).
    """

    task: str = "disassemble"
    preset: str = "cpu"
    seed: int = 0
    demo_seed: int = 0
    device: str = "cpu"
    out: str = "outputs/pipeline"
    policy: str = "fm"
    base_policy_rollouts: int = 100
    exploration_rollouts: int = 0
    branched_episodes: int = 0
    branched_stride: int = 3
    branched_candidates: int = 8
    branched_decisions: int = 0
    eval_episodes: int = 50
    eval_seed: int = 0
    eval_methods: list[str] = field(default_factory=lambda: ["base", "dalir", "argmax", "random"])
    calibration_episodes: int = 30
    calibration_seed: int = 1
    calibration_alpha: float = ALPHA
    calibration_confirm_episodes: int = 0
    # argmax (base policy or ensemble arg-max) | all (the margin settings and the other rules)
    # | margin (the margin settings only)
    calibration_grid: str = "argmax"
    calibration_design: str = "fixed"  # fixed | failures (sized by the base policy's failures)
    calibration_failures: int = FAILURES
    num_candidates: int = RerankingConfig.num_candidates
    dropout: float = RerankingConfig.dropout
    rerank_decisions: int = RerankingConfig.decisions
    redo: list[str] = field(default_factory=list)
    until: str = "evaluation"
    wandb: str = "off"  # off | offline | online (true/false: offline/off)
    collection: CollectionConfig = field(default_factory=CollectionConfig)
    policy_training: PolicyTrainingConfig = field(default_factory=PolicyTrainingConfig)
    world_model: WorldModelTrainingConfig = field(default_factory=WorldModelTrainingConfig)

    def __post_init__(self):
        get_task(self.task)  # an unknown name fails here, not after the demos
        check_choice("policy", self.policy, POLICY_KINDS)
        for method in self.eval_methods:
            check_choice("eval_methods entry", method, METHODS)
        check_choice("calibration_grid", self.calibration_grid, GRIDS)
        check_choice("calibration_design", self.calibration_design, DESIGNS)
        check_at_least("calibration_failures", self.calibration_failures, 1)
        if not 0 < self.calibration_alpha <= 1:
            raise ValueError(f"calibration_alpha is a p-value threshold in (0, 1], got {self.calibration_alpha}")
        check_evaluation_settings(self.eval_episodes, self.eval_seed, self.num_candidates, self.dropout, prefix="eval_")
        check_at_least("branched_stride", self.branched_stride, 1)
        if self.branched_episodes and (self.branched_episodes > MAX_BRANCHED_EPISODES or self.seed >= 100):
            raise ValueError(
                f"branched_episodes is at most {MAX_BRANCHED_EPISODES} and seed below 100 (their reset seeds "
                f"lie in a reserved range), got {self.branched_episodes} and {self.seed}"
            )
        check_at_least("branched_candidates", self.branched_candidates, 2)
        check_at_least("branched_decisions", self.branched_decisions, 0)
        check_at_least("rerank_decisions", self.rerank_decisions, 0)
        if self.calibration_grid == "critic" and self.calibration_episodes and self.branched_episodes < 2:
            raise ValueError(
                "calibration_grid=critic calibrates the branched stage's chunk critic: set branched_episodes >= 2"
            )
        check_eval_seed(self.calibration_seed, "calibration_seed")
        for name in (
            "calibration_episodes",
            "calibration_confirm_episodes",
            "base_policy_rollouts",
            "exploration_rollouts",
            "branched_episodes",
            "seed",
            "demo_seed",
        ):
            check_at_least(name, getattr(self, name), 0)
        confirms = self.calibration_confirm_episodes or self.calibration_design == "failures"
        if self.calibration_episodes and confirms and self.calibration_seed + 1 == self.eval_seed:
            raise ValueError(
                f"the confirmation's validation episodes (evaluation seed calibration_seed + 1 = {self.eval_seed}) "
                "would be the test episodes: choose another calibration_seed"
            )
        alternatives = len(GRIDS[self.calibration_grid]) - 1  # the first entry is the base policy
        if (
            self.calibration_episodes
            and self.calibration_design == "fixed"
            and not self.calibration_confirm_episodes
            and alternatives > 1
        ):
            warnings.warn(
                f"calibration_grid={self.calibration_grid} compares {alternatives} settings with the base policy "
                "on the same episodes: the best of them clears the sign-test bar by luck more often than "
                "calibration_alpha says; "
                f"set calibration_confirm_episodes={self.calibration_episodes}",
                stacklevel=2,
            )
        if self.calibration_episodes and self.calibration_seed == self.eval_seed:
            raise ValueError(
                f"calibration_seed must differ from eval_seed ({self.eval_seed}): "
                "the rule is chosen on validation, not test, episodes"
            )
        check_choice("until", self.until, STAGES)
        self.wandb = wandb_mode(self.wandb)
        unknown = set(self.redo) - set(STAGES)
        if unknown:
            raise ValueError(f"unknown stages {sorted(unknown)}; stages are {STAGES}")
        if self.redo:  # a redone stage invalidates every later stage
            self.redo = list(STAGES[min(STAGES.index(s) for s in self.redo) :])
        for stage, settings in self._stage_settings().items():
            config = getattr(self, stage)
            default = type(config)()
            for name, value in settings.items():
                if getattr(config, name) not in (value, getattr(default, name)):  # set by hand, and would be lost
                    raise ValueError(
                        f"{stage}.{name}={getattr(config, name)!r} would be replaced by the main job's {value!r}, "
                        f"which it derives from its own {DERIVED_FROM.get(name, name)}: set that instead"
                    )
                setattr(config, name, value)
            config.__post_init__()  # derived settings and checks again, with the job's values
        if self.exploration_rollouts > 0 and self.exploration_name() not in self.world_model.extra_data:
            self.world_model.extra_data = [*self.world_model.extra_data, self.exploration_name()]

    def _stage_settings(self) -> dict[str, dict]:
        """The stage settings that the job derives from its own: one task, seed, device, logging and folder."""
        root = Path(self.out)
        data = str(root / "data")
        # the mixed data holds this policy's rollouts: each policy and seed has its own
        mixed = f"mixed_{self.policy}_seed{self.seed}"
        policy = {
            "task": self.task,
            "data": data,
            "out": str(root / "policies"),
            "policy": self.policy,
            "seed": self.seed,
            "device": self.device,
            "wandb": self.wandb,
        }
        return {
            "collection": {"task": self.task, "out": data, "mixed_name": mixed, "seed": self.seed},
            "policy_training": policy,
            "world_model": {
                "task": self.task,
                "data": data,
                "out": str(root / "world_models" / self.policy),
                "mixed_name": mixed,
                "seed": self.seed,
                "device": self.device,
                "wandb": self.wandb,
                "policy_checkpoint": str(replace(self.policy_training, **policy).run_dir() / "checkpoint.pt"),
            },
        }

    def reranking(self) -> RerankingConfig:
        """DALI-R's settings in the job's calibration and evaluation: its ``num_candidates`` and
        ``dropout``, the evaluations' common noise, the selection rule the checkpoint stores."""
        return evaluation_reranking(
            num_candidates=self.num_candidates, dropout=self.dropout, decisions=self.rerank_decisions
        )

    def branched_dir(self) -> Path:
        return Path(self.out) / "data" / self.task / f"branched_{self.policy}_seed{self.seed}"

    def critic(self) -> Path | None:
        """The branched stage's chunk critic, if it trained one."""
        path = self.branched_dir() / "critic.pt"
        return path if self.branched_episodes >= 2 and path.exists() else None

    def exploration_name(self) -> str:
        return f"explore_{self.policy}_seed{self.seed}"

    def run_name(self) -> str:
        return f"{self.policy}_seed{self.seed}{self.world_model.variant()}"

    def calibration_dir(self) -> Path:
        return Path(self.out) / "calibration" / self.task / self.run_name()

    def results_dir(self) -> Path:
        return Path(self.out) / "results" / self.task / self.run_name()

    def stage_log_path(self) -> Path:
        return Path(self.out) / STAGE_LOG / self.task / f"{self.run_name()}.jsonl"


def _nest(preset: str) -> dict:
    return {
        "collection": COLLECTION_PRESETS[preset],
        "policy_training": POLICY_PRESETS[preset],
        "world_model": WORLD_MODEL_PRESETS[preset],
    }


#: Named overrides of :class:`PipelineConfig` (``preset=paper|cpu|smoke``), each nesting its stages' presets.
PRESETS: dict[str, dict] = {
    "paper": {**_nest("paper"), "base_policy_rollouts": 200, "eval_episodes": 100},
    # the reranking protocol (README, Results): exploration data; DALI-R leaves the base policy for the
    # ensemble arg-max only if it won on the validation episodes (calibration_grid's default)
    "cpu": {**_nest("cpu"), "exploration_rollouts": 60},
    "smoke": {
        **_nest("smoke"),
        "base_policy_rollouts": 2,
        "eval_episodes": 2,
        "num_candidates": 4,
        "calibration_episodes": 1,
    },
}
