#!/usr/bin/env bash
# The totals line of scripts/test.sh, from the output of `cargo test` (LOG) and the skip log the
# tests append to (SKIPS, lines `SKIPPED: <test>: <why>`, see tests/common/mod.rs):
#
#   tests: P passed, F failed, S skipped, I ignored (N run)
#
# N is the sum of cargo's `running N tests` lines; F and I are cargo's `test result:` counts.
# A skipped test is counted once, by its name, however many skip lines it wrote: the names of
# the skip log that cargo reports as `test <name> ... ok` are the skipped tests (cargo counts
# them as passed: P is cargo's passed minus them). A skip line of a test that then failed
# leaves it failed. A skip line naming no test cargo ran is an error (exit 1), as is a total
# that does not add up: P + F + S + I = N. Prints the skipped tests with their reasons first.
#
#   bash scripts/test_totals.sh LOG SKIPS
set -euo pipefail
log=$1
skips=$2
awk -v skiplog="$skips" '
  /^running [0-9]+ tests?$/ { run += $2 }
  /^test result: / {
    for (i = 1; i <= NF; i++) {
      if ($(i + 1) ~ /^passed/) passed += $i
      if ($(i + 1) ~ /^failed/) failed += $i
      if ($(i + 1) ~ /^ignored/) ignored += $i
    }
  }
  # A child process writing to the terminal can put text before the line of cargo: a name without
  # spaces is also found after it (doc-test names have spaces, and start their line).
  match($0, /^test .* \.\.\. (ok|FAILED|ignored)/) || match($0, /test [^ ]+ \.\.\. (ok|FAILED|ignored)/) {
    line = substr($0, RSTART + 5)
    name = line
    sub(/ \.\.\. .*$/, "", name)
    status = line
    sub(/^.* \.\.\. /, "", status)
    sub(/[ ,].*$/, "", status)
    result[name] = status
  }
  END {
    while ((getline s < skiplog) > 0) {
      if (s !~ /^SKIPPED: /) continue
      rest = substr(s, 10)
      k = index(rest, ": ")
      name = k ? substr(rest, 1, k - 1) : rest
      why = k ? substr(rest, k + 2) : ""
      if (!(name in seen)) { seen[name] = 1; order[++n] = name; reason[name] = why }
    }
    skipped = 0
    bad = 0
    for (i = 1; i <= n; i++) {
      name = order[i]
      if (result[name] == "ok") {
        skipped++
        if (skipped == 1) print "skipped tests (what they need is missing):"
        print "  " name ": " reason[name]
      }
    }
    for (i = 1; i <= n; i++) {
      name = order[i]
      if (result[name] == "FAILED") {
        print "failed after skipping a cross-check (counted as failed): " name
      } else if (result[name] != "ok") {
        print "test_totals: the skip log names " name ", which is no test cargo reports as passed or failed" > "/dev/stderr"
        bad = 1
      }
    }
    p = passed - skipped
    printf "tests: %d passed, %d failed, %d skipped, %d ignored (%d run)\n", p, failed, skipped, ignored, run
    if (p + failed + skipped + ignored != run) {
      printf "test_totals: %d passed + %d failed + %d skipped + %d ignored is not the %d tests cargo ran\n", p, failed, skipped, ignored, run > "/dev/stderr"
      bad = 1
    }
    exit bad
  }
' "$log"
