#!/usr/bin/env python
"""A learned safety critic: the lookahead planner's veto, distilled into a network that needs no simulator.

An experiment, not a method of record. The blind lookahead planner (``lookahead-blind:POLICY``) makes a
policy win more episodes by imagining each decision's future in simulator copies, which costs about 15x
a decision. DAgger taught the policy the planner's *choices* (about 1 correction in 250 states) without
gain. This tool teaches a separate network the planner's *survival labels* instead: for every state with
a choice, whether the imagined future after right / keep / left crashed, three labels a state.

``train`` lets POLICY drive ``--episodes`` training episodes (user seeds from ``--first-seed``), labels
every state with a choice by the expert's imagined futures (:attr:`lcsim.planning.LookaheadDriver.last_alive`),
keeps them in ``OUT/states.npz`` and fits ``--members`` critics (``current`` with contact features, an
MLP, three logits of the probability that each decision's future crashes) to them: ``OUT/critic.pt``,
with what was measured in ``OUT/critic.json``. ``--from-states FILE [FILE ...]`` refits on states kept before
(of several runs together: another policy's states, other episodes).

``score`` says how well a critic separates the labels of states kept by another ``train`` (other episodes).

``eval`` runs lc-eval's held-out episodes with POLICY behind the critic: the policy's decision stands
unless the critic gives it a crash probability above ``--threshold`` and another allowed decision one
lower by more than ``--margin`` (keep first). It prints one JSON object.

    python -m experiments.safety_critic.safety_critic train runs/pure91/policy.safetensors --expert lookahead-blind:runs/pure91/policy.safetensors \\
        --lookahead-horizon 32 --episodes 600 --workers 2 --out runs/critic
    python -m experiments.safety_critic.safety_critic eval runs/pure91/policy.safetensors --critic runs/critic/critic.pt --seed 0
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from lccli.common import fail, int_at_least, positive_int
from lccli.evaluate import add_heldout_arguments, eval_settings, heldout_driver
from lckit.pool import WorkerPool
from lcmodels.fileio import write_json
from lcmodels.policy.extractor import (
    CURRENT_SCALE,
    ConcatFeatures,
    ContactFeatures,
    ScaledMLP,
    WindowFeatures,
)
from lcsim.core import KEEP, LaneChangeCore

FORMAT = "lc-safety-critic"
VERSION = 1


class SafetyCritic(nn.Module):
    """``current`` ``(B, 1+K, 9)`` -> ``(B, 3)`` logits of "the future after right / keep / left crashes".

    The contact features always go in; ``window``: the window features too (lane slots only).
    """

    def __init__(self, slots: int, hidden: int = 256, window: bool = False) -> None:
        super().__init__()
        self.slots, self.hidden, self.window = slots, hidden, window
        extra = ConcatFeatures(ContactFeatures(slots), WindowFeatures(slots)) if window else ContactFeatures(slots)
        self.body = ScaledMLP((1 + slots, len(CURRENT_SCALE)), CURRENT_SCALE, hidden, hidden, extra=extra)
        self.head = nn.Sequential(nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, 3))

    def forward(self, current: torch.Tensor) -> torch.Tensor:
        return self.head(self.body(current))


class CriticEnsemble:
    """The mean crash probability of its members, on numpy batches."""

    def __init__(self, members: list[SafetyCritic], meta: dict[str, Any] | None = None) -> None:
        self.members, self.meta = members, dict(meta or {})
        for m in members:
            m.eval()

    def crash_probability(self, current: np.ndarray) -> np.ndarray:
        x = torch.as_tensor(np.asarray(current, dtype=np.float32))
        with torch.no_grad():
            return np.mean([torch.sigmoid(m(x)).numpy() for m in self.members], axis=0)

    def save(self, path: Path) -> None:
        tmp = path.with_name(path.name + ".partial")
        torch.save(
            {
                "format": FORMAT,
                "version": VERSION,
                "slots": self.members[0].slots,
                "hidden": self.members[0].hidden,
                "window": self.members[0].window,
                "members": [m.state_dict() for m in self.members],
                "meta": self.meta,
            },
            tmp,
        )
        tmp.replace(path)

    @classmethod
    def load(cls, path: Path) -> CriticEnsemble:
        """``ValueError`` with one line for a missing, corrupt or foreign file."""
        if not path.is_file():
            raise ValueError(f"critic {path} does not exist")
        try:
            blob = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # torch raises several kinds for a truncated or foreign file
            raise ValueError(
                f"{path} is not a readable safety critic (corrupt or truncated?): {str(exc).splitlines()[0]}"
            ) from exc
        if not isinstance(blob, dict) or blob.get("format") != FORMAT or blob.get("version") != VERSION:
            raise ValueError(f"{path} is not a safety critic of this version")
        members = []
        for state in blob["members"]:
            m = SafetyCritic(int(blob["slots"]), int(blob["hidden"]), bool(blob.get("window", False)))
            m.load_state_dict(state)
            members.append(m)
        return cls(members, blob.get("meta"))


def crash_targets(alive: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(target, weight)``: 1 - the share of imagined futures survived, and 1 where it was imagined (0 at NaN)."""
    seen = ~np.isnan(alive)
    return np.where(seen, 1.0 - np.nan_to_num(alive), 0.0).astype(np.float32), seen.astype(np.float32)


def critic_loss(critic: CriticEnsemble, current: np.ndarray, alive: np.ndarray) -> float:
    """Mean binary cross-entropy of the ensemble's mean probability over the imagined decisions."""
    target, weight = crash_targets(alive)
    p = torch.as_tensor(critic.crash_probability(current)).clamp(1e-7, 1 - 1e-7)
    loss = nn.functional.binary_cross_entropy(p, torch.as_tensor(target), weight=torch.as_tensor(weight),
                                              reduction="sum")
    return float(loss) / max(float(weight.sum()), 1.0)


def train_critics(
    current: np.ndarray,
    alive: np.ndarray,
    *,
    members: int = 3,
    epochs: int = 40,
    seed: int = 0,
    hidden: int = 256,
    batch: int = 512,
    lr: float = 1e-3,
    window: bool = False,
    progress: Any = None,
) -> CriticEnsemble:
    """Fit ``members`` critics (member ``i`` from torch seed ``seed + i``; ``window``: with the window
    features) to the survival labels."""
    x = torch.as_tensor(np.asarray(current, dtype=np.float32))
    target, weight = (torch.as_tensor(a) for a in crash_targets(alive))
    slots = x.shape[1] - 1
    nets = []
    for i in range(members):
        torch.manual_seed(seed + i)
        gen = np.random.default_rng(seed + i)
        net = SafetyCritic(slots, hidden, window)
        opt = torch.optim.Adam(net.parameters(), lr, weight_decay=1e-5)
        for epoch in range(epochs):
            order = gen.permutation(len(x))
            for j in range(0, len(order), batch):
                b = torch.as_tensor(order[j : j + batch])
                w = weight[b]
                loss = nn.functional.binary_cross_entropy_with_logits(
                    net(x[b]), target[b], weight=w, reduction="sum"
                ) / w.sum().clamp(min=1.0)
                opt.zero_grad()
                loss.backward()
                opt.step()
            if progress is not None:
                progress(i, epoch + 1)
        nets.append(net)
    return CriticEnsemble(nets)


class CriticGuard:
    """``driver(obs, mask, core)`` whose decision a critic overrides when it expects a crash after it."""

    def __init__(
        self, driver: Any, critic: CriticEnsemble, *, threshold: float = 0.5, margin: float = 0.2
    ) -> None:
        self.driver, self.critic, self.threshold, self.margin = driver, critic, threshold, margin
        self.name = f"{getattr(driver, 'name', 'driver')}+critic"
        self.choices = self.overrides = 0

    @property
    def last_prediction(self) -> np.ndarray | None:
        return getattr(self.driver, "last_prediction", None)

    def __call__(self, obs: dict[str, np.ndarray], mask: np.ndarray, core: LaneChangeCore) -> np.ndarray:
        actions = np.array(self.driver(obs, mask, core), dtype=np.int64).reshape(-1)
        mask = np.asarray(mask, dtype=bool).reshape(-1, 3)
        rows = np.arange(len(actions))
        p = self.critic.crash_probability(obs["current"])
        own = p[rows, actions]
        p = np.where(mask, p, np.inf)
        best = p.min(axis=1)
        choice = (mask.sum(axis=1) > 1) & mask[rows, actions]
        fallback = np.where(p[:, KEEP] <= best, KEEP, p.argmin(axis=1))
        override = choice & (own > self.threshold) & (best < own - self.margin)
        self.choices += int(choice.sum())
        self.overrides += int(override.sum())
        return np.where(override, fallback, actions).astype(np.int64)


def _collect_job(job: tuple[int, str, list[int], str, dict[str, int]]) -> Any:
    from lcmodels.policy.dagger import collect_from_driver
    from lcmodels.policy.driverspec import safety_layer_of

    worker, policy, seeds, expert, lookahead = job

    def show(done: int, total: int) -> None:
        print(f"collecting: worker {worker}: {done}/{total} episodes", flush=True)

    return collect_from_driver(policy, seeds, expert, safety=safety_layer_of(expert, lookahead), progress=show)


def _overridable(alive: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(doomed, overridable)``: no imagined future survives the policy's decision; and, of those, the ones
    where another decision's does (where the planner would override)."""
    doomed = alive[np.arange(len(actions)), actions] == 0
    return doomed, doomed & (np.nanmax(np.where(np.isnan(alive), -1.0, alive), axis=1) > 0)


def _summary(alive: np.ndarray, actions: np.ndarray) -> dict[str, Any]:
    """What the labels say about the policy's own decisions."""
    doomed, overridable = _overridable(alive, actions)
    imagined = ~np.isnan(alive)
    return {
        "states": len(actions),
        "crash_rate_per_decision": [
            float(1 - alive[imagined[:, a], a].mean()) if imagined[:, a].any() else None for a in range(3)
        ],
        "doomed_decisions": int(doomed.sum()),
        "doomed_with_a_surviving_alternative": int(overridable.sum()),
        "of_which_keep": int((overridable & (actions == KEEP)).sum()),
    }


def train_main(args: argparse.Namespace, prog: str) -> int:
    out = args.out
    if out.exists() and any(out.iterdir()):
        return fail(prog, f"{out} exists and is not empty; choose a new --out")
    meta: dict[str, Any] = {
        "policy": str(args.policy),
        "members": args.members,
        "epochs": args.epochs,
        "window_features": args.window_features,
        "seed": args.seed,
    }
    if args.window_features or args.from_states is None:  # the policy is read (it drives, or it sets the slots)
        from lcmodels.policy.checkpoint import read_meta

        try:
            selection = read_meta(args.policy).get("scenario", {}).get("neighbour_selection", "nearest")
        except ValueError as exc:
            return fail(prog, str(exc).splitlines()[0])
        if args.window_features and selection != "lanes":  # the window features read vehicles sorted by lane
            return fail(prog, f"--window-features needs lane slots; {args.policy} sees the {selection} vehicles")
    t0 = time.perf_counter()
    if args.from_states is not None:
        parts = []
        for path in args.from_states:
            try:
                with np.load(path) as kept:
                    parts.append((kept["current"], kept["alive"], kept["actions"]))
            except (OSError, ValueError, KeyError, EOFError) as exc:
                return fail(prog, f"{path}: not readable states of this tool ({str(exc).splitlines()[0]})")
        current, alive, actions = (np.concatenate(column) for column in zip(*parts, strict=True))
        meta["states_from"] = [str(p) for p in args.from_states]
    else:
        from lcmodels.policy.driverspec import safety_layer_of
        from lcmodels.policy.evaluate import driver_for
        from lcsim.planning import LookaheadDriver

        lookahead = {"horizon_decisions": args.lookahead_horizon} if args.lookahead_horizon else {}
        try:
            expert, _ = driver_for(args.expert, safety=safety_layer_of(args.expert, lookahead))
        except ValueError as exc:
            return fail(prog, str(exc).splitlines()[0])
        if not isinstance(expert, LookaheadDriver):
            return fail(
                prog, f"the expert must be a lookahead driver (lookahead[-blind][:POLICY]), not {args.expert}"
            )
        seeds = [args.first_seed + i for i in range(args.episodes)]
        parts = [seeds[i :: args.workers] for i in range(args.workers) if seeds[i :: args.workers]]
        print(
            f"collecting: {args.episodes} episodes of {args.policy} labelled by {args.expert} on "
            f"{len(parts)} workers",
            flush=True,
        )
        try:
            with WorkerPool(len(parts)) as pool:
                got = []
                for k, g in enumerate(
                    pool.map(_collect_job, [(k + 1, str(args.policy), p, args.expert, lookahead) for k, p in enumerate(parts)])
                ):
                    got.append(g)
                    print(
                        f"collecting: worker {k + 1}/{len(parts)} done ({len(g.labels)} states)", flush=True
                    )
        except (ValueError, OSError) as exc:
            return fail(prog, str(exc).splitlines()[0])
        current = np.concatenate([g.obs["current"] for g in got])
        alive = np.concatenate([g.alive for g in got])
        actions = np.concatenate([g.actions for g in got])
        outcomes = [o for g in got for o in g.outcomes]
        out.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(out / "states.npz", current=current, alive=alive, actions=actions)
        meta.update(
            expert=args.expert,
            lookahead=lookahead,
            episodes=args.episodes,
            first_seed=args.first_seed,
            policy_success_rate=outcomes.count("success") / len(outcomes),
            collect_wall_s=round(time.perf_counter() - t0, 1),
        )
    if len(current) == 0:
        return fail(prog, "no state with a choice was collected; nothing to fit")
    meta["labels"] = _summary(alive, actions)
    t1 = time.perf_counter()

    def show(member: int, epoch: int) -> None:
        if epoch % 10 == 0 or epoch == args.epochs:
            print(f"training: member {member + 1}/{args.members}, epoch {epoch}/{args.epochs}", flush=True)

    try:
        critic = train_critics(
            current, alive, members=args.members, epochs=args.epochs, seed=args.seed, window=args.window_features,
            progress=show,
        )
    except ValueError as exc:  # window features over too few slots for both side lanes
        return fail(prog, str(exc).splitlines()[0])
    meta.update(
        train_wall_s=round(time.perf_counter() - t1, 1), train_loss=critic_loss(critic, current, alive)
    )
    critic.meta = meta
    out.mkdir(parents=True, exist_ok=True)
    critic.save(out / "critic.pt")
    write_json(out / "critic.json", meta)
    print(f"wrote {out / 'critic.pt'} ({len(current)} states, loss {meta['train_loss']:.4f})")
    return 0


def _auc(score: np.ndarray, positive: np.ndarray) -> float | None:
    """Area under the ROC curve (ties count half); None without both classes."""
    import pandas as pd

    pos, n = int(positive.sum()), len(positive)
    if pos in (0, n):
        return None
    ranks = pd.Series(score).rank(method="average").to_numpy()
    return float((ranks[positive].sum() - pos * (pos + 1) / 2) / (pos * (n - pos)))


SCREEN_THRESHOLDS = (0.005, 0.01, 0.05, 0.2, 0.5)


def score_states(critic: CriticEnsemble, current: np.ndarray, alive: np.ndarray, actions: np.ndarray) -> dict[str, Any]:
    """How well the critic separates the labels: per-decision AUC, and for the policy's own decisions that the
    planner would override (no imagined future survives them, one of another decision does), the share of
    states whose crash probability exceeds each threshold and the share of those decisions among them."""
    p = critic.crash_probability(current)
    imagined = ~np.isnan(alive)
    crash = np.nan_to_num(alive) < 0.5
    rows = np.arange(len(actions))
    own = p[rows, actions]
    overridable = _overridable(alive, actions)[1]
    return {
        "states": len(actions),
        "loss": critic_loss(critic, current, alive),
        "auc_per_decision": [_auc(p[imagined[:, a], a], crash[imagined[:, a], a]) for a in range(3)],
        "auc_own_decision": _auc(own, crash[rows, actions]),
        "overridable": int(overridable.sum()),
        "screen": [{"threshold": t, "states_above": float((own > t).mean()),
                    "overridable_above": float((own > t)[overridable].mean()) if overridable.any() else None}
                   for t in SCREEN_THRESHOLDS],
    }


def score_main(args: argparse.Namespace, prog: str) -> int:
    try:
        critic = CriticEnsemble.load(args.critic)
        with np.load(args.states) as kept:
            current, alive, actions = kept["current"], kept["alive"], kept["actions"]
    except (OSError, ValueError, KeyError, EOFError) as exc:
        return fail(prog, str(exc).splitlines()[0])
    print(json.dumps({"critic": str(args.critic), "states_file": str(args.states),
                      **score_states(critic, current, alive, actions)}))
    return 0


def eval_main(args: argparse.Namespace, prog: str) -> int:
    from lcmodels.policy.evaluate import evaluate

    if not 0.0 <= args.threshold <= 1.0 or args.margin < 0:
        return fail(prog, "--threshold must lie in [0, 1] and --margin be >= 0")
    try:
        critic = CriticEnsemble.load(args.critic)
        driver, config = heldout_driver(args)
        batch = eval_settings(args)[0].batch
    except ValueError as exc:
        return fail(prog, str(exc).splitlines()[0])
    if critic.members[0].slots != config.num_neighbours:
        return fail(prog, f"{args.critic} reads {critic.members[0].slots} neighbour slots, the scenario of "
                     f"{args.policy} has {config.num_neighbours}")
    if critic.members[0].window and config.neighbour_selection != "lanes":
        return fail(prog, f"{args.critic} reads the window features, which need lane slots; the scenario of "
                     f"{args.policy} sees the {config.neighbour_selection} vehicles")
    guard = CriticGuard(driver, critic, threshold=args.threshold, margin=args.margin)
    t0 = time.perf_counter()
    summary, results = evaluate(guard, config, episodes=args.episodes, seed=args.seed, batch=batch)
    print(
        json.dumps(
            {
                "driver": guard.name,
                "policy": args.policy,
                "critic": str(args.critic),
                "threshold": args.threshold,
                "margin": args.margin,
                "episodes": args.episodes,
                "eval_seed": args.seed,
                **{
                    k: summary[k] for k in ("success_rate", "collision_rate", "off_road_rate", "timeout_rate")
                },
                "success_rate_ci95": summary["success_rate_ci95"],
                "choices": guard.choices,
                "overrides": guard.overrides,
                "decisions": sum(r.length for r in results),
                "wall_s": round(time.perf_counter() - t0, 1),
            }
        )
    )
    return 0


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="safety_critic",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__,
    )
    sub = p.add_subparsers(dest="command", required=True)
    t = sub.add_parser("train", help="collect survival labels along a policy's episodes and fit the critic")
    t.add_argument("policy", type=Path, help="the policy.safetensors that drives (its states are the ones labelled)")
    t.add_argument(
        "--expert",
        default="lookahead-blind",
        help="lookahead driver whose imagined futures label the states (default lookahead-blind, which "
        "follows the rule; lookahead-blind:POLICY follows a policy without image)",
    )
    t.add_argument(
        "--lookahead-horizon",
        type=positive_int,
        default=None,
        help="decisions the expert imagines after each candidate one (default 16, i.e. 8 s)",
    )
    t.add_argument(
        "--episodes", type=positive_int, default=600, help="training episodes driven (default 600)"
    )
    t.add_argument(
        "--first-seed",
        type=int_at_least(0),
        default=7_000_000,
        help="user seed of the first episode (default 7000000; evaluation's start at 10^9)",
    )
    t.add_argument("--workers", type=positive_int, default=2, help="collecting processes (default 2)")
    t.add_argument("--members", type=positive_int, default=3, help="critics in the ensemble (default 3)")
    t.add_argument("--epochs", type=positive_int, default=40, help="training epochs per critic (default 40)")
    t.add_argument(
        "--seed", type=int_at_least(0), default=0, help="torch seed of the first critic (default 0)"
    )
    t.add_argument(
        "--window-features", action="store_true",
        help="the critic also reads the window features (lcmodels.policy.extractor.WindowFeatures)"
    )
    t.add_argument(
        "--from-states", type=Path, nargs="+", default=None,
        help="fit to the states.npz files kept before, together; collect nothing"
    )
    t.add_argument(
        "--out", type=Path, required=True, help="new directory for states.npz, critic.pt, critic.json"
    )
    c = sub.add_parser("score", help="how well a critic separates the labels of states kept by train")
    c.add_argument("--critic", type=Path, required=True, help="critic.pt written by train")
    c.add_argument("--states", type=Path, required=True, help="states.npz written by train (other episodes)")
    e = sub.add_parser("eval", help="lc-eval's held-out episodes with the policy behind the critic")
    add_heldout_arguments(e)
    e.add_argument("--critic", type=Path, required=True, help="critic.pt written by train")
    e.add_argument(
        "--threshold",
        type=float,
        default=0.5,
        help="least crash probability of the policy's decision for an override (default 0.5)",
    )
    e.add_argument(
        "--margin",
        type=float,
        default=0.2,
        help="how much lower the alternative's crash probability must be (default 0.2)",
    )
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    torch.set_num_threads(1)
    run = {"train": train_main, "score": score_main, "eval": eval_main}[args.command]
    return run(args, f"safety_critic {args.command}")


if __name__ == "__main__":
    sys.exit(main())
