"""The image branch's cost on a CPU: cloning samples per second and frozen-branch images per second, per network.

Records a few oracle episodes of the paper's scenario with the bird's-eye image (the demonstrations a hybrid
recipe clones), then, for each image network (``compact``, ``strided``), times:

- ``clone``: ``lcmodels.policy.pretrain`` on them (an image-mode PPO policy, batch 256), which feeds the
  network images pooled ahead of it (``pooled_images``), against the same steps fed as stable-baselines3 feeds
  a policy (every pixel scaled to float, the network pooling them again: ``clone-full``);
- ``frozen``: the frozen branch run beside the environment during PPO (``ImageEncoder``, 16 images a call),
  against the network on full images (``frozen-full``).

One torch thread. Prints samples (images) per second, the median of ``--repeat`` runs, and each network's
ratio to the compact network fed full images (what cloning cost before).

    python tools/bench_image_branch.py                   # 8 episodes, 1 epoch, 3 repeats
    python tools/bench_image_branch.py --episodes 4 --repeat 5 --json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch


def _clone_full(model, demos, batch_size: int = 256) -> None:  # type: ignore[no-untyped-def]
    """One epoch of cloning as stable-baselines3 feeds the policy: full uint8 images, scaled and pooled."""
    from stable_baselines3.common.utils import obs_as_tensor

    policy = model.policy
    policy.set_training_mode(True)
    optimizer = torch.optim.Adam(policy.parameters(), lr=1e-3)
    perm = np.random.default_rng(0).permutation(len(demos))
    for start in range(0, len(demos), batch_size):
        idx = perm[start : start + batch_size]
        obs = obs_as_tensor({k: v[idx] for k, v in demos.obs.items()}, policy.device)
        _v, log_prob, _e = policy.evaluate_actions(obs, torch.as_tensor(demos.actions[idx]))
        loss = -log_prob.mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()


def _median_rate(fn, count: int, repeat: int) -> float:  # type: ignore[no-untyped-def]
    fn()  # warm: the first call loads the compiled pooling and torch's kernels
    rates = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        rates.append(count / (time.perf_counter() - start))
    return statistics.median(rates)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--episodes", type=int, default=8, help="oracle episodes recorded (default 8)")
    p.add_argument("--repeat", type=int, default=3, help="timed runs per figure; the median is printed (default 3)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    args = p.parse_args(argv)
    if args.episodes < 1 or args.repeat < 1:
        print("bench_image_branch: --episodes and --repeat must be >= 1", file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    from lcdata.record import record_episodes
    from lcmodels.policy import PolicyConfig, load_demonstrations, pretrain
    from lcmodels.policy.extractor import ImageEncoder, make_image_net
    from lcmodels.policy.network import build_model
    from lcmodels.policy.obs import policy_vec_env, scenario_for_mode
    from lcsim.config import paper_scenario
    from lcsim.sb3 import LaneChangeSB3VecEnv

    config = scenario_for_mode(paper_scenario(), "image")
    results: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        record_episodes(config, list(range(5000, 5000 + args.episodes)), "oracle", Path(tmp) / "demos",
                        scenario="paper")  # fmt: skip
        demos = load_demonstrations(Path(tmp) / "demos", "image", None, scenario=config)
    env = policy_vec_env(LaneChangeSB3VecEnv(1, config), "image")
    size = config.render.image_size_px
    images = demos.obs["image"][:16]
    n = len(demos)
    calls = 200  # frozen-branch calls per timed run
    if not args.json:
        print(f"{n} decisions of {args.episodes} oracle episodes, {size}x{size} px images, 1 torch thread")
    for net in ("compact", "strided"):
        model = build_model(PolicyConfig(obs="image", image_net=net, n_steps=256, batch_size=256), env)
        results[f"{net}/clone"] = _median_rate(lambda: pretrain(model, demos, epochs=1), n, args.repeat)  # noqa: B023
        results[f"{net}/clone-full"] = _median_rate(lambda: _clone_full(model, demos), n, args.repeat)  # noqa: B023
        encoder = ImageEncoder(make_image_net(net, 3, size, 10), 10)
        def frozen(encoder: ImageEncoder = encoder) -> None:
            for _ in range(calls):
                encoder(images)

        def frozen_full(encoder: ImageEncoder = encoder) -> None:
            with torch.no_grad():
                for _ in range(calls):
                    encoder.net(torch.as_tensor(images).float() / 255.0)

        results[f"{net}/frozen"] = _median_rate(frozen, calls * len(images), args.repeat)
        results[f"{net}/frozen-full"] = _median_rate(frozen_full, calls * len(images), args.repeat)
    base_clone, base_frozen = results["compact/clone-full"], results["compact/frozen-full"]
    if args.json:
        print(json.dumps({"decisions": n, **{k: round(v, 1) for k, v in results.items()}}))
        return 0
    print(f"{'network':10s} {'clone (pooled ahead)':>22s} {'clone (full images)':>21s} "
          f"{'frozen (pooled ahead)':>23s} {'frozen (full images)':>22s}")  # fmt: skip
    for net in ("compact", "strided"):
        cells = [f"{results[f'{net}/{k}']:9.0f} ({results[f'{net}/{k}'] / base:4.1f}x)"
                 for k, base in (("clone", base_clone), ("clone-full", base_clone), ("frozen", base_frozen),
                                 ("frozen-full", base_frozen))]  # fmt: skip
        print(f"{net:10s} {cells[0]:>22s} {cells[1]:>21s} {cells[2]:>23s} {cells[3]:>22s}")
    print("samples (images) per second, median of", args.repeat, "runs; ratios to the compact network on full images")
    return 0


if __name__ == "__main__":
    sys.exit(main())
