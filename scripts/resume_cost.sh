#!/usr/bin/env bash
# What checking the content of every output on every resume would cost (BENCHMARKS.md, "Resume").
#
#   bash scripts/resume_cost.sh GS4CITY_BINARY SCENE RUN
#
# RUN is a finished run of SCENE. In turn, three rounds each, warm and then cold:
#   A  resumes RUN as it is (every output's times unchanged: nothing is read back);
#   B  first moves every output's inode change time (chmod u+w: content untouched), so that the
#      resume reads every output back and digests it.
# Cold: every output is evicted from the page cache first (GNU dd iflag=nocache count=0:
# posix_fadvise DONTNEED on that file alone), so B reads from the disk.
set -u
G=$1; S=$2; R=$3
evict() { find "$R" -mindepth 2 -type f -exec sh -c 'for f; do dd if="$f" iflag=nocache count=0 status=none; done' _ {} +; }
echo "$(du -sh "$R" | cut -f1) in $(find "$R" -mindepth 2 -type f | wc -l) outputs; load $(cut -d' ' -f1-3 /proc/loadavg)"
for cache in warm cold; do
  for round in 1 2 3; do
    for v in A B; do
      [ "$v" = B ] && find "$R" -mindepth 2 -type f -exec chmod u+w {} +
      [ "$cache" = cold ] && evict
      log=$(mktemp)
      /usr/bin/time -f "$cache $v round $round: wall %e s, user %U s, sys %S s, read %I blocks of 512 B" \
        "$G" run --scene "$S" --out "$R" >"$log" 2>"$log.err"
      tail -1 "$log.err"
      rerun=$(sed -n '/^stage/,/^$/p' "$log" | grep -vcE 'resumed|^stage|^$')
      echo "  stages rerun: $rerun (load $(cut -d' ' -f1 /proc/loadavg))"
      rm -f "$log" "$log.err"
    done
  done
done
