#!/usr/bin/env bash
# docs/EXPERIMENTS.md, B3: fine-tuning and offline training with and without `learner.average_decay`,
# on the reproduction's cached datasets and inits (`uavmeta reproduce --out REPRO` first) and on a
# launch's run directory (`make run`: runs/default). Writes OUT/<data>/<task>/<method>-d<D>-s<S>/train.csv.
#
#   bash docs/average_ablation.sh REPRO runs/default OUT        # about 10 min on 2 cores
set -euo pipefail
repro=${1:?REPRO: the reproduction's --out}; launch=${2:?the launch's run.dir}; out=${3:?OUT}
bin=target/release/uavmeta

one() { # CONFIG SEED_DIR TASK METHOD SEED DECAY EPOCHS DEST
    local cfg=$1 dir=$2 task=$3 method=$4 seed=$5 decay=$6 epochs=$7 dest=$8
    local ds=$dir/datasets/$task.uavds init
    local common=(--config "$cfg" --task "$task" --dataset "$ds" --shots 500 --epochs "$epochs"
                  --seed "$seed" --out "$dest/$task/$method-d$decay-s$seed"
                  --set "learner.average_decay=$decay")
    case $method in
    cql) "$bin" train --algo cql --init random "${common[@]}" ;;
    cql-maml|cql-pretrain)
        init=$dir/$method-tasks-8/w0                        # the reproduction's cache
        if [ ! -f "$init.safetensors" ]; then                # a launch's run directory
            if [ "$method" = cql-maml ]; then init=$dir/inits/w0; else init=$dir/inits/cql-pretrain; fi
        fi
        "$bin" meta-test --init "$init" "${common[@]}" ;;
    esac >/dev/null 2>&1
}

for method in cql-maml cql-pretrain cql; do
    for seed in 0 1 2 3 4; do
        for decay in 0 0.9 0.95; do
            one configs/reproduce.toml "$repro/cache/seed-$seed" lambda-300 $method $seed $decay 250 "$out/repro"
        done
    done
    for seed in 0 1 2; do
        for decay in 0 0.95; do
            one configs/default.toml "$launch/seed-$seed" lambda-300 $method $seed $decay 100 "$out/launch"
        done
    done
done
for task in lambda-100 lambda-1000 lambda-300-rain-1; do
    for method in cql-maml cql-pretrain; do
        for seed in 0 1 2 3 4; do
            for decay in 0 0.95; do
                one configs/reproduce.toml "$repro/cache/seed-$seed" $task $method $seed $decay 200 "$out/repro"
            done
        done
    done
done
