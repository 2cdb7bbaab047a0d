#!/usr/bin/env bash
# The ablations of docs/EXPERIMENTS.md: each row changes one choice and measures its effect on the
# unseen task lambda-300 over seeds 0-4, through the plain CLI (collect, eval, train, meta-train,
# meta-test). Prints one markdown table per choice.
#
#   bash docs/ablations.sh [OUT]        # OUT defaults to runs/ablations; about 20 min on 2 cores
#
# Section C meta-trains (on all ten meta-train tasks of configs/reproduce.toml) on the datasets a
# reproduction cached (`uavmeta reproduce --out docs/reproduction`), so no agent is trained twice.
set -euo pipefail
cd "$(dirname "$0")/.."
UAV=${UAV:-target/release/uavmeta}
OUT=${1:-runs/ablations}
REPRO=${REPRO:-docs/reproduction}
SEEDS=(0 1 2 3 4)
mkdir -p "$OUT"

# Mean ± 95% CI (Student's t, 4 degrees of freedom) and the worst of five returns.
summary() {
    python3 -c 'import sys, statistics as s
v = [float(x) for x in sys.argv[1:]]
print(f"{s.mean(v):.0f} ± {2.776 * s.stdev(v) / len(v) ** 0.5:.0f} | {min(v):.0f}")' "$@"
}
# A section's heading and the header of its table, from the column names.
section() {
    local title=$1 columns rule
    shift
    columns=$(printf ' %s |' "$@")
    rule=$(printf ' --- |%.0s' "$@")
    printf '\n## %s\n\n|%s\n|%s\n' "$title" "$columns" "$rule"
}
# The greedy return of a checkpoint on lambda-300 over 20 episodes.
eval_return() {
    "$UAV" eval --config "$1" --task lambda-300 --checkpoint "$2" --episodes 20 "${@:3}" 2>/dev/null \
        | awk '$1 == "return" {print $2}'
}
# The return of a train.csv at epoch $2.
csv_return() { awk -F, -v e="$2" '$1 == e {print $6}' "$1/train.csv"; }
# Runs "$@" for every seed, two at a time (the machine's two cores), with SEED set.
for_seeds() {
    local pids=()
    for SEED in "${SEEDS[@]}"; do
        SEED=$SEED "$@" &
        pids+=($!)
        if (( ${#pids[@]} == 2 )); then wait "${pids[0]}"; pids=("${pids[@]:1}"); fi
    done
    wait
}

section "A. Online DQN on lambda-300 (configs/default.toml, 15 000 steps), greedy return" \
    change "return, mean ± 95% CI" "worst seed"
declare -A DQN=(
    [default]=""
    [target-500]="--set collect.dqn.target_update_every=500"
    [eps-end-0.05]="--set collect.dqn.eps_end=0.05"
    [lr-1e-3]="--set collect.dqn.lr=0.001"
    [no-stabilisers]="--set collect.dqn.double_dqn=false --set collect.dqn.huber=false --set collect.dqn.grad_clip_norm=0 --set collect.dqn.target_update_every=100"
    [old-defaults]="--set collect.dqn.double_dqn=false --set collect.dqn.huber=false --set collect.dqn.grad_clip_norm=0 --set collect.dqn.target_update_every=100 --set collect.dqn.lr=0.001 --set collect.dqn.hidden=[64,64]"
)
collect_one() {
    local dir=$OUT/dqn-$1
    mkdir -p "$dir"
    [ -e "$dir/$SEED.uavds.agent/online-dqn.json" ] ||
        "$UAV" collect --task lambda-300 --seed "$SEED" --out "$dir/$SEED.uavds" ${DQN[$1]} >/dev/null 2>&1
}
for variant in default target-500 eps-end-0.05 lr-1e-3 no-stabilisers old-defaults; do
    for_seeds collect_one "$variant"
    returns=()
    for s in "${SEEDS[@]}"; do
        # The agent's own config: it may have another network than configs/default.toml.
        returns+=("$(eval_return "$OUT/dqn-$variant/$s.uavds.config.toml" "$OUT/dqn-$variant/$s.uavds.agent/online-dqn")")
    done
    echo "| $variant: ${DQN[$variant]:-as configured} | $(summary "${returns[@]}") |"
done

section "A2. Online DQN on the AoI-dominated tasks (configs/reproduce.toml), greedy return over 10 episodes" \
    task change "return, mean ± 95% CI" "worst seed"
declare -A LOW=(
    [default]=""
    [eps-end-0.05]="--set collect.dqn.eps_end=0.05"
    [target-500]="--set collect.dqn.target_update_every=500"
    [target-500-eps-end-0.05]="--set collect.dqn.target_update_every=500 --set collect.dqn.eps_end=0.05"
    [target-500-steps-20k]="--set collect.dqn.target_update_every=500 --set collect.dqn.eps_end=0.05 --set collect.dqn.steps=20000 --set collect.dqn.eps_decay_steps=8000"
)
collect_low() {
    local dir=$OUT/dqn-$1-$2
    mkdir -p "$dir"
    [ -e "$dir/$SEED.uavds.agent/online-dqn.json" ] ||
        "$UAV" collect --config configs/reproduce.toml --task "$1" --seed "$SEED" \
            --out "$dir/$SEED.uavds" ${LOW[$2]} >/dev/null 2>&1
}
for task in lambda-0 lambda-100; do
    for variant in default target-500 target-500-eps-end-0.05 target-500-steps-20k; do
        for_seeds collect_low "$task" "$variant"
        returns=()
        for s in "${SEEDS[@]}"; do
            returns+=("$("$UAV" eval --config "$OUT/dqn-$task-$variant/$s.uavds.config.toml" --task "$task" \
                --checkpoint "$OUT/dqn-$task-$variant/$s.uavds.agent/online-dqn" --episodes 10 2>/dev/null |
                awk '$1 == "return" {print $2}')")
        done
        echo "| $task | $variant: ${LOW[$variant]:-as configured} | $(summary "${returns[@]}") |"
    done
done

section "B. CQL from a random init on 500 shots of that agent's replay, greedy return" \
    change "return, mean ± 95% CI" "worst seed"
train_one() {
    local data=$1 out=$2
    shift 2
    [ -e "$out/$SEED/train.csv" ] ||
        "$UAV" train --algo cql --task lambda-300 --dataset "$data/$SEED.uavds" --shots 500 \
            --epochs 250 --seed "$SEED" --out "$out/$SEED" "$@" >/dev/null 2>&1
}
whole_buffer() {
    local dir=$OUT/dqn-whole-buffer
    mkdir -p "$dir"
    [ -e "$dir/$SEED.uavds" ] ||
        "$UAV" collect --task lambda-300 --seed "$SEED" --out "$dir/$SEED.uavds" \
            --set collect.sample_newest=0 >/dev/null 2>&1
}
for_seeds whole_buffer
for_seeds train_one "$OUT/dqn-default" "$OUT/cql-default"
for_seeds train_one "$OUT/dqn-whole-buffer" "$OUT/cql-whole-buffer"
for_seeds train_one "$OUT/dqn-default" "$OUT/cql-64x64" --set learner.hidden=[64,64]
row() {
    local returns=()
    for s in "${SEEDS[@]}"; do returns+=("$(csv_return "$OUT/$1/$s" "$2")"); done
    echo "| $3 | $(summary "${returns[@]}") |"
}
row cql-default 250 "none: shots of the newest 3 000 steps, [256, 256], 250 epochs"
row cql-default 40 "40 epochs"
row cql-default 100 "100 epochs (the launch's budget)"
row cql-whole-buffer 250 "shots of the whole 8 000-step buffer (collect.sample_newest = 0)"
row cql-64x64 250 "learner.hidden = [64, 64]"

section "C. MAML on the reproduction's datasets ($REPRO/cache), w0 zero-shot and after 40 epochs" \
    change "w0 zero-shot" "worst seed" "CQL-MAML at epoch 40" "worst seed"
declare -A META=(
    [pass]=""
    [one-outer-step]="--set meta.outer_steps_per_meta_epoch=1"
    [target-every-10]="--set meta.target_update_meta_epochs=10"
    [first-order]="--set meta.first_order=true"
)
meta_one() {
    local out=$OUT/maml-$1/$SEED data=$REPRO/cache/seed-$SEED/datasets
    [ -e "$out/test/train.csv" ] || {
        "$UAV" meta-train --config configs/reproduce.toml --datasets "$data" --out "$out" \
            --seed "$SEED" ${META[$1]} >/dev/null 2>&1
        "$UAV" meta-test --config configs/reproduce.toml --task lambda-300 --init "$out/w0" \
            --dataset "$data/lambda-300.uavds" --shots 500 --epochs 40 --seed "$SEED" \
            --out "$out/test" >/dev/null 2>&1
    }
}
for variant in pass one-outer-step target-every-10 first-order; do
    for_seeds meta_one "$variant"
    zero=()
    tuned=()
    for s in "${SEEDS[@]}"; do
        zero+=("$(eval_return configs/reproduce.toml "$OUT/maml-$variant/$s/w0")")
        tuned+=("$(csv_return "$OUT/maml-$variant/$s/test" 40)")
    done
    echo "| $variant: ${META[$variant]:-as configured} | $(summary "${zero[@]}") | $(summary "${tuned[@]}") |"
done
