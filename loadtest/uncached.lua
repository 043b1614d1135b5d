-- Walks distinct tiles over the jacksboro demo DEM (zoom 17 by default, or $ZOOM from 15 to 17;
-- zoom 16 has only 3,840 tiles), so that no request hits the cache: the threads take
-- interleaved, disjoint steps of one permutation of the tiles (7919 is prime, so
-- k -> k * 7919 mod n visits each tile once).
local zoom = tonumber(os.getenv("ZOOM") or "17")
local scale = 2 ^ (17 - zoom)
local z, x0, y0 = zoom, math.floor(34803 / scale), math.floor(51140 / scale)
local cols, rows = math.floor(120 / scale), math.floor(127 / scale)
-- wrk's -t, as run.sh calls it.
local threads = tonumber(os.getenv("THREADS") or "2")
-- jacksboro-utm (the same terrain on a UTM grid) covers the same tiles.
local asset = os.getenv("ASSET") or "jacksboro"
local next_id = 0
local counter = 0
setup = function(thread)
  thread:set("id", next_id)
  next_id = next_id + 1
end
request = function()
  local k = ((counter * threads + id) * 7919) % (cols * rows)
  counter = counter + 1
  local path = string.format("/v1/assets/%s/tiles/%d/%d/%d.png?encoding=terrainrgb", asset, z, x0 + k % cols, y0 + math.floor(k / cols))
  return wrk.format("GET", path)
end
