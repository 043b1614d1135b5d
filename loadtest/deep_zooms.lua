-- Distinct zoom-16 and zoom-17 terrain-RGB tiles over jacksboro (one z16 in five), none
-- repeated for the first 18,900 requests (3,780 z16 and 15,120 z17 tiles): keep the run short
-- enough (`wrk -d3s` at about a thousand a second) that no request hits the tile cache.
-- Threads (wrk's -t, as THREADS) interleave one sequence; ASSET names the asset (default
-- jacksboro). Issue 55's measure of deep zooms: docs/benchmarks.md.
local threads = tonumber(os.getenv("THREADS") or "2")
local asset = os.getenv("ASSET") or "jacksboro"
local next_id = 0
local counter = 0
setup = function(thread)
  thread:set("id", next_id)
  next_id = next_id + 1
end
request = function()
  local n = counter * threads + id
  counter = counter + 1
  local zoom, k
  if n % 5 == 0 then
    zoom, k = 16, math.floor(n / 5)
  else
    zoom, k = 17, n - math.floor(n / 5) - 1
  end
  local scale = 2 ^ (17 - zoom)
  local x0, y0 = math.floor(34803 / scale), math.floor(51140 / scale)
  local cols, rows = math.floor(120 / scale), math.floor(127 / scale)
  -- 7919 is prime: k -> k * 7919 mod n visits each tile once.
  k = (k * 7919) % (cols * rows)
  local path = string.format("/v1/assets/%s/tiles/%d/%d/%d.png?encoding=terrainrgb",
    asset, zoom, x0 + k % cols, y0 + math.floor(k / cols))
  return wrk.format("GET", path)
end
