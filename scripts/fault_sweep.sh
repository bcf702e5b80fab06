#!/usr/bin/env bash
# The fault sweep of docs/robustness.md ("Interrupted, doubled or slowed"): whole commands killed
# at 20 moments, given a full disk at 10 sizes, and started twice on one folder, on the SIMULATED
# small scene. Prints three markdown tables (and keeps the logs in WORK).
#
#   bash scripts/fault_sweep.sh [GS4CITY_BINARY] [WORK]
#
# PARTS (environment; default "kill disk pairs") picks the tables to make.
# The disk part mounts tmpfs file systems of a given size (root only; skipped otherwise).
# The slow-client load is the view test (20 s): cargo test --release --test tests
# view::slow_clients -- --nocapture.
set -u
PARTS=${PARTS:-kill disk pairs}
has() { case " $PARTS " in *" $1 "*) return 0 ;; *) return 1 ;; esac; }
G=$(realpath "${1:-target/release/gs4city}")
W=${2:-$(mktemp -d)}
mkdir -p "$W"
cd "$W" || exit 1
echo "binary $G, work $W, $(nproc) cores, load $(cut -d' ' -f1-3 /proc/loadavg)" >&2

# Result files: every file but the records that hold times, run ids or the lock holder.
same() { diff -rq -x summary.json -x run.json -x report.html -x .lock "$1" "$2" >/dev/null 2>&1 && echo yes || echo NO; }
now() { date +%s.%N; }

[ -d S ] || "$G" -q synth --preset small --out S >/dev/null
rm -rf R0
t0=$(now)
"$G" -q run --scene S --out R0 >R0.log 2>&1 || { echo "the solo run failed" >&2; exit 1; }
T=$(echo "$(now) - $t0" | bc)
echo "solo run: $T s" >&2

if has kill; then
echo
echo "| kill -9 after | stage folders complete | summary.json left | resume exit | resume s | stages rerun | outputs = solo |"
echo "|---:|---:|---|---:|---:|---:|---|"
for k in $(seq 1 20); do
  at=$(echo "scale=2; $T * $k / 21" | bc)
  rm -rf "K$k"
  timeout -s KILL "$at" "$G" -q run --scene S --out "K$k" >/dev/null 2>&1
  stages=$(find "K$k" -mindepth 1 -maxdepth 1 -type d ! -name '.*' 2>/dev/null | wc -l)
  left=$([ -e "K$k/summary.json" ] && echo yes || echo no)
  t1=$(now)
  "$G" run --scene S --out "K$k" >"K$k.resume.log" 2>&1
  rc=$?
  dt=$(echo "$(now) - $t1" | bc)
  rerun=$(grep -cvE '\(resumed\)|^stage|^ *$' <(sed -n '/^stage/,/^$/p' "K$k.resume.log"))
  printf '| %.1f s | %d | %s | %d | %.1f | %d | %s |\n' "$at" "$stages" "$left" "$rc" "$dt" "$rerun" "$(same R0 "K$k")"
  rm -rf "K$k"
done
fi

if has disk; then
echo
echo "| free space | exit | error lines | the error (first 160 characters) | leftovers |"
echo "|---:|---:|---:|---|---|"
if [ "$(id -u)" = 0 ]; then
  for mb in 1 4 16 32 64 96 128 160 200 400; do
    mkdir -p "D$mb"
    mount -t tmpfs -o "size=${mb}M" tmpfs "D$mb" || { echo "| $mb MB | (no tmpfs) | | | |"; continue; }
    "$G" -q run --scene S --out "D$mb/R" >"D$mb.log" 2>&1
    rc=$?
    lines=$(grep -c '^error' "D$mb.log")
    first=$(grep -m1 '^error' "D$mb.log" | sed "s#$W/##g" | cut -c1-160 | sed 's/|/\\|/g')
    rest=$(find "D$mb/R" -maxdepth 1 -name '.*.partial' 2>/dev/null | wc -l)
    tmp=$(find "D$mb/R" -name '.*.tmp*' 2>/dev/null | wc -l)
    echo "| $mb MB | $rc | $lines | $first | $rest partial folders, $tmp temporary files |"
    umount "D$mb"
    rmdir "D$mb"
  done
else
  echo "| (not root: no tmpfs) | | | | |"
fi
fi

has pairs || exit 0
echo
echo "| first (A) | second (B), 1 s later | B exit | B says | A exit | A's result = solo |"
echo "|---|---|---:|---|---:|---|"
rm -rf P
"$G" -q tile --scene S --size 10 --margin 4 --out P >/dev/null
pair() { # name_a name_b folder_to_compare cmd_a... -- cmd_b...
  local na=$1 nb=$2 cmp=$3; shift 3
  local a=() b=()
  while [ "$1" != "--" ]; do a+=("$1"); shift; done; shift
  b=("$@")
  "$G" -q "${a[@]}" >A.log 2>&1 &
  local pa=$!
  sleep 1
  "$G" -q "${b[@]}" >B.log 2>&1
  local rb=$?
  # A server (view) does not end by itself: stopped by its pid.
  [ "${a[0]}" = view ] && kill "$pa"
  local says
  # B's error line where it has one (a refusal may come after warnings), else its first line.
  says=$( (grep -m1 '^error' B.log || grep -m1 . B.log) | sed "s#$W/##g; s#$G#gs4city#g" | cut -c1-150 | sed 's/|/\\|/g')
  [ -z "$says" ] && says="(nothing: ran)"
  wait "$pa"
  local ra=$?
  local eq="—"
  [ -n "$cmp" ] && eq=$(same R0 "$cmp")
  echo "| \`$na\` | \`$nb\` | $rb | $says | $ra | $eq |"
}
rm -rf R1; pair "run S → R1" "run S → R1" R1 run --scene S --out R1 -- run --scene S --out R1
rm -rf R1; pair "run S → R1" "run S → R1 --supervision city" R1 run --scene S --out R1 -- run --scene S --out R1 --supervision city
rm -rf R1; pair "run S → R1" "query --run R1" R1 run --scene S --out R1 -- query --run R1 --class Window --out Q1
pair "view --run R0" "run S → R0" "" view --run R0 --port 0 -- run --scene S --out R0
pair "query --run R0" "query --run R0" "" query --run R0 --class Window --out Q2 -- query --run R0 --class WallSurface --out Q3
pair "run-plan P --tile 0" "run-plan P --tile 0" "" run-plan P --tile 0 -- run-plan P --tile 0
pair "run-plan P --jobs 2" "run-plan P --jobs 2" "" run-plan P --jobs 2 --no-test-views -- run-plan P --jobs 2 --no-test-views
pair "merge P → M" "merge P → M" "" merge P --out M -- merge P --out M
pair "merge P → M" "query --run M" "" merge P --out M -- query --run M --class Window --out Q4
