#!/usr/bin/env bash
# The README is the front door and the docs are reachable (issue 33): README.md under 10 KB with
# table rows under 200 characters and no measured figure of its own (they live in
# docs/results.md, made by scripts/results, which must exist); every docs/*.md linked from
# docs/README.md; every relative link in README.md and docs/*.md names a file that exists.
# Usage: check_docs.sh SOURCE_DIR. Exit 1 naming each problem.
set -uo pipefail
cd "$1" || exit 2
bad=0
say() { echo "docs: $*"; bad=1; }
size=$(wc -c <README.md)
((size < 10240)) || say "README.md is $size bytes (the front door stays under 10 KB; details go to docs/)"
while IFS= read -r row; do
  say "README.md: a table row of ${#row} characters (one short line a row): ${row:0:80}..."
done < <(grep -E '^\|' README.md | awk 'length($0) >= 200')
# A measured figure (a latency, an error, a speed-up) belongs in docs/results.md.
while IFS= read -r hit; do
  say "README.md:$hit: a measured figure (docs/results.md holds them, made by scripts/results)"
done < <(grep -nE '[0-9]+(\.[0-9]+)? ?(ms|us|µs|px)\b|[0-9]+\.[0-9]+ ?mm\b|[0-9.]+x (faster|slower)' README.md |
         grep -v 'amplitudes of' | cut -c1-100)
[[ -f docs/results.md ]] || say "docs/results.md is missing (run scripts/results)"
grep -q 'scripts/results' docs/results.md 2>/dev/null || say "docs/results.md does not say it is made by scripts/results"
for f in docs/*.md; do
  name=${f#docs/}
  [[ $name == README.md ]] && continue
  grep -q "($name\(#[^)]*\)\?)" docs/README.md || say "docs/README.md does not link $name"
done
for f in README.md docs/*.md; do
  dir=$(dirname "$f")
  # Markdown links [text](target): relative targets only (no scheme, no pure anchor).
  while IFS= read -r target; do
    path=${target%%#*}
    [[ -z $path || $path =~ ^[a-z]+: ]] && continue
    [[ -e $dir/$path ]] || say "$f: link to $target: no such file"
  done < <(grep -oE '\]\([^) ]+\)' "$f" | sed -E 's/^\]\((.*)\)$/\1/')
done
((bad == 0)) && echo "docs: README.md $size bytes; $(ls docs/*.md | wc -l) docs, all linked from docs/README.md; links resolve"
exit $bad
