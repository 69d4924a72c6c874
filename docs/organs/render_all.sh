#!/usr/bin/env bash
# Regenerates the pictures of docs/builtin_organs.md: every built-in organ rendered off-screen
# (software rasteriser, no display) to docs/organs/NAME.png, and prints each organ's figures as
# a Markdown table row. Run after `./somasim build`:  bash docs/organs/render_all.sh
set -euo pipefail
cd "$(dirname "$0")"
tool=${SOMASIM_MESH:-../../build/bin/somasim-mesh}
# name  view direction (camera → organ)  up
views=(
  "liver4055       -0.35,1,-0.5    0,0,1"
  "liver288        -0.35,1,-0.5    0,0,1"
  "kidney424       0.1,0.3,-1      0,1,0"
  "plate192        0.35,0.6,-1     0,1,0"
  "tissue45        0.3,0.6,-1      0,1,0"
  "spleen600       0.3,1,0.5       0,0,1"
  "kidney2000      0.1,0.3,-1      0,1,0"
  "gallbladder5400 0.2,0.6,-1      0,0,1"
  "beam19k         0.45,1,-0.6     0,0,1"
)
echo "| organ | nodes | elements | size [cm] | volume [mL] | min dihedral [°] | watertight |"
echo "|---|---|---|---|---|---|---|"
for row in "${views[@]}"; do
  read -r name view up <<<"$row"
  "$tool" render "builtin:$name" "$name.png" --size 640x400 --view="$view" --up "$up" >/dev/null
  "$tool" info "builtin:$name" --json | python3 -c '
import json, sys
j = json.load(sys.stdin)
name = sys.argv[1]
size = " × ".join(f"{(b - a) * 100:.1f}" for a, b in zip(j["bbox_min"], j["bbox_max"]))
vol = j.get("volume_m3")
vol = f"{vol * 1e6:.0f}" if vol is not None else "—"
tets, tris, nodes = j["tetrahedra"], j["triangles"], j["nodes"]
elements = f"{tets} tets" if tets else f"{tris} triangles"
dihedral = j.get("min_dihedral_deg")
dihedral = f"{dihedral:.1f}" if dihedral is not None else "—"
closed = "yes" if j["watertight"] else "no (open)"
print(f"| `{name}` | {nodes} | {elements} | {size} | {vol} | {dihedral} | {closed} |")
' "$name"
done
