#!/usr/bin/env bash
# One random-policy actor sends 3 M transitions to a real `uavmeta store`; prints the wall time
# from the actor's start (libtorch's loading included) to its exit, which waits for the store to
# acknowledge its last transition. 3 times each at 64 and 1024 transitions per message
# (docs/BENCHMARKS.md, Transport). Usage: benches/store_roundtrip.sh [BIN]
set -euo pipefail
bin=${1:-target/release/uavmeta}
work=$(mktemp -d /tmp/uavmeta-roundtrip-XXXXXX)
store=
trap '[ -n "$store" ] && kill "$store" 2>/dev/null; rm -rf "$work"' EXIT

one() { # transitions per message
    local dir="$work/$1-$RANDOM"
    mkdir -p "$dir"
    printf '[[tasks]]\nname = "bench"\nlambda = 300.0\nrole = "meta-test"\n[collect]\ntransitions = 1000000000\n[run]\ntransitions_per_message = %s\n' \
        "$1" > "$dir/config.toml"
    "$bin" store --run "$dir/run" --config "$dir/config.toml" > /dev/null 2>&1 &
    store=$!
    until [ -f "$dir/run/ports/store.port" ]; do sleep 0.05; done
    local start end
    start=$(date +%s.%N)
    "$bin" actor --run "$dir/run" --task bench --policy random --transitions 3000000 > /dev/null 2>&1
    end=$(date +%s.%N)
    kill -TERM "$store"; wait "$store" || true; store=
    printf '| %s | %.3f s |\n' "$1" "$(echo "$end - $start" | bc)"
}

echo "| transitions per message | actor start to last transition acknowledged |"
echo "| ---: | ---: |"
for batch in 64 1024; do
    for _ in 1 2 3; do
        one "$batch"
    done
done
