-- Walks distinct zoom-17 tiles over the jacksboro demo DEM, so that no request hits the cache.
-- Each wrk thread starts at its own offset.
local z, x0, y0, cols, rows = 17, 34803, 51140, 120, 127
local counter = 0
local offset = 0
setup = function(thread)
  thread:set("offset", math.random(0, cols * rows - 1))
end
request = function()
  counter = counter + 1
  local k = (offset + counter * 7919) % (cols * rows)
  local path = string.format("/v1/assets/jacksboro/tiles/%d/%d/%d.png?encoding=terrainrgb", z, x0 + k % cols, y0 + math.floor(k / cols))
  return wrk.format("GET", path)
end
