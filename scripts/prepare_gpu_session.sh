#!/usr/bin/env bash
# Prepare what a device call of scripts/gpu_session.sh carries, in .gpu/ (ignored by git):
#   wheels/     what the device machine lacks (kornia; yappi, for `python -m benchmarks profile`) or holds in
#               other versions (typer, click)
#   wheels-rs/  kornia_rs (training calls only: 5 MB)
#   av/         PyAV (throughput calls only: 36 MB; its libavcodec has libx264 and h264_cuvid)
#   stills/     a few of ../shared/data's stills reduced to 1600 px, for training (about 6 MB); the
#               last in name order (zz_*) is kept out of training: the validation flights fly over it
#   footage/    the two stills `python -m benchmarks speed` flies over, for the 720p and 4K clips
# (the data does not travel otherwise).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
data=${DATA:-$here/../shared/data}
cd "$here"
grep -qxF '/.gpu/' .git/info/exclude 2>/dev/null || echo '/.gpu/' >> .git/info/exclude
mkdir -p .gpu/wheels .gpu/wheels-rs .gpu/av .gpu/stills .gpu/footage
download() {
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d "$@"
}
download .gpu/wheels kornia==0.9.0 typer==0.29.2 click==8.5.1 yappi==1.7.6 \
  pydantic==2.14.4 pydantic_core==2.50.5 annotated_types==0.8.0 typing_inspection==0.4.5 annotated_doc==0.0.7
download .gpu/wheels-rs kornia_rs==0.2.0
download .gpu/av av==18.1.0
stills=(
  aerial_stills/odm_orthomosaic_previews/aukerman.png
  aerial_stills/odm_orthomosaic_previews/zoo.png
  aerial_stills/odm_orthomosaic_previews/lewis.png
  aerial_stills/deepforest_neon_orthophoto/2019_YELL_2_528000_4978000_image_crop2.png
  aerial_sequences/odm_caliterra/IMG_9354.jpg
  aerial_sequences/odm_garfield_msp_rgb/IMG_161122_163234_0000_RGB.JPG
)
heldout=aerial_sequences/odm_boruszyn_kap/img_4854.jpg
python3 - "$data" "${stills[@]}" "zz:$heldout" <<'PY'
import sys
from pathlib import Path
import cv2
data = Path(sys.argv[1])
for k, name in enumerate(sys.argv[2:]):
    prefix = f"{k:02d}"
    if name.startswith("zz:"):
        prefix, name = "zz", name[3:]
    image = cv2.imread(str(data / name), cv2.IMREAD_COLOR)
    if image is None:
        sys.exit(f"{data / name}: not readable")
    scale = min(1.0, 1600 / max(image.shape[:2]))
    small = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    out = Path(".gpu/stills") / f"{prefix}_{Path(name).stem}.jpg"
    cv2.imwrite(str(out), small, [cv2.IMWRITE_JPEG_QUALITY, 92])
    print(out, small.shape[1], "x", small.shape[0])
PY
# The footage: JPEG, the 4K clip's photo at 3000 px (it fills a 3840x2160 frame at the zoom the
# shaky profile flies; the call has about 3 MB left for both).
python3 - "$data" <<'PY'
import sys
from pathlib import Path
import cv2
data = Path(sys.argv[1])
for key, name, longest in (("720p", "aerial_stills/odm_orthomosaic_previews/aukerman.png", 4000),
                           ("4k", "aerial_sequences/odm_caliterra/IMG_9356.jpg", 3000)):
    image = cv2.imread(str(data / name), cv2.IMREAD_COLOR)
    if image is None:
        sys.exit(f"{data / name}: not readable")
    scale = min(1.0, longest / max(image.shape[:2]))
    image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    out = Path(".gpu/footage") / f"{key}_{Path(name).stem}.jpg"
    cv2.imwrite(str(out), image, [cv2.IMWRITE_JPEG_QUALITY, 88])
    print(out, image.shape[1], "x", image.shape[0], out.stat().st_size // 1000, "kB")
PY
du -sh .gpu .gpu/*
# What each call sends, against the 64 MiB a device call takes: the tree (tracked and untracked,
# not ignored) and what it carries; the throughput call without the model it moves out.
tree=$( (git ls-files -z; git ls-files -z --others --exclude-standard) | xargs -0 -r du -cb 2>/dev/null | awk '$2 == "total" {s += $1} END {print s}')
models=$(du -cb models/cnn.safetensors | tail -1 | cut -f1)
limit=$((64 * 1024 * 1024))
for call in "training .gpu/wheels .gpu/wheels-rs .gpu/stills" "throughput .gpu/wheels .gpu/av .gpu/footage"; do
  set -- $call
  name=$1; shift
  size=$((tree + $(du -cb "$@" | tail -1 | cut -f1)))
  [ "$name" = throughput ] && size=$((size - models))
  echo "$name call: $((size / 1048576)) MiB of 64 $([ $size -le $limit ] && echo ok || echo 'OVER THE LIMIT')"
done
