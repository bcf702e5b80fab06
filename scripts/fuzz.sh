#!/usr/bin/env bash
# Coverage-guided fuzzing of one gs4city reader with libFuzzer, on the stable toolchain.
#
#   scripts/fuzz.sh READER MINUTES        e.g. scripts/fuzz.sh citygml 10
#   scripts/fuzz.sh build [READER...]     only build the fuzz targets
#   scripts/fuzz.sh list                  the readers
#
# READER: citygml citymodel where ply_splat ply_mesh colmap_bin colmap_txt sam npy align (docs/robustness.md).
# The targets live in fuzz/ (a crate of its own: the main build and CI never compile them).
# They are built with SanitizerCoverage instrumentation through stable rustc flags
# (-C passes=sancov-module, no nightly features) plus debug assertions and overflow checks,
# and linked with libFuzzer from the `libfuzzer-sys` crate.
#
# A run uses libFuzzer's fork mode with one worker (one core), continues after a crash,
# timeout or out-of-memory (each saved under fuzz/artifacts/READER/), keeps its corpus in
# fuzz/corpus/READER/ (seeded from fuzz/seeds/READER/) and writes its log to
# $FUZZ_LOG_DIR/READER-<UTC time>.log (default fuzz/logs/). Limits per input: 10 s
# (a hang), 2 GiB RSS, and any single allocation above 1 GiB aborts (fuzz/src/lib.rs).
# It runs under `nice -n ${FUZZ_NICE:-15}`. Exit status: 0 when no crash was found.
set -euo pipefail
cd "$(dirname "$0")/.."

READERS="citygml citymodel where ply_splat ply_mesh colmap_bin colmap_txt sam npy align"
TRIPLE="$(rustc -vV | sed -n 's/^host: //p')"
BIN_DIR="fuzz/target/$TRIPLE/release"

build() {
    local flags="-Cpasses=sancov-module -Cllvm-args=-sanitizer-coverage-level=4"
    flags+=" -Cllvm-args=-sanitizer-coverage-inline-8bit-counters"
    flags+=" -Cllvm-args=-sanitizer-coverage-pc-table"
    flags+=" -Cllvm-args=-sanitizer-coverage-trace-compares"
    flags+=" --cfg fuzzing -Cdebug-assertions -Coverflow-checks"
    local bins=()
    for r in "$@"; do bins+=(--bin "$r"); done
    # --target keeps RUSTFLAGS away from build scripts and proc macros.
    RUSTFLAGS="$flags" nice -n "${FUZZ_NICE:-15}" cargo build --release --manifest-path fuzz/Cargo.toml \
        --target "$TRIPLE" "${bins[@]}"
}

case "${1:-}" in
    list) echo "$READERS"; exit 0 ;;
    build)
        shift
        # shellcheck disable=SC2086 # one word per reader
        [ $# -gt 0 ] || set -- $READERS
        build "$@"
        exit 0
        ;;
    "" | -h | --help) sed -n '2,20p' "$0"; exit 2 ;;
esac

READER="$1"
MINUTES="${2:?usage: scripts/fuzz.sh READER MINUTES}"
case " $READERS " in *" $READER "*) ;; *) echo "unknown reader $READER (one of: $READERS)" >&2; exit 2 ;; esac

case "$READER" in
    citygml | citymodel) MAX_LEN=16384; DICT=citygml ;;
    where) MAX_LEN=4096; DICT=where ;;
    ply_splat | ply_mesh) MAX_LEN=8192; DICT=ply ;;
    colmap_bin | colmap_txt) MAX_LEN=4096; DICT=colmap ;;
    sam) MAX_LEN=8192; DICT=sam ;;
    npy) MAX_LEN=4096; DICT=npy ;;
    align) MAX_LEN=4096; DICT=align ;;
esac

[ -x "$BIN_DIR/$READER" ] && [ -z "${FUZZ_REBUILD:-}" ] || build "$READER"

CORPUS="fuzz/corpus/$READER"
ARTIFACTS="fuzz/artifacts/$READER"
LOG_DIR="${FUZZ_LOG_DIR:-fuzz/logs}"
mkdir -p "$CORPUS" "$ARTIFACTS" "$LOG_DIR"
LOG="$LOG_DIR/$READER-$(date -u +%Y%m%dT%H%M%SZ).log"
SECONDS_TOTAL=$((MINUTES * 60))

{
    echo "# gs4city fuzz: reader=$READER engine=libFuzzer(fork=1) minutes=$MINUTES start=$(date -u +%FT%TZ)"
    echo "# commit=$(git rev-parse --short HEAD 2>/dev/null || echo unknown) max_len=$MAX_LEN dict=fuzz/dict/$DICT.dict"
} >"$LOG"
echo "fuzzing $READER for $MINUTES min; log: $LOG"

MARK="$(mktemp)"
status=0
nice -n "${FUZZ_NICE:-15}" "$BIN_DIR/$READER" "$CORPUS" "fuzz/seeds/$READER" \
    -fork=1 -ignore_crashes=1 -ignore_timeouts=1 -ignore_ooms=1 \
    -max_total_time="$SECONDS_TOTAL" -timeout=10 -rss_limit_mb=2048 -max_len="$MAX_LEN" \
    -dict="fuzz/dict/$DICT.dict" -artifact_prefix="$ARTIFACTS/" -print_final_stats=1 \
    >>"$LOG" 2>&1 || status=$?

found=$(find "$ARTIFACTS" -type f \( -name 'crash-*' -o -name 'timeout-*' -o -name 'oom-*' \) -newer "$MARK" 2>/dev/null | wc -l)
rm -f "$MARK"
# The last fork-mode status line holds the totals: "#N: cov: … exec/s: … oom/timeout/crash: a/b/c time: Ts".
last=$(grep -E '^#[0-9]+: cov:' "$LOG" | tail -n 1 || true)
{
    echo "# end=$(date -u +%FT%TZ) libfuzzer_status=$status new_artifacts=$found"
    echo "# final: ${last:-no status line}"
} >>"$LOG"
echo "done: $found new crash/timeout/oom inputs in $ARTIFACTS; last status: ${last:-none}"
[ "$found" -eq 0 ]
