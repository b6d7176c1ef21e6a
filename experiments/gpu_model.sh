#!/bin/bash
# The short name of a GPU model that carried runs key their per-GPU caches by (FOLDER/gpu-MODEL/):
#   bash experiments/gpu_model.sh ["NVIDIA H100 80GB HBM3"]   # -> h100
# Without an argument, this host's first GPU as nvidia-smi names it; prints nothing without one.
# The name's first word after "NVIDIA", up to its first character that is not a letter or digit, in
# lower case: "NVIDIA H200" -> h200, "NVIDIA A100-SXM4-40GB" -> a100.
name=${1-$(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -1)}
printf '%s\n' "$name" | sed -E 's/^[[:space:]]*(NVIDIA[[:space:]]+)?//I; s/[^A-Za-z0-9].*$//' | tr '[:upper:]' '[:lower:]' | grep . || true
