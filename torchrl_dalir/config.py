"""Job configuration: a dataclass per job, named presets, and ``key=value`` overrides.

As in TorchRL's examples, every job reads its whole configuration from one place and accepts
hydra-style overrides on the command line (``task=shelf-place preset=smoke seed=1``); a
``preset`` applies a named set of overrides first, the command line wins over it.
"""

from __future__ import annotations

from typing import TypeVar

from omegaconf import OmegaConf

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
    return OmegaConf.to_object(OmegaConf.merge(*layers, cli))


def config_dict(config) -> dict:
    return OmegaConf.to_container(OmegaConf.structured(config))
