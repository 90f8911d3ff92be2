"""Action-space candidate search (the paper's Table 2): random shooting, CEM, MPPI and
score-gradient ascent through the world model and scorer, seeded from the frozen policy's samples.

DALI-R varies the policy's *input*; these alternatives vary the action chunk itself. Each method
starts from the ``K`` policy samples of a decision and searches the chunk's executed actions (the
ones the world model imagines and the scorer scores) in the policy's normalised action space,
clamped to the range its normaliser was fitted on, then maps them back to env units. It returns
``K`` candidates: candidate 0 is the clean policy sample, untouched; candidates ``1 .. K-1`` are
the best ``K - 1`` chunks the search scored (gradient ascent: each seed's best iterate), with their
unexecuted entries from the seed in the same slot (projected into the bounds). Under the arg-max
rule a searched chunk is executed only when it scores above the clean one (the paper's "accept
modified actions only when they improve the scorer value"). After the seeds, every method scores
``iterations`` populations of ``K - 1`` chunks (MPPI one more: its final mean), so all spend about
the same world-model evaluations per decision.

Why not ``torchrl.modules.planners``: ``CEMPlanner``/``MPPIPlanner`` start from N(0, I), roll a
``ModelBasedEnvBase`` step by step with torch's global generator and return the first action of
one mean plan, whereas this search starts from policy samples, must hand ``K`` whole chunks (the
clean one first) to the selection rule, and draws from the actor's generator for replayable
decisions; it is a small function beside them, not a subclass.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from torchrl_dalir.config import check_choice
from torchrl_dalir.modules.normalizer import MinMaxNormalizer

#: The action-space searches by name (:class:`SearchConfig`'s ``method``): none, random shooting, CEM, MPPI,
#: projected score-gradient ascent.
SEARCH_METHODS = ("none", "shooting", "cem", "mppi", "gradient")

Objective = Callable[[torch.Tensor], torch.Tensor]  # executed actions [B, N, k, A] (env units) -> score [B, N]


@dataclass
class SearchConfig:
    """How :class:`~torchrl_dalir.reranking.RerankingActor` searches the action space around its
    policy samples. Noise and step sizes are in the policy's normalised action units (the demos'
    range of every action dimension is ``[-1, 1]``).

    Args:
        method: one of :data:`SEARCH_METHODS`; ``none`` keeps the policy samples (DALI-R).
        iterations: populations of ``K - 1`` chunks scored after the seeds (gradient: ascent steps).
        noise_std: the std of the Gaussian perturbations (``shooting``, ``mppi``) and CEM's initial std.
        elites: the best chunks of a population that CEM refits its Gaussian to.
        temperature: MPPI's softmax temperature, in completion-probability units.
        step_size: how far one gradient step moves a chunk (root mean square over its entries).
        deviation: weight of gradient ascent's penalty on the mean squared distance from its seed.
        fixed_dims: action dimensions the search leaves at the seed's value (the paper keeps the
            gripper unchanged: ``[3]`` on MetaWorld).

    Example:
        >>> SearchConfig("cem", iterations=2, elites=3).name
        'cem(iterations=2, std=0.1, elites=3)'
    """

    method: str = "none"
    iterations: int = 3
    noise_std: float = 0.1
    elites: int = 4
    temperature: float = 0.01
    step_size: float = 0.05
    deviation: float = 0.0
    fixed_dims: list[int] = field(default_factory=list)

    def __post_init__(self):
        check_choice("search method", self.method, SEARCH_METHODS)
        if self.iterations < 1 or self.elites < 1:
            raise ValueError(f"need iterations >= 1 and elites >= 1; got {self}")
        if self.noise_std <= 0 or self.temperature <= 0 or self.step_size <= 0 or self.deviation < 0:
            raise ValueError(f"need noise_std, temperature and step_size > 0 and deviation >= 0; got {self}")

    @property
    def name(self) -> str:
        """A short description of the method and the settings it uses, e.g. ``mppi(iterations=3, std=0.1, T=0.01)``."""
        settings = {
            "shooting": f"std={self.noise_std:g}",
            "cem": f"std={self.noise_std:g}, elites={self.elites}",
            "mppi": f"std={self.noise_std:g}, T={self.temperature:g}",
            "gradient": f"step={self.step_size:g}, deviation={self.deviation:g}",
        }
        if self.method == "none":
            return "none"
        fixed = f", fixed={self.fixed_dims}" if self.fixed_dims else ""
        return f"{self.method}(iterations={self.iterations}, {settings[self.method]}{fixed})"

    def check(self, num_candidates: int, action_dim: int) -> None:
        """Refuses settings that do not fit ``num_candidates`` candidates of ``action_dim``-D actions."""
        if self.method == "none":
            return
        if num_candidates < 2:
            raise ValueError(
                f"search {self.method} keeps candidate 0 clean and needs num_candidates >= 2, got {num_candidates}"
            )
        if self.method == "cem" and self.elites > num_candidates - 1:
            raise ValueError(
                f"cem refits to elites={self.elites} of {num_candidates - 1} searched chunks: "
                "lower elites or raise num_candidates"
            )
        if any(not 0 <= d < action_dim for d in self.fixed_dims):
            raise ValueError(
                f"fixed_dims {self.fixed_dims} must lie in [0, {action_dim}) (the actions are {action_dim}-D)"
            )


def action_bounds(normalizer: MinMaxNormalizer) -> tuple[torch.Tensor, torch.Tensor]:
    """The normalised range ``[A]`` the search keeps each action dimension in: the range the policy's
    normaliser was fitted on, ``[-1, 1]`` for dimensions that vary (about 0 for constant ones)."""
    return normalizer(normalizer.low), normalizer(normalizer.high)


def search_candidates(
    chunks: torch.Tensor,
    objective: Objective,
    config: SearchConfig,
    normalizer: MinMaxNormalizer,
    executed: slice,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Candidates ``[B, K, H, A]`` found by ``config.method`` from policy samples ``chunks``
    ``[B, K, H, A]`` (candidate 0 the clean one, returned unchanged), maximising ``objective`` of
    the ``executed`` actions.

    Args:
        chunks: the seeds, in env units.
        objective: the score to maximise, from executed actions ``[B, N, k, A]`` in env units to
            ``[B, N]``; differentiable for ``gradient``.
        config: the method and its settings.
        normalizer: the policy's action normaliser (the search space and its bounds).
        executed: the chunk entries the objective reads.
        generator: all the search's random draws.
    """
    if config.method == "none":
        return chunks
    config.check(chunks.shape[1], chunks.shape[-1])
    low, high = action_bounds(normalizer)
    projected = normalizer(chunks).clamp(low, high)
    seeds = projected[:, :, executed]  # [B, K, k, A]
    free = torch.ones(chunks.shape[-1], dtype=torch.bool, device=chunks.device)
    free[config.fixed_dims] = False

    def score(x: torch.Tensor) -> torch.Tensor:
        return objective(normalizer.unnormalize(x))

    def noise(shape) -> torch.Tensor:
        return torch.randn(shape, generator=generator).to(chunks.device) * free

    search = {"shooting": _shooting, "cem": _cem, "mppi": _mppi, "gradient": _gradient}[config.method]
    found = search(seeds, score, noise, config, low, high, free)  # [B, K - 1, k, A]
    out = normalizer.unnormalize(projected)
    out[:, 1:, executed] = normalizer.unnormalize(found)
    out[:, 0] = chunks[:, 0]
    return out


def _best(pool: list[torch.Tensor], scores: list[torch.Tensor], count: int) -> torch.Tensor:
    """The ``count`` best-scored chunks ``[B, count, k, A]`` of a pool of populations."""
    return _elites(torch.cat(pool, 1), torch.cat(scores, 1), count)


def _elites(population: torch.Tensor, values: torch.Tensor, count: int) -> torch.Tensor:
    """The ``count`` best-scored chunks ``[B, count, k, A]`` of ``population`` ``[B, N, k, A]``."""
    best = values.topk(count, dim=1).indices
    return population.gather(1, best[..., None, None].expand(-1, -1, *population.shape[2:]))


def _shooting(seeds, score, noise, config, low, high, free):
    """Random shooting: ``iterations`` rounds of Gaussian perturbations of seeds ``1 .. K-1``."""
    others = seeds[:, 1:]
    pool, scores = [others], [score(others)]
    for _ in range(config.iterations):
        population = (others + config.noise_std * noise(others.shape)).clamp(low, high)
        pool.append(population)
        scores.append(score(population))
    return _best(pool, scores, others.shape[1])


def _cem(seeds, score, noise, config, low, high, free):
    """Cross-entropy method: a diagonal Gaussian over the executed actions, started at the mean of
    the seeds' elites with ``noise_std``, refitted to each population's elites."""
    others = seeds[:, 1:]
    seed_scores = score(seeds)
    pool, scores = [others], [seed_scores[:, 1:]]
    mean = _elites(seeds, seed_scores, min(config.elites, seeds.shape[1])).mean(1)
    mean = torch.where(free, mean, seeds[:, 0])  # fixed dimensions: the clean sample's
    std = torch.full_like(mean, config.noise_std)
    for _ in range(config.iterations):
        population = (mean.unsqueeze(1) + std.unsqueeze(1) * noise(others.shape)).clamp(low, high)
        values = score(population)
        pool.append(population)
        scores.append(values)
        elite = _elites(population, values, config.elites)
        mean, std = elite.mean(1), elite.std(1, correction=0)
    return _best(pool, scores, others.shape[1])


def _mppi(seeds, score, noise, config, low, high, free):
    """MPPI: Gaussian perturbations of a mean chunk, which moves to the softmax(score /
    temperature)-weighted average of each population; started from the seeds' weighted average."""
    others = seeds[:, 1:]
    seed_scores = score(seeds)
    pool, scores = [others], [seed_scores[:, 1:]]
    mean = torch.where(free, _weighted_mean(seeds, seed_scores, config.temperature), seeds[:, 0])
    for _ in range(config.iterations):
        population = (mean.unsqueeze(1) + config.noise_std * noise(others.shape)).clamp(low, high)
        values = score(population)
        pool.append(population)
        scores.append(values)
        mean = _weighted_mean(population, values, config.temperature)
    pool.append(mean.unsqueeze(1))
    scores.append(score(mean.unsqueeze(1)))
    return _best(pool, scores, others.shape[1])


def _weighted_mean(population: torch.Tensor, values: torch.Tensor, temperature: float) -> torch.Tensor:
    weights = torch.softmax(values / temperature, dim=1)
    return (weights[..., None, None] * population).sum(1)


def _gradient(seeds, score, noise, config, low, high, free):
    """Projected gradient ascent of ``score - deviation * mean((x - seed)^2)`` from each of seeds
    ``1 .. K-1``, each step of length ``step_size`` (root mean square over the chunk's entries);
    keeps each seed's best-scored iterate."""
    start = seeds[:, 1:]
    x, best, best_scores = start, start, None
    for step in range(config.iterations + 1):
        with torch.enable_grad():
            variable = x.detach().requires_grad_(step < config.iterations)
            values = score(variable)
            if step < config.iterations:
                penalty = config.deviation * (variable - start).pow(2).mean((-2, -1))
                (grad,) = torch.autograd.grad((values - penalty).sum(), variable)
        values = values.detach()
        if best_scores is None:
            best_scores = values
        else:
            better = values > best_scores
            best = torch.where(better[..., None, None], x, best)
            best_scores = torch.where(better, values, best_scores)
        if step < config.iterations:
            grad = grad * free
            length = grad.pow(2).mean((-2, -1), keepdim=True).sqrt().clamp_min(torch.finfo(grad.dtype).tiny)
            x = (x + config.step_size * grad / length).clamp(low, high)
    return best
