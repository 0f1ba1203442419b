#!/usr/bin/env bash
# Run the first stages (scene check with overlays, photo filtering, visibility) on every shared
# real scene and record what they print in evaluation/results/foundation_scenes.md.
#   bash evaluation/foundation_scenes.sh [long_side]   (default 512; overlays go to results/foundation/)
set -euo pipefail
cd "$(dirname "$0")/.."
LS=${1:-512}
DATA=../shared/data
OUT=results/foundation
MD=evaluation/results/foundation_scenes.md
mkdir -p "$OUT" evaluation/results
cfg="$OUT/config.yaml"
printf 'texture: {long_side: %s}\n' "$LS" > "$cfg"
{
  echo "# First stages on the shared real scenes"
  echo
  echo "\`bash evaluation/foundation_scenes.sh $LS\` on $(date -u '+%Y-%m-%d %H:%M UTC'), $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(nproc) cores."
  echo
  for s in "$DATA"/*/; do
    name=$(basename "$s")
    echo "## $name"
    echo '```'
    difftex inspect "$s" --overlays "$OUT/$name/overlays" --max-overlays 3 2>&1 | sed "s#$OUT#results/foundation#"
    difftex filter --scene "$s" --config "$cfg" --out "$OUT/$name/photos.json" --quiet 2>&1
    difftex visibility --scene "$s" --photos "$OUT/$name/photos.json" --config "$cfg" --out-dir "$OUT/$name/visibility" --quiet 2>&1
    echo '```'
    echo
  done
} > "$MD.part"
mv "$MD.part" "$MD"
cat "$MD"
