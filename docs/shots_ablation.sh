#!/usr/bin/env bash
# Is it the data or the number of shots? docs/EXPERIMENTS.md B5, one (task, seed) pair per call.
#
#   bash docs/shots_ablation.sh RUN NAME LAMBDA RAIN|- SEED
#
# RUN is a finished `make run` directory (runs/default): its seed-SEED inits (w0, cql-pretrain)
# are fine-tuned. The online agent (`collect --seed 100+SEED`, the same agent G2 and G3 use) trains
# once; from it come two datasets of 16 000 transitions: its whole replay buffer (the paper's
# data) and a rollout of the snapshot it kept (`--policy q:0.01:AGENT`, its greedy policy with
# the agent's final exploration rate). CQL-MAML (from w0), CQL-pretrain and CQL (random init)
# then learn from 500, 1000 and 2000 shots of each, and every policy is evaluated exactly over
# the 100 start cells. Output: runs/shots-ablation/NAME-sSEED/results.txt, one `what return`
# line each (`level-*`: the dataset's mean reward per step times the horizon).
set -euo pipefail
cd "$(dirname "$0")/.."
UAV=${UAV:-target/release/uavmeta}
RUN=$1 NAME=$2 LAMBDA=$3 RAIN=$4 SEED=$5
TASK=(--lambda "$LAMBDA")
[ "$RAIN" != "-" ] && TASK+=(--rain "$RAIN")
OUT=runs/shots-ablation/$NAME-s$SEED
INITS=$RUN/seed-$SEED/inits
mkdir -p "$OUT"

ret() { "$UAV" eval "${TASK[@]}" --checkpoint "$1" 2>/dev/null | awk '/return/ {print $2}'; }

[ -f "$OUT/buffer.uavds" ] || "$UAV" collect "${TASK[@]}" --policy dqn-online --transitions 16000 \
    --seed $((100 + SEED)) --out "$OUT/buffer.uavds" > "$OUT/buffer.log" 2>&1
AGENT=$OUT/buffer.uavds.agent/online-dqn
[ -f "$OUT/kept.uavds" ] || "$UAV" collect "${TASK[@]}" --policy "q:0.01:$AGENT" --transitions 16000 \
    --seed $((100 + SEED)) --out "$OUT/kept.uavds" > "$OUT/kept.log" 2>&1

echo "agent $(ret "$AGENT")" > "$OUT/results.txt"
for data in buffer kept; do
    "$UAV" dataset inspect "$OUT/$data.uavds" | awk -v d=$data '/rewards/ {print "level-" d, $5 * 100}' \
        >> "$OUT/results.txt"
    for shots in 500 1000 2000; do
        common=("${TASK[@]}" --dataset "$OUT/$data.uavds" --shots "$shots" --seed "$SEED" --out "$OUT/run")
        rm -rf "$OUT/run"; "$UAV" meta-test --init "$INITS/w0" "${common[@]}" > /dev/null 2>&1
        echo "cql-maml-$data-$shots $(ret "$OUT/run/final")" >> "$OUT/results.txt"
        rm -rf "$OUT/run"; "$UAV" train --algo cql --init "$INITS/cql-pretrain" "${common[@]}" > /dev/null 2>&1
        echo "cql-pretrain-$data-$shots $(ret "$OUT/run/final")" >> "$OUT/results.txt"
        rm -rf "$OUT/run"; "$UAV" train --algo cql --init random "${common[@]}" > /dev/null 2>&1
        echo "cql-$data-$shots $(ret "$OUT/run/final")" >> "$OUT/results.txt"
    done
done
rm -rf "$OUT/run"
cat "$OUT/results.txt"
