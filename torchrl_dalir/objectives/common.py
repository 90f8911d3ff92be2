"""The base of every loss in the package: TorchRL's ``LossModule`` key contract, kept in one place."""

from __future__ import annotations

from dataclasses import dataclass, fields

from tensordict import NestedKey, unravel_key
from torchrl.objectives import LossModule


class KeyedLossModule(LossModule):
    """A :class:`~torchrl.objectives.LossModule` that reads only the entries its ``_AcceptedKeys`` name.

    A subclass follows TorchRL's contract:

    - ``_AcceptedKeys``, a dataclass with one field per tensordict entry it reads, whose defaults
      come from :mod:`torchrl_dalir.keys`, and ``default_keys = _AcceptedKeys``;
    - ``out_keys``, its ``loss_*`` entries;
    - ``forward`` reads every input as ``tensordict[self.tensor_keys.<name>]`` (a missing entry
      raises a ``KeyError`` that names it).

    ``loss.set_keys(<name>=<nested key>)`` then renames an input (TorchRL refuses a name the
    dataclass lacks; ``None`` restores the default) and :attr:`in_keys` follows: the entries the
    loss reads under their current names, in the dataclass's order. A subclass whose configuration
    skips some of its keys overrides :meth:`_read_key_names`. There is no value estimator to forward
    keys to.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> class MeanLoss(KeyedLossModule):
        ...     @dataclass
        ...     class _AcceptedKeys:
        ...         value: NestedKey = "value"
        ...     default_keys = _AcceptedKeys
        ...     out_keys = ["loss_mean"]
        ...     def forward(self, tensordict):
        ...         return TensorDict({"loss_mean": tensordict[self.tensor_keys.value].mean()}, [])
        >>> loss = MeanLoss()
        >>> loss.set_keys(value=("nested", "value"))
        >>> loss.in_keys
        [('nested', 'value')]
        >>> loss(TensorDict({"nested": {"value": torch.ones(3)}}, [3]))["loss_mean"]
        tensor(1.)
    """

    @dataclass
    class _AcceptedKeys:
        """No keys: each subclass declares its own."""

    default_keys = _AcceptedKeys

    def __init__(self):
        super().__init__()
        self._in_keys = None

    def _read_key_names(self) -> tuple[str, ...]:
        """The ``_AcceptedKeys`` fields this instance reads: all of them unless overridden."""
        return tuple(field.name for field in fields(self._AcceptedKeys))

    def _set_in_keys(self) -> None:
        read = (unravel_key(getattr(self.tensor_keys, name)) for name in self._read_key_names())
        self._in_keys = list(dict.fromkeys(read))  # in declaration order, each entry once

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        self._set_in_keys()  # no value estimator: set_keys only renames inputs

    @property
    def in_keys(self) -> list[NestedKey]:
        if self._in_keys is None:
            self._set_in_keys()
        return self._in_keys

    @in_keys.setter
    def in_keys(self, values: list[NestedKey]) -> None:
        self._in_keys = values
