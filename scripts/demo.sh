#!/usr/bin/env bash
# The main job on the bundled sample incident: set up, generate the sample's photos (deterministic),
# run every stage, and print where the outputs are. Run it again: finished stages are skipped.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
INCIDENT=${1:-projects/spuyten-duyvil}
case "$INCIDENT" in
  *spuyten-duyvil) SCEN=(--scenario spuyten-duyvil --seed 1 --layers-dir ../../terrain/bronx) ;;
  *frankford-junction) SCEN=(--scenario frankford-junction --seed 1 --layers-dir ../../terrain/philadelphia) ;;
  *) SCEN=() ;;
esac
if [ ${#SCEN[@]} -gt 0 ]; then
  .venv/bin/workbench synth "$INCIDENT" "${SCEN[@]}"
fi
.venv/bin/workbench run "$INCIDENT"
.venv/bin/workbench status "$INCIDENT"
echo
echo "Outputs of $INCIDENT:"
echo "  stage outputs:  $INCIDENT/out/  (inputs/inputs.json, terrain/terrain.ply, terrain/buildings.ply, state.json)"
echo "  photos & truth: $INCIDENT/photos/  $INCIDENT/truth/ground_truth.json"
echo "  (the report and GIS exports come with the render/report/export stages, which are not built yet)"
