#!/bin/bash
# Lab: prediction-ppo (the recipe's clone and train stages, training seed $SEED, default 0) with predictor $2, into $1.
set -e
B=${B:-.venv/bin}
DEMOS=${DEMOS:-runs/paper/demos/oracle-s5000-n400}   # the oracle demonstrations of a paper-preset experiment
out=$1; pred=$2
common="--obs prediction --predictor $pred --scenario paper --seed ${SEED:-0} --threads 1 -q --set window_features=true --set eval_episodes=0"
[ -f $out/clone/policy.safetensors ] || $B/lc-train-policy $common --warm-start $DEMOS --timesteps 0 --set warm_start_epochs=20 --out $out/clone
$B/lc-train-policy $common --init-policy $out/clone/policy.safetensors --timesteps 1200000 --set learning_rate=3e-5 --out $out/train
echo done
