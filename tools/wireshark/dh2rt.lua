-- dh2rt.lua: a Wireshark dissector for dh2rt frames (the DH2 hormone runtime's wire format).
--
-- It reads both halves of a dh2rt capture (docs/capture.md):
--   * CAN frames in SocketCAN captures (link type 227): a heuristic dissector on "can", since
--     a dh2rt link id lives in the 29-bit arbitration id (kind, segment, seq, link id, side);
--     segments of a long hormone are reassembled per link end, as a module's transport does,
--     and a train whose CRC-32 fails (spliced from two hormones, or a piece lost) is refused;
--     the management frames of link negotiation (one arbitration id) show their op, link id
--     and tag;
--   * the emulated infrared serial links (link type 147, USER0): the 8-byte "D2" record
--     (side, lost, corrupted, link id), then the frame as on the wire: COBS, CRC-32, 0x00;
--   * on both, flashing's transfer frames (the second frame family: OFFER, REQUEST, SEGMENT,
--     ACK, COMMIT, REPORT ...), each field as `dh2rt dump` names it (dh2rt.transfer.*), and the
--     operator's control frames (the third: INJECT, PAUSE, RESUME, STATE, STATE_REPLY,
--     REFUSED; dh2rt.control.*) and the docking chain's motion frames in it (ASK, ANGLES,
--     TARGETS, END), as `dh2rt dump` shows them.
-- The Info column is the line `dh2rt dump` prints for the frame, without its time.
--
-- Frames carry hormone indices, not names. This file, as committed, knows no program: it
-- shows a hormone as #INDEX with its argument bytes. `dh2rt wireshark --capture
-- robot.pcapng -o dh2rt.lua` (or `--program caterpillar.dh2`) writes it with the names.
--
-- Load: tshark -X lua_script:dh2rt.lua -r robot.pcapng, or copy it into Wireshark's
-- personal Lua plugins folder (Help > About Wireshark > Folders).
--
-- The block below is written by tools/wireshark/generate.py from dh2rt's codec modules
-- (dh2rt/wire/frame.py, dh2rt/wire/can_frames.py, dh2rt/wire/negotiation.py,
-- dh2rt/wire/serial_framing.py, dh2rt/wire/transfer.py, tools/serial_records.py) and dump's
-- table of transfer messages (tools/transfer_view.py): a test checks that this file is what
-- the generator writes, so the dissector and the codec cannot drift apart. Edit the
-- generator, not the block.

-- BEGIN GENERATED
-- Written by `dh2rt wireshark`; do not edit.
-- Profile conro; programs: none.
local LAYOUT = {
    wire_version = 3,
    header = {
        version = { shift = 6, width = 2 },
        kind = { shift = 4, width = 2 },
        sender = { shift = 0, width = 4 },
    },
    kinds = { hormone = 0, routed = 1, keepalive = 2, hello = 3 },
    kind_names = { [0] = "hormone", [1] = "routed", [2] = "keepalive", [3] = "hello" },
    keepalive_bytes = 2,
    hello_digest_bytes = 6,
    connector_bits = 3,
    can = {
        kind = { shift = 27, width = 2 },
        segment = { shift = 25, width = 2 },
        seq = { shift = 19, width = 6 },
        link = { shift = 1, width = 18 },
        side = { shift = 0, width = 1 },
    },
    segments = { single = 0, first = 1, middle = 2, last = 3 },
    segment_names = { [0] = "single", [1] = "first", [2] = "middle", [3] = "last" },
    train = {
        check_bytes = 4,
        seq_modulus = 64,
        max_train = 516,
        refused = "train refused: its check fails (spliced from two hormones, or a piece lost)",
    },
    management = {
        id = 403177470,
        bytes = 8,
        ops = { [1] = "CLAIM", [2] = "RELEASE", [3] = "HOLD" },
        first_link_id = 1,
        last_link_id = 262142,
    },
    serial = {
        magic = "D2",
        version = 1,
        header_bytes = 8,
        flag_side = 1,
        flag_lost = 2,
        flag_corrupted = 4,
        crc_bytes = 4,
        delimiter = 0,
    },
    transfer = {
        family = 2,
        image_bytes = 8,
        max_connector = 15,
        max_segment_size = 506,
        hop = { sent = { shift = 4, width = 4 }, received = { shift = 0, width = 4 } },
        messages = {
            [1] = {
                name = "OFFER",
                class = 2,
                head = "offer fields",
                fields = {
                    { name = "version", wire = "u32", show = "%d", proto = "uint" },
                    { name = "image", wire = "image", show = "hex", proto = "bytes" },
                    { name = "length", wire = "u32", show = "%d", proto = "uint" },
                    { name = "segment_size", wire = "u16", show = "%d", proto = "uint" },
                    { name = "held", wire = "u16", show = "%d", proto = "uint" },
                    {
                        name = "running",
                        wire = "flag",
                        show = "flag",
                        proto = "bool",
                        text = ", running",
                    },
                    {
                        name = "path",
                        wire = "path",
                        show = "path",
                        proto = "string",
                        limit = 64,
                    },
                },
                line = "OFFER v{version} {image} {length} bytes, segments of {segment_size}, held {held}{running}, path {path}",
            },
            [2] = {
                name = "REQUEST",
                class = 2,
                head = "request fields",
                fields = {
                    { name = "image", wire = "image", show = "hex", proto = "bytes" },
                    { name = "next", wire = "u16", show = "%d", proto = "uint" },
                    { name = "window", wire = "u8", show = "%d", proto = "uint", limit = 64 },
                    {
                        name = "probe",
                        wire = "flag",
                        show = "flag",
                        proto = "bool",
                        text = ", probe",
                    },
                },
                line = "REQUEST {image} from #{next}, window {window}{probe}",
            },
            [3] = {
                name = "SEGMENT",
                class = 3,
                head = "segment header",
                fields = {
                    { name = "tag", wire = "u16", show = "%d", proto = "uint" },
                    { name = "index", wire = "u16", show = "%d", proto = "uint" },
                    {
                        name = "data",
                        wire = "rest",
                        show = "count",
                        proto = "bytes",
                        limit = 506,
                    },
                },
                line = "SEGMENT tag {tag} #{index} ({data} bytes)",
            },
            [4] = {
                name = "ACK",
                class = 2,
                head = "ack fields",
                fields = {
                    { name = "tag", wire = "u16", show = "%d", proto = "uint" },
                    { name = "next", wire = "u16", show = "%d", proto = "uint" },
                    { name = "sack", wire = "u16", show = "0x%04x", proto = "hex" },
                },
                line = "ACK tag {tag} next #{next} sack {sack}",
            },
            [5] = {
                name = "DECLINE",
                class = 2,
                head = "decline fields",
                fields = {
                    { name = "image", wire = "image", show = "hex", proto = "bytes" },
                    {
                        name = "reason",
                        wire = "u8",
                        show = "name",
                        proto = "string",
                        names = {
                            [1] = "have",
                            [2] = "current",
                            [3] = "newer",
                            [4] = "refused",
                            [5] = "reverted",
                            [6] = "busy",
                        },
                    },
                    { name = "version", wire = "u32", show = "%d", proto = "uint" },
                },
                line = "DECLINE {image} {reason} (runs v{version})",
            },
            [6] = {
                name = "CANCEL",
                class = 2,
                head = "image id",
                fields = {
                    { name = "image", wire = "image", show = "hex", proto = "bytes" },
                    {
                        name = "verdict",
                        wire = "ascii",
                        show = "%s",
                        proto = "string",
                        limit = 16,
                    },
                },
                line = "CANCEL {image}: {verdict}",
            },
            [7] = {
                name = "COMMIT",
                class = 1,
                head = "commit fields",
                fields = {
                    { name = "image", wire = "image", show = "hex", proto = "bytes" },
                    { name = "remaining_us", wire = "u32", show = "ms", proto = "uint" },
                    { name = "hops", wire = "u8", show = "%d", proto = "uint" },
                },
                line = "COMMIT {image} {remaining_us} (hops {hops})",
            },
            [8] = {
                name = "COMMIT_ACK",
                class = 1,
                head = "image id",
                fields = { { name = "image", wire = "image", show = "hex", proto = "bytes" } },
                line = "COMMIT_ACK {image}",
            },
            [9] = {
                name = "REPORT",
                class = 2,
                head = "report fields",
                fields = {
                    { name = "tag", wire = "u16", show = "%d", proto = "uint" },
                    { name = "seq", wire = "u16", show = "%d", proto = "uint" },
                    {
                        name = "outcome",
                        wire = "u8",
                        show = "name",
                        proto = "string",
                        names = {
                            [1] = "withheld",
                            [2] = "silent",
                            [3] = "staged",
                            [4] = "committed",
                            [5] = "current",
                            [6] = "confirmed",
                            [7] = "refused",
                            [8] = "reverted",
                        },
                    },
                    { name = "version", wire = "u32", show = "%d", proto = "uint" },
                    { name = "left", wire = "u8", show = "%d", proto = "uint" },
                    {
                        name = "path",
                        wire = "path",
                        show = "path",
                        proto = "string",
                        limit = 64,
                    },
                    {
                        name = "verdict",
                        wire = "ascii",
                        show = "suffix",
                        proto = "string",
                        limit = 16,
                    },
                    {
                        name = "reason",
                        wire = "utf8",
                        show = "suffix",
                        proto = "string",
                        limit = 48,
                    },
                },
                line = "REPORT {outcome} v{version} tag {tag} #{seq}, path {path}, left {left}{verdict}{reason}",
            },
            [10] = {
                name = "REPORT_ACK",
                class = 2,
                head = "report seq",
                fields = { { name = "seq", wire = "u16", show = "%d", proto = "uint" } },
                line = "REPORT_ACK #{seq}",
            },
        },
    },
}
local CONNECTORS = { "front", "back", "left", "right" }
local PROGRAMS = {}
-- END GENERATED

local FRAME_KINDS = LAYOUT.kind_names
local TRANSFER = LAYOUT.transfer
-- byte 0's top bits of the operator's control frames (dh2rt.wire.operator.CONTROL_FAMILY)
local CONTROL_FAMILY = 0
local SEGMENTS = LAYOUT.segment_names
local INT_MIN, INT_MAX = -2147483648, 2147483647
local TWO32 = 4294967296

-- ------------------------------------------------------------------------------------------
-- Bits and bytes (arithmetic, so any Lua version Wireshark embeds will do)

-- The ``width``-bit field at ``shift`` of ``value``.
local function bits(value, field)
    return math.floor(value / 2 ^ field.shift) % 2 ^ field.width
end

-- Bit ``index`` (0 = most significant bit of the first byte) of a byte string.
local function bit_at(data, index)
    local byte = data:byte(math.floor(index / 8) + 1)
    return math.floor(byte / 2 ^ (7 - index % 8)) % 2
end

-- ``count`` fields of ``width`` bits, MSB first, from bit ``start`` of a byte string.
local function unpack_fields(data, start, count, width)
    local values = {}
    for i = 0, count - 1 do
        local v = 0
        for j = 0, width - 1 do
            v = v * 2 + bit_at(data, start + i * width + j)
        end
        values[#values + 1] = v
    end
    return values
end

local function tohex(data)
    return (data:gsub(".", function(c) return string.format("%02x", c:byte()) end))
end

-- CRC-32/ISO-HDLC (binascii.crc32): reflected polynomial 0xEDB88320, init and final XOR all ones.
local bitlib = bit32 or bit
local CRC_TABLE = {}
for i = 0, 255 do
    local c = i
    for _ = 1, 8 do
        if c % 2 == 1 then
            c = bitlib.bxor(math.floor(c / 2), 0xEDB88320) % TWO32
        else
            c = math.floor(c / 2)
        end
    end
    CRC_TABLE[i] = c
end

local function crc32(data)
    local crc = 0xFFFFFFFF
    for i = 1, #data do
        local index = bitlib.bxor(crc % 256, data:byte(i)) % 256
        crc = bitlib.bxor(CRC_TABLE[index], math.floor(crc / 256)) % TWO32
    end
    return bitlib.bxor(crc, 0xFFFFFFFF) % TWO32
end

-- COBS decoding as dh2rt.wire.serial_framing.cobs_decode: the bytes, or nil and the reason.
local function cobs_decode(data)
    local out = {}
    local pos, n = 1, #data
    while pos <= n do
        local code = data:byte(pos)
        if code == 0 then
            return nil, "COBS: zero byte inside a frame"
        end
        local stop = pos + code
        if stop > n + 1 then
            return nil, "COBS: code byte runs past the end of the frame"
        end
        local block = data:sub(pos + 1, stop - 1)
        if block:find("\0", 1, true) then
            return nil, "COBS: zero byte inside a frame"
        end
        out[#out + 1] = block
        pos = stop
        if code ~= 0xFF and pos <= n then
            out[#out + 1] = "\0"
        end
    end
    return table.concat(out)
end

-- ------------------------------------------------------------------------------------------
-- Programs and connectors

local KNOWN_DIGESTS = {}
for i, program in ipairs(PROGRAMS) do
    KNOWN_DIGESTS[program.digest] = i
end

local function connector_name(index)
    if index == 0 then
        return "0"
    end
    return CONNECTORS[index] or ("#" .. index)
end

-- ------------------------------------------------------------------------------------------
-- The protocol and its fields

local dh2rt = Proto("dh2rt", "dh2rt hormone frames")

local F = {
    kind = ProtoField.string("dh2rt.kind", "Kind (hormone, routed, keepalive, hello, transfer, control, segment, error)"),
    medium = ProtoField.string("dh2rt.medium", "Medium (can, serial)"),
    link = ProtoField.uint32("dh2rt.link", "Link id"),
    side = ProtoField.uint8("dh2rt.side", "Side that sent it"),
    text = ProtoField.string("dh2rt.text", "Text (as dh2rt dump prints it)"),
    error = ProtoField.string("dh2rt.error", "Error"),
    lost = ProtoField.bool("dh2rt.lost", "Lost on the link"),
    -- CAN arbitration id
    can_kind = ProtoField.uint8("dh2rt.can.kind", "Kind (id)", base.DEC, FRAME_KINDS),
    segment = ProtoField.uint8("dh2rt.can.segment", "Segment", base.DEC, SEGMENTS),
    seq = ProtoField.uint8("dh2rt.can.seq", "Seq (the train's tag plus the segment's index)"),
    segment_frames = ProtoField.string("dh2rt.can.segment_frames", "Reassembled from frames"),
    train_tag = ProtoField.uint8("dh2rt.can.tag", "Train tag"),
    train_check = ProtoField.uint32("dh2rt.can.check", "Train check (CRC-32)", base.HEX),
    -- link negotiation's management frames
    op = ProtoField.string("dh2rt.link.op", "Management op (CLAIM, RELEASE, HOLD)"),
    pair_tag = ProtoField.uint32("dh2rt.link.tag", "Pair tag", base.HEX),
    -- serial record
    magic = ProtoField.string("dh2rt.serial.magic", "Magic"),
    record_version = ProtoField.uint8("dh2rt.serial.version", "Record version"),
    flags = ProtoField.uint8("dh2rt.serial.flags", "Flags", base.HEX),
    flag_side = ProtoField.uint8("dh2rt.serial.flags.side", "Side", base.DEC, nil, LAYOUT.serial.flag_side),
    flag_lost = ProtoField.bool("dh2rt.serial.flags.lost", "Lost", 8, nil, LAYOUT.serial.flag_lost),
    flag_corrupted = ProtoField.bool("dh2rt.serial.flags.corrupted", "Corrupted", 8, nil, LAYOUT.serial.flag_corrupted),
    wire = ProtoField.bytes("dh2rt.serial.wire", "Wire bytes (COBS, CRC-32, 0x00)"),
    crc = ProtoField.uint32("dh2rt.serial.crc", "CRC-32", base.HEX),
    crc_status = ProtoField.string("dh2rt.serial.crc.status", "CRC-32 status"),
    -- the frame
    version = ProtoField.uint8("dh2rt.frame.version", "Wire version", base.DEC, nil,
        (2 ^ LAYOUT.header.version.width - 1) * 2 ^ LAYOUT.header.version.shift),
    frame_kind = ProtoField.uint8("dh2rt.frame.kind", "Frame kind", base.DEC, FRAME_KINDS,
        (2 ^ LAYOUT.header.kind.width - 1) * 2 ^ LAYOUT.header.kind.shift),
    sender = ProtoField.uint8("dh2rt.sender", "Sent through connector", base.DEC, CONNECTORS,
        (2 ^ LAYOUT.header.sender.width - 1) * 2 ^ LAYOUT.header.sender.shift),
    hop_count = ProtoField.uint8("dh2rt.hops", "Hop count"),
    index = ProtoField.uint8("dh2rt.hormone.index", "Hormone index"),
    hormone = ProtoField.string("dh2rt.hormone", "Hormone"),
    arg = ProtoField.string("dh2rt.arg", "Argument"),
    arg_bytes = ProtoField.bytes("dh2rt.arg.bytes", "Argument bytes (no program to read them)"),
    content = ProtoField.string("dh2rt.content", "Content"),
    path = ProtoField.string("dh2rt.path", "Path (sent through>received at, newest first)"),
    route_length = ProtoField.uint8("dh2rt.route.length", "Route length"),
    route = ProtoField.string("dh2rt.route", "Route still to go"),
    keepalive_seq = ProtoField.uint8("dh2rt.keepalive.seq", "Keep-alive sequence number"),
    digest = ProtoField.bytes("dh2rt.hello.digest", "Program digest"),
    hello_version = ProtoField.uint32("dh2rt.hello.version", "Program version"),
    program = ProtoField.string("dh2rt.program", "Program naming the hormones"),
    -- transfer frames: the header; the messages' fields are in TF
    family = ProtoField.uint8("dh2rt.transfer.family", "Frame family", base.DEC, nil,
        (2 ^ LAYOUT.header.version.width - 1) * 2 ^ LAYOUT.header.version.shift),
    class = ProtoField.uint8("dh2rt.transfer.class", "Class (CAN priority)", base.DEC, nil,
        (2 ^ LAYOUT.header.kind.width - 1) * 2 ^ LAYOUT.header.kind.shift),
    message = ProtoField.string("dh2rt.transfer.message", "Transfer message (OFFER, REQUEST, SEGMENT, ...)"),
    -- control frames (the operator's): the message and its counter
    control_message = ProtoField.string("dh2rt.control.message", "Control message (INJECT, PAUSE, STATE, ...)"),
    control_counter = ProtoField.string("dh2rt.control.counter", "Command counter"),
}

-- A field of each name the transfer messages' fields have (dh2rt.transfer.NAME), of the type
-- the generator chose (one name, one type).
local PROTO_FIELDS = {
    uint = function(abbr, label) return ProtoField.uint32(abbr, label) end,
    hex = function(abbr, label) return ProtoField.uint32(abbr, label, base.HEX) end,
    bool = function(abbr, label) return ProtoField.bool(abbr, label) end,
    bytes = function(abbr, label) return ProtoField.bytes(abbr, label) end,
    string = function(abbr, label) return ProtoField.string(abbr, label) end,
}
local TF = {}
for _, message in pairs(TRANSFER.messages) do
    for _, field in ipairs(message.fields) do
        if TF[field.name] == nil then
            local label = "Transfer " .. field.name:gsub("_", " ")
            TF[field.name] = PROTO_FIELDS[field.proto]("dh2rt.transfer." .. field.name, label)
        end
    end
end

local field_list = {}
for _, fields in ipairs({ F, TF }) do
    for _, field in pairs(fields) do
        field_list[#field_list + 1] = field
    end
end
dh2rt.fields = field_list

local E = {
    error = ProtoExpert.new("dh2rt.error.expert", "dh2rt frame does not decode", expert.group.MALFORMED,
        expert.severity.ERROR),
    lost = ProtoExpert.new("dh2rt.lost.expert", "Lost on the link (never delivered)", expert.group.SEQUENCE,
        expert.severity.WARN),
}
dh2rt.experts = { E.error, E.lost }

local can_id_field = Field.new("can.id")
local can_xtd_field = Field.new("can.flags.xtd")

-- ------------------------------------------------------------------------------------------
-- State: what the first dissection of a frame learnt, kept per frame number so that any later
-- one (Wireshark's GUI dissects a frame again when it is clicked) shows the same. The first
-- dissection is the one with no entry yet, not the one with pinfo.visited unset: `tshark -2`
-- without a filter marks frames visited that its first pass never dissected.

local state = {}

local function reset()
    state = {
        frames = {},   -- frame number -> what its first dissection decided (program, payload, ...)
        programs = {}, -- "medium:link:side" -> index in PROGRAMS its last Hello named
        partial = {},  -- "link:side" -> a CAN payload being reassembled
        ends = {},     -- "link:side" -> true: a CAN link end that sent a dh2rt frame
    }
end
reset()
dh2rt.init = reset

-- ------------------------------------------------------------------------------------------
-- Decoding one frame (FrameCodec.decode), filling the tree; returns a hop as dump has it:
-- { kind, sender, text, path, route, error, digest }

local Decode = {}
Decode.__index = Decode

local function decode_error(message)
    error({ dh2rt = message }, 0)
end

-- A reader over one frame's bytes (a Tvb) that adds what it reads to a subtree.
function Decode.new(tvb, tree, program)
    local self = setmetatable({}, Decode)
    self.tvb, self.tree, self.program = tvb, tree, program
    self.data = tvb:len() > 0 and tvb:range(0):raw() or ""
    self.count = #CONNECTORS
    return self
end

function Decode:range(pos, length)
    return self.tvb:range(pos, length)
end

function Decode:unpack(pos, count, what)
    local width = LAYOUT.connector_bits
    local nbytes = math.ceil(count * width / 8)
    if pos + nbytes > #self.data then
        decode_error(string.format("frame: %s truncated (%d connectors need %d bytes)", what, count, nbytes))
    end
    local values = unpack_fields(self.data, pos * 8, count, width)
    for i = count * width, nbytes * 8 - 1 do
        if bit_at(self.data, pos * 8 + i) ~= 0 then
            decode_error(string.format("frame: %s padding bits are not zero", what))
        end
    end
    for _, v in ipairs(values) do
        if v < 1 or v > self.count then
            decode_error(string.format("frame: %s connector %d is outside 1..%d", what, v, self.count))
        end
    end
    return values, pos + nbytes, nbytes
end

function Decode:varint(pos)
    local result, scale = 0, 1
    for _ = 1, 5 do
        if pos >= #self.data then
            decode_error("varint truncated")
        end
        local b = self.data:byte(pos + 1)
        pos = pos + 1
        result = result + (b % 128) * scale
        if b < 128 then
            if b == 0 and scale > 1 then
                decode_error("varint not in its shortest form")
            end
            return result, pos
        end
        scale = scale * 128
    end
    decode_error("varint longer than 5 bytes")
end

-- Vocabulary.decode_content: name, argument texts, the offset after the content.
function Decode:content(pos)
    if pos >= #self.data then
        decode_error("hormone content: no bytes")
    end
    local index = self.data:byte(pos + 1)
    self.tree:add(F.index, self:range(pos, 1))
    local spec = self.program.hormones[index]
    if spec == nil then
        decode_error(string.format("hormone content: unknown hormone index %d", index))
    end
    self.tree:add(F.hormone, self:range(pos, 1), spec.name)
    pos = pos + 1
    local args = {}
    for _, param in ipairs(spec.params) do
        if pos >= #self.data then
            decode_error(string.format("hormone %s: content truncated at parameter %s", spec.name, param.name))
        end
        local start, value = pos, nil
        if param.domain ~= nil then
            local atom = self.data:byte(pos + 1)
            pos = pos + 1
            value = param.domain[atom + 1]
            if value == nil then
                decode_error(string.format("hormone %s.%s: atom index %d out of range", spec.name, param.name, atom))
            end
        else
            local raw
            raw, pos = self:varint(pos)
            local n = raw % 2 == 0 and raw / 2 or -(raw + 1) / 2
            if n < INT_MIN or n > INT_MAX then
                decode_error(string.format("hormone %s.%s: integer out of range", spec.name, param.name))
            end
            value = string.format("%d", n)
        end
        self.tree:add(F.arg, self:range(start, pos - start), value):set_text("Argument " .. param.name .. ": " .. value)
        args[#args + 1] = value
    end
    return spec.name, args, pos
end

-- Whether a route (its length, then its connectors) at ``at`` ends the frame exactly.
function Decode:route_fits(at)
    local ok, _, after = pcall(self.unpack, self, at + 1, self.data:byte(at + 1), "route")
    return ok and after == #self.data
end

-- Without a program: the content is what the path (and route) leave; its arguments unread.
-- A routed hormone's content ends where a valid route follows the path to the frame's end.
function Decode:raw_content(pos, kind, path_bytes)
    local length = #self.data - pos - path_bytes
    if kind == LAYOUT.kinds.routed then
        length = nil
        for l = 1, #self.data - pos - path_bytes - 1 do
            if self:route_fits(pos + l + path_bytes) then
                length = l
                break
            end
        end
        if length == nil then
            decode_error("hormone frame: no program names its hormones, and content and route do not part")
        end
    end
    if length < 1 then
        decode_error("hormone content: no bytes")
    end
    local index = self.data:byte(pos + 1)
    self.tree:add(F.index, self:range(pos, 1))
    local name = "#" .. index
    self.tree:add(F.hormone, self:range(pos, 1), name)
    local args = {}
    if length > 1 then
        self.tree:add(F.arg_bytes, self:range(pos + 1, length - 1))
        args[1] = "0x" .. tohex(self.data:sub(pos + 2, pos + length))
    end
    return name, args, pos + length
end

local function names(connectors)
    local out = {}
    for i, c in ipairs(connectors) do
        out[i] = connector_name(c)
    end
    return out
end

function Decode:hormone(kind)
    if #self.data < 2 then
        decode_error("hormone frame: truncated before the hop count")
    end
    local hops = self.data:byte(2)
    self.tree:add(F.hop_count, self:range(1, 1))
    local name, args, pos
    if self.program ~= nil then
        name, args, pos = self:content(2)
    else
        local path_bytes = math.ceil(2 * hops * LAYOUT.connector_bits / 8)
        name, args, pos = self:raw_content(2, kind, path_bytes)
    end
    local text = name .. "(" .. table.concat(args, ", ") .. ")"
    self.tree:add(F.content, self:range(2, pos - 2), text)
    local flat, after, nbytes = self:unpack(pos, 2 * hops, "path")
    local path = {}
    for i = 1, #flat, 2 do
        path[#path + 1] = connector_name(flat[i]) .. ">" .. connector_name(flat[i + 1])
    end
    if nbytes > 0 then
        self.tree:add(F.path, self:range(pos, nbytes), table.concat(path, " "))
    end
    pos = after
    local route
    if kind == LAYOUT.kinds.routed then
        if pos >= #self.data then
            decode_error(string.format("hormone frame %s: truncated before the route length", name))
        end
        local count = self.data:byte(pos + 1)
        self.tree:add(F.route_length, self:range(pos, 1))
        route, after, nbytes = self:unpack(pos + 1, count, "route")
        if nbytes > 0 then
            self.tree:add(F.route, self:range(pos + 1, nbytes), table.concat(names(route), " "))
        end
        pos = after
    end
    if pos ~= #self.data then
        decode_error(string.format("hormone frame %s: %d trailing byte(s)", name, #self.data - pos))
    end
    return { kind = FRAME_KINDS[kind], text = text, path = path, route = route }
end

function Decode:frame()
    local data = self.data
    if #data == 0 then
        decode_error("frame: no bytes")
    end
    local head = data:byte(1)
    local version = bits(head, LAYOUT.header.version)
    if version == TRANSFER.family then
        return self:transfer()
    end
    if version == CONTROL_FAMILY then
        return self:control()
    end
    local header = self:range(0, 1)
    self.tree:add(F.version, header)
    if version ~= LAYOUT.wire_version then
        decode_error(string.format("frame: wire version %d, expected %d", version, LAYOUT.wire_version))
    end
    local kind = bits(head, LAYOUT.header.kind)
    self.tree:add(F.frame_kind, header)
    local sender = bits(head, LAYOUT.header.sender)
    self.tree:add(F.sender, header)
    if sender < 1 or sender > self.count then
        decode_error(string.format("frame: sender connector %d is outside 1..%d", sender, self.count))
    end
    local hop
    if kind == LAYOUT.kinds.keepalive then
        if #data ~= LAYOUT.keepalive_bytes then
            decode_error(string.format("keep-alive frame: %d bytes, expected %d", #data, LAYOUT.keepalive_bytes))
        end
        self.tree:add(F.keepalive_seq, self:range(1, 1))
        hop = { kind = "keepalive", text = "#" .. data:byte(2) }
    elseif kind == LAYOUT.kinds.hello then
        local short = 1 + LAYOUT.hello_digest_bytes
        if #data < short or #data > short + 5 then
            decode_error(string.format("hello frame: %d bytes, expected %d (or %d..%d with a version)",
                #data, short, short + 1, short + 5))
        end
        self.tree:add(F.digest, self:range(1, LAYOUT.hello_digest_bytes))
        if #data > short then
            -- the program's version: a canonical unsigned LEB128 u32 filling the rest
            -- (dh2rt.wire.transfer.decode_hello)
            local value, scale = 0, 1
            local done = false
            for i = short + 1, #data do
                local b = data:byte(i)
                value = value + (b % 128) * scale
                scale = scale * 128
                if b < 128 then
                    if i ~= #data then
                        decode_error(string.format("hello frame: %d trailing byte(s) after the version", #data - i))
                    end
                    if b == 0 and i > short + 1 then
                        decode_error("hello frame: the version is not in its shortest form")
                    end
                    if value > 4294967295 then
                        decode_error(string.format("hello frame: version %d exceeds 32 bits", value))
                    end
                    done = true
                    break
                end
            end
            if not done then
                decode_error("hello frame: the version is cut short")
            end
            self.tree:add(F.hello_version, self:range(short, #data - short), value)
        end
        local digest = tohex(data:sub(2, short))
        local text = digest
        if #PROGRAMS > 0 and KNOWN_DIGESTS[digest] == nil then
            text = text .. " (a program this capture does not carry)"
        end
        hop = { kind = "hello", text = text, digest = digest }
    else
        hop = self:hormone(kind)
    end
    hop.sender = connector_name(sender)
    return hop
end

-- ------------------------------------------------------------------------------------------
-- Transfer frames (dh2rt.wire.transfer.decode), read field by field as LAYOUT.transfer (dump's
-- table) lists them; shown with the line dump prints (tools.transfer_view.transfer_text)

local FIXED_BYTES = { u8 = 1, u16 = 2, u32 = 4, flag = 1, image = TRANSFER.image_bytes }

-- Whether a byte string is UTF-8 as Python's strict decoder takes it (no overlong forms, no
-- surrogates, nothing past U+10FFFF).
local function is_utf8(text)
    local i, n = 1, #text
    while i <= n do
        local c = text:byte(i)
        local extra, low, high = 0, 0x80, 0xBF
        if c < 0x80 then
            extra = 0
        elseif c >= 0xC2 and c <= 0xDF then
            extra = 1
        elseif c == 0xE0 then
            extra, low = 2, 0xA0
        elseif c == 0xED then
            extra, high = 2, 0x9F
        elseif c >= 0xE1 and c <= 0xEF then
            extra = 2
        elseif c == 0xF0 then
            extra, low = 3, 0x90
        elseif c >= 0xF1 and c <= 0xF3 then
            extra = 3
        elseif c == 0xF4 then
            extra, high = 3, 0x8F
        else
            return false
        end
        for k = 1, extra do
            local b = text:byte(i + k)
            local lo, hi = k == 1 and low or 0x80, k == 1 and high or 0xBF
            if b == nil or b < lo or b > hi then
                return false
            end
        end
        i = i + 1 + extra
    end
    return true
end

-- The codec's checks that span fields, run after the field named: MESSAGE.FIELD.
local TRANSFER_CHECKS = {
    ["OFFER.held"] = function(what, v)
        local size = v.segment_size
        local segments = size >= 1 and math.ceil(v.length / size) or 0
        if v.length == 0 or size < 1 or size > TRANSFER.max_segment_size or segments > 0xFFFF then
            decode_error(string.format("%s: %d bytes in segments of %d is no image", what, v.length, size))
        end
        if v.held > segments then
            decode_error(string.format("%s: %d segments held of %d", what, v.held, segments))
        end
    end,
    ["REPORT.path"] = function(what, v)
        if v.left < 1 or v.left > #v.path then
            decode_error(string.format("%s: %d hops left of a %d-hop path", what, v.left, #v.path))
        end
    end,
}

-- Take ``n`` bytes at ``pos`` for ``field`` (what the codec's reader calls it), or fail as it does.
function Decode:take(what, pos, n, field)
    if pos + n > #self.data then
        decode_error(string.format("%s: cut short in the %s at byte %d", what, field, pos))
    end
    return self.data:sub(pos + 1, pos + n)
end

-- One field of a transfer message at ``pos``: its value and its length in bytes.
function Decode:transfer_field(what, field, pos)
    local wire, data = field.wire, self.data
    if FIXED_BYTES[wire] ~= nil then
        local n = FIXED_BYTES[wire]
        if wire == "image" then
            return data:sub(pos + 1, pos + n), n
        end
        local value = self:range(pos, n):uint()
        if wire == "flag" then
            if value > 1 then
                decode_error(string.format("%s: unknown flags 0x%02x", what, value))
            end
            return value == 1, n
        end
        if field.names ~= nil and field.names[value] == nil then
            decode_error(string.format("%s: unknown %s %d", what, field.name, value))
        end
        if field.limit ~= nil and (value < 1 or value > field.limit) then
            decode_error(string.format("%s: %s %d is outside 1..%d", what, field.name, value, field.limit))
        end
        return value, n
    end
    if wire == "rest" then
        local n = #data - pos
        if n < 1 or n > field.limit then
            decode_error(string.format("%s: %d data bytes, outside 1..%d", what, n, field.limit))
        end
        return data:sub(pos + 1), n
    end
    if wire == "path" then
        local count = self:take(what, pos, 1, "path length"):byte()
        if count > field.limit then
            decode_error(string.format("%s: path of %d hops exceeds %d", what, count, field.limit))
        end
        local raw = self:take(what, pos + 1, count, "path")
        local hops = {}
        for i = 1, count do
            local sent, received = bits(raw:byte(i), TRANSFER.hop.sent), bits(raw:byte(i), TRANSFER.hop.received)
            if sent == 0 or received == 0 then
                decode_error(what .. ": a path hop names connector 0")
            end
            hops[i] = connector_name(sent) .. ">" .. connector_name(received)
        end
        return hops, 1 + count
    end
    -- text: a length byte, then ASCII (ascii) or UTF-8 (utf8)
    local n = self:take(what, pos, 1, field.name .. " length"):byte()
    if n > field.limit then
        decode_error(string.format("%s: %s of %d bytes exceeds %d", what, field.name, n, field.limit))
    end
    local text = self:take(what, pos + 1, n, field.name)
    if wire == "ascii" and text:find("[\128-\255]") then
        decode_error(string.format("%s: %s is not ASCII", what, field.name))
    end
    if not is_utf8(text) then
        decode_error(string.format("%s: %s is not UTF-8", what, field.name))
    end
    return text, 1 + n
end

-- A field's value as dump shows it (tools.transfer_view.show).
local function transfer_show(field, value)
    local how = field.show
    if how == "hex" then
        return tohex(value)
    elseif how == "name" then
        return field.names[value]
    elseif how == "count" then
        return string.format("%d", #value)
    elseif how == "path" then
        return #value > 0 and table.concat(value, " ") or "(entry point)"
    elseif how == "ms" then
        return value ~= 0 and string.format("in %.1f ms", value / 1000) or "at once"
    elseif how == "flag" then
        return value and field.text or ""
    elseif how == "suffix" then
        return value ~= "" and ", " .. value or ""
    end
    return string.format(how, value)
end

-- The header a transfer or control frame starts with (``name``: "transfer frame", "control
-- frame"), as dh2rt.wire.fields.read_header reads it: its sender connector.
function Decode:family_header(name)
    local data = self.data
    if #data < 2 then
        decode_error(string.format("%s: %d bytes, too short for a header and a type", name, #data))
    end
    local header = self:range(0, 1)
    self.tree:add(F.family, header)
    self.tree:add(F.class, header)
    self.tree:add(F.sender, header)
    local sender = bits(data:byte(1), LAYOUT.header.sender)
    if sender == 0 then
        decode_error(name .. ": sender connector 0")
    end
    return sender
end

function Decode:transfer()
    local data = self.data
    local sender = self:family_header("transfer frame")
    local message = TRANSFER.messages[data:byte(2)]
    if message == nil then
        decode_error(string.format("transfer frame: unknown message type %d", data:byte(2)))
    end
    self.tree:add(F.message, self:range(1, 1), message.name)
    local what = "transfer frame " .. message.name
    local class = bits(data:byte(1), LAYOUT.header.kind)
    if class ~= message.class then
        decode_error(string.format("%s: class %d, expected %d", what, class, message.class))
    end
    -- the fixed fields before the first of variable length, which the codec takes at once
    local fixed = 0
    for _, field in ipairs(message.fields) do
        if FIXED_BYTES[field.wire] == nil then
            break
        end
        fixed = fixed + FIXED_BYTES[field.wire]
    end
    self:take(what, 2, fixed, message.head)
    local pos, values, shown = 2, {}, {}
    for _, field in ipairs(message.fields) do
        local value, n = self:transfer_field(what, field, pos)
        values[field.name] = value
        shown[field.name] = transfer_show(field, value)
        local check = TRANSFER_CHECKS[message.name .. "." .. field.name]
        if check ~= nil then
            check(what, values)
        end
        local item = self:range(pos, n)
        if field.proto == "bytes" then
            self.tree:add(TF[field.name], item)
        elseif field.proto == "string" then
            local text = field.wire == "path" and shown[field.name] or field.names and field.names[value] or value
            self.tree:add(TF[field.name], item, text)
        else
            self.tree:add(TF[field.name], item, value)
        end
        pos = pos + n
    end
    if pos ~= #data then
        decode_error(string.format("%s: %d trailing byte(s)", what, #data - pos))
    end
    local text = message.line:gsub("{([%w_]+)}", shown)
    return { kind = "transfer", text = text, sender = connector_name(sender) }
end

-- ------------------------------------------------------------------------------------------
-- Control frames (dh2rt.wire.operator.decode): the operator's signed commands and the
-- modules' answers (the third family, top bits 0), shown with the line dump prints
-- (tools.control_view.control_text). Counters are u64 (Wireshark's UInt64); the varints of a
-- status are exact up to 2^53.

local CONTROL_TYPES = {
    [1] = { name = "INJECT", class = 1, signed = true },
    [2] = { name = "PAUSE", class = 1, signed = true },
    [3] = { name = "RESUME", class = 1, signed = true },
    [4] = { name = "STATE", class = 2, signed = true },
    [5] = { name = "WATCH", class = 2, signed = true },
    [16] = { name = "STATE_REPLY", class = 2 },
    [17] = { name = "REFUSED", class = 2 },
    [18] = { name = "WATCHED", class = 3 },
}
local REFUSAL_REASONS = { "BAD_SIGNATURE", "UNTRUSTED_KEY", "REPLAYED", "NO_ROUTE", "WRONG_PROGRAM", "NO_CONTROL" }
local CONTROL_MAX_PATH = 64

-- A path (n, then a byte a hop: sent << 4 | received) as dump names its hops.
function Decode:control_path(what, pos, field)
    local count = self:take(what, pos, 1, field .. " length"):byte()
    if count > CONTROL_MAX_PATH then
        decode_error(string.format("%s: %s of %d hops exceeds %d", what, field, count, CONTROL_MAX_PATH))
    end
    local raw = self:take(what, pos + 1, count, field)
    local hops = {}
    for i = 1, count do
        local b = raw:byte(i)
        local sent, received = math.floor(b / 16), b % 16
        if sent == 0 or received == 0 then
            decode_error(string.format("%s: a %s hop names connector 0", what, field))
        end
        hops[i] = connector_name(sent) .. ">" .. connector_name(received)
    end
    return hops, pos + 1 + count
end

local function control_path_text(hops)
    return #hops > 0 and table.concat(hops, " ") or "(cable's module)"
end

-- An unsigned LEB128 varint of up to 64 bits, in its shortest form.
function Decode:control_varint(what, pos, field)
    local result, scale, shift = 0, 1, 0
    while true do
        local b = self:take(what, pos, 1, field):byte()
        pos = pos + 1
        if shift >= 64 or (shift == 63 and b > 1) then
            decode_error(string.format("%s: %s does not fit 64 bits", what, field))
        end
        result = result + (b % 128) * scale
        if b < 128 then
            if b == 0 and shift > 0 then
                decode_error(string.format("%s: %s is not in its shortest form", what, field))
            end
            return result, pos
        end
        scale, shift = scale * 128, shift + 7
    end
end

-- n u8, then n zig-zag varints (sensors, variables): only read, dump does not show them.
function Decode:control_values(what, pos, name)
    local n = self:take(what, pos, 1, "number of " .. name):byte()
    pos = pos + 1
    for _ = 1, n do
        local _value
        _value, pos = self:control_varint(what, pos, "a value of " .. name)
    end
    return pos
end

-- An INJECT's hormone: named by the program its digest names, when the dissector carries it.
function Decode:control_hormone(digest, content, pos)
    local known = KNOWN_DIGESTS[tohex(digest)]
    if known ~= nil then
        local saved = self.program
        self.program = PROGRAMS[known]
        local ok, name, args, after = pcall(self.content, self, pos)
        self.program = saved
        if ok and after == pos + #content then
            return #args > 0 and (name .. "(" .. table.concat(args, ", ") .. ")") or name
        end
    end
    return "hormone " .. tohex(content) .. " of program " .. tohex(digest)
end

function Decode:control()
    local data = self.data
    if #data >= 2 and data:byte(2) >= 64 and data:byte(2) < 128 then
        return self:motion()
    end
    local sender = self:family_header("control frame")
    local kind = data:byte(2)
    local message = CONTROL_TYPES[kind]
    if message == nil then
        decode_error(string.format("control frame: unknown message type %d", kind))
    end
    self.tree:add(F.control_message, self:range(1, 1), message.name)
    local what = "control frame " .. message.name
    local class = bits(data:byte(1), LAYOUT.header.kind)
    if class ~= message.class then
        decode_error(string.format("%s: class %d, expected %d", what, class, message.class))
    end
    local text
    if message.signed then
        local hops = self:take(what, 2, 1, "hops"):byte()
        local key = self:take(what, 3, 16, "counter and key id")
        local counter = tostring(self:range(3, 8):uint64())
        self.tree:add(F.control_counter, self:range(3, 8), counter)
        text = string.format("%s #%s key %s hops %d", message.name, counter, tohex(key:sub(9, 16)), hops)
        local pos = 19
        if message.name == "INJECT" then
            local digest = self:take(what, pos, 6, "program digest")
            local route
            route, pos = self:control_path(what, pos + 6, "route")
            local n = self:take(what, pos, 1, "content length"):byte()
            if n == 0 then
                decode_error(what .. ": empty hormone content")
            end
            local content = self:take(what, pos + 1, n, "content")
            text = text .. ", " .. self:control_hormone(digest, content, pos + 1) .. " at " .. control_path_text(route)
            pos = pos + 1 + n
        elseif message.name == "STATE" then
            local route
            route, pos = self:control_path(what, pos, "route")
            text = text .. ", at " .. control_path_text(route)
        elseif message.name == "WATCH" then
            local fields = self:take(what, pos, 3, "watch cycles and hormones")
            local cycles, n = fields:byte(1) * 256 + fields:byte(2), fields:byte(3)
            if cycles == 0 or n > 1 then
                decode_error(string.format("%s: %d cycles of %d hormone(s): not a watch", what, cycles, n))
            end
            pos = pos + 3
            local watched = "every hormone"
            if n == 1 then
                watched = "hormone #" .. self:take(what, pos, 1, "hormone index"):byte()
                pos = pos + 1
            end
            text = string.format("%s, %s for %d cycles", text, watched, cycles)
        end
        self:take(what, pos, 64, "signature")
        pos = pos + 64
        if pos ~= #data then
            decode_error(string.format("%s: %d trailing byte(s)", what, #data - pos))
        end
    elseif message.name == "WATCHED" then
        self:take(what, 2, 8, "counter")
        local counter = tostring(self:range(2, 8):uint64())
        self.tree:add(F.control_counter, self:range(2, 8), counter)
        local cycle, pos = self:control_varint(what, 10, "cycle")
        local at = self:take(what, pos, 1, "connector"):byte()
        if at > 15 then
            decode_error(string.format("%s: connector %d is outside 0..15", what, at))
        end
        local n = self:take(what, pos + 1, 1, "frame length"):byte()
        if n == 0 then
            decode_error(what .. ": an empty frame")
        end
        local frame = self:take(what, pos + 2, n, "frame")
        text = string.format("WATCHED #%s cycle %.0f at %s: %s", counter, cycle,
            at > 0 and connector_name(at) or "(injected)", tohex(frame))
        if pos + 2 + n ~= #data then
            decode_error(string.format("%s: %d trailing byte(s)", what, #data - pos - 2 - n))
        end
    else
        local head = self:take(what, 2, 9, "counter and hops left")
        local counter = tostring(self:range(2, 8):uint64())
        self.tree:add(F.control_counter, self:range(2, 8), counter)
        local left = head:byte(9)
        local path, pos = self:control_path(what, 11, "path")
        if left > #path then
            decode_error(string.format("%s: %d hops left of a %d-hop path", what, left, #path))
        end
        local where = string.format("#%s from %s, left %d", counter, control_path_text(path), left)
        if message.name == "REFUSED" then
            local reason = self:take(what, pos, 1, "reason"):byte()
            if REFUSAL_REASONS[reason] == nil then
                decode_error(string.format("%s: unknown reason %d", what, reason))
            end
            text = "REFUSED " .. where .. ": " .. REFUSAL_REASONS[reason]
            pos = pos + 1
        else
            self:take(what, pos, 6, "program digest")
            local type_index = self:take(what, pos + 6, 1, "type index"):byte()
            local flags = self:take(what, pos + 7, 1, "flags"):byte()
            if flags > 1 then
                decode_error(string.format("%s: unknown flags 0x%02x", what, flags))
            end
            local timer, cycle
            timer, pos = self:control_varint(what, pos + 8, "LocalTimer")
            cycle, pos = self:control_varint(what, pos, "cycle")
            local n = self:take(what, pos, 1, "number of connectors"):byte()
            local raw = self:take(what, pos + 1, n, "ConnectorStatus")
            local statuses = {}
            for i = 1, n do
                statuses[i] = string.format("%d", raw:byte(i))
            end
            pos = self:control_values(what, pos + 1 + n, "sensors")
            pos = self:control_values(what, pos, "variables")
            local receptors = self:take(what, pos, 1, "number of receptors"):byte()
            self:take(what, pos + 1, receptors, "receptor statuses")
            pos = pos + 1 + receptors
            text = string.format("STATE_REPLY %s: type %d, LocalTimer %.0f, cycle %.0f, status %s%s", where,
                type_index, timer, cycle, table.concat(statuses, ","), flags == 1 and ", paused" or "")
        end
        if pos ~= #data then
            decode_error(string.format("%s: %d trailing byte(s)", what, #data - pos))
        end
    end
    return { kind = "control", text = text, sender = connector_name(sender) }
end

-- ------------------------------------------------------------------------------------------
-- Motion frames (dh2rt.wire.motion.decode): what a docking chain says to itself, control
-- types 64..127, shown with the line dump prints (tools.control_view.motion_text).

local MOTION_TYPES = { [64] = "ASK", [65] = "ANGLES", [66] = "TARGETS", [67] = "END", [68] = "SET_OFF" }
local MOTION_MAX_MARKERS = 32
local MOTION_CLASS = 2
local MOTION_MAX_JOINTS = 8

-- An i16 of hundredths of a degree at ``pos``, in degrees as Python's ``:g`` shows it.
function Decode:motion_degrees(pos)
    local raw = self.data:byte(pos + 1) * 256 + self.data:byte(pos + 2)
    if raw >= 32768 then
        raw = raw - 65536
    end
    return string.format("%g", raw / 100)
end

function Decode:motion_count(what, pos)
    local n = self:take(what, pos, 1, "number of targets"):byte()
    if n < 1 or n > MOTION_MAX_JOINTS then
        decode_error(string.format("%s: %d targets; a frame carries 1..%d", what, n, MOTION_MAX_JOINTS))
    end
    return n
end

function Decode:motion()
    local data = self.data
    local sender = self:family_header("motion frame")
    local kind = data:byte(2)
    local name = MOTION_TYPES[kind]
    if name == nil then
        decode_error(string.format("control frame: message type %d is reserved (docking motion, not yet defined)", kind))
    end
    self.tree:add(F.control_message, self:range(1, 1), name)
    local what = "motion frame " .. name
    local class = bits(data:byte(1), LAYOUT.header.kind)
    if class ~= MOTION_CLASS then
        decode_error(string.format("%s: class %d, expected %d", what, class, MOTION_CLASS))
    end
    local head = self:take(what, 2, 5, "motion, seq and hops")
    local motion, seq, at = head:byte(1) * 256 + head:byte(2), head:byte(3) * 256 + head:byte(4), head:byte(5)
    self.tree:add(F.control_counter, self:range(4, 2), tostring(seq))
    local route, pos = self:control_path(what, 7, "route")
    if #route == 0 then
        decode_error(what .. ": an empty route (the asker is no member of its motion)")
    end
    if at > #route then
        decode_error(string.format("%s: hops %d beyond a %d-hop route", what, at, #route))
    end
    local where = table.concat(route, " ")
    local text
    if name == "ANGLES" then
        local head = self:take(what, pos, 3, "module and number of angles")
        local module, n = head:byte(1) * 256 + head:byte(2), head:byte(3)
        if n < 1 or n > MOTION_MAX_JOINTS then
            decode_error(string.format("%s: %d angles; a frame carries 1..%d", what, n, MOTION_MAX_JOINTS))
        end
        self:take(what, pos + 3, 2 * n, "angles")
        local angles = {}
        for i = 1, n do
            angles[i] = string.format("DOF%d %s", i, self:motion_degrees(pos + 1 + 2 * i))
        end
        pos = pos + 3 + 2 * n
        local count = self:take(what, pos, 1, "number of links"):byte()
        if count > 15 then
            decode_error(string.format("%s: %d links; a module has at most 15 connectors", what, count))
        end
        local raw = self:take(what, pos + 1, count, "links")
        local links, highest = {}, 0
        for i = 1, count do
            links[i] = tostring(raw:byte(i))
            highest = math.max(highest, raw:byte(i))
        end
        if highest > 15 then
            decode_error(string.format("%s: a link names connector %d, beyond 15", what, highest))
        end
        pos = pos + 1 + count
        text = string.format("ANGLES motion %d #%d from %s, left %d: module %d, %s, links %s", motion, seq, where, at,
            module, table.concat(angles, ", "), count > 0 and table.concat(links, ",") or "none")
    else
        text = string.format("%s motion %d #%d to %s, hops %d", name, motion, seq, where, at)
        if name == "TARGETS" then
            local n = self:motion_count(what, pos)
            pos = pos + 1
            local dofs, targets, ascending = {}, {}, true
            for i = 1, n do
                local pair = self:take(what, pos, 3, "targets")
                dofs[i] = pair:byte(1)
                ascending = ascending and (i == 1 or dofs[i] > dofs[i - 1])
                targets[i] = string.format("DOF%d %s", dofs[i] + 1, self:motion_degrees(pos + 1))
                pos = pos + 3
            end
            if not ascending or dofs[n] >= MOTION_MAX_JOINTS then
                decode_error(string.format("%s: target DOF indices [%s] are not strictly ascending below %d", what,
                    table.concat(dofs, ", "), MOTION_MAX_JOINTS))
            end
            text = text .. ": " .. table.concat(targets, ", ")
        elseif name == "SET_OFF" then
            local head = self:take(what, pos, 3, "target module and connector")
            local target, connector = head:byte(1) * 256 + head:byte(2), head:byte(3)
            if connector < 1 or connector > 15 then
                decode_error(string.format("%s: target connector %d, not 1..15", what, connector))
            end
            pos = pos + 3
            local lists, seen, twice = {}, {}, false
            for _, list in ipairs({ "body", "others" }) do
                local n = self:take(what, pos, 1, "number of markers in " .. list):byte()
                local raw = self:take(what, pos + 1, 2 * n, "markers in " .. list)
                local markers = {}
                for i = 1, n do
                    markers[i] = raw:byte(2 * i - 1) * 256 + raw:byte(2 * i)
                    twice = twice or seen[markers[i]] ~= nil
                    seen[markers[i]] = true
                end
                lists[list] = markers
                pos = pos + 1 + 2 * n
            end
            local body, others = lists.body, lists.others
            if #body < 1 or #body > MOTION_MAX_MARKERS then
                decode_error(string.format("%s: %d markers in body; 1..%d", what, #body, MOTION_MAX_MARKERS))
            end
            if #others > MOTION_MAX_MARKERS then
                decode_error(string.format("%s: %d markers in others; at most %d", what, #others, MOTION_MAX_MARKERS))
            end
            if twice then
                decode_error(string.format("%s: a marker named twice in body [%s] and others [%s]", what,
                    table.concat(body, ", "), table.concat(others, ", ")))
            end
            text = string.format("%s: to module %d connector %d, body %s, others %s", text, target, connector,
                table.concat(body, ","), #others > 0 and table.concat(others, ",") or "none")
        end
    end
    if pos ~= #data then
        decode_error(string.format("%s: %d trailing byte(s)", what, #data - pos))
    end
    return { kind = "control", text = text, sender = connector_name(sender) }
end

-- Decode ``tvb`` as one frame; a frame that does not decode gives an error hop.
local function decode_frame(tvb, tree, program)
    local reader = Decode.new(tvb, tree, program)
    local ok, result = pcall(Decode.frame, reader)
    if ok then
        return result
    end
    if type(result) == "table" and result.dh2rt then
        return { kind = "error", text = "", error = result.dh2rt }
    end
    error(result, 0)
end

-- ------------------------------------------------------------------------------------------
-- Showing a hop: the tree's summary fields and the Info column, as Hop.describe

local function describe(medium, link, side, hop)
    local label = medium == "serial" and "ir  " or "link"
    local line
    if link == nil then
        line = string.format("%s    ? side ?  %-9s %s", label, hop.kind, hop.text)
    else
        -- a management frame names a link, no side
        local shown = side == nil and "-" or string.format("%d", side)
        line = string.format("%s %4d side %s  %-9s %s", label, link, shown, hop.kind, hop.text)
    end
    if hop.sender then
        line = line .. " via " .. hop.sender
    end
    if hop.path and #hop.path > 0 then
        line = line .. "  path " .. table.concat(hop.path, " ")
    end
    if hop.route and #hop.route > 0 then
        line = line .. "  route " .. table.concat(names(hop.route), " ")
    end
    if hop.lost then
        line = line .. "  !! lost on the link (never delivered)"
    end
    if hop.error then
        line = line .. "  !! " .. hop.error
    end
    return line
end

local function show(tvb, pinfo, root, medium, link, side, hop)
    local line = describe(medium, link, side, hop)
    pinfo.cols.protocol:set("DH2RT")
    pinfo.cols.info:set(line)
    root:append_text(": " .. line)
    root:add(F.kind, hop.kind):set_generated()
    root:add(F.text, hop.text):set_generated()
    if hop.lost then
        root:add(F.lost, true):set_generated()
        root:add_proto_expert_info(E.lost)
    end
    if hop.error then
        root:add(F.error, hop.error):set_generated()
        root:add_proto_expert_info(E.error, hop.error)
    end
end

-- Decode a frame's payload with the program that names its end's hormones: its last
-- Hello's, else the first. Chosen the first time the frame is dissected and kept in
-- ``remembered``; a Hello then switches its end to the program it names.
local function dissect_payload(payload_tvb, root, remembered, medium, link, side)
    local key = medium .. ":" .. link .. ":" .. side
    local first = remembered.program == nil
    if first then
        remembered.program = state.programs[key] or 1
    end
    local program = PROGRAMS[remembered.program]
    local frame_tree = root:add(dh2rt, payload_tvb:range(0), string.format("dh2rt frame (%d bytes)", payload_tvb:len()))
    if program ~= nil then
        frame_tree:add(F.program, program.name):set_generated()
    end
    local hop = decode_frame(payload_tvb, frame_tree, program)
    if first and hop.kind == "hello" then
        state.programs[key] = KNOWN_DIGESTS[hop.digest] or 1
    end
    return hop
end

-- ------------------------------------------------------------------------------------------
-- CAN: the heuristic, the arbitration id, reassembly (as can_frames.Reassembler)

local function parse_can_id(id)
    local f = LAYOUT.can
    return {
        kind = bits(id, f.kind),
        segment = bits(id, f.segment),
        seq = bits(id, f.seq),
        link = bits(id, f.link),
        side = bits(id, f.side),
    }
end

-- Whether a CAN frame is dh2rt's: an extended id whose kind the frame's first byte repeats
-- with the wire version (or the transfer or control family), or a later segment from a link end that sent
-- dh2rt frames.
local function is_dh2rt(tvb, id)
    if id.segment == LAYOUT.segments.single or id.segment == LAYOUT.segments.first then
        if tvb:len() < 1 then
            return false
        end
        local head = tvb:range(0, 1):uint()
        local version = bits(head, LAYOUT.header.version)
        local family = version == LAYOUT.wire_version or version == TRANSFER.family or version == CONTROL_FAMILY
        return family and bits(head, LAYOUT.header.kind) == id.kind
    end
    return state.ends[id.link .. ":" .. id.side] == true
end

-- The little-endian number in a byte string.
local function little_endian(data)
    local value = 0
    for i = #data, 1, -1 do
        value = value * 256 + data:byte(i)
    end
    return value
end

-- One frame into the reassembler: the whole payload (or nil); whether a payload was lost
-- (true) or refused by its check ("refused"); the frame numbers a whole payload came in.
local function reassemble(id, data, number)
    local S, T = LAYOUT.segments, LAYOUT.train
    local key = id.link .. ":" .. id.side
    local part = state.partial[key]
    if id.segment == S.single or id.segment == S.first then
        state.partial[key] = nil
        local lost = part ~= nil
        if id.segment == S.single then
            return data, lost, nil
        end
        if #data == 0 then
            return nil, true, nil
        end
        state.partial[key] = {
            kind = id.kind, tag = id.seq, next_seq = (id.seq + 1) % T.seq_modulus,
            chunks = { data }, frames = { number }, length = #data,
        }
        return nil, lost, nil
    end
    if part == nil or id.seq ~= part.next_seq or id.kind ~= part.kind or #data == 0 then
        state.partial[key] = nil
        return nil, true, nil
    end
    part.chunks[#part.chunks + 1] = data
    part.frames[#part.frames + 1] = number
    part.next_seq = (id.seq + 1) % T.seq_modulus
    part.length = part.length + #data
    if id.segment == S.last then
        state.partial[key] = nil
        local body = table.concat(part.chunks)
        local payload = body:sub(1, -T.check_bytes - 1)
        local check = little_endian(body:sub(-T.check_bytes))
        if #body <= T.check_bytes or crc32(string.char(part.tag) .. payload) ~= check then
            return nil, "refused", nil
        end
        return payload, false, part.frames, part.tag, check
    end
    if part.length >= T.max_train then
        state.partial[key] = nil
        return nil, true, nil
    end
    return nil, false, nil
end

-- What the first dissection learns of a CAN frame, or nil for a frame that is not dh2rt's.
local function first_look_can(tvb, pinfo, id)
    if not is_dh2rt(tvb, id) then
        return nil
    end
    state.ends[id.link .. ":" .. id.side] = true
    local data = tvb:len() > 0 and tvb:range(0):raw() or ""
    local payload, lost, frames, tag, check = reassemble(id, data, pinfo.number)
    return { payload = payload, lost = lost, frames = frames, tag = tag, check = check }
end

local function add_can_id(tree, tvb, id)
    local here = tvb:range(0, 0)
    tree:add(F.medium, here, "can"):set_generated()
    tree:add(F.link, here, id.link):set_generated()
    tree:add(F.side, here, id.side):set_generated()
    tree:add(F.can_kind, here, id.kind):set_generated()
    tree:add(F.segment, here, id.segment):set_generated()
    tree:add(F.seq, here, id.seq):set_generated()
end

-- A management frame of link negotiation (dh2rt.wire.negotiation.decode_bus): its op, link
-- id and pair tag, or an error hop as dump has it.
local function management_hop(tvb, root)
    local M = LAYOUT.management
    local function fail(message)
        return { kind = "error", text = "", error = "link negotiation: " .. message }, nil
    end
    if tvb:len() ~= M.bytes then
        return fail(string.format("management frame of %d bytes; it must be %d", tvb:len(), M.bytes))
    end
    local op = tvb:range(0, 1):uint()
    local name = M.ops[op]
    if name == nil then
        return fail(string.format("management op %d is unknown", op))
    end
    local link = tvb:range(1, 3):uint()
    local tag = tvb:range(4, 4):uint()
    if link < M.first_link_id or link > M.last_link_id then
        return fail(string.format("management frame names link id %d, outside %d..%d", link, M.first_link_id,
            M.last_link_id))
    end
    if tag == 0 then
        return fail("management frame with tag 0 (no pair has it)")
    end
    root:add(F.op, tvb:range(0, 1), name)
    root:add(F.link, tvb:range(1, 3))
    root:add(F.pair_tag, tvb:range(4, 4))
    return { kind = "link", text = string.format("%s tag %08x", name, tag) }, link
end

local function dissect_management(tvb, pinfo, tree)
    local root = tree:add(dh2rt, tvb())
    root:add(F.medium, tvb:range(0, 0), "can"):set_generated()
    local hop, link = management_hop(tvb, root)
    show(tvb, pinfo, root, "can", link, nil, hop)
    return true
end

local function dissect_can(tvb, pinfo, tree)
    local xtd = can_xtd_field()
    local raw_id = can_id_field()
    if xtd == nil or not xtd.value or raw_id == nil then
        return false
    end
    if raw_id.value == LAYOUT.management.id then
        return dissect_management(tvb, pinfo, tree)
    end
    local id = parse_can_id(raw_id.value)
    local remembered = state.frames[pinfo.number]
    if remembered == nil then
        remembered = first_look_can(tvb, pinfo, id) or false
        state.frames[pinfo.number] = remembered
    end
    if not remembered then
        return false
    end
    local root = tree:add(dh2rt, tvb:range(0))
    add_can_id(root, tvb, id)
    local hop
    if remembered.payload ~= nil then
        local payload_tvb = tvb
        if remembered.frames ~= nil then
            payload_tvb = ByteArray.new(remembered.payload, true):tvb("Reassembled dh2rt frame")
            local numbers = {}
            for i, n in ipairs(remembered.frames) do
                numbers[i] = tostring(n)
            end
            root:add(F.segment_frames, table.concat(numbers, ", ")):set_generated()
            root:add(F.train_tag, remembered.tag):set_generated()
            root:add(F.train_check, remembered.check):set_generated()
        end
        hop = dissect_payload(payload_tvb, root, remembered, "can", id.link, id.side)
        if remembered.frames ~= nil and hop.kind ~= "error" then
            hop.text = hop.text .. " (reassembled)"
        end
    elseif remembered.lost == "refused" then
        hop = { kind = "error", text = "", error = string.format("segment %d: %s", id.seq, LAYOUT.train.refused) }
    elseif remembered.lost then
        hop = { kind = "error", text = "", error = string.format("segment %d out of order: lost", id.seq) }
    else
        hop = { kind = "segment", text = "#" .. id.seq }
    end
    show(tvb, pinfo, root, "can", id.link, id.side, hop)
    return true
end

-- ------------------------------------------------------------------------------------------
-- Serial links: the record header, COBS, the CRC-32

local function serial_header(tvb, root)
    local L = LAYOUT.serial
    root:add(F.medium, tvb:range(0, 0), "serial"):set_generated()
    root:add(F.magic, tvb:range(0, #L.magic))
    root:add(F.record_version, tvb:range(#L.magic, 1))
    local flags = tvb:range(#L.magic + 1, 1)
    local flag_tree = root:add(F.flags, flags)
    flag_tree:add(F.flag_side, flags)
    flag_tree:add(F.flag_lost, flags)
    flag_tree:add(F.flag_corrupted, flags)
    local link_range = tvb:range(#L.magic + 2, L.header_bytes - #L.magic - 2)
    root:add(F.link, link_range)
    local value = flags:uint()
    local side = math.floor(value / L.flag_side) % 2
    root:add(F.side, flags, side)
    return link_range:uint(), side, math.floor(value / L.flag_lost) % 2 == 1
end

-- The payload of a serial frame's wire bytes, or nil and the reason (as decode_serial).
local function serial_payload(wire, tree)
    local crc_bytes = LAYOUT.serial.crc_bytes
    if wire:sub(-1) == string.char(LAYOUT.serial.delimiter) then
        wire = wire:sub(1, -2)
    end
    local body, reason = cobs_decode(wire)
    if body == nil then
        return nil, reason
    end
    if #body <= crc_bytes then
        return nil, string.format("serial frame of %d bytes is too short for a payload and CRC", #body)
    end
    local payload = body:sub(1, -crc_bytes - 1)
    local stored = 0
    for i = #body, #body - crc_bytes + 1, -1 do
        stored = stored * 256 + body:byte(i)
    end
    local good = crc32(payload) == stored
    local decoded = ByteArray.new(body, true):tvb("COBS-decoded dh2rt frame")
    tree:add(F.crc, decoded:range(#payload, crc_bytes), stored)
    tree:add(F.crc_status, good and "good" or "bad"):set_generated()
    if not good then
        return nil, "serial frame failed its CRC"
    end
    return decoded:range(0, #payload):tvb()
end

function dh2rt.dissector(tvb, pinfo, tree)
    local L = LAYOUT.serial
    if tvb:len() < L.header_bytes or tvb:range(0, #L.magic):string() ~= L.magic
        or tvb:range(#L.magic, 1):uint() ~= L.version then
        return 0
    end
    local root = tree:add(dh2rt, tvb:range(0))
    local link, side, lost = serial_header(tvb, root)
    local remembered = state.frames[pinfo.number] or {}
    state.frames[pinfo.number] = remembered
    local hop
    local wire = ""
    if tvb:len() > L.header_bytes then
        wire = tvb:range(L.header_bytes):raw()
        root:add(F.wire, tvb:range(L.header_bytes))
    end
    local payload, reason = serial_payload(wire, root)
    if payload == nil then
        local what = lost and "lost, and its bytes are corrupted" or "corrupted on the link"
        hop = { kind = "error", text = "", error = what .. ": " .. reason }
    else
        hop = dissect_payload(payload, root, remembered, "serial", link, side)
        hop.lost = lost
    end
    show(tvb, pinfo, root, "serial", link, side, hop)
    return tvb:len()
end

dh2rt:register_heuristic("can", dissect_can)
DissectorTable.get("wtap_encap"):add(wtap_encaps and wtap_encaps.USER0 or wtap.USER0, dh2rt)
