-- 3D Tiles of a volume (issue 79): the paths of PATHS (a file, one path a line, such as the
-- level-4 tiles of fandisk's tileset: `find DIR/3dtiles/4 -name '*.glb'` of a folder that
-- `fractile-client tileset` wrote, made into /v1/assets/fandisk/... paths), cycled in turn by
-- all threads. Run against a server whose tile cache is off (`tile_cache_mib = 0` in its
-- --config) for uncached tiles; docs/benchmarks.md.
local paths = {}
for line in io.lines(os.getenv("PATHS")) do
  paths[#paths + 1] = line
end
local threads = tonumber(os.getenv("THREADS") or "2")
local next_id = 0
local counter = 0
setup = function(thread)
  thread:set("id", next_id)
  next_id = next_id + 1
end
request = function()
  local n = counter * threads + id
  counter = counter + 1
  return wrk.format("GET", paths[n % #paths + 1])
end
