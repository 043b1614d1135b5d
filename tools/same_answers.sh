#!/bin/bash
# Same answers from two builds of `fractile`: encodes a matrix of the test data with every codec
# (settings of each rate mode, colour, nodata, chunked files, a mesh, curves) with both, and
# checks that the files are the same bytes but for the metadata's creation time, and that both
# builds decode each file of the first to the same pixels. What a refactor that promises no
# change in behaviour or bytes runs (issue 57). psa2d's spacing is named: the CLI's default for
# it was FIS's 8 before issue 76, the codec's own 4 (Python's) since.
#
#   tools/same_answers.sh OLD_FRACTILE NEW_FRACTILE [WORKDIR]
set -euo pipefail
old=$1; new=$2; work=${3:-$(mktemp -d)}
data=$(cd "$(dirname "$0")/../testdata" && pwd)
mkdir -p "$work/old" "$work/new" "$work/decoded"
encodes=(
  "q.fra camera.png --codec quadtree-pifs"
  "qc.fra astronaut.png --codec quadtree-pifs --target-bpp 1.0"
  "q_dem.fra jacksboro.tif --codec quadtree-pifs --tolerance 2"
  "fisb.fra jacksboro.tif --codec fis-bilinear"
  "fisr.fra jacksboro.tif --codec fis-rect --target-bpp 1"
  "fisg.fra jacksboro.tif --codec fis-rect-global"
  "psar.fra camera.png --codec psa2d-rect --spacing 8"
  "psat.fra jacksboro.tif --codec psa2d-tri --target-bpp 1"
  "proj.fra jacksboro.tif"
  "proj_me.fra jacksboro.tif --codec projected --max-error 1"
  "proj_rate.fra etopo20.tif --codec projected --target-bpp 1.5"
  "proj_rgb.fra astronaut.png --codec projected --target-bpp 1"
  "chunked.fra etopo20.tif --chunk 256"
  "chunked_q.fra etopo20.tif --codec quadtree-pifs --chunk 256 --tolerance 3"
  "topo.fra topobathy.tif"
  "vol.fra mesh/fandisk.off"
  "curve.fra curve/coast5.geojson"
)
for e in "${encodes[@]}"; do
  read -r out input flags <<<"$e"
  for b in old new; do
    bin=$old; [ $b = new ] && bin=$new
    # shellcheck disable=SC2086
    "$bin" encode "$data/$input" -o "$work/$b/$out" --quiet $flags >/dev/null
  done
done
python3 - "$work/old" "$work/new" <<'PY'
import os, struct, sys
a, b = sys.argv[1], sys.argv[2]
bad = 0
for f in sorted(x for x in os.listdir(a) if x.endswith(".fra")):
    x = open(os.path.join(a, f), "rb").read()
    y = open(os.path.join(b, f), "rb").read()
    if x == y:
        print(f"{f}: the same bytes"); continue
    # The frame: magic, version, kind, codec, metadata length, metadata, then the payload. The
    # metadata holds the encode's time; everything else must be equal.
    m = struct.unpack("<I", x[12:16])[0]
    same = len(x) == len(y) and x[:16] == y[:16] and x[16 + m:-4] == y[16 + m:-4]
    print(f"{f}: {'the same bytes but the metadata' if same else 'DIFFERENT'}")
    bad += not same
sys.exit(1 if bad else 0)
PY
for f in "$work"/old/*.fra; do
  name=$(basename "$f" .fra)
  case $name in vol|curve) continue ;; esac
  ext=tif
  "$old" decode "$f" -o "$work/decoded/$name.old.$ext" >/dev/null 2>&1 || ext=png
  "$old" decode "$f" -o "$work/decoded/$name.old.$ext" >/dev/null 2>&1
  "$new" decode "$f" -o "$work/decoded/$name.new.$ext" >/dev/null 2>&1
  if cmp -s "$work/decoded/$name.old.$ext" "$work/decoded/$name.new.$ext"; then
    echo "$name: decoded to the same pixels"
  else
    echo "$name: decoded DIFFERENTLY"; exit 1
  fi
done
