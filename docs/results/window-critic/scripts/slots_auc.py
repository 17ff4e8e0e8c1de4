"""Fit critics on one states file of collect16.py and score them on another: 8 slots (the first 9 rows of
``current``) against 16, each with and without the window features.

A one-off experiment of the window-critic study (see ../NOTE.md), kept to reproduce its figures:

    python docs/results/window-critic/scripts/slots_auc.py FIT.npz SCORE.npz EPOCHS
"""
import json
import sys

import numpy as np
import torch

from experiments.safety_critic.safety_critic import score_states, train_critics

torch.set_num_threads(1)
fit, score = np.load(sys.argv[1]), np.load(sys.argv[2])
epochs = int(sys.argv[3])
for rows in (9, 17):
    for window in (False, True):
        critic = train_critics(fit["current"][:, :rows], fit["alive"], epochs=epochs, window=window)
        s = score_states(critic, score["current"][:, :rows], score["alive"], score["actions"])
        print(json.dumps({"slots": rows - 1, "window_features": window, "epochs": epochs, "fit_states": len(fit["alive"]),
                          "score_states": s["states"], "loss": round(s["loss"], 4),
                          "auc_per_decision": [round(a, 3) for a in s["auc_per_decision"]],
                          "auc_own_decision": round(s["auc_own_decision"], 3), "overridable": s["overridable"]}),
              flush=True)
