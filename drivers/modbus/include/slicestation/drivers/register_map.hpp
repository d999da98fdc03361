#pragma once
/// The Modbus register map of a stage drive, as data: which registers a move, a homing, a stop
/// and an alarm reset write, and where status, position and alarm code are read.
///
/// Presets ship for the Oriental Motor AZ direct-data operation ("oriental-az", the default),
/// Leadshine RS "PR mode" ("leadshine-pr") and Applied Motion Q drives ("applied-motion-q"),
/// from docs/hardware.md; other drives are described by a TOML map file in the same format.
/// Addresses are 0-based PDU addresses. 32-bit values span two registers and are always read
/// or written in one request.

#include "slicestation/core/result.hpp"

#include <cstdint>
#include <filesystem>
#include <string>
#include <string_view>
#include <vector>

namespace slicestation::drivers {

enum class WordOrder { HighFirst, LowFirst };

/// A value written by a step: a literal or a quantity of the move, converted to drive units.
struct MapValue {
    enum class Kind { Literal, Position, Speed, Accel, Decel };
    Kind kind = Kind::Literal;
    std::int64_t literal = 0;
};

struct MapStep {
    enum class Kind {
        Write16,      ///< FC06: one register = values[0]
        Write32,      ///< FC16: two registers = values[0]
        Write32Block, ///< FC16: consecutive 32-bit values
        PulseBit,     ///< FC06: register = 1 << bit, then register = 0
    };
    Kind kind = Kind::Write16;
    std::uint16_t address = 0;
    std::vector<MapValue> values;
    int bit = 0;
};

/// Bit numbers in the status register; -1 when the drive has no such bit.
struct StatusBits {
    std::uint16_t address = 0;
    int ready = -1, moving = -1, inPosition = -1, alarm = -1, homeEnd = -1, homing = -1;
};

struct RegisterMap {
    std::string name;
    WordOrder wordOrder = WordOrder::HighFirst;
    /// Drive units per step/s, per step/s^2; when accelInverse > 0 the acceleration register
    /// holds accelInverse / (steps/s^2) instead (e.g. "ms per 1000 rpm").
    double speedScale = 1.0;
    double accelScale = 1.0;
    double accelInverse = 0.0;
    std::vector<MapStep> moveAbs, home, stop, alarmReset;
    std::uint16_t positionAddress = 0; ///< signed 32-bit feedback position, steps
    StatusBits status;
    std::uint16_t alarmAddress = 0;
    bool alarm32 = false; ///< alarm code is 32-bit (else 16-bit)
};

/// The names of the shipped presets.
std::vector<std::string> presetNames();
/// NotFound (listing the presets) for an unknown name.
core::Result<RegisterMap> presetMap(std::string_view name);
/// The TOML text of a shipped preset (the map-file format), for docs and as an example.
core::Result<std::string> presetToml(std::string_view name);
/// Parses a map in the TOML map format; InvalidArgument names the key and `origin`.
core::Result<RegisterMap> parseRegisterMap(std::string_view tomlText, std::string_view origin);
/// Reads a map file: NotFound / IoError / InvalidArgument.
core::Result<RegisterMap> loadRegisterMap(const std::filesystem::path& file);

/// The quantities of one move in steps, for the value placeholders.
struct MoveQuantities {
    std::int64_t positionSteps = 0;
    double speedStepsPerS = 0;
    double accelStepsPerS2 = 0;
};

/// Encodes a value in drive units (before splitting into registers).
std::int64_t encodeValue(const RegisterMap& map, const MapValue& v, const MoveQuantities& q);
/// Encodes a value and checks that it fits its register: a 16-bit register holds 0..65535, a
/// 32-bit one -2^31..2^32-1 (signed or unsigned, as the drive reads it). OutOfRange says which
/// quantity and value did not fit (a speed scaled beyond the register, a position beyond the
/// drive's range), so that a caller sends nothing rather than a clipped or wrapped value.
core::Result<std::int64_t> encodeChecked(const RegisterMap& map, const MapValue& v,
                                         const MoveQuantities& q, bool register32);

} // namespace slicestation::drivers
