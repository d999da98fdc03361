#pragma once
// Private to config/: reading the station file's tables, shared by the [stage] reader
// (stage_config.cpp) and the rest (station_config.cpp).
#include "slicestation/daemon/config/config_document.hpp"
#include "slicestation/daemon/config/station_config.hpp"

#include <nlohmann/json.hpp>

#include <cmath>
#include <initializer_list>
#include <string>
#include <string_view>

namespace slicestation::daemon::station_file {

using core::ErrorCode;
using core::makeError;

using Json = nlohmann::json;

// The station file is read through parseDocument (size, depth and number limits) and
// FieldReader (strict keys); `prefix` ends in a dot ("stage.axes.x.").
struct Reader {
    std::string origin;
    FieldReader fields{origin};
    core::Error bad(const std::string& key, const std::string& what) const {
        return makeError(ErrorCode::InvalidArgument, origin + ": " + key + ": " + what);
    }
    static std::string path(const std::string& prefix) {
        return prefix.empty() ? prefix : prefix.substr(0, prefix.size() - 1);
    }
    core::Result<double> number(const Json& t, const std::string& prefix, const char* key,
                                std::optional<double> fallback, double min = -1e300,
                                double max = 1e300) const {
        if (!t.contains(key)) {
            if (fallback)
                return *fallback;
            return bad(prefix + key, "missing");
        }
        const Json& v = t[key];
        if (!v.is_number())
            return bad(prefix + key, "expected a number");
        const double d = v.get<double>();
        if (!std::isfinite(d))
            return bad(prefix + key, "expected a number");
        if (d < min)
            return bad(prefix + key, "must be >= " + shortNumber(min));
        if (d > max)
            return bad(prefix + key, "must be <= " + shortNumber(max));
        return d;
    }
    core::Result<std::string> string(const Json& t, const std::string& prefix, const char* key,
                                     std::optional<std::string> fallback) const {
        if (!t.contains(key)) {
            if (fallback)
                return *fallback;
            return bad(prefix + key, "missing");
        }
        if (!t[key].is_string())
            return bad(prefix + key, "expected a string");
        return t[key].get<std::string>();
    }
    /// Strict keys: a typo is refused with the nearest known key; a key of another driver or
    /// transport (`others`) is refused as such, not silently ignored.
    core::Result<void> keys(const Json& t, const std::string& prefix,
                            std::initializer_list<std::string_view> known,
                            std::initializer_list<std::string_view> others = {},
                            const std::string& only = "") const {
        for (const auto o : others)
            if (t.contains(o))
                return bad(prefix + std::string(o), "only for " + only);
        return fields.onlyKeys(t, path(prefix), known);
    }
    static std::string shortNumber(double v) {
        std::ostringstream os;
        os << v;
        return os.str();
    }
};

inline const Json* table(const Json& t, const char* key) {
    return t.contains(key) && t[key].is_object() ? &t[key] : nullptr;
}

inline core::Result<bool> boolean(const Json& t, const std::string& key, bool fallback,
                                  const Reader& rd) {
    if (!t.contains(key))
        return fallback;
    if (!t[key].is_boolean())
        return rd.bad(key, "expected true or false");
    return t[key].get<bool>();
}

inline core::Result<int> integer(const Reader& rd, const Json& t, const std::string& prefix,
                                 const char* key, int fallback, int min, int max) {
    auto v = rd.number(t, prefix, key, double(fallback));
    if (!v)
        return v.error();
    if (std::floor(*v) != *v || *v < min || *v > max)
        return rd.bad(prefix + key,
                      "must be an integer " + std::to_string(min) + ".." + std::to_string(max));
    return static_cast<int>(*v);
}

/// [stage], strict: the keys of its driver and transport only. stage_config.cpp
core::Result<StageConfig> parseStage(const Json& st, const Reader& rd);

} // namespace slicestation::daemon::station_file
