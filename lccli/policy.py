"""``lc-train-policy``: train the lane-change policy online (PPO, A2C, DQN), resumable, then evaluate it."""

from __future__ import annotations

import argparse
import functools
import logging
from pathlib import Path

from lccli.common import fail, int_at_least, positive_int
from lccli.evaluate import format_eval

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
    from lcmodels.policy.config import ALGORITHMS
    from lcmodels.policy.extractor import IMAGE_NETS
    from lcmodels.policy.obs import OBS_MODES
    from lcmodels.policy.train import PolicyConfig
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
    p.add_argument("--algo", choices=ALGORITHMS, default=d.algo, help="default %(default)s")
    p.add_argument("--obs", choices=OBS_MODES, default=d.obs,
                   help="observation mode (Table IV): pure, image, prediction, hybrid (default %(default)s)")
    p.add_argument("--predictor", type=Path, help="predictor.pt from lc-train-predictor (prediction, hybrid)")
    p.add_argument("--scenario", default=d.scenario, metavar="{paper,light,tiny,FILE}",
                   help="paper: 100 vehicles, 600 m route; light: 30 vehicles, 300 m; tiny: 8 vehicles, 150 m, "
                   "for smoke tests; or a scenario file (.toml/.json of ScenarioConfig fields) (default %(default)s)")
    p.add_argument("--neighbours", choices=NEIGHBOUR_SELECTIONS, default=d.neighbours,
                   help="the 8 vehicles the observation shows: lanes (leader and follower in the ego's lane and "
                   "the lanes beside it, then the second leaders beside it) or nearest (the 8 nearest by "
                   "distance) (default %(default)s)")
    p.add_argument("--slots", type=positive_int, default=d.slots,
                   help="how many vehicles the observation shows: the paper's 8, or with --neighbours lanes up to "
                   "16, the slots after the eighth a wider view (the leader's leaders, the second followers beside "
                   "the ego, leader and follower two lanes over) (default %(default)s)")
    p.add_argument("--timesteps", type=int_at_least(0), default=d.timesteps,
                   help="online decisions over all envs; 0 with --warm-start: behaviour cloning only, no online "
                   "training (default %(default)s)")
    p.add_argument("--n-envs", type=positive_int, default=d.n_envs, help="parallel episodes (default %(default)s)")
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
    p.add_argument("--n-steps", type=positive_int, default=None,
                   help="PPO/A2C rollout steps per env (default 128; A2C 8)")
    p.add_argument("--warm-start", type=Path, default=None,
                   help="directory of recorded MCAP episodes to pretrain on (behaviour cloning)")
    p.add_argument("--warm-start-epochs", type=positive_int, default=d.warm_start_epochs,
                   help="behaviour-cloning epochs (default %(default)s)")
    p.add_argument("--init-policy", type=Path, default=None,
                   help="a policy.safetensors to start online training from (a cloned run's, a DAgger round's); same "
                   "observation mode, predictor, scenario and network")
    p.add_argument("--freeze-image", action="store_true",
                   help="with --init-policy (image, hybrid): keep its image branch fixed and run it once per step "
                   "in the environment wrapper, so PPO's epochs do not re-run the network (several times the "
                   "steps per minute); policy.safetensors stays a plain policy")
    p.add_argument("--checkpoint-every", type=positive_int, default=d.checkpoint_every,
                   help="timesteps between checkpoints (default %(default)s)")
    p.add_argument("--eval-episodes", type=int_at_least(0), default=d.eval_episodes,
                   help="held-out evaluation episodes at the end, 0 to skip (default %(default)s)")
    p.add_argument("--eval-seed", type=int_at_least(0), default=d.eval_seed, help="evaluation seed (default 0)")
    p.add_argument("--no-record-eval", action="store_true", help="do not record the evaluation episodes")
    p.add_argument("--threads", type=positive_int, default=2, help="torch threads (default 2)")
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

    error = functools.partial(fail, "lc-train-policy")

    import torch

    from lcmodels.fileio import POLICY_FILE
    from lcmodels.policy.obs import needs_predictor
    from lcmodels.policy.train import PolicyConfig, default_learning_rate, train_policy

    if needs_predictor(args.obs) and args.predictor is None:
        return error(f"--obs {args.obs} needs --predictor (a predictor.pt from lc-train-predictor)")
    if args.predictor is not None and not needs_predictor(args.obs):
        return error(f"--obs {args.obs} uses no predictor; drop --predictor {args.predictor}")
    if args.predictor is not None and not args.predictor.is_file():
        return error(f"--predictor {args.predictor} does not exist")
    if args.warm_start is not None and not args.warm_start.exists():
        return error(f"--warm-start {args.warm_start} does not exist")
    if args.init_policy is not None and not args.init_policy.is_file():
        return error(f"--init-policy {args.init_policy} does not exist")
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
        return error(str(exc))
    torch.set_num_threads(args.threads)
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO, format="%(message)s")
    show = None if args.quiet else (lambda row: print(_fmt_row(row), flush=True))
    show_eval = None if args.quiet else (lambda k, n: print(f"evaluating: {k}/{n} episodes", flush=True))
    try:
        res = train_policy(cfg, args.out, predictor=args.predictor, device=args.device, progress=show,
                           eval_progress=show_eval, overwrite=args.overwrite,
                           trust_pickle=args.trust_pickle)  # fmt: skip
    except (ValueError, OSError) as exc:
        return error(str(exc).splitlines()[0])
    ev = res.metrics.get("eval")
    print(f"trained {res.timesteps} steps in {res.wall_s / 60:.1f} min -> {args.out / POLICY_FILE}")
    if ev:
        print(format_eval(ev))
    print(f"wrote {args.out / 'metrics.json'}")
    return 0
