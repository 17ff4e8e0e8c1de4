"""The names a policy is configured with, as plain constants: algorithms, image networks, observation modes.

Nothing here imports torch, numba or stable-baselines3, so :class:`~lcmodels.policy.config.PolicyConfig`, a
command's ``--help`` and a policy card's check name the choices without loading the networks that implement
them (:mod:`lcmodels.policy.extractor`, :mod:`lcmodels.policy.network`).
"""

from __future__ import annotations

import dataclasses
from enum import StrEnum
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from lcsim.config import ScenarioConfig

ALGORITHMS: tuple[str, ...] = ("ppo", "a2c", "dqn")
"""The learning algorithms a policy can be trained with (stable-baselines3's PPO, A2C and DQN)."""

IMAGE_NETS: tuple[str, ...] = ("compact", "strided", "vgg16")
"""The image branches (:func:`lcmodels.policy.extractor.make_image_net`)."""

SENSOR_ENCODERS: tuple[str, ...] = ("mlp", "attention")
"""How the sensor branch reads ``current``: the rows flattened into an MLP, or as a set
(:class:`lcmodels.policy.extractor.EgoAttention`)."""

IMAGE_FEATURES = "image_features"
"""The observation key that replaces ``image`` when the image branch is frozen and run by the environment
wrapper (:class:`lcmodels.policy.extractor.ImageEncoder`): what the branch would output, so the extractor
passes it through."""


class ObsMode(StrEnum):
    """An observation mode of the ablation: which keys the policy sees (a ``str``, so configs store it as one)."""

    PURE = "pure"
    IMAGE = "image"
    PREDICTION = "prediction"
    HYBRID = "hybrid"

    @classmethod
    def of(cls, mode: str) -> ObsMode:
        """The mode named ``mode``; ``ValueError`` listing the modes for an unknown one."""
        try:
            return cls(mode)
        except ValueError:
            raise ValueError(f"unknown observation mode {mode!r}; choose one of {', '.join(OBS_MODES)}") from None

    @property
    def keys(self) -> tuple[str, ...]:
        """The observation keys the policy sees."""
        return _KEYS[self]

    @property
    def reads_image(self) -> bool:
        return "image" in _KEYS[self]

    @property
    def needs_predictor(self) -> bool:
        return "prediction" in _KEYS[self]


_KEYS = {
    ObsMode.PURE: ("current",),
    ObsMode.IMAGE: ("current", "image"),
    ObsMode.PREDICTION: ("current", "prediction"),
    ObsMode.HYBRID: ("current", "image", "prediction"),
}
OBS_MODES: tuple[str, ...] = tuple(m.value for m in ObsMode)
"""The observation modes (:class:`ObsMode`): ``pure``, ``image``, ``prediction``, ``hybrid``."""


def mode_keys(mode: str) -> tuple[str, ...]:
    """The observation keys of ``mode``; ``ValueError`` for an unknown mode."""
    return ObsMode.of(mode).keys


def needs_predictor(mode: str) -> bool:
    return ObsMode.of(mode).needs_predictor


def scenario_for_mode(config: ScenarioConfig, mode: str) -> ScenarioConfig:
    """``config`` with the bird's-eye image rendered only when the mode uses it (rendering costs time)."""
    return dataclasses.replace(config, render_image=ObsMode.of(mode).reads_image)
