"""Reads a quantized-mesh-1.0 tile with an independent decoder, for server/tests/terrain.rs.

Usage: read_quantized_mesh.py TILE WEST SOUTH EAST NORTH. Prints JSON: the vertices as
[lon, lat, height], the triangles as vertex indices, the four edges' vertex indices and the
header. The decoder is the Python package quantized-mesh-tile (pinned by the test that runs
this), which we did not write.
"""

import json
import sys

from quantized_mesh_tile.terrain import TerrainTile

path = sys.argv[1]
west, south, east, north = map(float, sys.argv[2:6])
tile = TerrainTile(west=west, south=south, east=east, north=north)
tile.fromFile(path)
print(json.dumps({
    "vertices": tile.getVerticesCoordinates(),
    "triangles": [tile.indices[i:i + 3] for i in range(0, len(tile.indices), 3)],
    "edges": [tile.westI, tile.southI, tile.eastI, tile.northI],
    "header": tile.header,
}))
