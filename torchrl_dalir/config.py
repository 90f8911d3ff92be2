"""Job configuration: a dataclass per job, named presets, and ``key=value`` overrides.

As in TorchRL's examples, every job reads its whole configuration from one place and accepts
hydra-style overrides on the command line (``task=shelf-place preset=smoke seed=1``); a
``preset`` applies a named set of overrides first, the command line wins over it.
"""

from __future__ import annotations

from typing import TypeVar

from omegaconf import OmegaConf

C = TypeVar("C")


def parse_config(config_class: type[C], presets: dict[str, dict], argv: list[str]) -> C:
    """Builds ``config_class`` from its defaults, then ``presets[preset]``, then ``argv``."""
    cli = OmegaConf.from_dotlist(argv)
    base = OmegaConf.structured(config_class)
    preset = cli.get("preset", base.get("preset"))
    if preset not in presets:
        raise ValueError(f"unknown preset {preset!r}; choose one of {sorted(presets)}")
    merged = OmegaConf.merge(base, presets[preset], cli)
    return OmegaConf.to_object(merged)


def config_dict(config) -> dict:
    return OmegaConf.to_container(OmegaConf.structured(config))
