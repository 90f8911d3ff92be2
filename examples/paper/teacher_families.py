"""Is the privileged teacher's rung limited by its model? Other model families on the same rung, out of fold.

    pip install -e ".[analysis]"    # scikit-learn
    python examples/paper/teacher_families.py files=[fm_pen_s0,fm_pen_s1,fm_pen_s2,dp_pen_s0] \\
        json=docs/results/teacher_families.json

For every benchmark file (``benchmarks/scorer/<name>.pt``), the teacher rung as ``scorer_benchmark.py`` measures it
(episodes in ``folds`` groups, each scored by a model fit on the others; the within-decision AUC on the decisions
that split under the collection's draw; the offline gain judged by the mean over every draw), with each family of
``models`` learning every candidate's mean outcome over the draws:

- ``mlp``: the ladder's own teacher (``teacher_soft``: the chunk critic's MLP with its listwise loss);
- ``ridge``: ridge regression on standardised inputs;
- ``extra_trees`` and ``boosted_trees``: scikit-learn's extremely randomised trees and gradient-boosted trees.

Each reads the decision's privileged state with the candidate's executed actions, as they are (``chunk``) or
minus the mean over the decision's candidates (``centred``: a ranking within a decision reads only how its
candidates differ). If every family stays near chance where the true chance ranks well, the rung is limited by
what the data show, not by the MLP.
"""

import json
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch
from tensordict import TensorDict

from torchrl_dalir import keys
from torchrl_dalir.branching.scorer_benchmark import SCORERS, teacher_rows
from torchrl_dalir.config import check_at_least, parse_config
from torchrl_dalir.modules.config import executed_slice
from torchrl_dalir.training.ranking import (
    SOFT_SUCCESS,
    RankingTrainingConfig,
    cross_validated_auc,
    train_ranking_scorer,
)
from torchrl_dalir.utils import atomic_write, provenance

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks" / "scorer"
FEATURES = ("chunk", "centred")


def regressor(name: str, seed: int):
    """A scikit-learn regressor of a candidate's chance (imported here: the other rungs do not need it)."""
    from sklearn.ensemble import ExtraTreesRegressor, HistGradientBoostingRegressor
    from sklearn.linear_model import Ridge
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    if name == "ridge":
        return make_pipeline(StandardScaler(), Ridge(alpha=10.0))
    if name == "extra_trees":
        return ExtraTreesRegressor(n_estimators=200, min_samples_leaf=5, max_features=0.3, random_state=seed)
    return HistGradientBoostingRegressor(max_iter=200, learning_rate=0.05, max_leaf_nodes=15, random_state=seed)


MODELS = ("mlp", "ridge", "extra_trees", "boosted_trees")


@dataclass
class Config:
    files: list[str] = field(default_factory=list)  # benchmark names (benchmarks/scorer/<name>.pt)
    models: list[str] = field(default_factory=lambda: list(MODELS))
    features: list[str] = field(default_factory=lambda: list(FEATURES))
    folds: int = 10
    training: RankingTrainingConfig = field(default_factory=RankingTrainingConfig)  # the MLP's (and every seed)
    benchmarks: str = str(BENCHMARKS)
    json: str = ""  # where to write the results (none: print only)

    def __post_init__(self):
        check_at_least("files", len(self.files), 1)
        check_at_least("folds", self.folds, 2)
        for name, chosen, known in (("models", self.models, MODELS), ("features", self.features, FEATURES)):
            if unknown := set(chosen) - set(known):
                raise ValueError(f"unknown {name} {sorted(unknown)}; known: {list(known)}")


def centred(rows: TensorDict) -> TensorDict:
    """The decisions with each candidate's chunk minus the mean chunk of its decision's candidates."""
    chunk = rows[keys.ACTION_CHUNK]
    return rows.clone(False).set(keys.ACTION_CHUNK, chunk - chunk.mean(1, keepdim=True))


def fit_regressor(rows: TensorDict, policy, cfg: RankingTrainingConfig, held_out: torch.Tensor, model: str):
    """A :func:`~torchrl_dalir.training.ranking.train_ranking_scorer` of the same arguments and returns for
    ``cross_validated_auc``: ``model`` fit on the training decisions' candidates (state and executed actions) to
    their chance over draws, with its predictions on the held-out decisions as ``held_out_logits``."""
    executed = rows[keys.ACTION_CHUNK][:, :, executed_slice(policy.obs_steps, policy.action_steps)].flatten(2)
    state = rows[keys.PRIVILEGED_STATE].unsqueeze(1).expand(-1, executed.shape[1], -1)
    inputs, chance, held_out = torch.cat([state, executed], -1).numpy(), rows[SOFT_SUCCESS].numpy(), held_out.numpy()
    fitted = regressor(model, cfg.seed).fit(
        inputs[~held_out].reshape(-1, inputs.shape[-1]), chance[~held_out].reshape(-1)
    )
    predicted = fitted.predict(inputs[held_out].reshape(-1, inputs.shape[-1])).reshape(-1, inputs.shape[1])
    return fitted, {"held_out_logits": np.asarray(predicted).tolist()}


def family_rung(rows: TensorDict, sizes: dict, model: str, cfg: Config) -> dict:
    """One family's out-of-fold AUC and offline gain on one benchmark's (possibly centred) decisions."""
    training = replace(cfg.training, **SCORERS["teacher_soft"])
    train = train_ranking_scorer if model == "mlp" else fit_regressor
    extra = {} if model == "mlp" else {"model": model}
    cv = cross_validated_auc(
        rows, SimpleNamespace(**sizes), training, cfg.folds, rows[SOFT_SUCCESS], train=train, **extra
    )
    return {"auc": cv["auc"], "gain": cv["pick_success"] - cv["clean_success"]}


def main(argv: list[str]) -> dict:
    cfg = parse_config(Config, argv)
    results = {}
    for name in cfg.files:
        rows, info = teacher_rows(Path(cfg.benchmarks) / f"{name}.pt")
        results[name] = {"task": info["task"], "decisions": len(rows)}
        for features in cfg.features:
            read = centred(rows) if features == "centred" else rows
            for model in cfg.models:
                rung = results[name][f"{model}/{features}"] = family_rung(read, info["sizes"], model, cfg)
                print(f"{name} {model}/{features}: AUC {rung['auc']:.3f}, gain {100 * rung['gain']:+.1f}", flush=True)
    out = {**provenance("examples/paper/teacher_families.py", argv, cfg), "runs": results}
    if cfg.json:
        atomic_write(Path(cfg.json), json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main(sys.argv[1:])
