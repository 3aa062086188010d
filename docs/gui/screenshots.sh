#!/usr/bin/env bash
# The GUIs' setup windows in real Tk windows on a virtual screen, as a user first sees them (issue 29): each window's
# title (from the X server) goes to windows.txt and a screenshot to docs/gui/<module>.png. Module 4's images folder is
# a deliberately long path, to show that a path longer than its field shows its end and stays inside the field.
# Needs Linux with Debian's xvfb, twm and imagemagick:  apt-get install xvfb twm imagemagick
#   bash docs/gui/screenshots.sh            (from the repository root, with the environment `make` built)
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=${PYTHON:-.venv/bin/python}
OUT=docs/gui
TMP=$(mktemp -d)
trap 'rm -rf "$TMP"' EXIT
"$PY" -m matchplant.cli simfield --preset tiny --out "$TMP/field" >/dev/null
F=$TMP/field
LONG=$TMP/season_2026_sorghum_trial_north_field_block_A_flight_07/undistorted_images_selected_by_module_3
mkdir -p "$LONG"
printf 'RandomPlacement\nUsePPosition "on"\n' > "$TMP/twmrc"
: > "$OUT/windows.txt"

shoot() {  # name, then the command; the window manager draws each window's title bar
  local name=$1; shift
  cat > "$TMP/shot.sh" <<SH
twm -f "$TMP/twmrc" >/dev/null 2>&1 &
"\$@" > "$TMP/$name.log" 2>&1 &
p=\$!
for i in \$(seq 60); do xwininfo -root -tree | grep -q '"MatchPlant - ' && break; sleep 1; done
sleep 3
xwininfo -root -tree | grep -o '"MatchPlant - [^"]*"' | sed "s/^/$name: /" >> "$OUT/windows.txt"
import -window root "$TMP/$name.png"
kill \$p
SH
  MPLBACKEND=TkAgg xvfb-run -a -s "-screen 0 1600x1000x24" bash "$TMP/shot.sh" "$@"
  convert "$TMP/$name.png" -trim +repage "$OUT/$name.png"
}

shoot 1_gcp_finder "$PY" 1_gcp_finder/gcp_finder.py --gui --set images="$F/images" --set survey="$F/gcp/gcp_survey.csv" --set output_dir="$TMP/o1"
shoot 3_min_img_finder "$PY" 3_min_img_finder/min_img_finder.py --gui --set project_dir="$F" --set output_dir="$TMP/o3"
shoot 4_bbox_drawer "$PY" 4_bbox_drawer/bbox_drawer.py --gui --set images="$LONG" --set output_dir="$TMP/o4"
shoot 5_img_splitter "$PY" 5_img_splitter/img_splitter.py --gui --set images="$F/opensfm/undistorted/images" --set annotations="$F/truth/boxes_undistorted.json" --set output_dir="$TMP/o5"
shoot 9_spatial_stat_extractor "$PY" 9_spatial_stat_extractor/spatial_stat_extractor.py --gui --set rasters.dsm="$F/odm_dem/dsm.tif" --set rasters.dtm="$F/odm_dem/dtm.tif" --set output_dir="$TMP/o9"
cat "$OUT/windows.txt"
