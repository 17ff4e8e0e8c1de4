"""Lab: a predictor checkpoint's FDE at 0.5 s and 3 s against FV on validation windows (lcsim val split, SUMO val)."""
import os
import pathlib
import sys

import numpy as np

from lcdata.corpus import Corpus, WindowOptions, load_tracks, split_episodes
from lcmodels.predictor.checkpoint import load_model
from lcmodels.predictor.train import evaluate


def windows(folder, val, h, f, n=8000):
    c = Corpus.from_tracks(load_tracks(pathlib.Path(folder)), WindowOptions(history_steps=h, future_steps=f, stride=5))
    rows = np.arange(len(c))
    if val:
        rows = c.windows_of(split_episodes(c.episode_ids, seed=0).val)
    if len(rows) > n:
        rows = np.sort(np.random.default_rng(0).choice(rows, size=n, replace=False))
    return c.gather(rows)

for ck in sys.argv[1:]:
    model = load_model(pathlib.Path(ck))
    model = model[0]
    cfg = model.config
    for name, folder, val in (("lcsim-val", os.environ.get("LCSIM_TRAIN", "runs/pred/lcsim-train"), True), ("sumo-val", os.environ.get("SUMO_VAL", "runs/pred/sumo-val/corpus"), False)):
        b = windows(folder, val, cfg.history_steps, cfg.future_steps)
        m = evaluate(model, b, miss_threshold_m=2.0)
        row = []
        for hz in ("0.5s", "3s"):
            try:
                mf = m["model"]["horizons"][hz]["fde"]
                ff = m["constant_velocity_fit"]["horizons"][hz]["fde"]
                row.append(f"{hz} {mf:.4f} vs FV {ff:.4f} ({100*(mf/ff-1):+.1f}%)")
            except KeyError:
                row.append(f"{hz} n/a")
        print(ck, name, " | ".join(row), flush=True)
