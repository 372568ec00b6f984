-- Wireshark dissector for awaremw radio frames (docs/capture.md).
--
-- An awaremw frame is one msgpack array [type, src, dst, *body] carried as the
-- payload of an IEEE 802.15.4 data frame (captures from `awaremw ... --pcap`,
-- link type 230, IEEE802_15_4_NOFCS). On a secured radio the frame is followed
-- by a 4-byte frame counter and a 4- or 8-byte MIC (awaremw/radio/security.py).
--
-- Use:  tshark -X lua_script:$(awaremw sniff --dissector) -r out.pcap
--   or copy this file into Wireshark's personal plugins folder.
-- Registered as a heuristic dissector on the 802.15.4 payload ("wpan"), and
-- under "Decode As..." (wpan.panid) for captures where another heuristic wins.
-- Display filters: awaremw, awaremw.type, awaremw.type_name, awaremw.src, awaremw.dst.

local awaremw = Proto("awaremw", "awaremw radio frame")

-- The frame types of awaremw/protocol/frames.py (FRAME_TYPES), with their body fields.
local FRAME_TYPES = {
    [1] = "Hello",
    [2] = "DripItem",
    [3] = "DripSummary",
    [4] = "CtpBeacon",
    [5] = "CtpData",
    [6] = "LeaderBeacon",
    [7] = "Handover",
    [8] = "Partial",
    [16] = "DripSig",
}
local BODY_FIELDS = {
    [1] = { "seq" },
    [2] = { "kind", "item_id", "version", "item" },
    [3] = { "digest", "n_items" },
    [4] = { "cost", "parent", "pull" },
    [5] = { "origin", "seqno", "thl", "cost", "payload" },
    [6] = { "group_type", "group_id", "leader", "weight", "seq", "hops", "tentative", "parent" },
    [7] = { "group_type", "group_id", "weight", "seq" },
    [8] = { "channel", "group_type", "group_id", "epoch", "agg", "count", "state" },
    [16] = { "kind", "item_id", "version", "part", "chunk" },
}

local f_type = ProtoField.uint8("awaremw.type", "Frame type", base.DEC, FRAME_TYPES)
local f_type_name = ProtoField.string("awaremw.type_name", "Frame type name")
local f_src = ProtoField.uint16("awaremw.src", "Source", base.DEC)
local f_dst = ProtoField.uint16("awaremw.dst", "Destination", base.DEC)
local f_field = ProtoField.string("awaremw.field", "Field")
local f_counter = ProtoField.uint32("awaremw.counter", "Frame counter", base.DEC)
local f_mic = ProtoField.bytes("awaremw.mic", "MIC")
local f_trailer = ProtoField.bytes("awaremw.trailer", "Trailing bytes")
awaremw.fields = { f_type, f_type_name, f_src, f_dst, f_field, f_counter, f_mic, f_trailer }

-- A small msgpack reader over a TvbRange: returns (value or description, next offset),
-- or nil when the bytes are not msgpack. Depth and sizes are bounded by the buffer.
local function u(tvb, off, n)
    if off + n > tvb:len() then return nil end
    if n == 1 then return tvb(off, 1):uint() end
    if n == 2 then return tvb(off, 2):uint() end
    if n == 4 then return tvb(off, 4):uint() end
    return tvb(off, 8):uint64():tonumber()
end

local read
local function read_array(tvb, off, n, depth)
    local items = {}
    for i = 1, n do
        local v, nxt = read(tvb, off, depth + 1)
        if nxt == nil then return nil end
        items[i] = v
        off = nxt
    end
    return items, off
end

read = function(tvb, off, depth)
    if depth > 16 or off >= tvb:len() then return nil end
    local b = tvb(off, 1):uint()
    if b <= 0x7f then return b, off + 1 end
    if b >= 0xe0 then return b - 0x100, off + 1 end
    if b >= 0x90 and b <= 0x9f then return read_array(tvb, off + 1, b - 0x90, depth) end
    if b >= 0xa0 and b <= 0xbf then
        local n = b - 0xa0
        if off + 1 + n > tvb:len() then return nil end
        return tvb(off + 1, n):string(), off + 1 + n
    end
    if b >= 0x80 and b <= 0x8f then
        local m, nxt = read_array(tvb, off + 1, 2 * (b - 0x80), depth)
        if m == nil then return nil end
        return "{map}", nxt
    end
    if b == 0xc0 then return "nil", off + 1 end
    if b == 0xc2 then return "false", off + 1 end
    if b == 0xc3 then return "true", off + 1 end
    if b == 0xcc then local v = u(tvb, off + 1, 1); if v == nil then return nil end; return v, off + 2 end
    if b == 0xcd then local v = u(tvb, off + 1, 2); if v == nil then return nil end; return v, off + 3 end
    if b == 0xce then local v = u(tvb, off + 1, 4); if v == nil then return nil end; return v, off + 5 end
    if b == 0xcf then local v = u(tvb, off + 1, 8); if v == nil then return nil end; return v, off + 9 end
    if b == 0xd0 then if off + 2 > tvb:len() then return nil end; return tvb(off + 1, 1):int(), off + 2 end
    if b == 0xd1 then if off + 3 > tvb:len() then return nil end; return tvb(off + 1, 2):int(), off + 3 end
    if b == 0xd2 then if off + 5 > tvb:len() then return nil end; return tvb(off + 1, 4):int(), off + 5 end
    if b == 0xd3 then if off + 9 > tvb:len() then return nil end; return tvb(off + 1, 8):int64():tonumber(), off + 9 end
    if b == 0xca then if off + 5 > tvb:len() then return nil end; return tvb(off + 1, 4):float(), off + 5 end
    if b == 0xcb then if off + 9 > tvb:len() then return nil end; return tvb(off + 1, 8):float(), off + 9 end
    if b == 0xc4 or b == 0xd9 then
        local n = u(tvb, off + 1, 1); if n == nil or off + 2 + n > tvb:len() then return nil end
        return string.format("<%d bytes>", n), off + 2 + n
    end
    if b == 0xc5 or b == 0xda then
        local n = u(tvb, off + 1, 2); if n == nil or off + 3 + n > tvb:len() then return nil end
        return string.format("<%d bytes>", n), off + 3 + n
    end
    if b == 0xdc then
        local n = u(tvb, off + 1, 2); if n == nil then return nil end
        return read_array(tvb, off + 3, n, depth)
    end
    return nil
end

local function show(v)
    if type(v) == "table" then
        local parts = {}
        for i, x in ipairs(v) do parts[i] = show(x) end
        return "[" .. table.concat(parts, ", ") .. "]"
    end
    if type(v) == "number" and v ~= math.floor(v) then return string.format("%.6g", v) end
    return tostring(v)
end

-- The frame's header if the payload starts with an awaremw frame: type, src, dst, end offset.
local function header(tvb)
    if tvb:len() < 4 then return nil end
    local b = tvb(0, 1):uint()
    if b < 0x93 or b > 0x9f then return nil end -- [type, src, dst, ...]: 3..15 elements
    local v, nxt = read(tvb, 0, 0)
    if v == nil or type(v) ~= "table" then return nil end
    local t, src, dst = v[1], v[2], v[3]
    if type(t) ~= "number" or FRAME_TYPES[t] == nil then return nil end
    if type(src) ~= "number" or src < 0 or src > 0xfffd then return nil end
    if type(dst) ~= "number" or dst < 0 or (dst > 0xfffd and dst ~= 0xffff) then return nil end
    return v, nxt
end

local function dissect(tvb, pinfo, root)
    local v, nxt = header(tvb)
    if v == nil then return 0 end
    local t = v[1]
    local name = FRAME_TYPES[t]
    pinfo.cols.protocol = "awaremw"
    local dst = v[3] == 0xffff and "broadcast" or tostring(v[3])
    pinfo.cols.info = string.format("%s %d -> %s", name, v[2], dst)
    local tree = root:add(awaremw, tvb(0, nxt), "awaremw " .. name)
    tree:add(f_type, tvb(1, 1), t)
    tree:add(f_type_name, name):set_generated()
    tree:add(f_src, v[2])
    tree:add(f_dst, v[3])
    local names = BODY_FIELDS[t] or {}
    for i = 4, #v do
        local label = names[i - 3] or string.format("field %d", i - 3)
        tree:add(f_field, label .. " = " .. show(v[i]))
    end
    local rest = tvb:len() - nxt
    if rest == 8 or rest == 12 then -- secured: counter (4 B, big-endian) and MIC-32/64
        tree:add(f_counter, tvb(nxt, 4))
        tree:add(f_mic, tvb(nxt + 4, rest - 4))
    elseif rest > 0 then
        tree:add(f_trailer, tvb(nxt, rest))
    end
    return tvb:len()
end

function awaremw.dissector(tvb, pinfo, tree)
    return dissect(tvb, pinfo, tree)
end

local function heuristic(tvb, pinfo, tree)
    return dissect(tvb, pinfo, tree) > 0
end

awaremw:register_heuristic("wpan", heuristic)
local panid = DissectorTable.get("wpan.panid")
if panid ~= nil then panid:add(0x0022, awaremw) end
