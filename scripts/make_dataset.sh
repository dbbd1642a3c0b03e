#!/usr/bin/env bash
# Render the training clips and the held-out development flights used for the shipped weights
# (models/README.md) from the real aerial imagery in ../shared/data.  Nothing here is committed:
# the clips go to $OUT (default ../runs/data), outside the repository.
#
#   bash scripts/make_dataset.sh [OUT]
#
# Held out from training (whole sites): the Boruszyn orthomosaic and both Boruszyn photos,
# the NEON YELL 541000 tile and SOAP_061: they make the development flights (where settings are
# chosen) and the test flights (the same sites flown with other seeds, only for confirmation).
# Everything else in aerial_stills/aerial_sequences (nadir only) is used for training.
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
data=${DATA:-$here/../shared/data}
out=${1:-$here/../runs/data}
mkdir -p "$out/train" "$out/dev" "$out/test"

train_maps=(
  aerial_stills/odm_orthomosaic_previews/aukerman.png
  aerial_stills/odm_orthomosaic_previews/zoo.png
  aerial_stills/odm_orthomosaic_previews/caliterra.png
  aerial_stills/odm_orthomosaic_previews/lewis.png
  aerial_stills/deepforest_neon_orthophoto/2019_YELL_2_528000_4978000_image_crop2.png
  aerial_stills/deepforest_neon_orthophoto/SOAP_031.png
  aerial_stills/deepforest_neon_orthophoto/OSBS_029.tif
  aerial_sequences/odm_caliterra/IMG_9354.jpg
  aerial_sequences/odm_caliterra/IMG_9356.jpg
  aerial_sequences/odm_caliterra/IMG_9358.jpg
  aerial_sequences/odm_caliterra/IMG_9360.jpg
  aerial_sequences/odm_garfield_msp_rgb/IMG_161122_163234_0000_RGB.JPG
  aerial_sequences/odm_garfield_msp_rgb/IMG_161122_163244_0002_RGB.JPG
  aerial_sequences/odm_garfield_msp_rgb/IMG_161122_163338_0011_RGB.JPG
  aerial_sequences/odm_garfield_msp_rgb/IMG_161122_163346_0013_RGB.JPG
)
dev_maps=(
  aerial_stills/odm_orthomosaic_previews/boruszyn.png
  aerial_sequences/odm_boruszyn_kap/img_4854.jpg
  aerial_sequences/odm_boruszyn_kap/img_4858.jpg
  aerial_stills/deepforest_neon_orthophoto/2019_YELL_2_541000_4977000_image_crop.png
  aerial_stills/deepforest_neon_orthophoto/SOAP_061.png
)

seed=0
for map in "${train_maps[@]}"; do
  name=$(basename "${map%.*}")
  for profile in paper fast hard survey; do
    seed=$((seed + 1))
    clip="$out/train/${name}_${profile}.mp4"
    [ -f "$clip" ] || mosaic simulate "$data/$map" -o "$clip" --profile "$profile" --frames 300 \
      --size 640x360 --seed "$seed" --preset veryfast --quiet
  done
done

for map in "${dev_maps[@]}"; do
  name=$(basename "${map%.*}")
  for profile in paper fast hard; do
    seed=$((seed + 1))
    clip="$out/dev/${name}_${profile}.mp4"
    [ -f "$clip" ] || mosaic simulate "$data/$map" -o "$clip" --profile "$profile" --frames 300 \
      --size 1280x720 --seed "$seed" --preset veryfast --quiet
  done
done
# The test flights: the same held-out sites, flown again with other seeds.  Nothing is tuned on
# them; they confirm what the development flights (where settings were chosen) showed.
for map in "${dev_maps[@]}"; do
  name=$(basename "${map%.*}")
  for profile in paper fast hard; do
    seed=$((seed + 1))
    clip="$out/test/${name}_${profile}.mp4"
    [ -f "$clip" ] || mosaic simulate "$data/$map" -o "$clip" --profile "$profile" --frames 300 \
      --size 1280x720 --seed $((seed + 1000)) --preset veryfast --quiet
  done
done
# The fast degraded regime (issue 14): 25-60 px/frame, fast yaw turns, altitude changes,
# exposure drift and jumps, noise, motion blur, vignetting, haze, low-bitrate H.264.  Two flights
# per training image, one per held-out image for development and for test, plus a held-out
# low-texture site (the Black Sea coast, mostly water).  Seeds continue after the ones above, so
# the clips above stay as they were.
lowtex_maps=(aerial_video/teon2001_blacksea_drone_frames/video1_nadir/frame_0000.jpg)
for map in "${train_maps[@]}"; do
  name=$(basename "${map%.*}")
  for k in 1 2; do
    seed=$((seed + 1))
    clip="$out/train/${name}_extreme${k}.mp4"
    [ -f "$clip" ] || mosaic simulate "$data/$map" -o "$clip" --profile extreme --frames 300 \
      --size 640x360 --seed "$seed" --preset veryfast --quiet
  done
done
# (The Boruszyn orthomosaic and SOAP_061, a few hundred px once cropped, are too small for the
# extreme profile's altitude changes at 1280x720.)
extreme_maps=("${dev_maps[@]:1:3}" "${lowtex_maps[@]}")
for split in dev test; do
  for map in "${extreme_maps[@]}"; do
    name=$(basename "${map%.*}")
    [ "$name" = frame_0000 ] && name=blacksea
    seed=$((seed + 1))
    clip="$out/$split/${name}_extreme.mp4"
    [ -f "$clip" ] || mosaic simulate "$data/$map" -o "$clip" --profile extreme --frames 300 \
      --size 1280x720 --seed "$seed" --preset veryfast --quiet
  done
done
# Flights with bursts (issue 29): an ordinary 8-30 px/frame flight where every 12-30 frames 1-3
# frames carry no motion cue (glare, a gust's blur, near-black, featureless, a dropped or a
# duplicated frame): where only the motion carried across the frames can place a pair.  One per
# held-out site for development and one for test; seeds continue after the ones above.
# A flight with bursts over held-out MAP into SPLIT as NAME_bursts[SUFFIX].mp4, with the next seed.
burst_flight() {  # SPLIT MAP SUFFIX
  local name clip
  name=$(basename "${2%.*}")
  seed=$((seed + 1))
  clip="$out/$1/${name}_bursts$3.mp4"
  [ -f "$clip" ] || mosaic simulate "$data/$2" -o "$clip" --profile bursts --frames 300 \
    --size 1280x720 --seed "$seed" --preset veryfast --quiet
}
for split in dev test; do
  for map in "${dev_maps[@]}"; do burst_flight "$split" "$map" ""; done
done
# More flights with bursts (issue 38): four more per held-out site for development and for test,
# so that each split holds 25 burst flights (about 1,100 burst pairs) and the sequence model's
# goals are counted on over 1,000 burst pairs.  Seeds continue after the ones above.
for split in dev test; do
  for k in 2 3 4 5; do
    for map in "${dev_maps[@]}"; do burst_flight "$split" "$map" "$k"; done
  done
done
echo "clips in $out/train ($(ls "$out/train"/*.mp4 | wc -l)), $out/dev ($(ls "$out/dev"/*.mp4 | wc -l)) and $out/test ($(ls "$out/test"/*.mp4 | wc -l))"
