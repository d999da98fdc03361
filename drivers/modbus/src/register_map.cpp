#include "slicestation/drivers/register_map.hpp"

#include <toml++/toml.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <iomanip>
#include <sstream>

namespace slicestation::drivers {

using core::ErrorCode;
using core::makeError;

namespace {

// Oriental Motor AZ, direct data operation (HM-60262E; OM samples sample2_2.py, sample3.py):
// the 8 x 32-bit block at 0x0058 = [op no, type (1 = absolute), position, speed Hz,
// start rate, stop rate (0.001 kHz/s = 1 Hz/s), current 0.1 %, trigger 1] starts the move.
constexpr std::string_view kOrientalAz = R"(
name = "oriental-az"
word_order = "hi_lo"
speed_scale = 1.0
accel_scale = 1.0
move_abs = [ { write32_block = 0x0058, values = [0, 1, "{pos}", "{speed}", "{accel}", "{decel}", 1000, 1] } ]
stop = [ { pulse_bit = { reg = 0x007D, bit = 5 } } ]
home = [ { pulse_bit = { reg = 0x007D, bit = 4 } } ]
alarm_reset = [ { write32 = 0x0180, value = 1 }, { write32 = 0x0180, value = 0 } ]
position = { read_s32 = 0x00CC }
status = { read_u16 = 0x007F, ready = 5, alarm = 7, moving = 13, in_position = 14, home_end = 4 }
alarm_code = { read_u32 = 0x0080 }
)";

// Leadshine RS "PR mode" (EM2RS/DM2C-RS class): PR0 at 0x6200..0x6205, trigger 0x6002.
// Unit conversion assumes 10000 pulses/rev: rpm = steps/s * 60 / 10000; accel in ms per
// 1000 rpm = (1000 * 10000 / 60 steps/s) / a * 1000.
constexpr std::string_view kLeadshinePr = R"(
name = "leadshine-pr"
word_order = "hi_lo"
speed_scale = 0.006
accel_inverse = 166666666.7
move_abs = [
  { write16 = 0x6200, value = 0x0001 },
  { write32 = 0x6201, value = "{pos}" },
  { write16 = 0x6203, value = "{speed}" },
  { write16 = 0x6204, value = "{accel}" },
  { write16 = 0x6205, value = "{decel}" },
  { write16 = 0x6002, value = 0x0010 },
]
stop = [ { write16 = 0x6002, value = 0x0040 } ]
home = [ { write16 = 0x6002, value = 0x0020 } ]
alarm_reset = [ { write16 = 0x1801, value = 0x1111 } ]
position = { read_s32 = 0x602C }
status = { read_u16 = 0x1003, alarm = 0, moving = 2, in_position = 5, home_end = 6 }
alarm_code = { read_u16 = 0x2203 }
)";

// Applied Motion Q (920-0072 Rev E): DI at 40031 (PDU 30), VE 40030 (29, rps * 240),
// AC/DE 40028/29 (27/28, rps/s * 6), opcode register 40125 (124). 20000 steps/rev assumed.
constexpr std::string_view kAppliedMotionQ = R"(
name = "applied-motion-q"
word_order = "hi_lo"
speed_scale = 0.012
accel_scale = 0.0003
move_abs = [
  { write32 = 30, value = "{pos}" },
  { write16 = 29, value = "{speed}" },
  { write16 = 27, value = "{accel}" },
  { write16 = 28, value = "{decel}" },
  { write16 = 124, value = 0x67 },
]
stop = [ { write16 = 124, value = 0xE2 } ]
home = [ { write16 = 125, value = 0x34 }, { write16 = 126, value = 0x46 }, { write16 = 124, value = 0x6E } ]
alarm_reset = [ { write16 = 124, value = 0xBA } ]
position = { read_s32 = 6 }
status = { read_u16 = 1, alarm = 9, moving = 4, in_position = 3, homing = 10 }
alarm_code = { read_u16 = 0 }
)";

struct Preset {
    std::string_view name;
    std::string_view toml;
};
constexpr Preset kPresets[] = {
    {"oriental-az", kOrientalAz},
    {"leadshine-pr", kLeadshinePr},
    {"applied-motion-q", kAppliedMotionQ},
};

core::Error bad(std::string_view origin, const std::string& key, const std::string& what) {
    return makeError(ErrorCode::InvalidArgument,
                     std::string(origin) + ": key '" + key + "': " + what);
}

core::Result<std::uint16_t> address(const toml::node* n, std::string_view origin,
                                    const std::string& key) {
    if (!n || !n->is_integer())
        return bad(origin, key, "expected an integer register address");
    const auto v = n->as_integer()->get();
    if (v < 0 || v > 0xFFFF)
        return bad(origin, key, "register address outside 0..0xFFFF");
    return static_cast<std::uint16_t>(v);
}

core::Result<MapValue> value(const toml::node* n, std::string_view origin, const std::string& key) {
    if (n && n->is_integer())
        return MapValue{MapValue::Kind::Literal, n->as_integer()->get()};
    if (n && n->is_string()) {
        const std::string s = n->as_string()->get();
        if (s == "{pos}")
            return MapValue{MapValue::Kind::Position, 0};
        if (s == "{speed}")
            return MapValue{MapValue::Kind::Speed, 0};
        if (s == "{accel}")
            return MapValue{MapValue::Kind::Accel, 0};
        if (s == "{decel}")
            return MapValue{MapValue::Kind::Decel, 0};
        return bad(origin, key,
                   "unknown placeholder '" + s + "' (use {pos}, {speed}, {accel}, {decel})");
    }
    return bad(origin, key, "expected an integer or a placeholder string");
}

/// A literal must fit the register it is written to (0..65535; 32-bit: signed or unsigned).
core::Result<void> literalFits(const MapValue& v, bool register32, std::string_view origin,
                               const std::string& key) {
    if (v.kind != MapValue::Kind::Literal)
        return {};
    const std::int64_t lo = register32 ? -2147483648LL : 0, hi = register32 ? 4294967295LL : 65535;
    if (v.literal < lo || v.literal > hi)
        return bad(origin, key,
                   std::to_string(v.literal) + " does not fit a " + (register32 ? "32" : "16") +
                       "-bit register (" + std::to_string(lo) + ".." + std::to_string(hi) + ")");
    return {};
}

core::Result<std::vector<MapStep>> steps(const toml::table& t, const char* name,
                                         std::string_view origin, bool required) {
    std::vector<MapStep> out;
    const toml::node* n = t.get(name);
    if (!n) {
        if (required)
            return bad(origin, name, "missing");
        return out;
    }
    const toml::array* arr = n->as_array();
    if (!arr || arr->empty())
        return bad(origin, name, "expected a non-empty array of steps");
    for (std::size_t i = 0; i < arr->size(); ++i) {
        const std::string key = std::string(name) + "[" + std::to_string(i) + "]";
        const toml::table* st = arr->get(i)->as_table();
        if (!st)
            return bad(origin, key, "expected an inline table");
        MapStep step;
        if (st->contains("write16") || st->contains("write32")) {
            const bool w32 = st->contains("write32");
            step.kind = w32 ? MapStep::Kind::Write32 : MapStep::Kind::Write16;
            auto a = address(st->get(w32 ? "write32" : "write16"), origin, key);
            if (!a)
                return a.error();
            step.address = *a;
            auto v = value(st->get("value"), origin, key + ".value");
            if (!v)
                return v.error();
            if (auto fits = literalFits(*v, w32, origin, key + ".value"); !fits)
                return fits.error();
            step.values.push_back(*v);
        } else if (st->contains("write32_block")) {
            step.kind = MapStep::Kind::Write32Block;
            auto a = address(st->get("write32_block"), origin, key);
            if (!a)
                return a.error();
            step.address = *a;
            const toml::array* vals = st->get("values") ? st->get("values")->as_array() : nullptr;
            if (!vals || vals->empty() || vals->size() > 61)
                return bad(origin, key + ".values", "expected 1..61 values");
            for (std::size_t j = 0; j < vals->size(); ++j) {
                auto v = value(vals->get(j), origin, key + ".values[" + std::to_string(j) + "]");
                if (!v)
                    return v.error();
                if (auto fits =
                        literalFits(*v, true, origin, key + ".values[" + std::to_string(j) + "]");
                    !fits)
                    return fits.error();
                step.values.push_back(*v);
            }
        } else if (st->contains("pulse_bit")) {
            step.kind = MapStep::Kind::PulseBit;
            const toml::table* pb = st->get("pulse_bit")->as_table();
            if (!pb)
                return bad(origin, key + ".pulse_bit", "expected { reg = ..., bit = ... }");
            auto a = address(pb->get("reg"), origin, key + ".pulse_bit.reg");
            if (!a)
                return a.error();
            step.address = *a;
            const auto bit = (*pb)["bit"].value<std::int64_t>();
            if (!bit || *bit < 0 || *bit > 15)
                return bad(origin, key + ".pulse_bit.bit", "expected 0..15");
            step.bit = static_cast<int>(*bit);
        } else {
            return bad(origin, key, "expected write16, write32, write32_block or pulse_bit");
        }
        out.push_back(std::move(step));
    }
    return out;
}

core::Result<RegisterMap> parseTable(const toml::table& t, std::string_view origin) {
    RegisterMap m;
    m.name = t["name"].value_or(std::string(origin));
    const std::string order = t["word_order"].value_or(std::string("hi_lo"));
    if (order == "hi_lo")
        m.wordOrder = WordOrder::HighFirst;
    else if (order == "lo_hi")
        m.wordOrder = WordOrder::LowFirst;
    else
        return bad(origin, "word_order", "expected \"hi_lo\" or \"lo_hi\"");
    for (auto [key, dst] :
         {std::pair{"speed_scale", &m.speedScale}, std::pair{"accel_scale", &m.accelScale},
          std::pair{"accel_inverse", &m.accelInverse}}) {
        if (const toml::node* n = t.get(key)) {
            const auto v = n->value<double>();
            if (!v || !std::isfinite(*v) || *v < 0)
                return bad(origin, key, "expected a number >= 0");
            *dst = *v;
        }
    }
    auto move = steps(t, "move_abs", origin, true);
    if (!move)
        return move.error();
    m.moveAbs = std::move(*move);
    auto stop = steps(t, "stop", origin, true);
    if (!stop)
        return stop.error();
    m.stop = std::move(*stop);
    auto home = steps(t, "home", origin, false);
    if (!home)
        return home.error();
    m.home = std::move(*home);
    auto reset = steps(t, "alarm_reset", origin, false);
    if (!reset)
        return reset.error();
    m.alarmReset = std::move(*reset);

    const toml::table* pos = t["position"].as_table();
    if (!pos)
        return bad(origin, "position", "missing table { read_s32 = address }");
    auto pa = address(pos->get("read_s32"), origin, "position.read_s32");
    if (!pa)
        return pa.error();
    m.positionAddress = *pa;

    const toml::table* st = t["status"].as_table();
    if (!st)
        return bad(origin, "status", "missing table { read_u16 = address, ... bits }");
    auto sa = address(st->get("read_u16"), origin, "status.read_u16");
    if (!sa)
        return sa.error();
    m.status.address = *sa;
    for (auto [key, dst] :
         {std::pair{"ready", &m.status.ready}, std::pair{"moving", &m.status.moving},
          std::pair{"in_position", &m.status.inPosition}, std::pair{"alarm", &m.status.alarm},
          std::pair{"home_end", &m.status.homeEnd}, std::pair{"homing", &m.status.homing}}) {
        if (const toml::node* n = st->get(key)) {
            const auto v = n->value<std::int64_t>();
            if (!v || *v < 0 || *v > 15)
                return bad(origin, std::string("status.") + key, "expected a bit 0..15");
            *dst = static_cast<int>(*v);
        }
    }
    if (m.status.moving < 0 && m.status.inPosition < 0)
        return bad(origin, "status", "needs at least one of 'moving' and 'in_position'");

    const toml::table* al = t["alarm_code"].as_table();
    if (!al)
        return bad(origin, "alarm_code", "missing table { read_u16 | read_u32 = address }");
    m.alarm32 = al->contains("read_u32");
    auto aa = address(al->get(m.alarm32 ? "read_u32" : "read_u16"), origin,
                      m.alarm32 ? "alarm_code.read_u32" : "alarm_code.read_u16");
    if (!aa)
        return aa.error();
    m.alarmAddress = *aa;
    return m;
}

} // namespace

std::vector<std::string> presetNames() {
    std::vector<std::string> out;
    for (const auto& p : kPresets)
        out.emplace_back(p.name);
    return out;
}

core::Result<std::string> presetToml(std::string_view name) {
    for (const auto& p : kPresets)
        if (p.name == name)
            return std::string(p.toml);
    std::string list;
    for (const auto& p : kPresets)
        list += (list.empty() ? "" : ", ") + std::string(p.name);
    return makeError(ErrorCode::NotFound,
                     "unknown stage preset '" + std::string(name) + "' (known: " + list + ")");
}

core::Result<RegisterMap> presetMap(std::string_view name) {
    auto text = presetToml(name);
    if (!text)
        return text.error();
    return parseRegisterMap(*text, "preset " + std::string(name));
}

core::Result<RegisterMap> parseRegisterMap(std::string_view tomlText, std::string_view origin) {
    toml::table table;
    try {
        table = toml::parse(tomlText, origin);
    } catch (const toml::parse_error& e) {
        std::ostringstream os;
        os << origin << ":" << e.source().begin.line << ": " << e.description();
        return makeError(ErrorCode::InvalidArgument, os.str());
    }
    return parseTable(table, origin);
}

core::Result<RegisterMap> loadRegisterMap(const std::filesystem::path& file) {
    std::error_code ec;
    if (!std::filesystem::exists(file, ec))
        return makeError(ErrorCode::NotFound,
                         "register map file " + file.string() + " does not exist");
    std::ifstream in(file);
    std::stringstream ss;
    ss << in.rdbuf();
    if (!in.good() && !in.eof())
        return makeError(ErrorCode::IoError, "cannot read register map file " + file.string());
    return parseRegisterMap(ss.str(), file.string());
}

std::int64_t encodeValue(const RegisterMap& map, const MapValue& v, const MoveQuantities& q) {
    switch (v.kind) {
    case MapValue::Kind::Literal:
        return v.literal;
    case MapValue::Kind::Position:
        return q.positionSteps;
    case MapValue::Kind::Speed:
        return std::llround(q.speedStepsPerS * map.speedScale);
    case MapValue::Kind::Accel:
    case MapValue::Kind::Decel:
        if (map.accelInverse > 0)
            return std::llround(map.accelInverse / std::max(q.accelStepsPerS2, 1e-9));
        return std::llround(q.accelStepsPerS2 * map.accelScale);
    }
    return 0;
}

core::Result<std::int64_t> encodeChecked(const RegisterMap& map, const MapValue& v,
                                         const MoveQuantities& q, bool register32) {
    double x = 0;
    const char* what = "value";
    switch (v.kind) {
    case MapValue::Kind::Literal:
        x = static_cast<double>(v.literal);
        break;
    case MapValue::Kind::Position:
        x = static_cast<double>(q.positionSteps);
        what = "position";
        break;
    case MapValue::Kind::Speed:
        x = q.speedStepsPerS * map.speedScale;
        what = "speed";
        break;
    case MapValue::Kind::Accel:
    case MapValue::Kind::Decel:
        x = map.accelInverse > 0 ? map.accelInverse / std::max(q.accelStepsPerS2, 1e-9)
                                 : q.accelStepsPerS2 * map.accelScale;
        what = v.kind == MapValue::Kind::Accel ? "acceleration" : "deceleration";
        break;
    }
    const double lo = register32 ? -2147483648.0 : 0.0;
    const double hi = register32 ? 4294967295.0 : 65535.0;
    if (!std::isfinite(x) || std::round(x) < lo || std::round(x) > hi) {
        std::ostringstream m;
        m << what << " " << x << " (drive units) does not fit a " << (register32 ? "32" : "16")
          << "-bit register (" << std::fixed << std::setprecision(0) << lo << ".." << hi << ")";
        return makeError(ErrorCode::OutOfRange, m.str());
    }
    return static_cast<std::int64_t>(std::llround(x));
}

} // namespace slicestation::drivers
