"""The key of one stage of an experiment: its name, its directory and the name of its record.

A stage belongs to a recipe and a training seed (``hybrid-ppo/seed0/train`` in
``policies/hybrid-ppo/seed0/train/``) or to the whole experiment (``corpus`` in ``corpus/``, ``demos/<key>`` in
``demos/<key>/``, ``rule``, ``zoo/<entry>``, ``showcase``...). Its record is ``stages/<name with / as __>.json``.
These names and places are those of every experiment directory written so far, so that a directory resumes.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from lcmodels.presets import policy_dir

_WORD = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._+-]*$")
_RECIPE_STAGE = re.compile(r"^(?P<recipe>[^/]+)/seed(?P<seed>[0-9]+)/(?P<stage>[^/]+)$")


@dataclass(frozen=True, slots=True)
class StageKey:
    """``(recipe, seed, stage)`` of a recipe's stage; a stage of the whole experiment has no recipe and no seed,
    and ``part`` names one of several stages of a kind (``demos``' key, a zoo entry). Build the latter with
    :meth:`of`."""

    recipe: str | None
    seed: int | None
    stage: str
    part: str | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.stage, str) or not _WORD.match(self.stage):
            raise ValueError(f"a stage is one word of letters, digits and -._+, got {self.stage!r}")
        if (self.recipe is None) != (self.seed is None):
            raise ValueError(f"a recipe's stage has both a recipe and a seed, got {self.recipe!r} and {self.seed!r}")
        if self.recipe is not None:
            if not _WORD.match(self.recipe) or self.part is not None:
                raise ValueError(f"a recipe's stage has a recipe name and no part, got {self.recipe!r}, {self.part!r}")
            if not isinstance(self.seed, int) or isinstance(self.seed, bool) or self.seed < 0:
                raise ValueError(f"a training seed is an integer >= 0, got {self.seed!r}")
        elif self.part is not None and not _WORD.match(self.part):
            raise ValueError(f"a stage's part is one word of letters, digits and -._+, got {self.part!r}")

    @classmethod
    def of(cls, stage: str, part: str | None = None) -> StageKey:
        """A stage of the whole experiment (``corpus``, ``predictor``, ``demos`` with its key as ``part``...)."""
        return cls(None, None, stage, part)

    @classmethod
    def parse(cls, name: str) -> StageKey:
        """The key whose :attr:`name` is ``name``; ``ValueError`` for anything else."""
        try:
            if m := _RECIPE_STAGE.match(name):
                return cls(m["recipe"], int(m["seed"]), m["stage"])
            stage, _, part = name.partition("/")
            key = cls.of(stage, part or None)
        except ValueError:
            key = None
        if key is None or key.name != name:
            raise ValueError(f"not a stage name: {name!r}")
        return key

    @property
    def name(self) -> str:
        """``<recipe>/seed<k>/<stage>``, ``<stage>/<part>`` or ``<stage>``: what progress and the report show."""
        if self.recipe is not None:
            return f"{self.recipe}/seed{self.seed}/{self.stage}"
        return f"{self.stage}/{self.part}" if self.part is not None else self.stage

    @property
    def record_name(self) -> str:
        """The stem of the stage's records in ``stages/`` (``hybrid-ppo__seed0__train``)."""
        return self.name.replace("/", "__")

    def path(self, out: str | Path) -> Path:
        """The stage's directory in the experiment directory ``out``."""
        if self.recipe is not None:
            assert self.seed is not None
            return policy_dir(Path(out), self.recipe, self.seed) / self.stage
        return Path(out) / self.stage / self.part if self.part is not None else Path(out) / self.stage

    def __str__(self) -> str:
        return self.name
