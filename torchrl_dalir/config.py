"""Job configuration: a dataclass per job, named presets, and ``key=value`` overrides.

As in TorchRL's examples, every job reads its whole configuration from one place and accepts
hydra-style overrides on the command line (``task=shelf-place preset=smoke seed=1``); a
``preset`` applies a named set of overrides first, the command line wins over it.
"""

from __future__ import annotations

from collections.abc import Collection
from typing import TypeVar

from omegaconf import OmegaConf
from omegaconf.errors import ConfigKeyError, OmegaConfBaseException

C = TypeVar("C")


def parse_config(config_class: type[C], argv: list[str], presets: dict[str, dict] | None = None) -> C:
    """Builds ``config_class`` from its defaults, then ``presets[preset]`` (if the job has
    presets), then the ``key=value`` overrides of ``argv``."""
    cli = OmegaConf.from_dotlist(argv)
    base = OmegaConf.structured(config_class)
    layers = [base]
    if presets is not None:
        preset = cli.get("preset", base.get("preset"))
        if preset not in presets:
            raise ValueError(f"unknown preset {preset!r}; choose one of {sorted(presets)}")
        layers.append(presets[preset])
    try:
        return OmegaConf.to_object(OmegaConf.merge(*layers, cli))
    except OmegaConfBaseException as error:  # a misspelt key or a badly typed value
        raise ValueError(_explain(error, base)) from None


def _explain(error: OmegaConfBaseException, base) -> str:
    message = f"bad setting {error.full_key!r}: {str(error.msg).splitlines()[0]}"
    if isinstance(error, ConfigKeyError):
        parent = error.full_key.rpartition(".")[0]
        node = OmegaConf.select(base, parent) if parent else base
        message += f"; the settings {'of ' + repr(parent) if parent else 'here'} are {', '.join(node.keys())}"
    return message


def check_choice(name: str, value, choices: Collection) -> None:
    """A ``ValueError`` that lists the allowed values unless ``value`` is one of ``choices``."""
    if value not in choices:
        raise ValueError(f"{name} must be one of {sorted(choices)}, got {value!r}")


def check_at_least(name: str, value, minimum) -> None:
    """A ``ValueError`` that names the setting unless ``value >= minimum`` (counts, sizes, steps)."""
    if value < minimum:
        raise ValueError(f"{name} must be at least {minimum}, got {value}")


def check_probability(name: str, value: float) -> None:
    """A ``ValueError`` that names the setting unless ``0 <= value < 1`` (a dropout probability)."""
    if not 0.0 <= value < 1.0:
        raise ValueError(f"{name} must lie in [0, 1), got {value}")


def config_dict(config) -> dict:
    return OmegaConf.to_container(OmegaConf.structured(config))
