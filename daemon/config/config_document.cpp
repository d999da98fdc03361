#include "slicestation/daemon/config/config_document.hpp"

#include <toml++/toml.h>

#include <algorithm>
#include <climits>
#include <cmath>
#include <cstdint>
#include <fstream>
#include <sstream>
#include <vector>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;
using core::Result;

namespace {

core::Error tooDeep(const std::string& origin, std::size_t byte) {
    return makeError(ErrorCode::InvalidArgument,
                     origin + ": nested deeper than " + std::to_string(kMaxDocumentDepth) +
                         " levels (at byte " + std::to_string(byte) + ")");
}

// Both parsers and nlohmann's copy and dump recurse once per level, so a deep document
// (300'000 '[') overflows the stack before any field is read: the depth is counted on the bytes,
// skipping strings, before a parser sees them. Exact for JSON.
Result<void> checkJsonDepth(std::string_view text, const std::string& origin) {
    int depth = 0;
    bool inString = false;
    for (std::size_t i = 0; i < text.size(); ++i) {
        const char c = text[i];
        if (inString) {
            if (c == '\\')
                ++i;
            else if (c == '"')
                inString = false;
            continue;
        }
        if (c == '"')
            inString = true;
        else if (c == '[' || c == '{') {
            if (++depth > kMaxDocumentDepth)
                return tooDeep(origin, i);
        } else if (c == ']' || c == '}')
            --depth;
    }
    return {};
}

// TOML nests through brackets ([..], {..}) and through the parts of a dotted key or a table
// header (a.b.c = 1, [a.b.c]). Brackets are counted as in JSON; dots are counted per run between
// separators, numbers included (1.5 is one dot), which bounds a key's parts without telling keys
// from values. The exact depth is checked on the converted tree; this scan only keeps toml++ (and
// its recursive destructor) from seeing anything deep enough to exhaust the stack.
Result<void> checkTomlDepth(std::string_view text, const std::string& origin) {
    int depth = 0;
    int dots = 0;
    for (std::size_t i = 0; i < text.size(); ++i) {
        const char c = text[i];
        if (c == '"' || c == '\'') {
            const bool multi = text.substr(i, 3) == std::string_view(c == '"' ? "\"\"\"" : "'''");
            const bool escapes = c == '"';
            std::size_t j = i + (multi ? 3 : 1);
            for (; j < text.size(); ++j) {
                if (escapes && text[j] == '\\') {
                    ++j;
                    continue;
                }
                if (text[j] != c) {
                    if (!multi && text[j] == '\n')
                        break; // unterminated: the parser says so
                    continue;
                }
                if (!multi)
                    break;
                if (text.substr(j, 3) == std::string_view(c == '"' ? "\"\"\"" : "'''")) {
                    j += 2;
                    while (j + 1 < text.size() && text[j + 1] == c)
                        ++j; // """a"""" ends in a quote
                    break;
                }
            }
            i = j;
            continue;
        }
        switch (c) {
        case '#':
            while (i < text.size() && text[i] != '\n')
                ++i;
            dots = 0;
            break;
        case '.':
            if (++dots > kMaxDocumentDepth)
                return tooDeep(origin, i);
            break;
        case '[':
        case '{':
            if (++depth > kMaxDocumentDepth)
                return tooDeep(origin, i);
            dots = 0;
            break;
        case ']':
        case '}':
            --depth;
            dots = 0;
            break;
        case '=':
        case ',':
        case '\n':
            dots = 0;
            break;
        default:
            break;
        }
    }
    return {};
}

// toml++'s tree into nlohmann's, so one validator serves both formats. Direct (not through
// toml++'s JSON writer) so that a float TOML allows and JSON does not (inf, nan) is refused
// with its key, and the depth is checked exactly.
Result<nlohmann::json> tomlToJson(const toml::node& n, const std::string& path, int depth,
                                  const std::string& origin) {
    const auto bad = [&](const std::string& what) {
        return makeError(ErrorCode::InvalidArgument,
                         origin + ": " + (path.empty() ? std::string("(document)") : path) + ": " +
                             what);
    };
    if (depth > kMaxDocumentDepth)
        return bad("nested deeper than " + std::to_string(kMaxDocumentDepth) + " levels");
    if (const toml::table* t = n.as_table()) {
        nlohmann::json obj = nlohmann::json::object();
        for (const auto& [key, value] : *t) {
            const std::string k(key.str());
            auto v = tomlToJson(value, path.empty() ? k : path + "." + k, depth + 1, origin);
            if (!v)
                return v.error();
            obj[k] = std::move(*v);
        }
        return obj;
    }
    if (const toml::array* a = n.as_array()) {
        nlohmann::json arr = nlohmann::json::array();
        for (std::size_t i = 0; i < a->size(); ++i) {
            auto v = tomlToJson((*a)[i], path + "[" + std::to_string(i) + "]", depth + 1, origin);
            if (!v)
                return v.error();
            arr.push_back(std::move(*v));
        }
        return arr;
    }
    if (const auto* s = n.as_string())
        return nlohmann::json(s->get());
    if (const auto* i = n.as_integer())
        return nlohmann::json(i->get());
    if (const auto* f = n.as_floating_point()) {
        if (!std::isfinite(f->get()))
            return bad("expected a finite number");
        return nlohmann::json(f->get());
    }
    if (const auto* b = n.as_boolean())
        return nlohmann::json(b->get());
    std::ostringstream os; // dates and times, as TOML writes them
    if (const auto* d = n.as_date())
        os << *d;
    else if (const auto* t = n.as_time())
        os << *t;
    else if (const auto* dt = n.as_date_time())
        os << *dt;
    return nlohmann::json(os.str());
}

} // namespace

Result<nlohmann::json> parseDocument(std::string_view text, DocumentFormat format,
                                     const std::string& origin) {
    if (text.size() > kMaxDocumentBytes)
        return makeError(ErrorCode::InvalidArgument,
                         origin + ": " + std::to_string(text.size()) + " bytes is more than the " +
                             std::to_string(kMaxDocumentBytes) + " a document may have");
    if (format == DocumentFormat::Json) {
        if (auto d = checkJsonDepth(text, origin); !d)
            return d.error();
        try {
            return nlohmann::json::parse(text);
        } catch (const nlohmann::json::parse_error& e) {
            return makeError(ErrorCode::InvalidArgument, origin + ": not valid JSON at byte " +
                                                             std::to_string(e.byte) + ": " +
                                                             e.what());
        } catch (const nlohmann::json::exception& e) { // out_of_range 406: 1e400
            return makeError(ErrorCode::InvalidArgument, origin + ": not valid JSON: " + e.what());
        } catch (const std::exception& e) {
            return makeError(ErrorCode::InvalidArgument,
                             origin + ": cannot read JSON: " + e.what());
        }
    }
    if (auto d = checkTomlDepth(text, origin); !d)
        return d.error();
    try {
        const toml::table table = toml::parse(text, origin);
        return tomlToJson(table, "", 0, origin);
    } catch (const toml::parse_error& e) {
        const auto& where = e.source().begin;
        return makeError(ErrorCode::InvalidArgument,
                         origin + ":" + std::to_string(where.line) + ":" +
                             std::to_string(where.column) +
                             ": not valid TOML: " + std::string(e.description()));
    } catch (const std::exception& e) {
        return makeError(ErrorCode::InvalidArgument, origin + ": cannot read TOML: " + e.what());
    }
}

Result<nlohmann::json> readDocument(const std::filesystem::path& file) {
    std::error_code ec;
    if (!std::filesystem::exists(file, ec))
        return makeError(ErrorCode::NotFound, file.string() + ": no such file");
    std::ifstream in(file, std::ios::binary);
    if (!in)
        return makeError(ErrorCode::IoError, file.string() + ": cannot open", errno);
    // Read one byte past the limit: enough to refuse, without reading a huge file whole.
    std::string text(kMaxDocumentBytes + 1, '\0');
    in.read(text.data(), static_cast<std::streamsize>(text.size()));
    if (in.bad())
        return makeError(ErrorCode::IoError, file.string() + ": read failed", errno);
    text.resize(static_cast<std::size_t>(in.gcount()));
    if (text.size() > kMaxDocumentBytes)
        return makeError(ErrorCode::InvalidArgument, file.string() + ": larger than the " +
                                                         std::to_string(kMaxDocumentBytes) +
                                                         " bytes a document may have");
    DocumentFormat format = DocumentFormat::Toml;
    const auto ext = file.extension().string();
    if (ext == ".json") {
        format = DocumentFormat::Json;
    } else if (ext != ".toml") {
        const auto first = text.find_first_not_of(" \t\r\n");
        if (first != std::string::npos && text[first] == '{')
            format = DocumentFormat::Json;
    }
    return parseDocument(text, format, file.string());
}

std::string preview(const nlohmann::json& v) {
    std::string s = v.dump(-1, ' ', false, nlohmann::json::error_handler_t::replace);
    if (s.size() > 60)
        s = s.substr(0, 57) + "...";
    return s;
}

namespace {

// Optimal string alignment distance: a swap of two neighbours (slcie) counts one edit.
std::size_t editDistance(std::string_view a, std::string_view b) {
    std::vector<std::vector<std::size_t>> d(a.size() + 1, std::vector<std::size_t>(b.size() + 1));
    for (std::size_t i = 0; i <= a.size(); ++i)
        d[i][0] = i;
    for (std::size_t j = 0; j <= b.size(); ++j)
        d[0][j] = j;
    for (std::size_t i = 1; i <= a.size(); ++i)
        for (std::size_t j = 1; j <= b.size(); ++j) {
            const std::size_t cost = a[i - 1] == b[j - 1] ? 0 : 1;
            d[i][j] = std::min({d[i - 1][j] + 1, d[i][j - 1] + 1, d[i - 1][j - 1] + cost});
            if (i > 1 && j > 1 && a[i - 1] == b[j - 2] && a[i - 2] == b[j - 1])
                d[i][j] = std::min(d[i][j], d[i - 2][j - 2] + 1);
        }
    return d[a.size()][b.size()];
}

} // namespace

Result<void> FieldReader::onlyKeys(const nlohmann::json& obj, const std::string& path,
                                   std::span<const std::string_view> known) const {
    if (!obj.is_object())
        return {};
    for (const auto& [key, value] : obj.items()) {
        if (std::find(known.begin(), known.end(), std::string_view(key)) != known.end())
            continue;
        const std::string shown = key.size() > 60 ? key.substr(0, 57) + "..." : key;
        std::string_view nearest;
        std::size_t best = SIZE_MAX;
        if (key.size() <= 256) // a long key is near nothing; and the distance costs its square
            for (const auto k : known)
                if (const auto d = editDistance(key, k); d < best) {
                    best = d;
                    nearest = k;
                }
        std::string what = "unknown key \"" + shown + "\"";
        if (best <= std::max<std::size_t>(2, (nearest.size() + 2) / 3)) {
            what += "; did you mean \"" + std::string(nearest) + "\"?";
        } else {
            std::string list;
            for (const auto k : known)
                list += (list.empty() ? "" : ", ") + std::string(k);
            what += " (known: " + list + ")";
        }
        return bad(path, what);
    }
    return {};
}

core::Error FieldReader::bad(const std::string& field, const std::string& what) const {
    return makeError(ErrorCode::InvalidArgument,
                     origin_ + ": " + (field.empty() ? "" : field + ": ") + what);
}

namespace {

/// An absent key: its default when it has one, else "missing".
template <class T>
Result<T> absent(const FieldReader& rd, const std::string& field,
                 const std::optional<T>& fallback) {
    if (fallback)
        return *fallback;
    return rd.bad(field, "missing");
}

} // namespace

std::string FieldReader::join(const std::string& path, const char* key) {
    return path.empty() ? std::string(key) : path + "." + key;
}

Result<double> FieldReader::number(const nlohmann::json& obj, const std::string& path,
                                   const char* key, std::optional<double> fallback, double min,
                                   double max) const {
    const std::string field = join(path, key);
    if (!obj.is_object() || !obj.contains(key))
        return absent(*this, field, fallback);
    const auto& v = obj[key];
    if (!v.is_number())
        return bad(field, "expected a number, got " + preview(v));
    const double d = v.get<double>();
    if (!std::isfinite(d))
        return bad(field, "expected a finite number");
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
    if (!obj.is_object() || !obj.contains(key))
        return absent(*this, field, fallback);
    const auto& v = obj[key];
    if (!v.is_number_integer())
        return bad(field, "expected an integer, got " + preview(v));
    if (v.is_number_unsigned() && v.get<std::uint64_t>() > static_cast<std::uint64_t>(INT64_MAX))
        return bad(field, preview(v) + " is outside [" + std::to_string(min) + ", " +
                              std::to_string(max) + "]");
    const auto i = v.get<std::int64_t>();
    if (i < min || i > max)
        return bad(field, std::to_string(i) + " is outside [" + std::to_string(min) + ", " +
                              std::to_string(max) + "]");
    return i;
}

Result<std::string> FieldReader::string(const nlohmann::json& obj, const std::string& path,
                                        const char* key,
                                        std::optional<std::string> fallback) const {
    const std::string field = join(path, key);
    if (!obj.is_object() || !obj.contains(key))
        return absent(*this, field, fallback);
    const auto& v = obj[key];
    if (!v.is_string())
        return bad(field, "expected a string, got " + preview(v));
    return v.get<std::string>();
}

Result<bool> FieldReader::boolean(const nlohmann::json& obj, const std::string& path,
                                  const char* key, std::optional<bool> fallback) const {
    const std::string field = join(path, key);
    if (!obj.is_object() || !obj.contains(key))
        return absent(*this, field, fallback);
    const auto& v = obj[key];
    if (!v.is_boolean())
        return bad(field, "expected true or false, got " + preview(v));
    return v.get<bool>();
}

} // namespace slicestation::daemon
