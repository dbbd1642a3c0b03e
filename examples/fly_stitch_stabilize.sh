#!/usr/bin/env bash
# End-to-end example: fly a virtual drone over an aerial image, then stitch and stabilise the
# flight and score the homographies against the exact ground truth.
#
#   bash examples/fly_stitch_stabilize.sh [MAP_IMAGE] [OUT_DIR]
#
# With no MAP_IMAGE the flight goes over mosaic's built-in procedural map.  Everything it
# writes goes to OUT_DIR (default: ./example_out).
set -euo pipefail
map=${1:-}
out=${2:-example_out}
mkdir -p "$out"

# 1. A lawnmower survey (revisits ground: what stitching's drift control is for) and a shaky
#    flight (what stabilising is for), each with its exact homographies in *.gt.json.
mosaic simulate $map -o "$out/survey.mp4" --profile survey --frames 600 --seed 1
mosaic simulate $map -o "$out/shaky.mp4" --profile shaky --frames 300 --seed 2

# 2. The homographies themselves, scored by the paper's MACE against the ground truth.
mosaic track "$out/shaky.mp4" -o "$out/shaky.track.json"
mosaic eval "$out/shaky.track.json" --gt "$out/shaky.gt.json"

# 3. A panorama of the survey, with each used frame's placement.
mosaic stitch "$out/survey.mp4" -o "$out/panorama.png" --transforms "$out/panorama.json"

# 4. A stabilised copy of the shaky flight, and input | output side by side.
mosaic stabilize "$out/shaky.mp4" "$out/stable.mp4" --compare "$out/side_by_side.mp4"

echo "wrote $out/panorama.png, $out/stable.mp4 and $out/side_by_side.mp4"
