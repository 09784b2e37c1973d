#!/usr/bin/env bash
# Speed–accuracy sweeps of the texture operators on graphs/texture.ron (see bench/notes/texture.md).
# Usage: bench/texture_sweep.sh NODE METRICS_OUTPUT SETTINGS...
#   each SETTING is a comma-separated list of node.param=value overrides.
# Prints one line per setting: the overrides, the node's median time over 3 runs (ms) and the
# named metrics output.
set -euo pipefail
node=$1; metrics=$2; shift 2
for setting in "$@"; do
  args=()
  IFS=',' read -ra parts <<< "$setting"
  for p in "${parts[@]}"; do args+=(--set "$p"); done
  out=$(cargo run --release -q -- run graphs/texture.ron "${args[@]}" --repeat 3 \
        --profile /tmp/texture_profile.json --output "$metrics" 2>&1)
  ms=$(python3 -c "import json,sys; print(round(json.load(open('/tmp/texture_profile.json'))['nodes']['$node']['median_ms'],1))")
  echo "$setting | ${ms} ms | $(echo "$out" | tr -s ' \n' ' ')"
done
