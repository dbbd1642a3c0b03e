#!/usr/bin/env bash
# Prepare what a device call of scripts/gpu_session.sh carries, in .gpu/ (ignored by git):
# the wheels the device machine lacks (kornia) or holds in other versions (typer, click), and a few of ../shared/data's stills, reduced to
# 1600 px (the data does not travel otherwise; about 6 MB here).  The last still in name order
# (zz_*) is kept out of training: the validation flights fly over it.
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
data=${DATA:-$here/../shared/data}
cd "$here"
grep -qxF '/.gpu/' .git/info/exclude 2>/dev/null || echo '/.gpu/' >> .git/info/exclude
mkdir -p .gpu/wheels .gpu/stills
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
  -d .gpu/wheels kornia==0.9.0 kornia_rs==0.2.0 typer==0.29.2 click==8.5.1 \
  pydantic==2.14.4 pydantic_core==2.50.5 annotated_types==0.8.0 typing_inspection==0.4.5 annotated_doc==0.0.7
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
du -sh .gpu
