#!/usr/bin/env bash
# Builds every fuzz target and runs each for SECONDS (default 30); exits
# non-zero when any target finds a crash, a timeout or an out-of-memory input.
#
#   fuzz/run.sh [SECONDS]
#
# Needs a nightly toolchain (installed through rustup when it is missing) and
# cargo-fuzz (installed with `cargo install cargo-fuzz --locked` when missing).
# Each target starts from its committed seeds (fuzz/seeds/TARGET) plus the
# local working corpus (fuzz/corpus/TARGET, ignored by git), which keeps what
# earlier runs found. Crashing inputs land in fuzz/artifacts/TARGET/.
set -euo pipefail
seconds=${1:-30}
case $seconds in
'' | *[!0-9]*)
    echo "usage: $0 [SECONDS]" >&2
    exit 2
    ;;
esac
cd "$(dirname "$0")/.."
export CARGO_TERM_COLOR=${CARGO_TERM_COLOR:-never}

if command -v rustup >/dev/null && ! rustup run nightly rustc --version >/dev/null 2>&1; then
    rustup toolchain install nightly --profile minimal
fi
if ! cargo +nightly fuzz --version >/dev/null 2>&1; then
    cargo install cargo-fuzz --locked
fi
cargo +nightly fuzz --version

targets=$(cargo +nightly fuzz list)
start=$(date +%s)
echo "== build ($(echo $targets | tr '\n' ' '))"
cargo +nightly fuzz build
echo "== built in $(($(date +%s) - start)) s"

failed=()
for t in $targets; do
    echo "== $t: ${seconds} s"
    mkdir -p "fuzz/corpus/$t"
    dirs=("fuzz/corpus/$t")
    [ -d "fuzz/seeds/$t" ] && dirs+=("fuzz/seeds/$t")
    args=(-max_total_time="$seconds" -timeout=20 -rss_limit_mb=2048 -print_final_stats=1)
    case $t in
    wire*) args+=(-dict=fuzz/dict/wire.dict) ;;
    config) args+=(-dict=fuzz/dict/config.dict) ;;
    esac
    if ! cargo +nightly fuzz run "$t" "${dirs[@]}" -- "${args[@]}"; then
        failed+=("$t")
    fi
done

echo "== done in $(($(date +%s) - start)) s"
if [ ${#failed[@]} -gt 0 ]; then
    echo "fuzzing found crashes in: ${failed[*]}" >&2
    echo "inputs are in fuzz/artifacts/<target>/; see fuzz/README.md to reproduce one" >&2
    exit 1
fi
