#include "slicestation/core/nrrd.hpp"

#include <zlib.h>

#include <algorithm>
#include <cassert>
#include <cctype>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstring>
#include <fstream>
#include <limits>
#include <map>
#include <new>
#include <optional>
#include <sstream>

namespace slicestation::core {

std::uint32_t Volume::at(int i0, int i1, int i2) const {
    assert(i0 >= 0 && i0 < sizes[0] && i1 >= 0 && i1 < sizes[1] && i2 >= 0 && i2 < sizes[2]);
    const auto s0 = static_cast<std::size_t>(sizes[0]);
    const auto s1 = static_cast<std::size_t>(sizes[1]);
    return data[static_cast<std::size_t>(i0) +
                s0 * (static_cast<std::size_t>(i1) + s1 * static_cast<std::size_t>(i2))];
}

namespace {

namespace fs = std::filesystem;

/// Largest volume accepted, in voxels: kMaxVolumeBytes of uint32 voxels.
constexpr std::uint64_t kMaxVoxels = kMaxVolumeBytes / sizeof(std::uint32_t);
/// Largest file read: a raw volume at the limit plus a generous header.
constexpr std::uint64_t kMaxFileBytes = kMaxVolumeBytes + (std::uint64_t{1} << 20);
/// Deflate expands at most 1032:1 (zlib's "technical details": a run of identical bytes is
/// coded at best as 258 bytes per 2 bits); gzip data shorter than that can not hold the volume.
constexpr std::uint64_t kMaxDeflateRatio = 1032;
/// Voxel sizes accepted from "space directions" / "spacings", micrometres.
constexpr double kMinSpacingUm = 1e-3;
constexpr double kMaxSpacingUm = 1e6;

struct Field {
    std::string value;
    int line = 0;
};

struct Header {
    std::map<std::string, Field> fields; ///< lower-case field name -> value
    std::size_t dataOffset = 0;          ///< first byte after the blank line
    bool terminated = false;             ///< a blank line ended the header
};

struct SampleType {
    int bytes = 0;
    bool isSigned = false;
};

std::string trim(std::string_view text) {
    const auto* begin =
        std::find_if_not(text.begin(), text.end(), [](unsigned char c) { return std::isspace(c); });
    const auto* end =
        std::find_if_not(text.rbegin(), std::make_reverse_iterator(begin), [](unsigned char c) {
            return std::isspace(c);
        }).base();
    return std::string(begin, end);
}

std::string lower(std::string text) {
    std::transform(text.begin(), text.end(), text.begin(),
                   [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
    return text;
}

std::vector<std::string> splitWhitespace(const std::string& text) {
    std::istringstream in(text);
    std::vector<std::string> words;
    for (std::string word; in >> word;) {
        words.push_back(word);
    }
    return words;
}

/// Collapses runs of spaces so "unsigned  int" matches "unsigned int".
std::string normaliseType(const std::string& text) {
    std::string out;
    for (const auto& word : splitWhitespace(lower(text))) {
        out += (out.empty() ? "" : " ") + word;
    }
    return out;
}

/// Integer types under all spellings of the NRRD spec, section "type".
std::optional<SampleType> integerType(const std::string& type) {
    static const std::map<std::string, SampleType> kTypes{
        {"uchar", {1, false}},
        {"unsigned char", {1, false}},
        {"uint8", {1, false}},
        {"uint8_t", {1, false}},
        {"signed char", {1, true}},
        {"int8", {1, true}},
        {"int8_t", {1, true}},
        {"ushort", {2, false}},
        {"unsigned short", {2, false}},
        {"unsigned short int", {2, false}},
        {"uint16", {2, false}},
        {"uint16_t", {2, false}},
        {"short", {2, true}},
        {"short int", {2, true}},
        {"signed short", {2, true}},
        {"signed short int", {2, true}},
        {"int16", {2, true}},
        {"int16_t", {2, true}},
        {"uint", {4, false}},
        {"unsigned int", {4, false}},
        {"uint32", {4, false}},
        {"uint32_t", {4, false}},
        {"int", {4, true}},
        {"signed int", {4, true}},
        {"int32", {4, true}},
        {"int32_t", {4, true}},
    };
    const auto it = kTypes.find(type);
    return it == kTypes.end() ? std::nullopt : std::optional<SampleType>(it->second);
}

bool isOtherNrrdType(const std::string& type) {
    static const std::vector<std::string> kOthers{
        "float",
        "double",
        "longlong",
        "long long",
        "long long int",
        "signed long long",
        "signed long long int",
        "int64",
        "int64_t",
        "ulonglong",
        "unsigned long long",
        "unsigned long long int",
        "uint64",
        "uint64_t",
        "block",
    };
    return std::find(kOthers.begin(), kOthers.end(), type) != kOthers.end();
}

std::optional<double> parseDouble(const std::string& text) {
    const std::string t = trim(text);
    double value = 0;
    const auto [end, ec] = std::from_chars(t.data(), t.data() + t.size(), value);
    if (ec != std::errc() || end != t.data() + t.size() || t.empty()) {
        return std::nullopt;
    }
    return value;
}

std::optional<long long> parseInteger(const std::string& text) {
    const std::string t = trim(text);
    long long value = 0;
    const auto [end, ec] = std::from_chars(t.data(), t.data() + t.size(), value);
    if (ec != std::errc() || end != t.data() + t.size() || t.empty()) {
        return std::nullopt;
    }
    return value;
}

class NrrdReader {
public:
    explicit NrrdReader(fs::path path) : path_(std::move(path)) {}

    Result<Volume> read() {
        auto content = readFile();
        if (!content) {
            return content.error();
        }
        content_ = std::move(content.value());
        auto header = parseHeader();
        if (!header) {
            return header.error();
        }
        header_ = std::move(header.value());
        return buildVolume();
    }

private:
    std::string where() const { return "NRRD '" + path_.string() + "'"; }

    Error fieldError(ErrorCode code, const std::string& field, const std::string& problem) const {
        const auto it = header_.fields.find(field);
        const std::string line =
            it == header_.fields.end() ? "" : " (line " + std::to_string(it->second.line) + ")";
        return makeError(code, where() + ": field '" + field + "'" + line + ": " + problem);
    }

    const std::string* field(const std::string& name) const {
        const auto it = header_.fields.find(name);
        return it == header_.fields.end() ? nullptr : &it->second.value;
    }

    Result<std::string> readFile() const {
        std::error_code ec;
        const auto status = fs::status(path_, ec);
        if (!fs::exists(status)) {
            return makeError(ErrorCode::NotFound, where() + " does not exist");
        }
        if (fs::is_directory(status)) {
            return makeError(ErrorCode::IoError, where() + " is a directory");
        }
        const std::uintmax_t fileBytes = fs::file_size(path_, ec);
        if (!ec && fileBytes > kMaxFileBytes) {
            return makeError(ErrorCode::Unsupported,
                             where() + ": file of " + std::to_string(fileBytes) +
                                 " bytes exceeds the limit of " + std::to_string(kMaxFileBytes) +
                                 " bytes for a volume");
        }
        std::ifstream in(path_, std::ios::binary);
        if (!in.is_open()) {
            const int err = errno;
            return makeError(ErrorCode::IoError,
                             "cannot open " + where() + ": " + std::strerror(err), err);
        }
        std::ostringstream bytes;
        bytes << in.rdbuf();
        if (in.bad()) {
            return makeError(ErrorCode::IoError, "cannot read " + where());
        }
        std::string text = std::move(bytes).str();
        if (text.empty()) {
            return makeError(ErrorCode::IoError, where() + " is empty");
        }
        return text;
    }

    Result<Header> parseHeader() const {
        Header header;
        std::size_t pos = 0;
        int lineNumber = 0;
        while (pos < content_.size()) {
            const std::size_t newline = content_.find('\n', pos);
            const std::size_t end = newline == std::string::npos ? content_.size() : newline;
            std::string_view line(content_.data() + pos, end - pos);
            pos = newline == std::string::npos ? content_.size() : newline + 1;
            ++lineNumber;
            if (!line.empty() && line.back() == '\r') {
                line.remove_suffix(1);
            }
            if (lineNumber == 1) {
                if (line.size() != 8 || line.substr(0, 7) != "NRRD000" || line[7] < '1' ||
                    line[7] > '5') {
                    return makeError(ErrorCode::InvalidArgument,
                                     where() + ": not a NRRD file (first line must be "
                                               "NRRD0001..NRRD0005)");
                }
                continue;
            }
            if (line.empty()) {
                if (newline != std::string::npos) {
                    header.terminated = true;
                    header.dataOffset = pos;
                }
                break;
            }
            if (line.front() == '#') {
                continue;
            }
            const std::size_t fieldSep = line.find(": ");
            const std::size_t keySep = line.find(":=");
            if (keySep != std::string_view::npos &&
                (fieldSep == std::string_view::npos || keySep < fieldSep)) {
                continue; // key/value pair: free-form metadata
            }
            if (fieldSep == std::string_view::npos) {
                return makeError(ErrorCode::InvalidArgument,
                                 where() + ": line " + std::to_string(lineNumber) +
                                     ": expected 'field: value', got '" + std::string(line) + "'");
            }
            const std::string name = lower(trim(line.substr(0, fieldSep)));
            const std::string value = trim(line.substr(fieldSep + 2));
            if (!header.fields.emplace(name, Field{value, lineNumber}).second) {
                return makeError(ErrorCode::InvalidArgument,
                                 where() + ": line " + std::to_string(lineNumber) + ": field '" +
                                     name + "' given twice");
            }
        }
        return header;
    }

    /// Lengths of the "space directions" vectors, e.g. "(50,0,0) (0,50,0) none".
    Result<std::array<double, 3>> parseSpaceDirections(const std::string& text) const {
        std::array<double, 3> spacing{};
        std::size_t axis = 0;
        std::size_t pos = 0;
        const auto bad = [&](const std::string& why) {
            return fieldError(ErrorCode::InvalidArgument, "space directions",
                              why + " in '" + text + "'");
        };
        while (true) {
            while (pos < text.size() && std::isspace(static_cast<unsigned char>(text[pos]))) {
                ++pos;
            }
            if (pos >= text.size()) {
                break;
            }
            if (axis == 3) {
                return bad("more than 3 vectors");
            }
            if (text.compare(pos, 4, "none") == 0) {
                spacing[axis++] = 0;
                pos += 4;
                continue;
            }
            if (text[pos] != '(') {
                return bad("expected '(' or 'none'");
            }
            const std::size_t close = text.find(')', pos);
            if (close == std::string::npos) {
                return bad("missing ')'");
            }
            double squares = 0;
            std::istringstream components(text.substr(pos + 1, close - pos - 1));
            int count = 0;
            for (std::string component; std::getline(components, component, ',');) {
                const auto value = parseDouble(component);
                if (!value || !std::isfinite(*value)) {
                    return bad("component '" + trim(component) + "' is not a number");
                }
                squares += *value * *value;
                ++count;
            }
            if (count == 0) {
                return bad("empty vector");
            }
            const double length = std::sqrt(squares);
            if (!std::isfinite(length) || length > kMaxSpacingUm ||
                (length > 0 && length < kMinSpacingUm)) {
                return bad("vector length " + std::to_string(length) + " is outside " +
                           spacingRange());
            }
            spacing[axis++] = length;
            pos = close + 1;
        }
        if (axis != 3) {
            return bad("expected 3 vectors, got " + std::to_string(axis));
        }
        return spacing;
    }

    static std::string spacingRange() {
        std::ostringstream os;
        os << "[" << kMinSpacingUm << ", " << kMaxSpacingUm << "] um";
        return os.str();
    }

    Result<std::array<double, 3>> parseSpacings(const std::string& text) const {
        const auto words = splitWhitespace(text);
        std::array<double, 3> spacing{};
        if (words.size() != 3) {
            return fieldError(ErrorCode::InvalidArgument, "spacings",
                              "expected 3 values, got '" + text + "'");
        }
        for (std::size_t i = 0; i < 3; ++i) {
            const auto value = parseDouble(words[i]);
            if (!value) {
                return fieldError(ErrorCode::InvalidArgument, "spacings",
                                  "'" + words[i] + "' is not a number");
            }
            spacing[i] = std::isfinite(*value) ? std::abs(*value) : 0.0; // "nan": unknown
            if (spacing[i] > kMaxSpacingUm || (spacing[i] > 0 && spacing[i] < kMinSpacingUm)) {
                return fieldError(ErrorCode::InvalidArgument, "spacings",
                                  "'" + words[i] + "' is outside " + spacingRange());
            }
        }
        return spacing;
    }

    Result<std::vector<std::uint8_t>> inflateData(std::size_t expectedBytes) const {
        const std::size_t compressedBytes = content_.size() - header_.dataOffset;
        // gzip and zlib wrappers add at most a few dozen bytes; 64 more covers both.
        if (expectedBytes / kMaxDeflateRatio > compressedBytes + 64) {
            return makeError(ErrorCode::IoError,
                             where() + ": gzip data of " + std::to_string(compressedBytes) +
                                 " bytes cannot hold the " + std::to_string(expectedBytes) +
                                 " bytes that 'sizes' and 'type' call for (truncated file or "
                                 "wrong sizes)");
        }
        // Grown as data arrives, so that a stream ending early never cost the full size.
        constexpr std::size_t kFirstChunk = std::size_t{16} << 20;
        std::vector<std::uint8_t> out(std::min(expectedBytes, kFirstChunk));
        z_stream stream{};
        // 15 + 32: accept gzip and zlib headers alike.
        if (inflateInit2(&stream, 15 + 32) != Z_OK) {
            return makeError(ErrorCode::Internal, where() + ": zlib inflateInit2 failed");
        }
        struct End {
            z_stream& s;
            ~End() { inflateEnd(&s); }
        } end{stream};

        const auto* in = reinterpret_cast<const Bytef*>(content_.data() + header_.dataOffset);
        std::size_t inLeft = content_.size() - header_.dataOffset;
        std::size_t outDone = 0;
        std::array<Bytef, 16> excess{}; // receives data beyond the expected size
        int rc = Z_OK;
        while (rc != Z_STREAM_END) {
            if (stream.avail_in == 0 && inLeft > 0) {
                const auto chunk = static_cast<uInt>(
                    std::min<std::size_t>(inLeft, std::numeric_limits<uInt>::max()));
                stream.next_in = const_cast<Bytef*>(in); // zlib's API is not const-correct
                stream.avail_in = chunk;
                in += chunk;
                inLeft -= chunk;
            }
            if (outDone == out.size() && out.size() < expectedBytes) {
                out.resize(std::min(expectedBytes, 2 * out.size()));
            }
            const bool full = outDone == out.size();
            Bytef* target = full ? excess.data() : out.data() + outDone;
            const std::size_t room = full ? excess.size()
                                          : std::min<std::size_t>(out.size() - outDone,
                                                                  std::numeric_limits<uInt>::max());
            stream.next_out = target;
            stream.avail_out = static_cast<uInt>(room);
            rc = inflate(&stream, Z_NO_FLUSH);
            const std::size_t produced = room - stream.avail_out;
            if (full && produced > 0) {
                return makeError(ErrorCode::IoError, where() + ": gzip data holds more than the " +
                                                         std::to_string(expectedBytes) +
                                                         " bytes that 'sizes' and 'type' call for");
            }
            outDone += full ? 0 : produced;
            if (rc == Z_NEED_DICT || rc == Z_DATA_ERROR || rc == Z_STREAM_ERROR) {
                return makeError(ErrorCode::IoError,
                                 where() + ": corrupt gzip data (zlib: " +
                                     (stream.msg != nullptr ? stream.msg : "data error") + ")");
            }
            if (rc == Z_MEM_ERROR) {
                return makeError(ErrorCode::IoError, where() + ": out of memory inflating data");
            }
            if (rc == Z_BUF_ERROR && stream.avail_in == 0 && inLeft == 0) {
                return makeError(ErrorCode::IoError, where() + ": gzip data is truncated (got " +
                                                         std::to_string(outDone) + " of " +
                                                         std::to_string(expectedBytes) + " bytes)");
            }
        }
        if (outDone != expectedBytes) {
            return makeError(ErrorCode::IoError, where() + ": gzip data holds " +
                                                     std::to_string(outDone) +
                                                     " bytes, 'sizes' and 'type' call for " +
                                                     std::to_string(expectedBytes));
        }
        return out;
    }

    Result<Volume> buildVolume() const {
        if (field("data file") != nullptr || field("datafile") != nullptr) {
            const std::string name = field("data file") != nullptr ? "data file" : "datafile";
            return fieldError(ErrorCode::Unsupported, name,
                              "detached data files are not supported");
        }
        if (!header_.terminated) {
            return makeError(ErrorCode::IoError, where() +
                                                     ": header does not end with a blank line "
                                                     "(file truncated?)");
        }
        for (const char* required : {"type", "dimension", "sizes", "encoding"}) {
            if (field(required) == nullptr) {
                return makeError(ErrorCode::InvalidArgument,
                                 where() + ": missing field '" + required + "'");
            }
        }
        for (const char* skip : {"line skip", "lineskip", "byte skip", "byteskip"}) {
            if (const auto* value = field(skip); value != nullptr && *value != "0") {
                return fieldError(ErrorCode::Unsupported, skip, "only 0 is supported");
            }
        }

        const auto dimension = parseInteger(*field("dimension"));
        if (!dimension || *dimension < 1) {
            return fieldError(ErrorCode::InvalidArgument, "dimension",
                              "'" + *field("dimension") + "' is not a positive integer");
        }
        if (*dimension != 3) {
            return fieldError(ErrorCode::Unsupported, "dimension",
                              "only 3-D volumes are supported, got " + std::to_string(*dimension));
        }

        Volume volume;
        volume.type = *field("type");
        const std::string type = normaliseType(volume.type);
        const auto sample = integerType(type);
        if (!sample) {
            return fieldError(
                isOtherNrrdType(type) ? ErrorCode::Unsupported : ErrorCode::InvalidArgument, "type",
                "'" + volume.type + "' is not supported (integers of 8, 16 or 32 bits only)");
        }

        const auto sizeWords = splitWhitespace(*field("sizes"));
        std::uint64_t voxels = 1;
        for (std::size_t i = 0; i < sizeWords.size() && i < 3; ++i) {
            const auto size = parseInteger(sizeWords[i]);
            if (!size || *size < 1 || *size > std::numeric_limits<int>::max()) {
                return fieldError(ErrorCode::InvalidArgument, "sizes",
                                  "'" + sizeWords[i] + "' is not a positive integer");
            }
            volume.sizes[i] = static_cast<int>(*size);
            voxels *= static_cast<std::uint64_t>(*size); // <= 2^93 cannot happen: checked below
            if (voxels > kMaxVoxels) {
                return fieldError(ErrorCode::Unsupported, "sizes",
                                  "'" + *field("sizes") + "' is more than " +
                                      std::to_string(kMaxVoxels) + " voxels (" +
                                      std::to_string(kMaxVolumeBytes >> 20) +
                                      " MiB as 32-bit labels), the limit for a volume");
            }
        }
        if (sizeWords.size() != 3) {
            return fieldError(ErrorCode::InvalidArgument, "sizes",
                              "expected 3 sizes, got '" + *field("sizes") + "'");
        }

        const std::string encoding = lower(*field("encoding"));
        const bool gzip = encoding == "gzip" || encoding == "gz";
        if (!gzip && encoding != "raw") {
            const bool known = encoding == "bzip2" || encoding == "bz2" || encoding == "ascii" ||
                               encoding == "text" || encoding == "txt" || encoding == "hex";
            return fieldError(known ? ErrorCode::Unsupported : ErrorCode::InvalidArgument,
                              "encoding",
                              "'" + *field("encoding") + "' is not supported (raw or gzip only)");
        }

        bool bigEndian = false;
        if (sample->bytes > 1) {
            const auto* endian = field("endian");
            if (endian == nullptr) {
                return makeError(ErrorCode::InvalidArgument,
                                 where() + ": missing field 'endian' (required for " + volume.type +
                                     ")");
            }
            const std::string value = lower(*endian);
            if (value != "little" && value != "big") {
                return fieldError(ErrorCode::InvalidArgument, "endian",
                                  "'" + *endian + "' is neither 'little' nor 'big'");
            }
            bigEndian = value == "big";
        }

        if (const auto* directions = field("space directions")) {
            auto spacing = parseSpaceDirections(*directions);
            if (!spacing) {
                return spacing.error();
            }
            volume.spacingUm = *spacing;
        } else if (const auto* spacings = field("spacings")) {
            auto spacing = parseSpacings(*spacings);
            if (!spacing) {
                return spacing.error();
            }
            volume.spacingUm = *spacing;
        }

        const auto bytesPerVoxel = static_cast<std::size_t>(sample->bytes);
        const std::size_t expectedBytes = static_cast<std::size_t>(voxels) * bytesPerVoxel;
        std::vector<std::uint8_t> inflated;
        const std::uint8_t* raw = nullptr;
        if (gzip) {
            auto data = inflateData(expectedBytes);
            if (!data) {
                return data.error();
            }
            inflated = std::move(data.value());
            raw = inflated.data();
        } else {
            const std::size_t available = content_.size() - header_.dataOffset;
            if (available < expectedBytes) {
                return makeError(ErrorCode::IoError, where() + ": raw data is truncated (got " +
                                                         std::to_string(available) + " of " +
                                                         std::to_string(expectedBytes) + " bytes)");
            }
            raw = reinterpret_cast<const std::uint8_t*>(content_.data() + header_.dataOffset);
        }

        volume.data.resize(static_cast<std::size_t>(voxels));
        for (std::size_t i = 0; i < volume.data.size(); ++i) {
            const std::uint8_t* bytes = raw + i * bytesPerVoxel;
            std::uint32_t value = 0;
            for (std::size_t b = 0; b < bytesPerVoxel; ++b) {
                const std::size_t index = bigEndian ? b : bytesPerVoxel - 1 - b;
                value = (value << 8) | bytes[index];
            }
            if (sample->isSigned) {
                const std::uint32_t signBit = std::uint32_t{1} << (8 * bytesPerVoxel - 1);
                if ((value & signBit) != 0) {
                    const std::size_t s0 = static_cast<std::size_t>(volume.sizes[0]);
                    const std::size_t s1 = static_cast<std::size_t>(volume.sizes[1]);
                    return makeError(ErrorCode::Unsupported,
                                     where() + ": negative voxel at (" + std::to_string(i % s0) +
                                         ", " + std::to_string(i / s0 % s1) + ", " +
                                         std::to_string(i / s0 / s1) + ") of type '" + volume.type +
                                         "'; labels must be >= 0");
                }
            }
            volume.data[i] = value;
        }
        return volume;
    }

    fs::path path_;
    std::string content_;
    Header header_;
};

} // namespace

Result<Volume> readNrrd(const std::filesystem::path& path) {
    try {
        return NrrdReader(path).read();
    } catch (const std::bad_alloc&) {
        return makeError(ErrorCode::IoError,
                         "NRRD '" + path.string() + "' is too large to load into memory");
    } catch (const std::exception& e) {
        return makeError(ErrorCode::Internal, "NRRD '" + path.string() + "': " + e.what());
    }
}

} // namespace slicestation::core
