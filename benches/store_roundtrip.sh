#!/usr/bin/env bash
# One random-policy actor sends 3 M transitions to a real `uavmeta store`; prints the wall time
# from the actor's start (libtorch's loading included) to its exit, which waits for the store to
# acknowledge its last transition. Runs `keep_until_stored` on and off in turns, 3 times each, at
# batch 64 and 1024 (docs/BENCHMARKS.md, Transport). Usage: benches/store_roundtrip.sh [BIN]
set -euo pipefail
bin=${1:-target/release/uavmeta}
work=$(mktemp -d /tmp/uavmeta-roundtrip-XXXXXX)
store=
trap '[ -n "$store" ] && kill "$store" 2>/dev/null; rm -rf "$work"' EXIT

one() { # keep batch
    local dir="$work/$1-$2-$RANDOM"
    mkdir -p "$dir"
    printf '[[tasks]]\nname = "bench"\nlambda = 300.0\nrole = "meta-test"\n[collect]\ntransitions = 1000000000\n[run]\nbatch_size = %s\nkeep_until_stored = %s\n' \
        "$2" "$1" > "$dir/config.toml"
    "$bin" store --run "$dir/run" --config "$dir/config.toml" > /dev/null 2>&1 &
    store=$!
    until [ -f "$dir/run/ports/store.port" ]; do sleep 0.05; done
    local start end
    start=$(date +%s.%N)
    "$bin" actor --run "$dir/run" --task bench --policy random --transitions 3000000 > /dev/null 2>&1
    end=$(date +%s.%N)
    kill -TERM "$store"; wait "$store" || true; store=
    printf '| %s | %s | %.3f s |\n' "$2" "$1" "$(echo "$end - $start" | bc)"
}

echo "| batch | keep_until_stored | actor start to last transition acknowledged |"
echo "| ---: | --- | ---: |"
for batch in 64 1024; do
    for _ in 1 2 3; do
        one true "$batch"
        one false "$batch"
    done
done
