// OME-XML: the document written into a section image, and the small parser that reads it back.
#include "slicestation/daemon/storage/ome_tiff.hpp"

#include "ome_text.hpp"

#include "slicestation/core/atomic_file.hpp"

#include "slicestation/core/image_file.hpp"
#include "slicestation/core/unique_fd.hpp"

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <tiffio.h>

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <bit>
#include <cerrno>
#include <charconv>
#include <chrono>
#include <cmath>
#include <cstdarg>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <memory>
#include <optional>
#include <random>
#include <regex>
#include <vector>
namespace slicestation::daemon {
namespace {

namespace fs = std::filesystem;
using core::ErrorCode;
using core::makeError;
using ome_text::formatDouble;
using ome_text::quoted;

std::optional<double> parseDouble(std::string_view text) {
    while (!text.empty() && (text.front() == ' ' || text.front() == '+')) {
        text.remove_prefix(1);
    }
    double v = 0;
    const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), v);
    if (ec != std::errc() || end != text.data() + text.size() || !std::isfinite(v)) {
        return std::nullopt;
    }
    return v;
}

std::string xmlEscape(std::string_view text) {
    std::string out;
    out.reserve(text.size());
    for (const char c : text) {
        switch (c) {
        case '&':
            out += "&amp;";
            break;
        case '<':
            out += "&lt;";
            break;
        case '>':
            out += "&gt;";
            break;
        case '"':
            out += "&quot;";
            break;
        case '\'':
            out += "&apos;";
            break;
        default:
            out += c;
        }
    }
    return out;
}

std::string randomUuid() {
    std::random_device rd;
    std::array<std::uint8_t, 16> b{};
    for (auto& byte : b) {
        byte = static_cast<std::uint8_t>(rd());
    }
    b[6] = static_cast<std::uint8_t>((b[6] & 0x0f) | 0x40); // version 4 (RFC 4122 section 4.4)
    b[8] = static_cast<std::uint8_t>((b[8] & 0x3f) | 0x80);
    std::string out;
    constexpr std::string_view hex = "0123456789abcdef";
    for (std::size_t i = 0; i < b.size(); ++i) {
        if (i == 4 || i == 6 || i == 8 || i == 10) {
            out += '-';
        }
        out += hex[b[i] >> 4];
        out += hex[b[i] & 0xf];
    }
    return out;
}

// ---------------------------------------------------------------------------------------------
// A minimal XML reader: elements, attributes, text; enough for OME-XML, with namespace
// prefixes dropped. Comments, processing instructions and DOCTYPE are skipped.

struct XmlElement {
    std::string name; ///< local name (prefix removed)
    std::vector<std::pair<std::string, std::string>> attributes;
    std::vector<XmlElement> children;
    std::string text;

    const std::string* attribute(std::string_view key) const {
        for (const auto& [k, v] : attributes) {
            if (k == key) {
                return &v;
            }
        }
        return nullptr;
    }
    const XmlElement* child(std::string_view key) const {
        for (const auto& c : children) {
            if (c.name == key) {
                return &c;
            }
        }
        return nullptr;
    }
};

class XmlParser {
public:
    explicit XmlParser(std::string_view text) : s_(text) {}

    core::Result<XmlElement> parseDocument() {
        skipMisc();
        if (!peek('<')) {
            return fail("no root element");
        }
        auto root = parseElement(0);
        if (!root) {
            return root;
        }
        skipMisc();
        if (pos_ != s_.size()) {
            return fail("content after the root element");
        }
        return root;
    }

private:
    static constexpr int kMaxDepth = 64;

    core::Error fail(const std::string& what) const {
        return makeError(ErrorCode::IoError,
                         "malformed OME-XML at byte " + std::to_string(pos_) + ": " + what);
    }
    bool peek(char c) const { return pos_ < s_.size() && s_[pos_] == c; }
    bool startsWith(std::string_view p) const { return s_.substr(pos_, p.size()) == p; }
    void skipSpace() {
        while (pos_ < s_.size() && std::strchr(" \t\r\n", s_[pos_]) != nullptr) {
            ++pos_;
        }
    }
    bool skipPast(std::string_view end) {
        const auto at = s_.find(end, pos_);
        if (at == std::string_view::npos) {
            pos_ = s_.size();
            return false;
        }
        pos_ = at + end.size();
        return true;
    }
    /// Skips whitespace, comments, processing instructions and DOCTYPE.
    void skipMisc() {
        for (;;) {
            skipSpace();
            if (startsWith("<?")) {
                skipPast("?>");
            } else if (startsWith("<!--")) {
                skipPast("-->");
            } else if (startsWith("<!DOCTYPE")) {
                skipPast(">");
            } else {
                return;
            }
        }
    }
    std::string_view parseName() {
        const std::size_t start = pos_;
        while (pos_ < s_.size() && std::strchr(" \t\r\n/>=", s_[pos_]) == nullptr) {
            ++pos_;
        }
        return s_.substr(start, pos_ - start);
    }
    static std::string localName(std::string_view name) {
        const auto colon = name.find(':');
        return std::string(colon == std::string_view::npos ? name : name.substr(colon + 1));
    }
    std::optional<std::string> unescape(std::string_view raw) const {
        std::string out;
        out.reserve(raw.size());
        for (std::size_t i = 0; i < raw.size(); ++i) {
            if (raw[i] != '&') {
                out += raw[i];
                continue;
            }
            const auto semi = raw.find(';', i);
            if (semi == std::string_view::npos) {
                return std::nullopt;
            }
            const std::string_view entity = raw.substr(i + 1, semi - i - 1);
            if (entity == "lt") {
                out += '<';
            } else if (entity == "gt") {
                out += '>';
            } else if (entity == "amp") {
                out += '&';
            } else if (entity == "quot") {
                out += '"';
            } else if (entity == "apos") {
                out += '\'';
            } else if (entity.size() > 1 && entity[0] == '#') {
                const bool hex = entity[1] == 'x' || entity[1] == 'X';
                const std::string_view digits = entity.substr(hex ? 2 : 1);
                unsigned long code = 0;
                const auto [end, ec] = std::from_chars(digits.data(), digits.data() + digits.size(),
                                                       code, hex ? 16 : 10);
                if (ec != std::errc() || end != digits.data() + digits.size() || code > 0x10FFFF) {
                    return std::nullopt;
                }
                appendUtf8(out, static_cast<std::uint32_t>(code));
            } else {
                return std::nullopt;
            }
            i = semi;
        }
        return out;
    }
    static void appendUtf8(std::string& out, std::uint32_t cp) {
        if (cp < 0x80) {
            out += static_cast<char>(cp);
        } else if (cp < 0x800) {
            out += static_cast<char>(0xC0 | (cp >> 6));
            out += static_cast<char>(0x80 | (cp & 0x3F));
        } else if (cp < 0x10000) {
            out += static_cast<char>(0xE0 | (cp >> 12));
            out += static_cast<char>(0x80 | ((cp >> 6) & 0x3F));
            out += static_cast<char>(0x80 | (cp & 0x3F));
        } else {
            out += static_cast<char>(0xF0 | (cp >> 18));
            out += static_cast<char>(0x80 | ((cp >> 12) & 0x3F));
            out += static_cast<char>(0x80 | ((cp >> 6) & 0x3F));
            out += static_cast<char>(0x80 | (cp & 0x3F));
        }
    }

    core::Result<XmlElement> parseElement(int depth) {
        if (depth > kMaxDepth) {
            return fail("elements nested too deeply");
        }
        ++pos_; // '<'
        const std::string_view rawName = parseName();
        if (rawName.empty()) {
            return fail("element without a name");
        }
        XmlElement element;
        element.name = localName(rawName);
        for (;;) {
            skipSpace();
            if (startsWith("/>")) {
                pos_ += 2;
                return element;
            }
            if (peek('>')) {
                ++pos_;
                break;
            }
            const std::string_view key = parseName();
            skipSpace();
            if (key.empty() || !peek('=')) {
                return fail("attribute without a value in <" + std::string(rawName) + ">");
            }
            ++pos_;
            skipSpace();
            if (!peek('"') && !peek('\'')) {
                return fail("unquoted attribute value");
            }
            const char quote = s_[pos_++];
            const auto end = s_.find(quote, pos_);
            if (end == std::string_view::npos) {
                return fail("unterminated attribute value");
            }
            auto value = unescape(s_.substr(pos_, end - pos_));
            if (!value) {
                return fail("bad entity in attribute " + std::string(key));
            }
            element.attributes.emplace_back(localName(key), std::move(*value));
            pos_ = end + 1;
        }
        // Content: text, children, comments, CDATA, until the matching end tag.
        for (;;) {
            if (pos_ >= s_.size()) {
                return fail("unterminated element <" + std::string(rawName) + ">");
            }
            if (startsWith("</")) {
                pos_ += 2;
                const std::string_view endName = parseName();
                skipSpace();
                if (endName != rawName || !peek('>')) {
                    return fail("end tag does not match <" + std::string(rawName) + ">");
                }
                ++pos_;
                return element;
            }
            if (startsWith("<!--")) {
                if (!skipPast("-->")) {
                    return fail("unterminated comment");
                }
            } else if (startsWith("<![CDATA[")) {
                pos_ += 9;
                const auto end = s_.find("]]>", pos_);
                if (end == std::string_view::npos) {
                    return fail("unterminated CDATA");
                }
                element.text += s_.substr(pos_, end - pos_);
                pos_ = end + 3;
            } else if (startsWith("<?")) {
                skipPast("?>");
            } else if (peek('<')) {
                auto child = parseElement(depth + 1);
                if (!child) {
                    return child;
                }
                element.children.push_back(std::move(child.value()));
            } else {
                const auto end = s_.find('<', pos_);
                const auto stop = end == std::string_view::npos ? s_.size() : end;
                auto text = unescape(s_.substr(pos_, stop - pos_));
                if (!text) {
                    return fail("bad entity in text");
                }
                element.text += *text;
                pos_ = stop;
            }
        }
    }

    std::string_view s_;
    std::size_t pos_ = 0;
};

/// Factor to µm of an OME UnitsLength symbol; "reference frame" (the schema's default for stage
/// positions) is taken as µm, the stage's own unit.
std::optional<double> lengthToUm(std::string_view unit) {
    if (unit.empty() || unit == "µm" || unit == "\xce\xbcm" || unit == "um" ||
        unit == "reference frame") {
        return 1.0;
    }
    if (unit == "nm")
        return 1e-3;
    if (unit == "pm")
        return 1e-6;
    if (unit == "Å")
        return 1e-4;
    if (unit == "mm")
        return 1e3;
    if (unit == "cm")
        return 1e4;
    if (unit == "m")
        return 1e6;
    return std::nullopt;
}

/// Factor to µs of an OME UnitsTime symbol (default: s).
std::optional<double> timeToUs(std::string_view unit) {
    if (unit.empty() || unit == "s")
        return 1e6;
    if (unit == "ms")
        return 1e3;
    if (unit == "µs" || unit == "\xce\xbcs" || unit == "us")
        return 1.0;
    if (unit == "ns")
        return 1e-3;
    if (unit == "min")
        return 6e7;
    if (unit == "h")
        return 3.6e9;
    return std::nullopt;
}

const char* pixelType(int cvType) {
    return CV_MAT_DEPTH(cvType) == CV_16U ? "uint16" : "uint8";
}

} // namespace

std::string makeOmeXml(int width, int height, int cvType, const OmeTiffInfo& info) {
    const bool rgb = CV_MAT_CN(cvType) == 3;
    const std::string um = "µm";
    std::string x;
    x += "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n";
    x += "<OME xmlns=\"http://www.openmicroscopy.org/Schemas/OME/2016-06\" "
         "xmlns:xsi=\"http://www.w3.org/2001/XMLSchema-instance\" "
         "xsi:schemaLocation=\"http://www.openmicroscopy.org/Schemas/OME/2016-06 "
         "http://www.openmicroscopy.org/Schemas/OME/2016-06/ome.xsd\" "
         "Creator=\"slicestation\" UUID=\"urn:uuid:" +
         randomUuid() + "\">\n";
    // Element order follows the schema's sequences: Instrument before Image; in Image,
    // AcquisitionDate, InstrumentRef, Pixels; in Pixels, Channel, TiffData, Plane.
    x += "  <Instrument ID=\"Instrument:0\">\n";
    x += "    <Detector ID=\"Detector:0:0\" Type=\"CMOS\"/>\n";
    x += "  </Instrument>\n";
    x += "  <Image ID=\"Image:0\" Name=\"" + xmlEscape(info.name) + "\">\n";
    if (!info.acquiredUtc.empty()) {
        x += "    <AcquisitionDate>" + xmlEscape(info.acquiredUtc) + "</AcquisitionDate>\n";
    }
    x += "    <InstrumentRef ID=\"Instrument:0\"/>\n";
    x += "    <Pixels ID=\"Pixels:0\" DimensionOrder=\"XYCZT\" Type=\"" +
         std::string(pixelType(cvType)) + "\" SignificantBits=\"" +
         std::to_string(CV_MAT_DEPTH(cvType) == CV_16U ? 16 : 8) + "\" BigEndian=\"" +
         (std::endian::native == std::endian::big ? "true" : "false") + "\" Interleaved=\"" +
         (rgb ? "true" : "false") + "\" SizeX=\"" + std::to_string(width) + "\" SizeY=\"" +
         std::to_string(height) + "\" SizeZ=\"1\" SizeC=\"" + (rgb ? "3" : "1") +
         "\" SizeT=\"1\" PhysicalSizeX=\"" + formatDouble(info.umPerPx) +
         "\" PhysicalSizeXUnit=\"" + um + "\" PhysicalSizeY=\"" + formatDouble(info.umPerPx) +
         "\" PhysicalSizeYUnit=\"" + um + "\">\n";
    x += "      <Channel ID=\"Channel:0:0\" Name=\"" + xmlEscape(info.channel) +
         "\" SamplesPerPixel=\"" + (rgb ? "3" : "1") + "\">\n";
    x += "        <DetectorSettings ID=\"Detector:0:0\" Gain=\"" + formatDouble(info.gain) +
         "\"/>\n";
    x += "      </Channel>\n";
    x += "      <TiffData IFD=\"0\" PlaneCount=\"1\"/>\n";
    x += "      <Plane TheZ=\"0\" TheC=\"0\" TheT=\"0\" ExposureTime=\"" +
         std::to_string(info.exposureUs) + "\" ExposureTimeUnit=\"µs\" PositionX=\"" +
         formatDouble(info.stage.xUm) + "\" PositionXUnit=\"" + um + "\" PositionY=\"" +
         formatDouble(info.stage.yUm) + "\" PositionYUnit=\"" + um + "\" PositionZ=\"" +
         formatDouble(info.stage.zUm) + "\" PositionZUnit=\"" + um + "\"/>\n";
    x += "    </Pixels>\n";
    x += "  </Image>\n";
    x += "</OME>\n";
    return x;
}

core::Result<OmeXmlContent> parseOmeXml(std::string_view xml) {
    auto doc = XmlParser(xml).parseDocument();
    if (!doc)
        return doc.error();
    const auto bad = [](const std::string& what) {
        return makeError(ErrorCode::IoError, "OME-XML: " + what);
    };
    if (doc->name != "OME")
        return bad("root element is <" + doc->name + ">, not <OME>");
    const XmlElement* image = doc->child("Image");
    if (image == nullptr)
        return bad("no <Image>");
    const XmlElement* pixels = image->child("Pixels");
    if (pixels == nullptr)
        return bad("no <Pixels> in the first <Image>");

    OmeXmlContent out;
    auto& info = out.info;
    if (const auto* n = image->attribute("Name"))
        info.name = *n;
    if (const auto* d = image->child("AcquisitionDate"))
        info.acquiredUtc = d->text;

    const auto number = [&](const XmlElement& e, std::string_view key) -> core::Result<double> {
        const std::string* text = e.attribute(key);
        if (text == nullptr)
            return bad("no " + std::string(key) + " in <" + e.name + ">");
        const auto v = parseDouble(*text);
        if (!v)
            return bad(std::string(key) + "=\"" + *text + "\" is not a number");
        return *v;
    };
    const auto length = [&](const XmlElement& e, std::string_view key) -> core::Result<double> {
        auto v = number(e, key);
        if (!v)
            return v;
        const std::string* unit = e.attribute(std::string(key) + "Unit");
        const auto factor = lengthToUm(unit ? *unit : std::string_view());
        if (!factor)
            return bad(std::string(key) + "Unit=\"" + *unit + "\" is not a known length");
        return *v * *factor;
    };

    for (const char* key : {"SizeX", "SizeY"}) {
        auto v = number(*pixels, key);
        if (!v)
            return v.error();
        // A pixel count: a whole number that an int holds (found by fuzz_small_formats:
        // SizeX="1.6e55" was cast to int, which is undefined).
        if (!(*v >= 1 && *v <= 2147483647.0 && *v == std::floor(*v)))
            return bad(std::string(key) + "=\"" + *pixels->attribute(key) +
                       "\" is not a pixel count");
        (std::string_view(key) == "SizeX" ? out.sizeX : out.sizeY) = static_cast<int>(*v);
    }
    auto sizeUm = length(*pixels, "PhysicalSizeX");
    if (!sizeUm)
        return sizeUm.error();
    if (!(*sizeUm > 0))
        return bad("PhysicalSizeX must be > 0");
    info.umPerPx = *sizeUm;

    if (const XmlElement* channel = pixels->child("Channel")) {
        if (const auto* n = channel->attribute("Name"))
            info.channel = *n;
        if (const XmlElement* ds = channel->child("DetectorSettings");
            ds != nullptr && ds->attribute("Gain") != nullptr) {
            auto gain = number(*ds, "Gain");
            if (!gain)
                return gain.error();
            info.gain = *gain;
        }
    }
    if (const XmlElement* plane = pixels->child("Plane")) {
        double* targets[] = {&info.stage.xUm, &info.stage.yUm, &info.stage.zUm};
        const char* keys[] = {"PositionX", "PositionY", "PositionZ"};
        for (int i = 0; i < 3; ++i) {
            if (plane->attribute(keys[i]) == nullptr)
                continue;
            auto v = length(*plane, keys[i]);
            if (!v)
                return v.error();
            *targets[i] = *v;
        }
        if (plane->attribute("ExposureTime") != nullptr) {
            auto v = number(*plane, "ExposureTime");
            if (!v)
                return v.error();
            const std::string* unit = plane->attribute("ExposureTimeUnit");
            const auto factor = timeToUs(unit ? *unit : std::string_view());
            if (!factor)
                return bad("ExposureTimeUnit=\"" + *unit + "\" is not a known time");
            info.exposureUs = std::llround(*v * *factor);
        }
    }
    return out;
}

} // namespace slicestation::daemon
