#!/usr/bin/env bash
# A new plane codec with no edit outside its folder and its lines in the registry (issue 76):
# puts the test codec `codec/tests/toy/mod.rs` (the projected codec under another byte and name,
# coded to a max error) in a temporary folder `codec/src/codecs/toy/`, adds its `mod` line and
# its line in `plane_codecs!` to `codec/src/codecs/mod.rs`, builds, and checks that
#   - the command line encodes with `--codec toy --max-error 2`, `info` names the codec and
#     `decode` gives every cell within 2 of the source (and refuses a flag toy does not read),
#   - `fractile serve` lists the asset as `toy` and answers a tile and a point,
#   - Python encodes with `codec="toy"` and reads the file back within its max error;
# then takes the folder and the lines out again (on exit, whatever happened).
#
# Not run by CI: it builds the workspace twice in release (with the codec, then without it,
# about 8 minutes on 2 cores). `codec/tests/layout.rs` checks in CI what makes it pass: that
# nothing outside the codec crate names a plane codec.
#
#   tests/new_codec.sh [--no-python]
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$PWD
registry=$repo/codec/src/codecs/mod.rs
folder=$repo/codec/src/codecs/toy
work=$(mktemp -d)
cp "$registry" "$work/mod.rs.orig"
server=
cleanup() {
  [ -n "$server" ] && kill "$server" 2>/dev/null || true
  cp "$work/mod.rs.orig" "$registry"
  rm -rf "$folder" "$work"
}
trap cleanup EXIT
[ -e "$folder" ] && { echo "new_codec: $folder exists" >&2; exit 1; }

# The codec: its folder, and two lines in the registry's file.
mkdir -p "$folder"
cp codec/tests/toy/mod.rs "$folder/mod.rs"
python3 - "$registry" <<'PY'
import sys
p = sys.argv[1]
s = open(p).read()
line = ("            /// The new-codec test's codec.\n"
        "            Toy(crate::codecs::toy::ToyHeader, crate::codecs::toy::ToySettings),\n")
end = "        }\n    };\n}\n"
assert s.count(end) == 1, "the end of plane_codecs! moved"
s = s.replace(end, line + end).replace("pub mod quadtree;\n", "pub mod quadtree;\npub mod toy;\n")
open(p, "w").write(s)
PY
git diff --stat -- codec/src | tail -1

cargo build --release -q -p fractile-cli
bin=$repo/target/release/fractile
cd "$work"
src=$repo/testdata/jacksboro.tif
"$bin" encode "$src" --codec toy --max-error 2 -o toy.fra --quiet
"$bin" info toy.fra | grep -q 'codec: "toy"' || { echo "new_codec: info does not name toy" >&2; "$bin" info toy.fra >&2; exit 1; }
if "$bin" encode "$src" --codec toy --spacing 4 -o no.fra --quiet 2>err.txt; then
  echo "new_codec: --spacing was not refused for toy" >&2; exit 1
fi
grep -q -- "--spacing" err.txt
"$bin" decode toy.fra -o toy.tif >/dev/null
"$bin" compare "$src" toy.tif --json > cmp.json
python3 - cmp.json <<'PY'
import json, re, sys
text = open(sys.argv[1]).read()
try:
    worst = json.loads(text)["max_error"]
except ValueError:
    worst = float(re.search(r"max error ([0-9.eE+-]+)", text).group(1))
assert worst <= 2.0 + 1e-9, f"toy: max error {worst} over 2"
print(f"new_codec: CLI encoded and decoded toy, max error {worst:.3f} <= 2")
PY

# The server, on the asset folder.
mkdir assets && cp toy.fra assets/toy.fra
port=$((20000 + RANDOM % 20000))
"$bin" serve --assets assets --bind 127.0.0.1:$port >server.log 2>&1 &
server=$!
for _ in $(seq 100); do curl -fs "http://127.0.0.1:$port/v1/assets" >/dev/null 2>&1 && break; sleep 0.1; done
python3 - "$port" <<'PY'
import json, sys, urllib.request
base = f"http://127.0.0.1:{sys.argv[1]}/v1/assets"
get = lambda u: urllib.request.urlopen(u, timeout=30).read()
meta = json.loads(get(f"{base}/toy"))
assert meta.get("codec") == "toy", meta
tj = json.loads(get(f"{base}/toy/tilejson.json"))
w, s, e, n = tj["bounds"]
lon, lat = (w + e) / 2, (s + n) / 2
point = json.loads(get(f"{base}/toy/point/{lon},{lat}"))
lo, hi = meta["value_range"]
h = point["values"][0]
assert lo - 2 <= h <= hi + 2, (h, lo, hi)
z = tj["maxzoom"]
import math
x = int((lon + 180) / 360 * 2**z)
y = int((1 - math.asinh(math.tan(math.radians(lat))) / math.pi) / 2 * 2**z)
png = get(f"{base}/toy/tiles/{z}/{x}/{y}.png?encoding=terrainrgb")
assert png[:4] == b"\x89PNG", png[:8]
print(f"new_codec: the server answers toy: point {h:.2f}, tile {z}/{x}/{y} of {len(png)} bytes")
PY
kill "$server"; server=

# Python: the wheel of this tree, imported ahead of any installed one.
if [ "${1:-}" != --no-python ]; then
  venv=$repo/target/python-tools
  [ -x "$venv/bin/python" ] || python3 -m venv "$venv"
  "$venv/bin/pip" install -q maturin==1.16.0 numpy==2.4.6
  (cd "$repo" && "$venv/bin/maturin" build --release -q -m python/Cargo.toml -o "$work/wheels")
  "$venv/bin/pip" install -q --no-deps --target "$work/py" "$work"/wheels/fractile-*.whl
  PYTHONPATH="$work/py" "$venv/bin/python" - "$src" <<'PY'
import sys
import numpy as np
import fractile
info = fractile.encode_file(sys.argv[1], "py.fra", codec="toy", max_error=2.0)
assert info["codec"] == "toy", info
a = fractile.open("py.fra")
assert a.meta["codec"] == "toy", a.meta
decoded = a.read()
src = fractile.open("toy.fra").read()  # the CLI's file of the same codec and bound
assert decoded.shape == src.shape, (decoded.shape, src.shape)
print(f"new_codec: Python encoded and read toy, {info['bytes']} bytes, max error {info['max_error']:.3f}")
assert info["max_error"] <= 2.0 + 1e-9
PY
fi
echo "new_codec: a codec added in its folder and the registry alone works in the CLI, the server and Python"
