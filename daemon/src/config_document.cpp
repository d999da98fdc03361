#include "slicestation/daemon/config_document.hpp"

#include <toml++/toml.h>

#include <cmath>
#include <fstream>
#include <sstream>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;
using core::Result;

Result<nlohmann::json> parseDocument(std::string_view text, DocumentFormat format,
                                     const std::string& origin) {
    if (format == DocumentFormat::Json) {
        try {
            return nlohmann::json::parse(text);
        } catch (const nlohmann::json::parse_error& e) {
            return makeError(ErrorCode::InvalidArgument,
                             origin + ": not valid JSON at byte " + std::to_string(e.byte) + ": " + e.what());
        }
    }
    try {
        const toml::table table = toml::parse(text, origin);
        // toml++ renders JSON; one JSON tree keeps a single validator for both formats.
        std::ostringstream os;
        os << toml::json_formatter{table};
        return nlohmann::json::parse(os.str());
    } catch (const toml::parse_error& e) {
        const auto& where = e.source().begin;
        return makeError(ErrorCode::InvalidArgument,
                         origin + ":" + std::to_string(where.line) + ":" + std::to_string(where.column) +
                             ": not valid TOML: " + std::string(e.description()));
    } catch (const nlohmann::json::exception& e) {
        return makeError(ErrorCode::InvalidArgument, origin + ": cannot convert TOML: " + e.what());
    }
}

Result<nlohmann::json> readDocument(const std::filesystem::path& file) {
    std::error_code ec;
    if (!std::filesystem::exists(file, ec))
        return makeError(ErrorCode::NotFound, file.string() + ": no such file");
    std::ifstream in(file, std::ios::binary);
    if (!in) return makeError(ErrorCode::IoError, file.string() + ": cannot open", errno);
    std::ostringstream ss;
    ss << in.rdbuf();
    if (in.bad()) return makeError(ErrorCode::IoError, file.string() + ": read failed", errno);
    const std::string text = ss.str();
    DocumentFormat format = DocumentFormat::Toml;
    const auto ext = file.extension().string();
    if (ext == ".json") {
        format = DocumentFormat::Json;
    } else if (ext != ".toml") {
        const auto first = text.find_first_not_of(" \t\r\n");
        if (first != std::string::npos && text[first] == '{') format = DocumentFormat::Json;
    }
    return parseDocument(text, format, file.string());
}

core::Error FieldReader::bad(const std::string& field, const std::string& what) const {
    return makeError(ErrorCode::InvalidArgument, origin_ + ": " + field + ": " + what);
}

std::string FieldReader::join(const std::string& path, const char* key) {
    return path.empty() ? std::string(key) : path + "." + key;
}

Result<double> FieldReader::number(const nlohmann::json& obj, const std::string& path, const char* key,
                                   std::optional<double> fallback, double min, double max) const {
    const std::string field = join(path, key);
    if (!obj.is_object() || !obj.contains(key)) {
        if (fallback) return *fallback;
        return bad(field, "missing");
    }
    const auto& v = obj[key];
    if (!v.is_number()) return bad(field, "expected a number, got " + v.dump());
    const double d = v.get<double>();
    if (!std::isfinite(d)) return bad(field, "expected a finite number");
    if (d < min || d > max) {
        std::ostringstream os;
        os << d << " is outside [" << min << ", " << max << "]";
        return bad(field, os.str());
    }
    return d;
}

Result<std::int64_t> FieldReader::integer(const nlohmann::json& obj, const std::string& path,
                                          const char* key, std::optional<std::int64_t> fallback,
                                          std::int64_t min, std::int64_t max) const {
    const std::string field = join(path, key);
    if (!obj.is_object() || !obj.contains(key)) {
        if (fallback) return *fallback;
        return bad(field, "missing");
    }
    const auto& v = obj[key];
    if (!v.is_number_integer()) return bad(field, "expected an integer, got " + v.dump());
    const auto i = v.get<std::int64_t>();
    if (i < min || i > max)
        return bad(field, std::to_string(i) + " is outside [" + std::to_string(min) + ", " +
                              std::to_string(max) + "]");
    return i;
}

Result<std::string> FieldReader::string(const nlohmann::json& obj, const std::string& path,
                                        const char* key, std::optional<std::string> fallback) const {
    const std::string field = join(path, key);
    if (!obj.is_object() || !obj.contains(key)) {
        if (fallback) return *fallback;
        return bad(field, "missing");
    }
    const auto& v = obj[key];
    if (!v.is_string()) return bad(field, "expected a string, got " + v.dump());
    return v.get<std::string>();
}

Result<bool> FieldReader::boolean(const nlohmann::json& obj, const std::string& path, const char* key,
                                  std::optional<bool> fallback) const {
    const std::string field = join(path, key);
    if (!obj.is_object() || !obj.contains(key)) {
        if (fallback) return *fallback;
        return bad(field, "missing");
    }
    const auto& v = obj[key];
    if (!v.is_boolean()) return bad(field, "expected true or false, got " + v.dump());
    return v.get<bool>();
}

} // namespace slicestation::daemon
