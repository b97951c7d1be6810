--[[
  esc-bridge: the ESCs' telemetry into ArduPilot's own ESC telemetry (AP_ESC_Telem).

  The bridge (a companion computer driving CAN ESCs, component 191 by default) sends
  ESC_TELEMETRY_1_TO_4 .. 29_TO_32 on its link to the autopilot. This script reads them from
  that link (mavlink:register_rx_msgid / receive_chan) and feeds each ESC's rpm, volts, amps,
  consumed mAh and temperature into AP_ESC_Telem, as ArduPilot's own ESC drivers do. ArduPilot
  then has them for everything its drivers' data is used for: the harmonic notch on ESC rpm
  (INS_HNTCH_MODE 3), the ESC records in its dataflash log, its ESC telemetry checks, battery
  monitor type ESC, and its own ESC_TELEMETRY_x_TO_y to the ground stations.

  Staleness is ArduPilot's: an ESC is fed only when its frame counter (the message's `count`,
  telemetry frames the bridge received from that ESC) has moved since the last message. An ESC
  that went silent (the bridge repeats its frozen count with zero measurements), a bridge that
  stopped sending and a link that died all end the same way: no update, so ArduPilot sees that
  ESC's rpm go stale after 1 s and its other data after 5 s, as with its own drivers.

  Install: copy this file into the autopilot's scripts directory (APM/scripts on the SD card;
  scripts/ beside a SITL's working directory), set SCR_ENABLE 1, reboot, then set the ESCB_
  parameters below (they appear after the first boot with the script) and reboot again or
  restart scripting. docs/telemetry.md, "ArduPilot: ESC telemetry into the autopilot", has the steps
  and the bridge's rate to set.

  Parameters (table key 49, prefix ESCB_):
    ESCB_ENABLE  1      0: the script does nothing
    ESCB_SYSID   0      only messages from this MAVLink system (0: any)
    ESCB_COMPID  191    only messages from this component (the bridge's [mavlink]
                        component_id; 0: any)
    ESCB_OUT1    1      the ArduPilot ESC (servo output number, 1-based) of the bridge's first
                        ESC: the bridge's ESC k feeds ESC OUT1 + k - 1
    ESCB_NUM     4      how many of the bridge's ESCs to feed, from its first (1..32)
  ESCB_SYSID/COMPID/OUT1/NUM are read when the script starts.
--]]

local PARAM_TABLE_KEY = 49 -- change it if another script of yours uses table key 49
local PARAM_TABLE_PREFIX = "ESCB_"

local MAV_SEVERITY_WARNING = 4
local MAV_SEVERITY_INFO = 6

-- AP_ESC_Telem_Backend::TelemetryType
local TEMPERATURE = 1
local VOLTAGE = 4
local CURRENT = 8
local CONSUMPTION = 16

-- ESC_TELEMETRY_1_TO_4 .. 29_TO_32: the message ids, four ESCs each.
local BATCH_IDS = { 11030, 11031, 11032, 11040, 11041, 11042, 11043, 11044 }
-- mavlink_message_t as receive_chan gives it: checksum (2), magic, len, incompat, compat, seq,
-- sysid, compid, msgid (3), then the payload, zero-filled to the message's full length.
local SYSID_AT, MSGID_AT, PAYLOAD_AT = 8, 10, 13
-- The payload in wire order: voltage[4] cV, current[4] cA, totalcurrent[4] mAh, rpm[4],
-- count[4] (uint16 each), temperature[4] degC (uint8).
local PAYLOAD_FORMAT = "<" .. string.rep("I2", 20) .. string.rep("B", 4)
local PAYLOAD_LEN = 44

local POLL_MS = 5
local LOST_MS = 1000 -- no fresh data for this long: say so once

assert(param:add_table(PARAM_TABLE_KEY, PARAM_TABLE_PREFIX, 5), "ESCB: could not add param table")

local function bind_add_param(name, idx, default_value)
  assert(param:add_param(PARAM_TABLE_KEY, idx, name, default_value), "ESCB: could not add " .. name)
  return Parameter(PARAM_TABLE_PREFIX .. name)
end

local ESCB_ENABLE = bind_add_param("ENABLE", 1, 1)
local ESCB_SYSID = bind_add_param("SYSID", 2, 0)
local ESCB_COMPID = bind_add_param("COMPID", 3, 191)
local ESCB_OUT1 = bind_add_param("OUT1", 4, 1)
local ESCB_NUM = bind_add_param("NUM", 5, 4)

local want_sysid = math.floor(ESCB_SYSID:get())
local want_compid = math.floor(ESCB_COMPID:get())
local first_instance = math.floor(ESCB_OUT1:get()) - 1 -- AP_ESC_Telem instances are 0-based
local num_escs = math.max(1, math.min(32, math.floor(ESCB_NUM:get())))
if first_instance < 0 or first_instance + num_escs > 32 then
  error(string.format("ESCB_OUT1 %d with ESCB_NUM %d is outside ESCs 1..32", first_instance + 1, num_escs))
end

local batch_of_msgid = {}
local num_batches = (num_escs + 3) // 4
mavlink:init(2 * num_batches + 4, num_batches)
for batch = 1, num_batches do
  mavlink:register_rx_msgid(BATCH_IDS[batch])
  batch_of_msgid[BATCH_IDS[batch]] = batch
end

local last_count = {} -- per bridge ESC (1-based): the count fed last
local has_consumption = {}
local last_fresh_ms = nil
local lost_reported = false

local function feed(esc, voltage_cv, current_ca, consumed_mah, rpm, count, temp_c)
  if count == last_count[esc] or (count == 0 and last_count[esc] == nil) then
    return false -- a repeat (nothing new from that ESC), or an ESC the bridge never heard
  end
  last_count[esc] = count
  local instance = first_instance + esc - 1
  esc_telem:update_rpm(instance, rpm, 0)
  local data = ESCTelemetryData()
  local mask = CURRENT
  data:current(current_ca / 100)
  if voltage_cv > 0 then
    data:voltage(voltage_cv / 100)
    mask = mask | VOLTAGE
  end
  if temp_c > 0 then -- 0: not known
    data:temperature_cdeg(temp_c * 100)
    mask = mask | TEMPERATURE
  end
  if consumed_mah > 0 or has_consumption[esc] then
    has_consumption[esc] = true
    data:consumption_mah(consumed_mah)
    mask = mask | CONSUMPTION
  end
  esc_telem:update_telem_data(instance, data, mask)
  return true
end

local function handle(msg)
  local batch = batch_of_msgid[string.unpack("<I3", msg, MSGID_AT)]
  if batch == nil then
    return false
  end
  local sysid, compid = string.unpack("<BB", msg, SYSID_AT)
  if (want_sysid ~= 0 and sysid ~= want_sysid) or (want_compid ~= 0 and compid ~= want_compid) then
    return false
  end
  if #msg < PAYLOAD_AT - 1 + PAYLOAD_LEN then
    msg = msg .. string.rep("\0", PAYLOAD_AT - 1 + PAYLOAD_LEN - #msg)
  end
  local v = { string.unpack(PAYLOAD_FORMAT, msg, PAYLOAD_AT) }
  local fresh = false
  for j = 1, 4 do
    local esc = 4 * (batch - 1) + j
    if esc <= num_escs then
      -- voltage, current, totalcurrent, rpm, count at j, 4 + j, 8 + j, 12 + j, 16 + j;
      -- temperature at 20 + j
      if feed(esc, v[j], v[4 + j], v[8 + j], v[12 + j], v[16 + j], v[20 + j]) then
        fresh = true
      end
    end
  end
  if fresh then
    if last_fresh_ms == nil or lost_reported then
      gcs:send_text(MAV_SEVERITY_INFO, string.format("ESCB: ESC telemetry from %d/%d", sysid, compid))
    end
    last_fresh_ms = millis()
    lost_reported = false
  end
  return true
end

-- One round: everything queued since the last, then the lost-link check; the next delay.
local function update()
  local enabled = ESCB_ENABLE:get() ~= 0
  while true do
    local msg = mavlink:receive_chan()
    if msg == nil then
      break
    end
    if enabled then
      handle(msg)
    end
  end
  if not enabled then
    last_fresh_ms = nil -- the queue is drained, so nothing old is fed once enabled again
    return 100
  end
  if last_fresh_ms ~= nil and not lost_reported and millis() - last_fresh_ms > LOST_MS then
    gcs:send_text(MAV_SEVERITY_WARNING, "ESCB: no fresh ESC telemetry for 1 s")
    lost_reported = true
  end
  return POLL_MS
end

local function protected_update()
  local ok, result = pcall(update)
  if not ok then
    gcs:send_text(MAV_SEVERITY_WARNING, "ESCB: " .. tostring(result))
    return protected_update, 1000
  end
  return protected_update, result
end

gcs:send_text(MAV_SEVERITY_INFO, string.format("ESCB: feeding ESCs %d..%d", first_instance + 1, first_instance + num_escs))
return protected_update, POLL_MS
