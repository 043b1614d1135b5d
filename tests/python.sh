#!/usr/bin/env bash
# The Python package (python/): its wheel built by maturin (from PyPI) into a venv under
# target/, then its pytest suite against real data, a `fractile serve` and SeaweedFS on
# loopback (python/tests), its type stubs against the module (mypy's stubtest), then the
# README's ```python blocks as written. Needs the release
# build of the command line (`cargo build --release`, as `.ci/run` does before) and, for the
# s3:// test, FRACTILE_WEED (`.ci/run` sets it; without it that test is skipped, except
# under CI).
set -euo pipefail
cd "$(dirname "$0")/.."
venv=target/python-tools
[ -x "$venv/bin/python" ] || python3 -m venv "$venv"
# Pinned, so that CI tests what was measured: the build tool, the test runner and the peers.
"$venv/bin/pip" install -q maturin==1.16.0 pytest==9.2.0 numpy==2.4.6 rasterio==1.4.4 mypy==1.19.0
"$venv/bin/maturin" build --release -q -m python/Cargo.toml -o target/wheels
wheel=$(ls -t target/wheels/fractile-*-abi3-*.whl | head -1)
"$venv/bin/pip" install -q --force-reinstall --no-deps "$wheel"
# The type stubs (python/fractile.pyi) against the module as built: every name, signature and
# class there, and nothing missing (mypy's stubtest).
(cd "$venv" && bin/python -m mypy.stubtest fractile --allowlist "$OLDPWD/python/stubtest-allowlist.txt")
[ -x target/release/fractile ] || cargo build --release -q -p fractile-cli
"$venv/bin/python" -m pytest -q -p no:cacheprovider -W ignore::rasterio.errors.NotGeoreferencedWarning python/tests
# The README's Python examples, in a scratch folder holding the test data they name.
scratch=$(mktemp -d)
trap 'rm -rf "$scratch"' EXIT
awk -v q='```' '$0 == q "python" { inb = 1; n++; next } inb && $0 == q { inb = 0; next }
  inb { print > (dir "/readme-" n ".py") }' dir="$scratch" README.md
ln -s "$PWD/testdata" "$scratch/testdata"
count=0
for f in "$scratch"/readme-*.py; do
  [ -e "$f" ] || continue
  (cd "$scratch" && "$OLDPWD/$venv/bin/python" "$f") || { echo "python: README block $f failed" >&2; cat "$f" >&2; exit 1; }
  count=$((count + 1))
done
[ "$count" -gt 0 ] || { echo "python: README has no python block" >&2; exit 1; }
echo "python: the package's tests and $count README example(s) passed"
