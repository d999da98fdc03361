#pragma once
/// TOML or JSON documents from outside (scan plans, the daemon part of the station file), read
/// into one JSON tree and checked field by field. Every error is InvalidArgument and names the
/// origin and the field path (`plan.toml: slides[0].sections[2].x_um: expected a number`).
#include "slicestation/core/result.hpp"

#include <nlohmann/json.hpp>

#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>
#include <string_view>

namespace slicestation::daemon {

enum class DocumentFormat { Toml, Json };

/// Parses `text`; \return InvalidArgument with the parser's line and column on a syntax error.
[[nodiscard]] core::Result<nlohmann::json> parseDocument(std::string_view text, DocumentFormat format,
                                                         const std::string& origin);
/// Reads a file; the format comes from the extension (.toml, .json), else from the first
/// non-blank character ('{' is JSON). NotFound / IoError for the file.
[[nodiscard]] core::Result<nlohmann::json> readDocument(const std::filesystem::path& file);

/// Reads typed fields out of a JSON object, naming `path.key` in every error.
class FieldReader {
public:
    explicit FieldReader(std::string origin) : origin_(std::move(origin)) {}
    core::Error bad(const std::string& field, const std::string& what) const;

    core::Result<double> number(const nlohmann::json& obj, const std::string& path, const char* key,
                                std::optional<double> fallback, double min = -1e300,
                                double max = 1e300) const;
    core::Result<std::int64_t> integer(const nlohmann::json& obj, const std::string& path,
                                       const char* key, std::optional<std::int64_t> fallback,
                                       std::int64_t min = INT64_MIN, std::int64_t max = INT64_MAX) const;
    core::Result<std::string> string(const nlohmann::json& obj, const std::string& path,
                                     const char* key, std::optional<std::string> fallback) const;
    core::Result<bool> boolean(const nlohmann::json& obj, const std::string& path, const char* key,
                               std::optional<bool> fallback) const;
    /// "path.key" or "key" when path is empty.
    static std::string join(const std::string& path, const char* key);

private:
    std::string origin_;
};

} // namespace slicestation::daemon
