#pragma once
/// TOML or JSON documents from outside (scan plans, the daemon part of the station file), read
/// into one JSON tree and checked field by field. Every error is InvalidArgument and names the
/// origin and the field path (`plan.toml: slides[0].sections[2].x_um: expected a number`).
///
/// Limits on every document, checked before a parser builds anything from it: at most
/// kMaxDocumentBytes, nested at most kMaxDocumentDepth levels (arrays and tables; in TOML also
/// the parts of one dotted key), numbers finite and inside a double's range.
#include "slicestation/core/result.hpp"

#include <nlohmann/json.hpp>

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <initializer_list>
#include <optional>
#include <span>
#include <string>
#include <string_view>

namespace slicestation::daemon {

enum class DocumentFormat { Toml, Json };

inline constexpr std::size_t kMaxDocumentBytes = std::size_t{4} << 20; ///< 4 MiB
inline constexpr int kMaxDocumentDepth = 64;

/// Parses `text`; \return InvalidArgument naming `origin`: a syntax error (with the parser's
/// line and column or byte), a document over kMaxDocumentBytes or nested deeper than
/// kMaxDocumentDepth, a number out of range (1e400) or not finite (TOML inf, nan). Never throws.
[[nodiscard]] core::Result<nlohmann::json>
parseDocument(std::string_view text, DocumentFormat format, const std::string& origin);
/// Reads a file; the format comes from the extension (.toml, .json), else from the first
/// non-blank character ('{' is JSON). NotFound / IoError for the file, InvalidArgument for a file
/// over kMaxDocumentBytes (not read) and everything parseDocument refuses.
[[nodiscard]] core::Result<nlohmann::json> readDocument(const std::filesystem::path& file);

/// The JSON text of `v` for an error message: at most ~60 characters, never throws.
std::string preview(const nlohmann::json& v);

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
                                       std::int64_t min = INT64_MIN,
                                       std::int64_t max = INT64_MAX) const;
    core::Result<std::string> string(const nlohmann::json& obj, const std::string& path,
                                     const char* key, std::optional<std::string> fallback) const;
    core::Result<bool> boolean(const nlohmann::json& obj, const std::string& path, const char* key,
                               std::optional<bool> fallback) const;
    /// Refuses a key of `obj` (an object) that is not in `known`: InvalidArgument
    /// `origin: path: unknown key "widht_um"; did you mean "width_um"?` (the nearest known key by
    /// edit distance, else the list of known keys). Every table of a station file and a plan
    /// goes through this, so a misspelt key is never silently ignored.
    core::Result<void> onlyKeys(const nlohmann::json& obj, const std::string& path,
                                std::span<const std::string_view> known) const;
    core::Result<void> onlyKeys(const nlohmann::json& obj, const std::string& path,
                                std::initializer_list<std::string_view> known) const {
        return onlyKeys(obj, path, std::span<const std::string_view>(known.begin(), known.size()));
    }
    /// "path.key" or "key" when path is empty.
    static std::string join(const std::string& path, const char* key);

private:
    std::string origin_;
};

} // namespace slicestation::daemon
