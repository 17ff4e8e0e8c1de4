"""A policy run resolved once: what its config names, read before anything is built.

A :class:`~lcmodels.policy.config.PolicyConfig` is data: constructing one reads no file. :func:`resolve` reads
what it names once, at the start of a run: the scenario (a registered name or a scenario file) with the
policy's view of the traffic, the roads training drives, the predictor its observation reads; and it builds the
safety layer the run trains behind. What comes after (the run directory's checks, the environments, the
network, the policy cards) takes the :class:`RunPlan` and reads none of it again.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lcmodels.fileio import file_sha256
from lcmodels.policy.config import PolicyConfig
from lcmodels.policy.names import IMAGE_FEATURES, needs_predictor
from lcmodels.policy.shield import Shield, shield_for
from lcmodels.predictor.inference import Predictor
from lcsim.config import ScenarioConfig
from lcsim.envs import observation_space
from lcsim.planning import SafetyLayerConfig
from lcsim.registry import scenario as named_scenario


@dataclass(frozen=True)
class RunPlan:
    """A policy run's config with what it names, read (:func:`resolve`)."""

    config: PolicyConfig
    scenario: ScenarioConfig
    """The scenario the policy sees (its view applied): what every card of the run stores (read once: a file
    edited meanwhile changes none)."""
    roads: tuple[ScenarioConfig, ...]
    """The scenarios training drives (:attr:`PolicyConfig.train_roads`; one: ``scenario`` itself)."""
    predictor: Predictor | None = None
    """The trained predictor the observation reads (None: the mode reads no predictions)."""
    predictor_path: Path | None = None
    predictor_sha256: str | None = None
    layer: Shield | None = None
    """The safety layer that executes the policy's decisions while it trains (None: it drives itself)."""

    @property
    def predictor_file(self) -> str | None:
        """Where the predictor was read from, for ``run.json`` (the run's own record)."""
        return None if self.predictor_path is None else str(self.predictor_path.resolve())

    def card(self, timesteps: int, folder: Path, training_form: bool = False) -> dict[str, Any]:
        """The card of a policy file saved in ``folder``; ``training_form``: a frozen-image run's checkpoint,
        which sees the image branch's features in place of the image (resumable, not loadable as a policy).

        It names the predictor by its file name and SHA-256, which find it beside the policy or in a folder
        above it wherever the policy is copied (``find_predictor``), and by where it lay relative to the
        policy file (a hint, checked by the digest), never by an absolute path of this machine."""
        cfg, predictor = self.config, None
        if self.predictor_path is not None:
            predictor = {"file": self.predictor_path.name, "sha256": str(self.predictor_sha256)}
            with contextlib.suppress(ValueError):  # no relative path between two drives: name and digest only
                predictor["path"] = os.path.relpath(str(self.predictor_file), Path(folder).resolve())
        meta = {"algo": cfg.algo, "obs_mode": cfg.obs, "image_net": cfg.image_net,
                "scenario_name": cfg.scenario, "scenario": self.scenario.to_dict(),
                "predictor": predictor, "train_config": cfg.to_dict(), "timesteps": timesteps}  # fmt: skip
        if training_form:
            meta["training_form"] = IMAGE_FEATURES
        return meta


def policy_scenario(cfg: PolicyConfig) -> ScenarioConfig:
    """The scenario ``cfg.scenario`` names (a registered name, or a scenario file, read now) with ``cfg``'s view
    of the traffic. ``ValueError`` naming the field for an unknown name or an unreadable file."""
    try:
        return cfg.scenario_config(named_scenario(cfg.scenario))
    except ValueError as exc:
        raise ValueError(f"PolicyConfig.scenario: {exc}") from None


def resolve(cfg: PolicyConfig, *, predictor: str | os.PathLike[str] | None = None,
            layer: SafetyLayerConfig | None = None, penalty: float = 0.0) -> RunPlan:  # fmt: skip
    """The plan of a run of ``cfg``: its scenario, its roads (each checked to give the scenario's observations and
    reward), the ``predictor`` file of a mode that reads predictions (ignored by the others), and the safety
    ``layer`` it trains behind (blind, its imagined futures following ``layer.follow``: a policy file or a built-in
    driver), each decision the layer overrides costing ``penalty``. ``ValueError`` in one line, nothing built,
    for what cannot be resolved."""
    pred_path = Path(predictor) if predictor is not None and needs_predictor(cfg.obs) else None
    if needs_predictor(cfg.obs) and pred_path is None:
        raise ValueError(f"observation mode {cfg.obs!r} needs a trained predictor (--predictor)")
    if layer is not None and cfg.train_roads:
        raise ValueError("training behind the safety layer drives the scenario alone: train_roads must be ''")
    scenario = policy_scenario(cfg)
    roads = cfg.road_configs() or (scenario,)
    for name, road in zip(cfg.road_names(), roads, strict=False):
        if observation_space(road) != observation_space(scenario):
            raise ValueError(f"train_roads: {name!r} gives other observations than the scenario {cfg.scenario!r} "
                             "(neighbours, history or image size): a policy reads one shape")  # fmt: skip
        if road.reward != scenario.reward:
            raise ValueError(f"train_roads: {name!r} pays another reward than the scenario {cfg.scenario!r}: the "
                             "training statistics read one")  # fmt: skip
    pred = Predictor.load(pred_path) if pred_path is not None else None
    sha = file_sha256(pred_path) if pred_path is not None else None
    shield = None
    if layer is not None:
        shield = shield_for(layer, penalty, scenario, None if pred_path is None else str(pred_path))
    return RunPlan(cfg, scenario, roads, pred, pred_path, sha, shield)


__all__ = ["RunPlan", "policy_scenario", "resolve"]
