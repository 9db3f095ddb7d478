-- net_hold.lua: ArduSub applet that holds a set distance to a fish-farm net and faces it
-- squarely, from the net plane netpose measures with the camera (docs/net-hold.md).
--
-- Input: netpose's DEBUG_VECT named "NET_PLANE": the vector from the camera to the nearest
-- point of the net plane in the camera frame (x right, y down, z forward; metres), stamped with
-- the capture time of the frame it was measured in (time_usec, autopilot boot clock). netpose
-- sends it only for frames whose measurement its filter accepted, so its age is the age of the
-- evidence; for a frame that did not confirm the net it sends a zero vector ("no net").
-- Output: RC overrides of the forward (RCMAP_FORWARD) and yaw (RCMAP_YAW) channels. Depth stays
-- with ArduSub's depth hold, lateral motion with the pilot.
--
-- The pilot is always in command: a script button (NETH_BTN) or MAV_CMD_USER_1 (param1 = 1 on,
-- 0 off) engages and disengages; pilot stick input on forward or yaw, a mode change or disarming
-- disengages at once, sets both channels to neutral and says why (STATUSTEXT). A frame without
-- the net, or a net plane older than NETH_TIMEOUT (from its frame's capture), stops all thrust at
-- once and says so; if no fresh plane comes within NETH_GRACE, net hold disengages. It never
-- commands thrust toward the net closer than NETH_DIST_MIN.
--
-- What is not believed (thrust stops, and the pilot is told): a plane stamped later than it
-- arrived (the clocks disagree: its age would never grow), a plane that is not a finite distance,
-- a distance that jumps faster than the vehicle moves (until three frames agree again), planes or
-- commands from anyone but netpose and the ground station. No pilot input for a second (the
-- pilot could not take over) hands back. Parameters outside their ranges refuse to engage.

local PARAM_TABLE_KEY = 86
local PARAM_PREFIX = "NETH_"
local PLANE_NAME = "NET_PLANE"
-- MAVLink message ids, and the command and results used (tables: see JUMP below).
local MSG = {DEBUG_VECT = 250, MANUAL_CONTROL = 69, COMMAND_LONG = 76, COMMAND_INT = 75,
             COMMAND_ACK = 77,
             RC_CHANNELS_OVERRIDE = 70}
local MAV = {CMD_USER_1 = 31010, RESULT_ACCEPTED = 0, RESULT_DENIED = 2}
local SEV = {WARNING = 4, INFO = 6}  -- MAV_SEVERITY
local NEUTRAL = 1500
local UPDATE_MS = 10  -- re-assert overrides often: the pilot's MANUAL_CONTROL writes them too
-- A plane is stamped with its frame's capture time (the autopilot's clock), so it can only be
-- older than its arrival; one stamped later than this after it came is not believed.
local FUTURE_TOLERANCE_S = 0.2
-- A plane stamped this much before the newest one is a new clock (netpose re-based on a
-- rebooted autopilot, or the clock wrapped): the history starts again from it.
local CLOCK_REBASE_S = 1.0
-- Without any pilot input (MANUAL_CONTROL, RC_CHANNELS_OVERRIDE) for this long the pilot could
-- not take over by stick: net hold does not engage, or hands back.
local PILOT_TIMEOUT_S = 1.0
-- Constants in tables where they belong together: ArduPilot's Lua allows at most 100 locals
-- in the main chunk (MAXVARS in its lparser.c, 200 in stock Lua; over it the script does not
-- load at all), and tests/test_net_hold_applet.py counts them.
-- A distance that changes faster than `speed` between two frames (plus the slack: netpose's
-- noise, a few per cent) is doubtful (a harmonic locked for a moment, a fish): no thrust until
-- `confirm` frames agree again. A BlueROV2 tops out near 1.5 m/s. With thrust stopped (a frame
-- without the net, a doubt) the vehicle only coasts on from the speed it had then, a bounded
-- distance however long the pause, plus `drift` (a current): a distance that changed more
-- than that meanwhile is a reading gone wrong.
local JUMP = {speed = 1.5, drift = 0.05, drift_away_m = 0.05, slack_m = 0.02,
              slack_share = 0.05, confirm = 3, longest_s = 2.0}
local PLAUSIBLE_M = {0.05, 100.0}
-- Coasting with thrust stopped, as ArduSub SITL's vectored model does (dv/dt = -0.22 v -
-- 2.18 v|v|: 0.63 m from 0.3 m/s, 1.1 m from 1 m/s), with `margin` for a real vehicle:
-- toward the net it never goes faster than it can coast to a stop outside NETH_DIST_MIN.
local COAST = {linear = 0.22, quadratic = 2.18, margin = 1.5}
-- Nearer than the set point by this (beyond the dead band's play): a trim toward the net goes.
local TRIM_DROP_M = 0.05
-- millis() is a uint32: it wraps after 49.7 days.
local CLOCK_WRAP_S = 4294967.296
local HISTORY_N = 160    -- heading samples kept: 1.6 s at the 10 ms update
-- What this ArduSub offers and expects.
-- The vehicle's attitude, radians: 4.5 has ahrs:get_roll()/get_pitch()/get_yaw(); 4.7 renamed
-- them *_rad (ArduPilot PR #30222, 2025) and keeps the old names, deprecated. A method a
-- firmware lacks reads as nil (the binding's __index finds nothing), so take what this one has.
-- The modes whose forward and yaw channels are thrust and turn rate as the pilot's sticks give
-- them (Sub's mode numbers): not GUIDED or AUTO (they never read forward), not POSHOLD (forward
-- is a velocity demand there), not SURFACE or MOTOR_DETECT.
-- Steering pulse widths stay where ArduSub's own joystick keeps them (joystick.cpp); beyond
-- 0..2200 set_override raises.
local SUB = {roll = ahrs.get_roll_rad or ahrs.get_roll,
             pitch = ahrs.get_pitch_rad or ahrs.get_pitch,
             yaw = ahrs.get_yaw_rad or ahrs.get_yaw,
             hold_modes = {[0] = "STABILIZE", [1] = "ACRO", [2] = "ALT_HOLD", [19] = "MANUAL",
                           [21] = "SURFTRAK"},
             pwm_min = 1100, pwm_max = 1900}
-- An update that fails (a bug, a binding this firmware lacks) is said at most every `every_s`;
-- after `give_up` failures in a row (a second) the applet stops, thrust neutral, rather than
-- fill the pilot's link (and ArduPilot's text queue, which drops its oldest: a leak warning)
-- with the same two lines a hundred times a second.
local FAULTS = {count = 0, said = nil, every_s = 5.0, give_up = 100}

-- Parameters: name, default, and the range net hold engages with (outside it, or NaN, it
-- refuses and says which: an inverted clamp or a dead zone no stick can leave would otherwise
-- turn into thrust). Units in docs/net-hold.md.
local PARAMS = {
  {"ENABLE", 1, 0, 1},            -- 0: the applet does nothing
  {"DIST", 1.0, 0.3, 10},         -- set point, m (clamped to 0.5..3)
  {"DIST_MIN", 0.4, 0.3, 2.9},    -- hard minimum, m: no thrust toward the net at or below it
  {"DIST_MAX", 4.0, 0.5, 20},     -- refuse to engage (and disengage) beyond this distance, m
  {"TIMEOUT", 0.4, 0.1, 1.0},     -- a plane older than this (from its capture) stops thrust, s
  {"GRACE", 3.0, 0.5, 10},        -- no fresh plane for this long disengages, s
  {"KP", 0.5, 0, 5},              -- speed command per metre of distance error, 1/s
  {"KI", 0.1, 0, 2},              -- integral of the distance error (a current), 1/s^2
  {"I_BAND", 0.2, 0, 2},          -- the integral winds toward the net only this near, m
  {"SPD_MAX", 0.3, 0, 1},         -- speed limit toward and away from the net, m/s
  {"ACC_MAX", 0.3, 0.01, 2},      -- limit on speeding up toward the net, m/s^2
  {"FWD_GAIN", 190, 10, 1000},    -- forward PWM offset per m/s (SITL vectored: ~194 us per m/s)
  {"KV", 150, 0, 1000},           -- extra forward PWM per m/s of speed error (damping)
  {"FWD_MAX", 150, 0, 400},       -- largest forward PWM offset, us
  {"FWD_DZ", 20, 0, 100},         -- ESC dead band to step over, us (no thrust within 25 us)
  {"FWD_DZ_RAMP", 5, 1, 100},     -- the step is blended in over this command, us
  {"YAW_P", 0.5, 0, 5},           -- yaw rate command per degree of heading error, 1/s
  {"YAW_RATE", 8, 0, 45},         -- yaw rate limit, deg/s
  {"YAW_ACC", 8, 0.1, 90},        -- yaw rate command slew limit, deg/s^2
  {"YAW_GAIN", 3.0, 0.1, 20},     -- yaw PWM offset per deg/s (SITL: ~3 us per deg/s)
  {"YAW_DZ", 20, 0, 100},         -- yaw dead zone to step over, us (RC4_DZ 40 x gain 0.5)
  {"YAW_I", 0.5, 0, 10},          -- integral of the heading error, us per deg*s
  {"YAW_DB", 1.0, 0, 20},         -- heading error left to ArduSub's heading hold, deg
  {"CAM_TILT", 0, -90, 90},       -- camera tilt on the vehicle, deg (positive = looking down)
  {"BTN", 1, 0, 4},               -- script button (1..4) that toggles net hold; 0 = none
  {"PILOT_DZ", 100, 10, 500},     -- pilot stick beyond this (of +-1000) disengages
  {"PLANE_COMP", 197, 0, 255},    -- netpose's component id (its system id is the vehicle's)
}

local P = {}

local function setup_params()
  assert(param:add_table(PARAM_TABLE_KEY, PARAM_PREFIX, #PARAMS), "net_hold: param table")
  for i, p in ipairs(PARAMS) do
    assert(param:add_param(PARAM_TABLE_KEY, i, p[1], p[2]), "net_hold: param " .. p[1])
    P[p[1]] = Parameter(PARAM_PREFIX .. p[1])
  end
end

local function get(name)
  return P[name]:get()
end

-- The first parameter outside its range (or NaN, or unset), described; nil when all are good.
local function bad_param()
  for _, p in ipairs(PARAMS) do
    local v = P[p[1]]:get()
    if type(v) ~= "number" or not (v >= p[3] and v <= p[4]) then
      -- Short: the pilot's text holds 50 characters ("NetHold: refused: " takes 18).
      local shown = type(v) == "number" and string.format("%.3g", v) or tostring(v)
      return string.format("%s=%s (%g..%g)", p[1], shown, p[3], p[4])
    end
  end
  if get("DIST_MAX") <= get("DIST_MIN") then
    return "DIST_MAX not above DIST_MIN"
  end
  return nil
end

local function clamp(v, lo, hi)
  if v < lo then return lo end
  if v > hi then return hi end
  return v
end

local function now_s()
  return millis():tofloat() * 0.001
end

-- Seconds from `t` to `now` on this clock, across its wrap (a plain difference turns negative
-- there, and a timeout on it never ran out).
local function since(t, now)
  local d = now - t
  if d < -1.0 then d = d + CLOCK_WRAP_S end
  return d
end

local function say(severity, text)
  gcs:send_text(severity, "NetHold: " .. text)
end

-- State -------------------------------------------------------------------------------------
local fwd_channel = nil
local fwd_rc, yaw_rc = 5, 4
local lateral_rc = 6
local yaw_channel = nil
local gcs_sysid = 255
local my_sysid = 1
local engaged = false
local paused = false     -- engaged, but the net plane is stale: no thrust until a fresh one
local yaw_rate_cmd = 0
local engaged_mode = nil
local plane = nil        -- {t = capture time s, x, y, z}: the newest plane with the net
local no_net_t = nil     -- capture time of the newest frame without the net, if newer than plane
local last_pause_text = -math.huge
local doubt = 0          -- frames that must still agree after a jump before thrust resumes
local doubt_why = nil    -- what is not believed (pilot text while paused for it)
local jump = nil         -- {d, t}: the last believed distance before a jump, while in doubt
local level_changed = nil  -- a jump the next frames confirmed: why net hold hands back
local last_pilot = -math.huge  -- when the ground station's pilot input last arrived
-- The vehicle's own heading over the last 1.6 s (AHRS, no delay), so the net's heading measured
-- in a frame captured a few hundred ms ago becomes a heading to hold now. A ring buffer looked
-- up by bisection: each plane costs a few dozen VM instructions (ArduPilot stops a script that
-- runs more than SCR_VM_I_COUNT, 10000 by default, in one call, overrides and all).
local yaw_t, yaw_v = {}, {}
local yaw_n, yaw_head = 0, 0
local target_yaw = nil   -- heading (rad) that faces the net squarely, from the newest plane
local said_pause = false
local prev_plane = nil
local closing_speed = 0  -- toward the net, m/s, from successive planes
local last_speed = 0     -- the last measured closing speed, kept when a jump clears the above
-- When thrust last stopped: the speed toward the net and away from it the vehicle may have
-- had (toward: the larger of the commanded and the measured; away: the commanded only, the
-- measured is noisy), what it coasts on.
local stop = {toward = 0, away = 0, cmd = 0, at = 0}
local v_cmd = 0          -- speed command toward the net, m/s
-- The integral of the distance error (`sum`, m*s): the trim a current needs. `held`: the last
-- run's output toward the net was held back by a limit (no winding toward the net then).
local trim = {sum = 0, held = false}
local yaw_integral = 0
local last_update = nil
local last_report = 0

local function param_or(name, default)
  local v = param:get(name)
  if v == nil then return default end
  return v
end

-- The ground station's system id: MAV_GCS_SYSID (4.7), SYSID_MYGCS before. Bound once (a lookup
-- by name searches the parameter table), read each run: ArduSub takes the pilot from the live
-- value, so must net hold.
local gcs_param = nil

local function bind_gcs_param()
  for _, name in ipairs({"MAV_GCS_SYSID", "SYSID_MYGCS"}) do
    local ok, p = pcall(Parameter, name)
    if ok and p ~= nil and p:get() ~= nil then return p end
  end
  return nil
end

local function read_gcs_sysid()
  if gcs_param ~= nil then gcs_sysid = math.floor(gcs_param:get()) end
end

local function setup()
  setup_params()
  fwd_rc = math.floor(param_or("RCMAP_FORWARD", 5))
  yaw_rc = math.floor(param_or("RCMAP_YAW", 4))
  fwd_channel = rc:get_channel(fwd_rc)
  yaw_channel = rc:get_channel(yaw_rc)
  lateral_rc = math.floor(param_or("RCMAP_LATERAL", 6))
  my_sysid = math.floor(param_or("MAV_SYSID", param_or("SYSID_THISMAV", 1)))
  gcs_param = bind_gcs_param()
  -- A queue of 20 messages (about half a second of the pilot's and netpose's, should the
  -- scripting thread stall: a full queue drops what comes), five message ids. The queue's
  -- length comes first (lua_bindings.cpp): (4, 20) was a queue of four.
  mavlink:init(20, 5)
  mavlink:register_rx_msgid(MSG.DEBUG_VECT)
  mavlink:register_rx_msgid(MSG.MANUAL_CONTROL)
  mavlink:register_rx_msgid(MSG.RC_CHANNELS_OVERRIDE)
  mavlink:register_rx_msgid(MSG.COMMAND_LONG)
  -- block_command holds MAV_CMD_USER_1 back from ArduSub as COMMAND_INT too: unanswered, a
  -- ground station that sends it so would time out.
  mavlink:register_rx_msgid(MSG.COMMAND_INT)
  mavlink:block_command(MAV.CMD_USER_1)
end


-- Geometry: the plane vector into a level frame (x forward, y right), from the camera tilt and
-- the vehicle's roll and pitch.
local function level_vector(x, y, z)
  local t = math.rad(get("CAM_TILT"))
  -- camera (x right, y down, z forward) -> body FRD
  local bx = -math.sin(t) * y + math.cos(t) * z
  local by = x
  local bz = math.cos(t) * y + math.sin(t) * z
  -- body -> level: R = Ry(pitch) Rx(roll)
  local r, p = SUB.roll(ahrs), SUB.pitch(ahrs)
  local cr, sr, cp, sp = math.cos(r), math.sin(r), math.cos(p), math.sin(p)
  local y1 = cr * by - sr * bz
  local z1 = sr * by + cr * bz
  local lx = cp * bx + sp * z1
  return lx, y1
end

local function wrap_pi(a)
  return (a + math.pi) % (2 * math.pi) - math.pi
end

local function record_yaw(now)
  if yaw_n > 0 and now < yaw_t[yaw_head] then yaw_n = 0 end  -- the clock wrapped: start again
  yaw_head = yaw_head % HISTORY_N + 1
  yaw_t[yaw_head], yaw_v[yaw_head] = now, SUB.yaw(ahrs)
  if yaw_n < HISTORY_N then yaw_n = yaw_n + 1 end
end

local function yaw_at(t)
  -- The recorded heading nearest to time t (the samples are 10 ms apart, oldest first).
  if yaw_n == 0 then return SUB.yaw(ahrs) end
  local oldest = (yaw_head - yaw_n) % HISTORY_N
  local lo, hi = 0, yaw_n - 1
  while lo < hi do  -- the first sample at or after t (or the newest)
    local mid = (lo + hi) // 2
    if yaw_t[(oldest + mid) % HISTORY_N + 1] < t then lo = mid + 1 else hi = mid end
  end
  local i = (oldest + lo) % HISTORY_N + 1
  if lo > 0 then
    local j = (oldest + lo - 1) % HISTORY_N + 1
    if math.abs(yaw_t[j] - t) < math.abs(yaw_t[i] - t) then i = j end
  end
  return yaw_v[i]
end

-- Messages ------------------------------------------------------------------------------------
local function send_ack(chan, command, result, sysid, compid)
  -- Every field of COMMAND_ACK (10 bytes): send_chan sends as many bytes as the message has
  -- whatever the string holds, and a short one sent the autopilot's memory after it as the
  -- target (a ground station that drops ACKs not addressed to it timed the command out).
  mavlink:send_chan(chan, MSG.COMMAND_ACK,
                    string.pack("<HBBi4BB", command, result, 0, 0, sysid, compid))
end

local disengage

local function coast_distance(v)
  return math.log(1 + COAST.quadratic / COAST.linear * math.abs(v)) / COAST.quadratic
end

-- How far the distance can fall and rise in `elapsed` s. In the pilot's hands: as fast as a
-- vehicle goes (1.5 m/s) either way. While net hold is on, a reading farther than it is is the
-- dangerous one (the hold drives in), so a rise is bounded by what the vehicle can do away
-- from the net: while steering, NETH_SPD_MAX; with thrust stopped, only what it coasts from
-- the speed it had away. A fall may be as fast as a wave pushes while steering (a reading too
-- near only makes the hold back off), and with thrust stopped what it coasts from the speed it
-- had toward the net. A drift either way. (1.5 m/s over a pause of seconds, and later the
-- coasting distance either way, let readings at twice the distance pass as movement.)
local function move_limits(elapsed)
  elapsed = math.max(elapsed, 0)
  if not engaged then return JUMP.speed * elapsed, JUMP.speed * elapsed end
  local drift = JUMP.drift * elapsed
  if paused then
    -- Away, the drift counts up to `drift_away_m` only: 0.05 m/s over a pause of 2.5 s let a
    -- reading 1.5 times too far pass at a 0.5 m set point. A current that carries the vehicle
    -- farther than that meanwhile hands back to the pilot (safe); toward the net it may.
    return math.min(stop.toward * elapsed, coast_distance(stop.toward)) + drift,
           math.min(stop.away * elapsed, coast_distance(stop.away))
           + math.min(drift, JUMP.drift_away_m)
  end
  return JUMP.speed * elapsed, get("SPD_MAX") * elapsed + drift
end

-- Whether the distance went from d0 to d1 in `elapsed` s faster than the vehicle can move.
local function beyond_movement(d0, d1, elapsed)
  local fall, rise = move_limits(elapsed)
  local slack = JUMP.slack_m + JUMP.slack_share * d0
  return d1 - d0 > rise + slack or d0 - d1 > fall + slack
end

local function stop_thrust_speeds(measured, now)
  stop.cmd, stop.at = v_cmd, now
  stop.toward = math.max(v_cmd, measured, 0)
  stop.away = math.max(-v_cmd, 0)
end

local function no_net_at(t)
  if no_net_t == nil or t > no_net_t then no_net_t = t end
end

local function on_plane(msg, now)
  local t_us, x, y, z, name = string.unpack("<I8fffc10", msg, 13)
  if name:gsub("%z", "") ~= PLANE_NAME then return end
  local t = t_us * 1e-6
  if t > now + FUTURE_TOLERANCE_S then
    -- Stamped after it arrived: the clocks disagree (netpose's estimate of this autopilot's
    -- boot, another sender). Its age would not grow; thrust stops until a plane that can be
    -- timed comes. Not kept, so it cannot freeze the planes after it either.
    doubt_why = "net plane ahead of clock"
    no_net_at(now)
    return
  end
  local rebased = false
  if plane ~= nil and (t < plane.t - CLOCK_REBASE_S or now < plane.arrival) then
    -- A new clock (netpose re-based, this clock wrapped): stamps before it are not
    -- comparable with its own. The distance believed still is, and a doubt about it stays:
    -- the next plane is compared with it by arrival time.
    rebased = true
    plane.clock_ended = true
    no_net_t, closing_speed = nil, 0
  end
  if plane ~= nil and not rebased and t <= plane.t then return end  -- repeated, out of order
  local d = math.sqrt(x * x + y * y + z * z)
  if x == 0 and y == 0 and z == 0 then  -- netpose: this frame did not confirm the net
    if doubt == 0 then doubt_why = nil end
    no_net_at(t)
    return
  end
  if not (d > PLAUSIBLE_M[1] and d < PLAUSIBLE_M[2]) then  -- NaN, infinite or nonsense
    doubt_why = "net plane not a distance"
    no_net_at(t)
    return
  end
  if no_net_t ~= nil and no_net_t >= t then return end  -- older than a frame without the net
  no_net_t = nil
  prev_plane = plane
  plane = {t = t, x = x, y = y, z = z, d = d, arrival = now}
  local lx, ly = level_vector(x, y, z)
  target_yaw = wrap_pi(yaw_at(t) + math.atan(ly, lx))
  if prev_plane == nil then
    if doubt == 0 then doubt_why = nil end
    return
  end
  -- The time the vehicle had to move: by the stamps, but never more than by this clock (a
  -- stamp shifted by a clock re-base is not time the vehicle moved), and across a new clock by
  -- this clock alone.
  local dt = plane.t - prev_plane.t
  local elapsed = now - prev_plane.arrival
  if not prev_plane.clock_ended then elapsed = math.min(dt, elapsed) end
  if dt >= 1.0 or prev_plane.clock_ended then
    closing_speed = 0  -- after a gap the speed before it says nothing
  end
  if beyond_movement(prev_plane.d, plane.d, elapsed) then
    -- Faster than the vehicle moves (after a gap too: thrust had stopped): doubtful until the
    -- next frames agree with this one.
    if jump == nil then jump = {d = prev_plane.d, arrival = prev_plane.arrival, began = now} end
    if engaged and not paused then stop_thrust_speeds(closing_speed, now) end  -- thrust stops
    doubt, doubt_why, closing_speed = JUMP.confirm, "net distance jumped", 0
  else
    if doubt > 0 then
      doubt = doubt - 1
      if doubt == 0 then
        -- The frames agree again. Back where the net was: a glitch, hold on. Somewhere the
        -- vehicle cannot have gone since: one of the two readings is wrong, and which one
        -- cannot be told here, so the pilot takes over.
        -- Thrust was stopped all the while (the doubt, a gap before it): the vehicle only
        -- coasted, however long the wait for the frames to agree.
        if beyond_movement(jump.d, plane.d, since(jump.arrival, now)) then
          level_changed = string.format("net distance jumped %.2f->%.2f m", jump.d,
                                        plane.d)
        end
        jump = nil
      end
    end
    if doubt == 0 then doubt_why = nil end
    if dt > 0.01 and dt < 1.0 and not prev_plane.clock_ended then
      local rate = (prev_plane.d - plane.d) / dt
      closing_speed = closing_speed + 0.35 * (rate - closing_speed)
      last_speed = closing_speed
    end
  end
end

local function pilot_moves(x, r)
  local dz = get("PILOT_DZ")
  return math.abs(x) > dz or math.abs(r) > dz
end

local engage

local function on_manual_control(msg, now)
  local x, _, _, r, _, target = string.unpack("<hhhhHB", msg, 13)
  if target ~= my_sysid then return end
  last_pilot = now
  if engaged and pilot_moves(x, r) then
    -- The pilot's own message has already set the channels: leave them to the pilot.
    disengage("pilot input", false)
  end
end

local function override_of(msg, channel)
  -- RC_CHANNELS_OVERRIDE: chan1..8 raw (uint16), target system, target component, chan9..18.
  if channel <= 8 then return string.unpack("<H", msg, 13 + 2 * (channel - 1)) end
  return string.unpack("<H", msg, 31 + 2 * (channel - 9))
end

local function on_rc_override(msg, now)
  -- A ground station that flies by RC overrides: pilot input too (ArduSub takes it from the GCS).
  if string.byte(msg, 29) ~= my_sysid then return end
  last_pilot = now
  -- Joystick units to us as ArduSub maps them at its default gain (0.5): 0.2 us per unit.
  local limit = get("PILOT_DZ") * 0.2
  for _, channel in ipairs({fwd_rc, yaw_rc}) do
    local pwm = override_of(msg, channel)
    -- Only a pulse width is a stick (0, 65534 and 65535 release or leave the channel alone).
    if engaged and pwm >= 800 and pwm <= 2200 and math.abs(pwm - NEUTRAL) > limit then
      disengage("pilot input", false)
      return
    end
  end
end

local function on_command(msg, chan, from_gcs)
  -- COMMAND_LONG (param1..7 floats) and COMMAND_INT (param1..4, x, y int32, z): both put
  -- param1 first and the command and its target after 28 bytes.
  local p1, _, _, _, _, _, _, command, target = string.unpack("<fffffffHB", msg, 13)
  if command ~= MAV.CMD_USER_1 or (target ~= my_sysid and target ~= 0) then return end
  local sysid, compid = string.byte(msg, 8), string.byte(msg, 9)
  if p1 >= 0.5 and not from_gcs then  -- only the pilot's ground station engages
    send_ack(chan, command, MAV.RESULT_DENIED, sysid, compid)
    return
  end
  if p1 >= 0.5 then
    send_ack(chan, command, engage() and MAV.RESULT_ACCEPTED or MAV.RESULT_DENIED, sysid,
             compid)
  else
    if engaged then disengage("command", true) end
    send_ack(chan, command, MAV.RESULT_ACCEPTED, sysid, compid)
  end
end

local function read_messages(now)
  local plane_comp = math.floor(get("PLANE_COMP"))
  for _ = 1, 30 do
    local msg, chan = mavlink:receive_chan()
    if msg == nil then return end
    local msgid = string.unpack("<I3", msg, 10)
    local sysid, compid = string.byte(msg, 8), string.byte(msg, 9)
    if msgid == MSG.DEBUG_VECT then
      -- Only netpose's (this vehicle's system id, its component): a replay tool, a second
      -- netpose or a stranger on the network must not steer.
      if sysid == my_sysid and (plane_comp == 0 or compid == plane_comp) then
        on_plane(msg, now)
      end
    elseif msgid == MSG.COMMAND_LONG or msgid == MSG.COMMAND_INT then
      on_command(msg, chan, sysid == gcs_sysid)
    elseif sysid ~= gcs_sysid then
      -- The pilot's input comes from the ground station only (as ArduSub takes it).
    elseif msgid == MSG.MANUAL_CONTROL then
      on_manual_control(msg, now)
    elseif msgid == MSG.RC_CHANNELS_OVERRIDE then
      on_rc_override(msg, now)
    end
  end
end

-- Engage / disengage ----------------------------------------------------------------------------

local function plane_age(now)
  if plane == nil then return math.huge end
  local age = now - plane.t
  if age < -CLOCK_REBASE_S then age = age + CLOCK_WRAP_S end  -- the clock wrapped since
  return age
end

local function set_point()
  -- Never closer than 10 cm outside the hard minimum, whatever NETH_DIST says.
  return clamp(get("DIST"), math.max(0.5, get("DIST_MIN") + 0.1), 3.0)
end

local function neutral()
  fwd_channel:set_override(NEUTRAL)
  yaw_channel:set_override(NEUTRAL)
end

disengage = function(why, to_neutral)
  if not engaged then return end
  engaged, paused, yaw_rate_cmd = false, false, 0
  if to_neutral then neutral() end
  v_cmd, trim.sum, trim.held, yaw_integral = 0, 0, false, 0
  say(SEV.WARNING, "OFF, " .. why)
  gcs:send_named_float("NH_ON", 0)
end

engage = function()
  if engaged then return true end
  local now = now_s()
  if get("ENABLE") < 1 then
    say(SEV.WARNING, "disabled (NETH_ENABLE = 0)")
    return false
  end
  local bad = bad_param()
  if bad ~= nil then
    say(SEV.WARNING, "refused: " .. bad)
    return false
  end
  if not arming:is_armed() then
    say(SEV.WARNING, "refused: disarmed")
    return false
  end
  if SUB.hold_modes[vehicle:get_mode()] == nil then
    say(SEV.WARNING, "refused in this mode (use ALT_HOLD)")
    return false
  end
  if since(last_pilot, now) > PILOT_TIMEOUT_S then
    say(SEV.WARNING, "refused: no joystick input from the GCS")
    return false
  end
  if plane_age(now) > get("TIMEOUT") or no_net_t ~= nil then
    say(SEV.WARNING, "refused: no net in view")
    return false
  end
  if plane.d > get("DIST_MAX") or plane.d < get("DIST_MIN") then
    say(SEV.WARNING, string.format("refused: net at %.2f m", plane.d))
    return false
  end
  if doubt > 0 then
    say(SEV.WARNING, "refused: " .. (doubt_why or "net distance not steady"))
    return false
  end
  engaged, paused, yaw_rate_cmd = true, false, 0
  engaged_mode = vehicle:get_mode()
  v_cmd, trim.sum, trim.held, yaw_integral = 0, 0, false, 0
  last_update = now
  say(SEV.INFO, string.format("ON, holding %.2f m (net at %.2f m)", set_point(), plane.d))
  gcs:send_named_float("NH_ON", 1)
  return true
end

-- Only the applet's own button is read (ArduSub's counts are one set for every script); a
-- press counted while the button was not the applet's (NETH_BTN 0 or another, before the
-- applet loaded) engaged the hold as soon as it became so, with nobody pressing anything:
-- when NETH_BTN changes, and at load, its count so far is discarded once.
local counted_button = 0

local function clear_buttons()
  counted_button = math.floor(get("BTN"))
  if counted_button >= 1 and counted_button <= 4 then
    sub:get_and_clear_button_count(counted_button)
  end
end

local function check_button()
  local button = math.floor(get("BTN"))
  if button ~= counted_button then
    clear_buttons()
    return
  end
  if button < 1 or button > 4 then return end
  if sub:get_and_clear_button_count(button) > 0 then
    if engaged then disengage("button", true) else engage() end
  end
end

-- Control -----------------------------------------------------------------------------------------
local function control(now)
  local dt = clamp(since(last_update or now, now), 0.0, 0.1)
  last_update = now
  -- The distance now: the plane's, carried forward over its age at the measured closing speed
  -- (netpose's frames are 0.1-0.4 s old when they arrive; the vehicle keeps moving meanwhile).
  local d = plane.d - closing_speed * clamp(now - plane.t, 0, get("TIMEOUT"))
  local err = d - set_point()  -- positive: too far, move toward the net
  -- Speed toward the net: P + I, limited in speed, and in acceleration toward the net.
  -- The integral trims a steady offset: the thrust a current needs. It winds toward the net
  -- only within I_BAND of the set point (never on the approach) and while the output toward
  -- the net was not held back by a limit (a trim wound there filled to NETH_SPD_MAX, and when
  -- the current stopped it drove a 0.6 m hold to the minimum); away from the net (too close) at
  -- any distance, inside the minimum too, where a current pushed a P-only hold and stayed; and
  -- it unwinds an away trim at any distance, never past zero. A trim toward the net is dropped
  -- once the vehicle is TRIM_DROP_M nearer than the set point: the current it stood against
  -- has eased, and the trim would carry the vehicle on in (14 cm at a 1 m set point, 9 now).
  local spd = get("SPD_MAX")
  local grown = trim.sum + err * dt
  if err < 0 or (math.abs(err) < get("I_BAND") and d > get("DIST_MIN") and not trim.held) then
    trim.sum = grown
  elseif trim.sum < 0 then
    trim.sum = math.min(grown, 0)
  end
  if d <= get("DIST_MIN") or err < -TRIM_DROP_M then trim.sum = math.min(trim.sum, 0) end
  local ki = get("KI")
  local i_max = ki > 0 and spd / ki or 0  -- the trim at most NETH_SPD_MAX
  trim.sum = clamp(trim.sum, -i_max, i_max)
  local asked = get("KP") * err + ki * trim.sum
  local want = clamp(asked, -spd, spd)
  local stop_dist = d - get("DIST_MIN") - math.max(closing_speed, 0) * get("TIMEOUT")
  if stop_dist <= 0 then
    want = math.min(want, 0)  -- hard minimum: nothing toward the net
  end
  -- Toward the net no faster than the vehicle can coast to a stop from here, should the next
  -- frame lose the net (thrust then stops at once, but the vehicle coasts on): with the speed
  -- limits NETH_SPD_MAX and NETH_KP allow, a camera blocked on the approach coasted it into
  -- the net. The speed whose coasting distance is the room left, over the margin.
  local room = stop_dist / COAST.margin
  local coast_speed = 0
  if room > 0 then
    coast_speed = (math.exp(COAST.quadratic * room) - 1) * COAST.linear / COAST.quadratic
  end
  want = math.min(want, coast_speed)
  local held = asked > want
  if want > v_cmd then
    v_cmd = math.min(want, v_cmd + get("ACC_MAX") * dt)
  else
    v_cmd = want
  end
  local fwd_max = get("FWD_MAX")
  -- Feed-forward of the speed wanted, plus feedback on the measured closing speed: the vehicle
  -- coasts a long way on its own (mostly quadratic drag), so it must be braked actively.
  local fwd = v_cmd * get("FWD_GAIN") + (v_cmd - closing_speed) * get("KV")
  -- Toward the net, never more than the thrust that holds NETH_SPD_MAX: the speed limit holds
  -- even while the measured speed lags.
  -- Step over (part of) the ESCs' dead band (no thrust within 25 us of neutral), blended in over
  -- the first FWD_DZ_RAMP us so that the output stays continuous through zero.
  -- Only while the thrusters idle: a lateral command (the pilot sweeping along the net) already
  -- takes them out of the dead band, and the step would then double the loop's gain.
  local lateral = rc:get_pwm(lateral_rc) or NEUTRAL
  local dz = get("FWD_DZ") * clamp(1.0 - math.abs(lateral - NEUTRAL) / 25.0, 0.0, 1.0)
  fwd = fwd + dz * clamp(fwd / get("FWD_DZ_RAMP"), -1.0, 1.0)
  local fwd_toward = math.min(fwd_max, spd * get("FWD_GAIN"))
  trim.held = held or fwd > fwd_toward
  fwd = clamp(fwd, -fwd_max, fwd_toward)
  if stop_dist <= 0 then fwd = math.min(fwd, 0) end
  fwd_channel:set_override(math.floor(NEUTRAL + fwd + 0.5))

  -- Heading: yaw until the net's normal is straight ahead in the level frame.
  -- Heading error now: the heading that faces the net (from the plane, at its capture time)
  -- minus the heading now. Positive: yaw right.
  local heading_err = math.deg(wrap_pi(target_yaw - SUB.yaw(ahrs)))
  local yaw_pwm = NEUTRAL
  local max_rate = get("YAW_RATE")
  local rate_want = 0
  if math.abs(heading_err) > get("YAW_DB") then
    rate_want = clamp(get("YAW_P") * heading_err, -max_rate, max_rate)
  end
  local rate_step = get("YAW_ACC") * dt
  yaw_rate_cmd = clamp(rate_want, yaw_rate_cmd - rate_step, yaw_rate_cmd + rate_step)
  if math.abs(heading_err) > get("YAW_DB") then
    local rate = yaw_rate_cmd
    yaw_integral = clamp(yaw_integral + heading_err * dt * get("YAW_I"), -30, 30)
    local offset = math.abs(rate) * get("YAW_GAIN")
    if rate < 0 then offset = -offset end
    offset = offset + yaw_integral
    if offset ~= 0 then
      offset = offset + (offset > 0 and get("YAW_DZ") or -get("YAW_DZ"))
    end
    local yaw_max = get("YAW_DZ") + max_rate * get("YAW_GAIN")
    yaw_pwm = clamp(math.floor(NEUTRAL + clamp(offset, -yaw_max, yaw_max) + 0.5), SUB.pwm_min,
                    SUB.pwm_max)
  else
    yaw_integral = 0  -- square: ArduSub's heading hold keeps it
  end
  yaw_channel:set_override(yaw_pwm)

  if since(last_report, now) > 0.5 then
    last_report = now
    gcs:send_named_float("NH_ERR", err)
    gcs:send_named_float("NH_YAWERR", heading_err)
  end
  if logger ~= nil then
    logger:write("NETH", "D,Set,Err,Yaw,Vcmd,Fwd,YawP", "fffffhh", d, set_point(), err,
                 heading_err, v_cmd, math.floor(fwd), yaw_pwm)
  end
end

local function update()
  local now = now_s()
  record_yaw(now)
  read_gcs_sysid()
  read_messages(now)
  check_button()
  local changed = level_changed
  level_changed = nil
  if not engaged then return end
  local age = plane_age(now)
  local bad = bad_param()
  if get("ENABLE") < 1 then
    disengage("disabled", true)
  elseif bad ~= nil then
    disengage(bad, true)
  elseif changed ~= nil then
    disengage(changed, true)
  elseif doubt > 0 and jump ~= nil and since(jump.began, now) > JUMP.longest_s then
    -- Readings that keep changing their mind (a harmonic that comes and goes): each change
    -- starts the doubt again, and the hold would wait with thrust stopped for ever.
    disengage(string.format("net distance not steady (%.1f s)", since(jump.began, now)), true)
  elseif since(last_pilot, now) > PILOT_TIMEOUT_S then
    -- The pilot could not take over by stick (link lost, joystick gone, a failsafe that only
    -- warns): hand back rather than drive on unattended.
    disengage(string.format("no pilot input (%.1f s)", math.min(since(last_pilot, now), 99)),
              true)
  elseif not arming:is_armed() then
    disengage("disarmed", true)
  elseif vehicle:get_mode() ~= engaged_mode then
    disengage("mode changed", true)
  elseif age > get("GRACE") then
    disengage(string.format("net lost (%.1f s)", math.min(age, 99)), true)
  elseif age > get("TIMEOUT") or no_net_t ~= nil or doubt > 0 then
    if not paused then
      -- What the vehicle coasts on from here (the last measured speed: a jump has cleared
      -- closing_speed already).
      if doubt == 0 then stop_thrust_speeds(last_speed, now) end
      paused, v_cmd, yaw_rate_cmd = true, 0, 0
      -- At most one message per 3 s: a fish passing must not flood the pilot's screen.
      said_pause = since(last_pause_text, now) > 3.0
      if said_pause then
        last_pause_text = now
        if doubt_why ~= nil then
          say(SEV.WARNING, doubt_why .. ": thrust stopped")
        elseif no_net_t ~= nil then
          say(SEV.WARNING, "net not seen: thrust stopped")
        else
          say(SEV.WARNING, string.format("no fresh net (%.2f s): thrust stopped", age))
        end
      end
    end
    neutral()
  elseif plane.d > get("DIST_MAX") then
    disengage(string.format("net too far (%.2f m)", plane.d), true)
  else
    if paused then
      -- Closing in when thrust stopped, and long enough that the vehicle may have coasted
      -- 5 cm since: where it is now cannot be checked against where it was (a reading 1.3
      -- times too far looks like less coasting), so the pilot takes over rather than the hold
      -- resuming on it. Holding still, or after a short pause, it resumes.
      local unknown = math.min(math.max(stop.cmd, 0) * since(stop.at, now),
                               coast_distance(math.max(stop.cmd, 0)))
      if unknown > 0.05 then
        disengage(string.format("net lost while closing in (%.1f s)", since(stop.at, now)),
                  true)
        return
      end
      paused = false
      last_update = now
      if said_pause then say(SEV.INFO, "net back, holding again") end
    end
    control(now)
  end
end

local function protected_update()
  local ok, err = pcall(update)
  if ok then
    FAULTS.count = 0
    return protected_update, UPDATE_MS
  end
  -- A bug must not leave thrust behind: neutral, off, and keep running (a fault that comes
  -- and goes, one odd message), but not for ever on one that stays.
  local was_engaged = engaged
  if engaged then
    engaged = false
    pcall(neutral)
  end
  gcs:send_named_float("NH_ON", 0)
  FAULTS.count = FAULTS.count + 1
  local now = now_s()
  -- Switching off is always said: the pilot must not think it still holds.
  if was_engaged or FAULTS.said == nil or since(FAULTS.said, now) >= FAULTS.every_s then
    FAULTS.said = now
    -- Two texts: each holds 50 characters, and the error's start (file and line) matters most.
    gcs:send_text(3, "NetHold: internal error, OFF")
    gcs:send_text(3, "NetHold: " .. string.sub(tostring(err), 1, 41))
  end
  if FAULTS.count >= FAULTS.give_up then
    pcall(neutral)
    gcs:send_text(3, "NetHold: stopped after repeated errors")
    return  -- no next run: ArduPilot ends the script
  end
  return protected_update, UPDATE_MS
end

setup()
clear_buttons()  -- presses from before the applet was there are not the pilot's to it
say(SEV.INFO, string.format("loaded, set point %.2f m, button %d", set_point(), math.floor(get("BTN"))))
-- The first run at once: a command in the first second after loading (the pilot engaging
-- right after a reboot) got no COMMAND_ACK at all, the command being blocked for the applet.
return protected_update, UPDATE_MS
