"""``lc-train-policy``: train the lane-change policy online (PPO, A2C, DQN), resumable, then evaluate it."""

from __future__ import annotations

import argparse
import functools
import sys
from pathlib import Path
from typing import Any

from lccli.common import fail, int_at_least, positive_int, setup_logging
from lccli.evaluate import format_eval

TRAIN_POLICY_EPILOG = """examples:
  lc-train-policy --algo ppo --obs pure --timesteps 100000 --out runs/ppo-pure
  lc-train-policy --obs hybrid --predictor runs/predictor/predictor.pt --out runs/hybrid-ppo
  lc-train-policy --obs pure --warm-start runs/oracle-demos --timesteps 0 --out runs/clone   # cloning only
  lc-train-policy --config my-run.toml --set gamma=0.99 --set window_features=true --out runs/mine

configuration: the defaults of lcmodels.policy.PolicyConfig, then --config FILE (a TOML or JSON table of
its fields, also under [policy]), then the flags given here, then each --set KEY=VALUE in order. Every
field can be set; the ones most runs change:
  n_envs (16)  neighbours (lanes|nearest)  slots (8)  image_net (compact|vgg16)  contact_features (true)
  window_features (false)  accel_features (false)  learning_rate (3e-4; 3e-5 for PPO from a warm start or
  an initial policy)  gamma (0.95)  n_steps (128; A2C 8)  collision_weight (1.0)  warm_start_epochs (10)
  freeze_image (false; with --init-policy)  checkpoint_every (20000)  eval_episodes (200)  eval_seed (0)
  record_eval (true)  sensor_encoder (mlp|attention)  train_roads ("": the scenario alone; "highway":
  every road of the benchmark suite, or scenario names joined by commas)

Rerunning with the same --out resumes from the last checkpoint (the step count continues) or, when
training is complete, only redoes a missing evaluation. A different config in --out is refused.

outputs (in --out): policy.safetensors (the policy; lc-eval and lc-record --driver policy:PATH load it),
checkpoints/latest.json, progress.csv (outcome rates, return, safe forward distance over the last 100
episodes at each log step), tb/ (TensorBoard), eval/metrics.json and eval/episodes/*.mcap (held-out
evaluation), metrics.json (training summary + evaluation), run.json (the full config, predictor, versions).
"""


def train_policy_parser() -> argparse.ArgumentParser:
    from lcmodels.policy.names import ALGORITHMS, OBS_MODES

    p = argparse.ArgumentParser(
        prog="lc-train-policy",
        description="Train the lane-change policy online on the batched simulator (PPO, A2C or DQN with the "
        "hybrid features extractor), optionally warm-started from recorded episodes, then evaluate it "
        "on held-out seeds.",
        epilog=TRAIN_POLICY_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--config", type=Path, default=None,
                   help="a TOML or JSON file of PolicyConfig fields (what --set can set), applied first")
    p.add_argument("--set", dest="settings", action="append", default=[], metavar="KEY=VALUE",
                   help="set a PolicyConfig field, last; repeatable (see below)")
    p.add_argument("--algo", choices=ALGORITHMS, default=None, help="ppo (default), a2c or dqn")
    p.add_argument("--obs", choices=OBS_MODES, default=None,
                   help="observation mode (Table IV): pure, image, prediction, hybrid (default hybrid)")
    p.add_argument("--predictor", type=Path, help="predictor.pt from lc-train-predictor (prediction, hybrid)")
    p.add_argument("--scenario", default=None, metavar="{paper,light,tiny,FILE}",
                   help="paper (default): 100 vehicles, 600 m route; light: 30 vehicles, 300 m; tiny: 8 vehicles, "
                   "150 m, for smoke tests; or a scenario file (.toml/.json of ScenarioConfig fields)")
    p.add_argument("--timesteps", type=int_at_least(0), default=None,
                   help="online decisions over all envs; 0 with --warm-start: behaviour cloning only (default 100000)")
    p.add_argument("--seed", type=int_at_least(0), default=None, help="training seed (default 0)")
    p.add_argument("--warm-start", type=Path, default=None,
                   help="directory of recorded MCAP episodes to pretrain on (behaviour cloning)")
    p.add_argument("--init-policy", type=Path, default=None,
                   help="a policy.safetensors to start online training from (a cloned run's, a DAgger round's); same "
                   "observation mode, predictor, scenario and network")
    p.add_argument("--out", type=Path, required=True, help="run directory (resumed when it holds this run)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a run of another configuration in --out: only the files a training run writes are "
                   "removed, after every other check has passed; anything else there stays")
    p.add_argument("--threads", type=positive_int, default=1,
                   help="torch threads (default 1: more collapse when another process shares the cores)")
    p.add_argument("--device", default="cpu", help="torch device (default cpu; cuda for the GPU)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    return p


def policy_config_of(args: argparse.Namespace) -> Any:
    """The :class:`~lcmodels.policy.PolicyConfig` of the command line: defaults, ``--config``, the flags
    given, ``--set`` (:meth:`PolicyConfig.of <lcmodels.policy.PolicyConfig.of>`, which gives a learning rate and
    rollout length nobody gave the algorithm's, and for the rate whether the run starts from a warm start or an
    initial policy). ``ValueError`` naming the problem."""
    from lckit.config import read_data_file
    from lcmodels.policy.config import PolicyConfig

    data: dict[str, Any] = {}
    if args.config is not None:
        data = read_data_file(args.config, "config file")
        data = data["policy"] if isinstance(data.get("policy"), dict) else data
        try:
            PolicyConfig.from_dict(data, stored=False)
        except ValueError as exc:
            raise ValueError(f"{args.config}: {exc}") from None
    given = {"algo": args.algo, "obs": args.obs, "scenario": args.scenario, "timesteps": args.timesteps,
             "seed": args.seed, "warm_start": None if args.warm_start is None else str(args.warm_start),
             "init_policy": None if args.init_policy is None else str(args.init_policy)}  # fmt: skip
    return PolicyConfig.of({**data, **{k: v for k, v in given.items() if v is not None}}, args.settings)


def _fmt_row(row: dict) -> str:
    return (f"step {int(row['timesteps']):>8d}  {row['wall_s'] / 60:6.1f} min  episodes {int(row['episodes_total']):>5d}  "
            f"success {row['success_rate']:.2f}  collision {row['collision_rate']:.2f}  "
            f"timeout {row['timeout_rate']:.2f}  return {row['mean_return']:8.1f}  "
            f"safe forward {row['mean_safe_forward_m']:6.1f} m")


def train_policy_main(argv: list[str] | None = None) -> int:
    args = train_policy_parser().parse_args(argv)

    error = functools.partial(fail, "lc-train-policy")

    import torch

    from lcmodels.fileio import POLICY_FILE
    from lcmodels.policy.names import needs_predictor
    from lcmodels.policy.train import train_policy

    if args.predictor is not None and not args.predictor.is_file():
        return error(f"--predictor {args.predictor} does not exist")
    if args.warm_start is not None and not args.warm_start.exists():
        return error(f"--warm-start {args.warm_start} does not exist")
    if args.init_policy is not None and not args.init_policy.is_file():
        return error(f"--init-policy {args.init_policy} does not exist")
    try:
        cfg = policy_config_of(args)
    except ValueError as exc:
        return error(str(exc))
    if needs_predictor(cfg.obs) and args.predictor is None:
        return error(f"--obs {cfg.obs} needs --predictor (a predictor.pt from lc-train-predictor)")
    if args.predictor is not None and not needs_predictor(cfg.obs):
        return error(f"--obs {cfg.obs} uses no predictor; drop --predictor {args.predictor}")
    torch.set_num_threads(args.threads)
    setup_logging("lc-train-policy", verbose=not args.quiet)
    show = None if args.quiet else (lambda row: print(_fmt_row(row), flush=True))
    show_eval = None if args.quiet else (lambda k, n: print(f"evaluating: {k}/{n} episodes", flush=True))
    try:
        res = train_policy(cfg, args.out, predictor=args.predictor, device=args.device, progress=show,
                           eval_progress=show_eval, overwrite=args.overwrite)
    except (ValueError, OSError) as exc:
        return error(str(exc).splitlines()[0])
    except KeyboardInterrupt:
        print(f"\nlc-train-policy: interrupted; rerun the same command to resume {args.out} from its last "
              "checkpoint", file=sys.stderr)
        return 130
    ev = res.metrics.get("eval")
    print(f"trained {res.timesteps} steps in {res.wall_s / 60:.1f} min -> {args.out / POLICY_FILE}")
    if ev:
        print(format_eval(ev))
    print(f"wrote {args.out / 'metrics.json'}")
    return 0
