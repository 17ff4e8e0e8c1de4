"""Naming a policy's choices costs no deep-learning import: the policy config and every command's ``--help``
load neither torch nor stable-baselines3 (each checked in a fresh interpreter)."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
HEAVY = ("torch", "stable_baselines3")


def _loaded_after(code: str) -> list[str]:
    """The heavy modules in ``sys.modules`` after ``code`` runs in a fresh interpreter (from the repository root)."""
    probe = f"{code}\nimport sys\nprint(' '.join(m for m in {HEAVY!r} if m in sys.modules))"
    done = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return done.stdout.split()


def test_importing_the_policy_config_imports_no_torch() -> None:
    code = ("from lcmodels.policy.config import PolicyConfig\n"
            "from lcmodels.policy.names import IMAGE_NETS, OBS_MODES\n"
            "assert PolicyConfig(image_net=IMAGE_NETS[0], obs=OBS_MODES[0]).with_settings(['gamma=0.9']).gamma == 0.9")
    assert _loaded_after(code) == []
    assert _loaded_after("import lcmodels.policy.extractor") == list(HEAVY)  # the probe sees them when they are there


COMMANDS = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_help_imports_no_torch(command: str) -> None:
    module, main = COMMANDS[command].split(":")
    code = (f"from {module} import {main}\n"
            f"import contextlib, io\n"
            f"with contextlib.redirect_stdout(io.StringIO()) as out:\n"
            f"    try:\n        {main}(['--help'])\n    except SystemExit as exc:\n        assert exc.code == 0\n"
            f"assert 'usage' in out.getvalue().lower(), out.getvalue()")
    assert _loaded_after(code) == []
