-- Cesium terrain tiles (quantized-mesh) over jacksboro at levels 12 (the source's own), 13 and
-- 14 (past it), in turn, each level's tiles cycled in a scrambled order. Run against a server
-- whose tile cache is off (`tile_cache_mib = 0` in its --config) so every request meshes.
-- Threads (wrk's -t, as THREADS) interleave one sequence; ASSET names the asset (default
-- jacksboro). Issue 56's serving measure of its meshes: docs/benchmarks.md.
local threads = tonumber(os.getenv("THREADS") or "2")
local asset = os.getenv("ASSET") or "jacksboro"
local west, south, east, north = -84.41375, 36.44625, -84.07791666666667, 36.73291666666667
local next_id = 0
local counter = 0
setup = function(thread)
  thread:set("id", next_id)
  next_id = next_id + 1
end
request = function()
  local n = counter * threads + id
  counter = counter + 1
  local zoom = 12 + n % 3
  local size = 180 / 2 ^ zoom
  local x0, x1 = math.floor((west + 180) / size), math.floor((east + 180) / size)
  local y0, y1 = math.floor((south + 90) / size), math.floor((north + 90) / size)
  local cols, rows = x1 - x0 + 1, y1 - y0 + 1
  -- 7919 is prime: k -> k * 7919 mod n visits each tile once a cycle.
  local k = (math.floor(n / 3) * 7919) % (cols * rows)
  local path = string.format("/v1/assets/%s/terrain/%d/%d/%d.terrain", asset, zoom,
    x0 + k % cols, y0 + math.floor(k / cols))
  return wrk.format("GET", path)
end
