"""A student scorer learns a teacher's ranking of each decision's candidates, as a TorchRL ``LossModule``."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn

from torchrl_dalir.objectives.common import KeyedLossModule

TEACHER_LOGITS = "teacher_logits"  # [B, K] a teacher's logits of a decision's candidates


class CriticDistillationLoss(KeyedLossModule):
    """Distils a teacher's scores of a decision's candidates into a student: a listwise KL beside a probability loss.

    Within each decision, the student's softmax over its ``K`` candidates (temperature ``T``) is pulled towards
    the teacher's (Hinton et al.'s distillation, scaled by ``T**2``): only the candidates' scores *relative to
    each other at the same state* are asked for, which is what reranking uses. Beside it, a binary
    cross-entropy pulls each student logit towards the teacher's probability (``probability_weight``), so the
    student's scores stay calibrated as success chances (the selection rules compare them with the clean
    candidate's). Every decision carries signal: the teacher labels states that no branching has visited
    ("Learning by Cheating", Chen et al. 2019: dense supervision from every state).

    Args:
        student: a TensorDict module that reads a batch of decisions and writes the candidates' logits
            ``[B, K]`` (e.g. a :class:`~torchrl_dalir.modules.PointCloudCriticModule`); its ``out_keys[0]`` is read.
        temperature: ``T``, the softmax temperature of both.
        probability_weight: the binary cross-entropy's weight (0: the ranking alone).

    Keys (``set_keys``): ``teacher_logits`` ``[B, K]``.

    Example:
        >>> from torchrl_dalir.modules import PointCloudCritic, PointCloudCriticModule
        >>> critic = PointCloudCritic(2, 4, 4, 8, point_hidden=(8,), point_out=8, state_out=8, hidden=16)
        >>> loss = CriticDistillationLoss(PointCloudCriticModule(critic))
        >>> decisions = TensorDict(point_cloud=torch.rand(3, 2, 64, 3), agent_pos=torch.rand(3, 2, 4),
        ...                        executed_actions=torch.rand(3, 5, 8, 4), teacher_logits=torch.randn(3, 5),
        ...                        batch_size=[3])
        >>> sorted(loss(decisions).keys())
        ['loss_distillation', 'loss_probability']
        >>> loss.set_keys(teacher_logits="privileged_logits")
        >>> loss.in_keys
        ['privileged_logits']
    """

    @dataclass
    class _AcceptedKeys:
        """The entries a batch of decisions holds beside what the student reads.

        Attributes:
            teacher_logits: the teacher's logits of each candidate ``[B, K]``. Defaults to ``"teacher_logits"``.
        """

        teacher_logits: NestedKey = TEACHER_LOGITS

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys = ["loss_distillation", "loss_probability"]

    def __init__(self, student: TensorDictModuleBase, temperature: float = 1.0, probability_weight: float = 0.5):
        super().__init__()
        if temperature <= 0 or probability_weight < 0:
            raise ValueError(
                f"temperature must be positive and probability_weight non-negative, got {temperature} and "
                f"{probability_weight}"
            )
        self.student, self.temperature, self.probability_weight = student, temperature, probability_weight

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        teacher = tensordict[self.tensor_keys.teacher_logits]
        logits = self.student(tensordict.copy())[self.student.out_keys[0]]
        if logits.shape != teacher.shape:
            raise ValueError(
                f"the student's logits {tuple(logits.shape)} and the teacher's {tuple(teacher.shape)} differ"
            )
        t = self.temperature
        target = (teacher / t).softmax(-1)
        kl = (target * (target.clamp(min=1e-12).log() - (logits / t).log_softmax(-1))).sum(-1).mean() * t**2
        probability = nn.functional.binary_cross_entropy_with_logits(logits, torch.sigmoid(teacher))
        return TensorDict({"loss_distillation": kl, "loss_probability": self.probability_weight * probability}, [])
