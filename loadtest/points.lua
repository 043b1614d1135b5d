-- POSTs batches of 1,000 points spread over the jacksboro demo DEM.
local pts = {}
for i = 1, 1000 do
  local lon = -84.41 + (i * 0.6180339 % 1) * 0.33
  local lat = 36.45 + (i * 0.4142135 % 1) * 0.28
  pts[#pts + 1] = string.format("[%.6f,%.6f]", lon, lat)
end
wrk.method = "POST"
wrk.headers["Content-Type"] = "application/json"
wrk.body = '{"iterations":12,"points":[' .. table.concat(pts, ",") .. ']}'
