"""Same seed and actions, same result, bit for bit; the batch agrees with single environments."""

import numpy as np

from lcsim.envs import LaneChangeEnv, LaneChangeVectorEnv

from .conftest import small_config


def _rollout(env, seed, actions):
    obs, _ = env.reset(seed=seed)
    out = [obs]
    for a in actions:
        obs, r, term, trunc, info = env.step(a)
        out.append((obs, r, term, trunc, info["outcome"]))
        if term or trunc:
            obs, _ = env.reset()
            out.append(obs)
    sim = env.core.sim
    return out, sim.x.copy(), sim.y.copy(), sim.yaw.copy(), sim.speed.copy()


def _equal(a, b):
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a)
    if isinstance(a, tuple | list):
        return len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and np.array_equal(a, b)
    return a == b


def test_same_seed_same_actions_bit_identical():
    actions = np.random.default_rng(0).integers(0, 3, size=60).tolist()
    r1 = _rollout(LaneChangeEnv(small_config()), 7, actions)
    r2 = _rollout(LaneChangeEnv(small_config()), 7, actions)
    assert _equal(r1, r2)
    r3 = _rollout(LaneChangeEnv(small_config()), 8, actions)
    assert not np.array_equal(r1[1], r3[1])


def test_batch_equals_single_envs():
    cfg = small_config()
    e, steps = 5, 40
    actions = np.random.default_rng(1).integers(0, 3, size=(steps, e))
    venv = LaneChangeVectorEnv(e, cfg)
    obs_v, _ = venv.reset(seed=100)
    singles = [LaneChangeEnv(cfg) for _ in range(e)]
    obs_s = [env.reset(seed=100 + i)[0] for i, env in enumerate(singles)]
    for i in range(e):
        assert all(np.array_equal(obs_v[k][i], obs_s[i][k]) for k in obs_v)
    for t in range(steps):
        obs_v, r_v, term_v, trunc_v, info_v = venv.step(actions[t])
        for i, env in enumerate(singles):
            o, r, term, trunc, _info = env.step(int(actions[t, i]))
            assert r == r_v[i] and term == term_v[i] and trunc == trunc_v[i], (t, i)
            if term or trunc:  # the vector env reset in the same step; its final obs is in the info
                assert all(np.array_equal(info_v["final_obs"][i][k], o[k]) for k in o)
                o, _ = env.reset()
            assert all(np.array_equal(obs_v[k][i], o[k]) for k in o), (t, i)
