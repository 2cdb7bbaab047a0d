#!/usr/bin/env bash
# The online agents' ablations of docs/EXPERIMENTS.md (A5): trains one online DQN agent per task
# and seed with configs/default.toml and the given `--set`s, two at a time (the machine's two
# cores), and prints each agent's exact return (over the 100 start cells) for the policy it kept
# and for its last one, beside the planner's.
#
#   TASKS="lambda-400 lambda-600" SEEDS="0 1 2" bash docs/agent_ablation.sh NAME [--set KEY=V ...]
#
# Output: runs/agent-ablation/NAME/TASK-sS.uavds (+ .agent/online-dqn) and NAME/results.tsv.
set -euo pipefail
cd "$(dirname "$0")/.."
UAV=${UAV:-target/release/uavmeta}
TASKS=${TASKS:-lambda-400 lambda-600 lambda-800}
SEEDS=${SEEDS:-0 1 2}
NAME=$1
shift
OUT=runs/agent-ablation/$NAME
mkdir -p "$OUT"

one() {
    local task=$1 seed=$2 data=$OUT/$1-s$2.uavds
    rm -rf "$data" "$data.agent" "$data.config.toml"
    "$UAV" collect --task "$task" --policy dqn-online --seed "$seed" --out "$data" "${@:3}" \
        2> "$data.log" >/dev/null
    # The kept policy's return and the last one's, both exact, from the agent's own log.
    local kept last
    kept=$(sed -n 's/.*kept the best snapshot.* ret=\([-0-9.]*\).*/\1/p' "$data.log")
    last=$(sed -n 's/.*kept the best snapshot.* last=\([-0-9.]*\).*/\1/p' "$data.log")
    printf '%s\t%s\t%s\t%s\n' "$task" "$seed" "$kept" "${last:--}" >> "$OUT/results.tsv"
}

: > "$OUT/results.tsv"
pids=()
for task in $TASKS; do
    for seed in $SEEDS; do
        one "$task" "$seed" "$@" &
        pids+=($!)
        if (( ${#pids[@]} == 2 )); then wait "${pids[0]}"; pids=("${pids[@]:1}"); fi
    done
done
wait
for task in $TASKS; do
    planner=$("$UAV" env rollout --task "$task" --policy planner --exact --json "$@" 2>/dev/null |
        python3 -c 'import sys, json; print(json.load(sys.stdin)["mean"]["ret"]["mean"])')
    awk -v t="$task" -v p="$planner" -F'\t' '$1 == t {
        printf "%s seed %s: kept %s (%.2f%%), last %s, planner %.1f\n", $1, $2, $3, 100 * ($3 - p) / p, $4, p
    }' "$OUT/results.tsv"
done
