"""Triangles a tile: ours (read from a quantized-mesh file by quantized-mesh-tile) against
pydelatin's on the source cells under the tile at the same max error.

Input (argv[1]): a JSON list of tiles, each {"terrain": path of our .terrain tile, "window":
path of the source cells under it (little-endian f32, row-major), "decoded": the same cells as
the asset decodes them, "width", "height",
"max_error", "bounds": [w, s, e, n], "bend": the globe's curvature a cell}. Output (stdout): a JSON list of {"ours": triangles, "delatin": triangles on the source cells,
"delatin_decoded": on the decoded cells}."""
import json
import sys

import numpy as np
from pydelatin import Delatin
from quantized_mesh_tile.terrain import TerrainTile


def main():
    tiles = json.load(open(sys.argv[1]))
    out = []
    for t in tiles:
        w, s, e, n = t["bounds"]
        ours = TerrainTile(west=w, south=s, east=e, north=n)
        ours.fromFile(t["terrain"])
        # On the globe, as ours: the heights over the sphere's second-order arc about the
        # window's centre, `bend` a cell (radius x (radians a cell)^2 / 2).
        y, x = np.mgrid[0 : t["height"], 0 : t["width"]]
        cy, cx = (t["height"] - 1) / 2, (t["width"] - 1) / 2
        arc = t["bend"] * ((x - cx) ** 2 + (y - cy) ** 2)
        counts = {"ours": len(ours.indices) // 3}
        for key, path in [("delatin", t["window"]), ("delatin_decoded", t["decoded"])]:
            heights = np.fromfile(path, dtype="<f4").reshape(t["height"], t["width"]) - arc
            mesh = Delatin(heights.astype("float32"), max_error=t["max_error"])
            counts[key] = int(len(mesh.triangles))
        out.append(counts)
    json.dump(out, sys.stdout)


main()
