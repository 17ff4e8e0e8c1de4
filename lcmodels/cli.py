"""Command lines of lcmodels: ``lc-train-predictor``, ``lc-train-policy``, ``lc-eval``.

A console script is a thin ``main(argv) -> int`` that turns flags into a config and calls the library,
so tests call it in-process. Bad input ends with one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import functools
import json
import logging
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from lcsim.cli import add_lookahead_arguments, int_at_least, lookahead_options

if TYPE_CHECKING:
    from lcsim.config import ScenarioConfig

TRAIN_PREDICTOR_EPILOG = """examples:
  lc-record --scenario corpus --episodes 24 --seed 100 --out runs/corpus --workers 2
  lc-train-predictor --data runs/corpus --out runs/predictor-10-10
  lc-train-predictor --data runs/corpus --history 20 --future 60 --stride 5 --out runs/predictor-20-60

outputs (in --out): predictor.pt (weights, normalisation statistics, config; loads with
torch.load(weights_only=True)), metrics.json (test-split ADE/FDE/curve/miss rate of the model,
constant velocity and constant acceleration on the same windows, corpus statistics), tensorboard/.
"""


_positive_int = int_at_least(1)


def _fail(prog: str, msg: str) -> int:
    """Print ``prog: error: msg`` on stderr (one line, no traceback) and return the exit status 2."""
    print(f"{prog}: error: {msg}", file=sys.stderr)
    return 2


def train_predictor_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="lc-train-predictor",
        description="Build the trajectory corpus from recorded MCAP episodes (split by episode), train the "
        "transformer predictor with early stopping, and report test ADE/FDE next to the "
        "constant-velocity and constant-acceleration baselines.",
        epilog=TRAIN_PREDICTOR_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--data", type=Path, required=True, help="directory of recorded .mcap episodes (at least 3)"
    )
    p.add_argument(
        "--out", type=Path, default=Path("runs/predictor"), help="output directory (default runs/predictor)"
    )
    p.add_argument("--history", type=_positive_int, default=10, help="history steps H at 20 Hz (default 10)")
    p.add_argument("--future", type=_positive_int, default=10, help="future steps F at 20 Hz (default 10)")
    p.add_argument("--epochs", type=_positive_int, default=20, help="maximum epochs (default 20)")
    p.add_argument(
        "--patience", type=int, default=4, help="epochs without improvement before stopping (default 4)"
    )
    p.add_argument(
        "--stride", type=_positive_int, default=1, help="steps between windows of a vehicle (default 1)"
    )
    p.add_argument("--batch-size", type=_positive_int, default=512, help="windows per step (default 512)")
    p.add_argument(
        "--max-train-windows",
        type=_positive_int,
        default=200_000,
        help="deterministic subsample of training windows (default 200000)",
    )
    p.add_argument(
        "--time-limit", type=float, default=None, help="stop after the epoch that passes this many seconds"
    )
    p.add_argument(
        "--seed", type=int, default=0, help="seed for the split, initialisation and batches (default 0)"
    )
    p.add_argument("--threads", type=_positive_int, default=2, help="torch threads (default 2)")
    p.add_argument(
        "--overwrite", action="store_true", help="replace an existing predictor.pt / metrics.json in --out"
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    return p


def train_predictor_main(argv: list[str] | None = None) -> int:
    args = train_predictor_parser().parse_args(argv)

    fail = functools.partial(_fail, "lc-train-predictor")

    if not args.data.is_dir():
        return fail(f"--data {args.data} is not a directory")
    from lcmodels.predictor.train import METRICS_NAME

    existing = [p for p in (args.out / "predictor.pt", args.out / METRICS_NAME) if p.exists()]
    if existing and not args.overwrite:
        return fail(f"{existing[0]} already exists; choose another --out or pass --overwrite")
    if args.time_limit is not None and args.time_limit <= 0:
        return fail(f"--time-limit must be > 0, got {args.time_limit}")
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO, format="%(message)s")

    from lcdata.corpus import load_tracks
    from lcmodels.predictor import PredictorConfig, TrainConfig, train_predictor

    try:
        config = TrainConfig(
            model=PredictorConfig(history_steps=args.history, future_steps=args.future),
            stride=args.stride,
            batch_size=args.batch_size,
            max_epochs=args.epochs,
            patience=args.patience,
            max_train_windows=args.max_train_windows,
            seed=args.seed,
            num_threads=args.threads,
            time_limit_s=args.time_limit,
            progress=not args.quiet,
        )
        tracks = load_tracks(args.data)
        metrics = train_predictor(tracks, config, args.out)
    except (ValueError, OSError) as exc:
        return fail(str(exc).splitlines()[0])
    rows = [
        ("model", metrics["model"]),
        ("constant velocity", metrics["constant_velocity"]),
        ("constant acceleration", metrics["constant_acceleration"]),
    ]
    print(
        f"test split, {args.history}+{args.future} steps ({metrics['corpus'].get('windows', {}).get('test', '?')} windows):"
    )
    for name, m in rows:
        print(f"  {name:22s} ADE {m['ade']:.4f} m   FDE {m['fde']:.4f} m   miss rate {m['miss_rate']:.4f}")
    print(f"wrote {args.out / 'predictor.pt'} and {args.out / METRICS_NAME}")
    if not args.quiet:
        logging.getLogger(__name__).info("training: %s", json.dumps(metrics.get("training", {}))[:300])
    return 0




# --------------------------------------------------------------------------------------- lc-train-policy
TRAIN_POLICY_EPILOG = """examples:
  lc-train-policy --algo ppo --obs pure --timesteps 100000 --out runs/ppo-pure
  lc-train-policy --algo ppo --obs hybrid --predictor runs/predictor/predictor.pt --out runs/hybrid-ppo
  lc-record --episodes 40 --seed 5000 --out runs/rule-demos --no-images   # then:
  lc-train-policy --obs pure --warm-start runs/rule-demos --out runs/ppo-pure-warm

Rerunning with the same --out resumes from the last checkpoint (the step count continues) or, when
training is complete, only redoes a missing evaluation. A different config in --out is refused.

outputs (in --out): policy.safetensors (the policy; lc-eval and lc-record --driver policy:PATH load it),
checkpoints/latest.json, progress.csv (outcome rates, return, safe forward distance over the last 100
episodes at each log step), tb/ (TensorBoard), eval/metrics.json and eval/episodes/*.mcap (held-out
evaluation), metrics.json (training summary + evaluation), run.json (config, predictor, versions).
"""


def train_policy_parser() -> argparse.ArgumentParser:
    from lcmodels.policy.checkpoint import ALGOS
    from lcmodels.policy.extractor import IMAGE_NETS
    from lcmodels.policy.obs import OBS_MODES
    from lcmodels.policy.train import POLICY_SCENARIOS, PolicyConfig
    from lcsim.config import NEIGHBOUR_SELECTIONS

    d = PolicyConfig()
    p = argparse.ArgumentParser(
        prog="lc-train-policy",
        description="Train the lane-change policy online on the batched simulator (PPO, A2C or DQN with the "
        "hybrid features extractor), optionally warm-started from recorded episodes, then evaluate it "
        "on held-out seeds.",
        epilog=TRAIN_POLICY_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--algo", choices=list(ALGOS), default=d.algo, help="default %(default)s")
    p.add_argument("--obs", choices=OBS_MODES, default=d.obs,
                   help="observation mode (Table IV): pure, image, prediction, hybrid (default %(default)s)")
    p.add_argument("--predictor", type=Path, help="predictor.pt from lc-train-predictor (prediction, hybrid)")
    p.add_argument("--scenario", choices=list(POLICY_SCENARIOS), default=d.scenario,
                   help="paper: 100 vehicles, 600 m route; light: 30 vehicles, 300 m; tiny: 8 vehicles, 150 m, "
                   "for smoke tests (default %(default)s)")
    p.add_argument("--neighbours", choices=NEIGHBOUR_SELECTIONS, default=d.neighbours,
                   help="the 8 vehicles the observation shows: lanes (leader and follower in the ego's lane and "
                   "the lanes beside it, then the second leaders beside it) or nearest (the 8 nearest by "
                   "distance) (default %(default)s)")
    p.add_argument("--slots", type=_positive_int, default=d.slots,
                   help="how many vehicles the observation shows: the paper's 8, or with --neighbours lanes up to "
                   "16, the slots after the eighth a wider view (the leader's leaders, the second followers beside "
                   "the ego, leader and follower two lanes over) (default %(default)s)")
    p.add_argument("--timesteps", type=int_at_least(0), default=d.timesteps,
                   help="online decisions over all envs; 0 with --warm-start: behaviour cloning only, no online "
                   "training (default %(default)s)")
    p.add_argument("--n-envs", type=_positive_int, default=d.n_envs, help="parallel episodes (default %(default)s)")
    p.add_argument("--seed", type=int_at_least(0), default=d.seed, help="training seed (default %(default)s)")
    p.add_argument("--image-net", choices=IMAGE_NETS, default=d.image_net,
                   help="image branch: compact VGG-style (CPU) or the paper's VGG-16 (default %(default)s)")
    p.add_argument("--contact-features", action=argparse.BooleanOptionalAction, default=d.contact_features,
                   help="give the sensor branch each neighbour slot's time to contact, gap and proximity "
                   "(default on)")
    p.add_argument("--window-features", action="store_true",
                   help="give the sensor branch, per side lane, when over the next 16 s the ego could change into "
                   "it, against when its own leader traps it (every shown vehicle at its present speed)")
    p.add_argument("--collision-weight", type=float, default=d.collision_weight,
                   help="multiply the learner's collision reward by this (training only; returns are logged and "
                   "evaluated with the paper's reward; default %(default)s)")
    p.add_argument("--accel-features", action="store_true",
                   help="observe each vehicle's acceleration too (a tenth column of `current`); with "
                   "--window-features, also the same look with the accelerations kept for 2.5 s")
    p.add_argument("--lr", type=float, default=None,
                   help="learning rate (default 3e-4, and 3e-5 for PPO after --warm-start or --init-policy, which "
                   "keeps what the clone learnt; A2C 7e-4; DQN 1e-4)")
    p.add_argument("--gamma", type=float, default=d.gamma,
                   help="discount factor per decision (default %(default)s: a 10 s horizon at 2 decisions a second)")
    p.add_argument("--n-steps", type=_positive_int, default=None,
                   help="PPO/A2C rollout steps per env (default 128; A2C 8)")
    p.add_argument("--warm-start", type=Path, default=None,
                   help="directory of recorded MCAP episodes to pretrain on (behaviour cloning)")
    p.add_argument("--warm-start-epochs", type=_positive_int, default=d.warm_start_epochs,
                   help="behaviour-cloning epochs (default %(default)s)")
    p.add_argument("--init-policy", type=Path, default=None,
                   help="a policy.safetensors to start online training from (a cloned run's, a DAgger round's); same "
                   "observation mode, predictor, scenario and network")
    p.add_argument("--freeze-image", action="store_true",
                   help="with --init-policy (image, hybrid): keep its image branch fixed and run it once per step "
                   "in the environment wrapper, so PPO's epochs do not re-run the network (several times the "
                   "steps per minute); policy.safetensors stays a plain policy")
    p.add_argument("--checkpoint-every", type=_positive_int, default=d.checkpoint_every,
                   help="timesteps between checkpoints (default %(default)s)")
    p.add_argument("--eval-episodes", type=int_at_least(0), default=d.eval_episodes,
                   help="held-out evaluation episodes at the end, 0 to skip (default %(default)s)")
    p.add_argument("--eval-seed", type=int_at_least(0), default=d.eval_seed, help="evaluation seed (default 0)")
    p.add_argument("--no-record-eval", action="store_true", help="do not record the evaluation episodes")
    p.add_argument("--threads", type=_positive_int, default=2, help="torch threads (default 2)")
    p.add_argument("--device", default="cpu", help="torch device (default cpu; cuda for the GPU)")
    p.add_argument("--out", type=Path, required=True, help="run directory (resumed when it holds this run)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a run of another configuration in --out: only the files a training run writes are "
                   "removed, after every other check has passed; anything else there stays")
    p.add_argument("--trust-pickle", action="store_true",
                   help="let --init-policy be a legacy stable-baselines3 .zip; loading one runs code stored in it, so "
                   "only for files from a source you trust")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    return p


def _fmt_row(row: dict) -> str:
    return (f"step {int(row['timesteps']):>8d}  {row['wall_s'] / 60:6.1f} min  episodes {int(row['episodes_total']):>5d}  "
            f"success {row['success_rate']:.2f}  collision {row['collision_rate']:.2f}  "
            f"timeout {row['timeout_rate']:.2f}  return {row['mean_return']:8.1f}  "
            f"safe forward {row['mean_safe_forward_m']:6.1f} m")


def train_policy_main(argv: list[str] | None = None) -> int:
    args = train_policy_parser().parse_args(argv)

    fail = functools.partial(_fail, "lc-train-policy")

    import torch

    from lcmodels.fileio import POLICY_FILE
    from lcmodels.policy.obs import needs_predictor
    from lcmodels.policy.train import PolicyConfig, default_learning_rate, train_policy

    if needs_predictor(args.obs) and args.predictor is None:
        return fail(f"--obs {args.obs} needs --predictor (a predictor.pt from lc-train-predictor)")
    if args.predictor is not None and not needs_predictor(args.obs):
        return fail(f"--obs {args.obs} uses no predictor; drop --predictor {args.predictor}")
    if args.predictor is not None and not args.predictor.is_file():
        return fail(f"--predictor {args.predictor} does not exist")
    if args.warm_start is not None and not args.warm_start.exists():
        return fail(f"--warm-start {args.warm_start} does not exist")
    if args.init_policy is not None and not args.init_policy.is_file():
        return fail(f"--init-policy {args.init_policy} does not exist")
    fine_tune = args.warm_start is not None or args.init_policy is not None
    learning_rate = args.lr if args.lr is not None else default_learning_rate(args.algo, fine_tune)
    try:
        cfg = PolicyConfig(
            algo=args.algo, obs=args.obs, scenario=args.scenario, neighbours=args.neighbours,
            slots=args.slots, gamma=args.gamma, window_features=args.window_features,
            accel_features=args.accel_features, collision_weight=args.collision_weight,
            timesteps=args.timesteps, n_envs=args.n_envs,
            seed=args.seed, image_net=args.image_net, contact_features=args.contact_features,
            learning_rate=learning_rate,
            n_steps=args.n_steps or (8 if args.algo == "a2c" else 128), checkpoint_every=args.checkpoint_every,
            eval_episodes=args.eval_episodes, eval_seed=args.eval_seed, record_eval=not args.no_record_eval,
            warm_start=str(args.warm_start or ""), warm_start_epochs=args.warm_start_epochs,
            init_policy=str(args.init_policy or ""), freeze_image=args.freeze_image,
        )  # fmt: skip
    except ValueError as exc:
        return fail(str(exc))
    torch.set_num_threads(args.threads)
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO, format="%(message)s")
    show = None if args.quiet else (lambda row: print(_fmt_row(row), flush=True))
    show_eval = None if args.quiet else (lambda k, n: print(f"evaluating: {k}/{n} episodes", flush=True))
    try:
        res = train_policy(cfg, args.out, predictor=args.predictor, device=args.device, progress=show,
                           eval_progress=show_eval, overwrite=args.overwrite,
                           trust_pickle=args.trust_pickle)  # fmt: skip
    except (ValueError, OSError) as exc:
        return fail(str(exc).splitlines()[0])
    ev = res.metrics.get("eval")
    print(f"trained {res.timesteps} steps in {res.wall_s / 60:.1f} min -> {args.out / POLICY_FILE}")
    if ev:
        print(_fmt_eval(ev))
    print(f"wrote {args.out / 'metrics.json'}")
    return 0


def _fmt_eval(ev: dict) -> str:
    def rate(k: str) -> str:
        lo, hi = ev[f"{k}_rate_ci95"]
        return f"{k} {100 * ev[f'{k}_rate']:.1f}% [{100 * lo:.1f}, {100 * hi:.1f}]"

    lo, hi = ev["mean_safe_forward_m_ci95"]
    rlo, rhi = ev["mean_return_ci95"]
    return (f"held-out evaluation, {ev['episodes']} episodes: " + ", ".join(rate(k) for k in
            ("success", "collision", "off_road", "timeout")) +
            f"; safe forward {ev['mean_safe_forward_m']:.1f} m [{lo:.1f}, {hi:.1f}]"
            f"; return {ev['mean_return']:.1f} [{rlo:.1f}, {rhi:.1f}]")


# --------------------------------------------------------------------------------------------- lc-eval
EVAL_EPILOG = """examples:
  lc-eval runs/hybrid-ppo/policy.safetensors --episodes 200 --seed 0 --json-out runs/hybrid-ppo/eval200.json
  lc-eval rule --episodes 200 --out runs/rule-eval
  lc-eval lookahead-blind:runs/hybrid-ppo/policy.safetensors --lookahead-follow runs/ppo-pure/policy.safetensors \\
      --lookahead-horizon 32 --no-record     # Hybrid-PPO behind the planner, imagining 16 s with the pure policy

Evaluation episode i uses the user seed 1000000000 + 100000 * SEED + i, disjoint from training seeds.
Prints outcome rates (fractions) and means with 95% intervals; --json-out writes them as JSON; every
episode is recorded to MCAP under --out (actions, reward components, predictions the policy saw).
"""


def heldout_driver(args: argparse.Namespace) -> tuple[Any, ScenarioConfig]:
    """The driver and scenario named by :func:`add_heldout_arguments`' ``policy`` and ``--predictor``
    (a built-in driver runs the paper scenario without the image). ``ValueError`` with a one-line message
    for a checkpoint that is missing, unreadable or does not fit its predictor."""
    from lcmodels.policy.evaluate import driver_for
    from lcsim.config import paper_scenario

    try:
        driver, config = driver_for(args.policy, predictor=args.predictor, lookahead=lookahead_options(args),
                                    follow=args.lookahead_follow, trust_pickle=args.trust_pickle)
    except (ValueError, OSError) as exc:
        raise ValueError(str(exc).splitlines()[0]) from exc
    return driver, config or paper_scenario(render_image=False)


def predictor_unused(policy: str, follow: str | None, predictor: Path) -> str:
    """Why ``--predictor`` makes no sense for the policies named (none reads a prediction), or "" when one
    does or a policy file cannot be read (loading it reports that)."""
    from lcmodels.policy.checkpoint import read_meta
    from lcmodels.policy.evaluate import policy_path_of
    from lcmodels.policy.obs import OBS_MODES, needs_predictor
    from lcsim.drivers import DRIVER_NAMES

    modes = []
    for spec in (policy, follow):
        if spec is None or spec in DRIVER_NAMES:
            continue
        try:
            modes.append(str(read_meta(policy_path_of(spec)).get("obs_mode")))
        except ValueError:
            return ""
    if any(needs_predictor(m) for m in modes if m in OBS_MODES):
        return ""
    what = f"observation mode {', '.join(modes)}" if modes else "a built-in driver"
    return f"--predictor {predictor}: {policy} reads no prediction ({what}); drop --predictor"


def add_heldout_arguments(p: argparse.ArgumentParser, episodes: int = 200) -> None:
    """Who drives which held-out episodes: ``policy``, ``--episodes``, ``--seed``, ``--predictor``, ``--batch``
    (lc-eval's arguments, shared by the tools that run the same episodes)."""
    p.add_argument("policy", help="policy checkpoint (policy.safetensors), or a built-in driver: rule / lookahead / "
                   "lookahead-blind / oracle (planners, upper references) / keep / random, or lookahead:POLICY / "
                   "lookahead-blind:POLICY (the lookahead following a policy without image in its imagined futures; "
                   "see --lookahead-follow)")
    p.add_argument("--episodes", type=_positive_int, default=episodes, help="episodes (default %(default)s)")
    p.add_argument("--seed", type=int_at_least(0), default=0, help="evaluation seed (default %(default)s)")
    p.add_argument("--predictor", type=Path, default=None,
                   help="predictor checkpoint (default: the one the policy was trained with)")
    p.add_argument("--batch", type=_positive_int, default=20, help="episodes simulated together (default 20)")
    add_lookahead_arguments(p)
    p.add_argument("--lookahead-follow", metavar="DRIVER", default=None,
                   help="with lookahead:POLICY / lookahead-blind:POLICY: the policy proposes each decision and the "
                   "imagined futures follow DRIVER (a built-in driver or a policy.safetensors without image), which "
                   "lets the lookahead guard a policy that reads the image (default: the policy itself)")
    p.add_argument("--trust-pickle", action="store_true",
                   help="accept legacy stable-baselines3 .zip policies; loading one runs code stored in it, so only "
                   "for files from a source you trust")


def eval_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="lc-eval",
        description="Evaluate a trained policy (or a non-learning driver) on fixed held-out seeds.",
        epilog=EVAL_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_heldout_arguments(p)
    p.add_argument("--scenario", choices=("paper", "light", "tiny"), default=None,
                   help="scenario for a built-in driver (default paper); a policy uses its own")
    p.add_argument("--out", type=Path, default=None,
                   help="record every episode here (default: eval-<name>-s<seed> next to the checkpoint, "
                   "or runs/eval-<driver> for a driver)")
    p.add_argument("--no-record", action="store_true", help="do not record episodes")
    p.add_argument("--overwrite", action="store_true", help="replace existing episode files")
    p.add_argument("--json-out", type=Path, default=None, help="write the summary as JSON here")
    p.add_argument("--threads", type=_positive_int, default=2, help="torch threads (default 2)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    return p


def eval_main(argv: list[str] | None = None) -> int:
    args = eval_parser().parse_args(argv)

    fail = functools.partial(_fail, "lc-eval")

    import numpy as np
    import torch

    from lcmodels.policy.evaluate import driver_for, evaluate, policy_path_of
    from lcmodels.policy.train import POLICY_SCENARIOS
    from lcsim.drivers import DRIVER_NAMES, LookaheadDriver

    is_driver = args.policy in DRIVER_NAMES
    ckpt = policy_path_of(args.policy)
    if not is_driver and not ckpt.is_file():
        what = "is a directory" if ckpt.is_dir() else "does not exist"
        return fail(f"{args.policy} {what} (expected a policy.safetensors, or {' / '.join(DRIVER_NAMES)})")
    if args.json_out is not None and args.json_out.exists() and not args.overwrite:
        return fail(f"{args.json_out} already exists; pass --overwrite or choose another --json-out")
    if args.predictor is not None:
        problem = predictor_unused(args.policy, args.lookahead_follow, args.predictor)
        if problem:
            return fail(problem)
    torch.set_num_threads(args.threads)
    try:
        driver, config = driver_for(args.policy, predictor=str(args.predictor) if args.predictor else None,
                                    lookahead=lookahead_options(args), follow=args.lookahead_follow,
                                    trust_pickle=args.trust_pickle)
    except ValueError as exc:
        return fail(str(exc).splitlines()[0])
    if config is None:
        config = POLICY_SCENARIOS[args.scenario or "paper"]()
    elif args.scenario is not None:
        return fail("--scenario applies to built-in drivers; a policy is evaluated in its own scenario")
    out = None
    if not args.no_record:
        if args.out is not None:
            out = args.out
        elif is_driver:
            out = Path("runs") / f"eval-{args.policy}-s{args.seed}"
        else:
            out = ckpt.parent / f"eval-{ckpt.stem}-s{args.seed}"
    train_seeds = None
    if not is_driver:
        seeds_file = ckpt.parent / "train_episode_seeds.npy"
        train_seeds = np.load(seeds_file) if seeds_file.exists() else None
    show = None if args.quiet else (lambda k, n: print(f"evaluating: {k}/{n} episodes", flush=True))
    start = time.perf_counter()
    try:
        summary, results = evaluate(driver, config, episodes=args.episodes, seed=args.seed, out_dir=out,
                                    batch=args.batch, overwrite=args.overwrite, train_seeds=train_seeds,
                                    progress=show)  # fmt: skip
    except (ValueError, OSError) as exc:
        return fail(str(exc).splitlines()[0])
    summary["wall_s"] = round(time.perf_counter() - start, 1)
    summary["decisions"] = sum(r.length for r in results)
    if isinstance(driver, LookaheadDriver):  # a planner: how often it overrode the driver it checks
        summary["planner_choices"], summary["planner_overrides"] = driver.choices, driver.overrides
    print(_fmt_eval(summary))
    print(f"{summary['decisions']} decisions in {summary['wall_s']} s ({args.batch} episodes at a time, "
          f"{args.threads} torch threads)")
    if "planner_overrides" in summary:
        print(f"the planner overrode {summary['planner_overrides']} of {summary['planner_choices']} decisions "
              "with a choice")
    if "overlap_with_training" in summary:
        print(f"evaluation episodes also seen in training: {summary['overlap_with_training']}")
    if out is not None:
        print(f"recorded {args.episodes} episodes in {out}")
    if args.json_out is not None:
        args.json_out.parent.mkdir(parents=True, exist_ok=True)
        args.json_out.write_text(json.dumps(summary, indent=2, sort_keys=True) + "\n")
        print(f"wrote {args.json_out}")
    return 0


# ---------------------------------------------------------------------------------------- lc-experiment
EXPERIMENT_EPILOG = """stages (each skipped when complete, redone when missing or stale):
  corpus      autopilot trajectory corpus (MCAP)                 DIR/corpus/
  predictor   transformer + constant velocity/acceleration        DIR/predictor/metrics.json  (Table II)
  demos       demonstrations (the oracle's) for the warm start    DIR/demos/
  rule        rule-based reference on the held-out seeds          DIR/rule/metrics.json
  policies    A2C, DQN, PPO pure/image/prediction/hybrid, Hybrid-PPO + warm start, K seeds each
                                                                  DIR/policies/<method>/seed<k>/
  report      DIR/REPORT.md, DIR/fig5_safe_forward.png, DIR/fig6_total_reward.png

presets: tiny (seconds, for tests), quick (about 15 min on 2 cores, what `make demo` runs),
paper (the budgets each method needs to converge: hours).

examples:
  lc-experiment --preset quick --out runs/demo
  lc-experiment --preset paper --seeds 3 --jobs 2 --out runs/paper   # stop any time; rerun to continue
"""


def experiment_parser() -> argparse.ArgumentParser:
    from lcmodels.experiment import PRESETS

    p = argparse.ArgumentParser(
        prog="lc-experiment",
        description="Reproduce the paper's tables and figures end to end: record the trajectory corpus, train "
        "the predictor, record rule-based warm-start episodes, train every policy with K seeds, evaluate on "
        "held-out seeds and write DIR/REPORT.md. Resumable: a rerun skips what is complete.",
        epilog=EXPERIMENT_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--preset", choices=list(PRESETS), default="quick", help="budgets (default %(default)s)")
    p.add_argument("--seeds", type=_positive_int, default=1, help="training seeds per method (default 1)")
    p.add_argument("--out", type=Path, required=True, help="experiment directory (resumed when it holds one)")
    p.add_argument("--threads", type=_positive_int, default=1,
                   help="torch threads (default 1: on a shared 2-core machine 1 is often fastest; results do "
                   "not depend on it beyond float rounding, and changing it does not make stages stale)")
    p.add_argument("--jobs", type=_positive_int, default=1,
                   help="policies trained at once, each in its own process with --threads torch threads "
                   "(default 1; on 2 cores --jobs 2 --threads 1 keeps both busy; results do not depend on it)")
    p.add_argument("--skip-train", action="store_true",
                   help="do not train policies; report what the directory already holds")
    p.add_argument("--dry-run", action="store_true",
                   help="only say which stages are complete and which would run (and why)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    return p


def experiment_main(argv: list[str] | None = None) -> int:
    import shlex
    import time

    parser = experiment_parser()
    args = parser.parse_args(argv)

    fail = functools.partial(_fail, "lc-experiment")

    from lcmodels.experiment import PRESETS, Experiment

    words = sys.argv[1:] if argv is None else list(argv)
    command = shlex.join(["lc-experiment", *words])
    t0 = time.perf_counter()

    def show(msg: str) -> None:
        print(f"{(time.perf_counter() - t0) / 60:6.1f} min  {msg}", flush=True)

    exp = Experiment(PRESETS[args.preset], args.out, seeds=args.seeds, command=command, threads=args.threads,
                     progress=None if args.quiet else show)  # fmt: skip
    try:
        exp.check_out()
    except ValueError as exc:
        return fail(str(exc))
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    if args.dry_run:
        if not args.out.exists():
            print(f"{args.out} does not exist: every stage would run")
            return 0
        stages = exp.plan()
        print(f"{sum(s.status == 'skipped' for s in stages)} stages complete, "
              f"{sum(s.status != 'skipped' for s in stages)} would run")
        return 0
    try:
        res = exp.run(skip_train=args.skip_train, jobs=args.jobs)
    except (ValueError, OSError) as exc:
        return fail(str(exc).splitlines()[0])
    done = sum(s.status == "done" for s in res.stages)
    skipped = sum(s.status == "skipped" for s in res.stages)
    print(f"{done} stages computed, {skipped} complete and skipped, {res.wall_s / 60:.1f} min")
    print(f"report: {res.report}")
    return 0
