#!/usr/bin/env bash
# Puts CesiumJS's build (the npm package `cesium`, pinned) in target/cesium/Cesium, for
# `fractile serve --cesium target/cesium/Cesium` (or FRACTILE_CESIUM): the viewer then shows the
# DEM on a globe through our Cesium terrain. Needs npm and the npm registry. Prints the folder.
set -euo pipefail
cd "$(dirname "$0")/.."
VERSION=1.145.0
DEST=target/cesium
if [ ! -f "$DEST/Cesium/Cesium.js" ] || [ "$(cat "$DEST/version" 2>/dev/null)" != "$VERSION" ]; then
  rm -rf "$DEST" && mkdir -p "$DEST"
  (cd "$DEST" && npm pack --silent "cesium@$VERSION" >/dev/null 2>&1 && tar xzf "cesium-$VERSION.tgz")
  # The browser build only: the script, its workers, assets, widgets and third-party code.
  mkdir -p "$DEST/Cesium"
  for part in Cesium.js Workers Assets Widgets ThirdParty; do
    mv "$DEST/package/Build/Cesium/$part" "$DEST/Cesium/"
  done
  cp "$DEST/package/LICENSE.md" "$DEST/Cesium/" 2>/dev/null || true
  rm -rf "$DEST/package" "$DEST/cesium-$VERSION.tgz"
  echo "$VERSION" > "$DEST/version"
fi
echo "$(pwd)/$DEST/Cesium"
