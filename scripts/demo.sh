#!/usr/bin/env bash
# The main job on the bundled sample incident: set up, generate the sample's photos (deterministic),
# run every stage, and print where the outputs are. Run it again: finished stages are skipped.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --demo  # what a run needs; scripts/test.sh installs the test clients
INCIDENT=${1:-projects/spuyten-duyvil}
case "$INCIDENT" in
  *spuyten-duyvil) SCEN=(--scenario spuyten-duyvil --seed 1 --layers-dir ../../terrain/bronx) ;;
  *frankford-junction) SCEN=(--scenario frankford-junction --seed 1 --layers-dir ../../terrain/philadelphia) ;;
  *) SCEN=() ;;
esac
if [ ${#SCEN[@]} -gt 0 ]; then
  .venv/bin/workbench synth "$INCIDENT" "${SCEN[@]}"
fi
if [ -f "$INCIDENT/photos.txt" ]; then  # a real-photo sample: its photos come from ../shared/data (not in git)
  mkdir -p "$INCIDENT/photos"
  while read -r src; do
    case "$src" in ''|'#'*) continue ;; esac
    [ -f "$src" ] || { echo "error: $INCIDENT/photos.txt names $src, which is not here; this sample needs the shared data folder beside the clone (../shared/data)" >&2; exit 2; }
    cp -n "$src" "$INCIDENT/photos/"
  done < "$INCIDENT/photos.txt"
fi
.venv/bin/workbench run "$INCIDENT"
.venv/bin/workbench status "$INCIDENT"
echo
echo "Outputs of $INCIDENT:"
echo "  report:         $INCIDENT/out/report/report.pdf  (and report.html)"
echo "  exports:        $INCIDENT/out/export/  (scene.glb; georeferenced incidents also carriages.geojson, scene.kmz, scene.city.json, tiles/)"
echo "  renders:        $INCIDENT/out/render/"
echo "  poses:          $INCIDENT/out/solve/solution.json"
echo "  photos:         $INCIDENT/photos/$([ -d "$INCIDENT/truth" ] && echo "  truth: $INCIDENT/truth/ground_truth.json")"
echo "  3D viewer:      xvfb-run -a .venv/bin/workbench view $INCIDENT --screenshot view.png  (or without xvfb-run on a desktop)"
